"""Early fusion (Cooper): the agents' clouds merged in the ego frame, one detector."""
from __future__ import annotations

import torch

from models.fusion.base import BYTES_PER_POINT, FusionModule, _check, merge_agent_points


class EarlyFusion(FusionModule):
    """Early fusion (Cooper): the plain detector on :func:`merge_agent_points` of each sample;
    its batches have one slot per sample, the merged ego-frame cloud."""

    merge_points = staticmethod(merge_agent_points)

    def forward(self, pillars: dict, *, agent_mask: torch.Tensor, transforms=None, time_delay=None,
                agent_types=None) -> dict[str, torch.Tensor]:
        """``pillarize`` of the B merged, ego-frame clouds (agent_mask (B, 1)) -> the ego's head dict."""
        agent_mask = _check(agent_mask)
        return self.detector(pillars, agent_mask.shape[0] * agent_mask.shape[1])

    def message_bytes(self, *, points: float, boxes: float) -> float:
        return float(points * BYTES_PER_POINT)
