"""A trained fusion detector as a servable module: named arrays in, its head dict out.

What ``StageRun.log_model`` logs for each method, so that the MLflow model runs on a batch's
arrays (``tasks.fusion_batch.Inputs.batch`` layout) without typ's :class:`Batch`.
"""
from __future__ import annotations

import torch
from torch import nn

from tasks.fusion_batch import Inputs
from tasks.fusion_train import Trained


class ServedDetector(nn.Module):
    """A trained method called with a batch's arrays by name, returning its head dict."""

    def __init__(self, trained: Trained):
        super().__init__()
        self.method, self.model = trained.method, trained.model

    def forward(self, voxel_features, voxel_coords, voxel_num_points, agent_mask, transforms, time_delay):
        pillars = {"voxel_features": voxel_features.float(), "voxel_coords": voxel_coords.long(),
                   "voxel_num_points": voxel_num_points.long()}
        return self.model(pillars, agent_mask=agent_mask.bool(), transforms=transforms.double(),
                          time_delay=time_delay.long())

    @staticmethod
    def example(method: str, inputs: Inputs, n: int = 2) -> dict[str, torch.Tensor]:
        """The named arrays of the first ``n`` samples of ``inputs``, as ``forward`` takes them."""
        batch = inputs.batch(method, range(min(n, len(inputs))))
        return {**batch.pillars, "agent_mask": batch.agent_mask, "transforms": batch.transforms,
                "time_delay": batch.time_delay}
