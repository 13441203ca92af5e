"""No fusion: the ego's own detector on the ego's own points."""
from __future__ import annotations

import torch

from models.fusion.base import FusionModule, _check


class NoFusion(FusionModule):
    """The ego's own detector on the ego's own points ("No Fusion" rows of TYP Tables 1–3).

    It is :class:`LateFusion`'s detector (the same state dict): OpenCOOD's no fusion runs the
    single-agent detector on the ego's cloud only."""

    def forward(self, pillars: dict, *, agent_mask: torch.Tensor, transforms=None, time_delay=None,
                agent_types=None) -> dict[str, torch.Tensor]:
        """Batch layout of the module doc; only the ego slots are encoded."""
        agent_mask = _check(agent_mask)
        b, l = agent_mask.shape
        ego = torch.zeros_like(agent_mask)
        ego[:, 0] = True
        d = self.detector
        return d.head(d.backbone(d.bev(pillars, b * l, keep=ego.flatten())))
