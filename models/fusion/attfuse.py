"""OPV2V's AttFuse: per BEV cell, the ego's feature attends over every agent's at that cell."""
from __future__ import annotations

import math

import torch

from models.fusion.base import FusionModule, _check, _dense_map_bytes, _regroup, _to_ego, quantize


class AttFuse(FusionModule):
    """OPV2V's AttFuse: at every backbone level, per BEV cell, the ego's feature attends (scaled
    dot product, no projections) over all agents' features at that cell; then upsample + head.
    Messages are the cooperating agents' level maps, quantised as the ego receives them (after
    the warp, which interpolates, so the value range is the sent one)."""

    @staticmethod
    def attend(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(B, L, C, h, w) ego-frame maps, (B, L, h, w) validity -> (B, C, h, w) fused ego map."""
        x = x.masked_fill(~mask[:, :, None], 0.0)
        score = (x * x[:, :1]).sum(2) / math.sqrt(x.shape[2])
        weight = torch.softmax(score.masked_fill(~mask, float("-inf")), dim=1)
        return (weight[:, :, None] * x).sum(1)

    def forward(self, pillars: dict, *, agent_mask: torch.Tensor, transforms, time_delay=None,
                agent_types=None) -> dict[str, torch.Tensor]:
        """Batch layout of the module doc -> the ego's head dict."""
        agent_mask = _check(agent_mask)
        b, l = agent_mask.shape
        d, keep = self.detector, agent_mask.flatten()
        fused = []
        for feat, stride in zip(d.backbone.down(d.bev(pillars, b * l, keep=keep)), d.backbone.level_strides):
            x, mask = _to_ego(_regroup(feat, keep, b, l), agent_mask, transforms, voxel_size=d.voxel_size,
                              stride=stride, lidar_range=d.lidar_range)
            if self.message_bits is not None:
                x = torch.cat([x[:, :1], quantize(x[:, 1:], self.message_bits, (3, 4))], 1)
            fused.append(self.attend(x, mask))
        return d.head(d.backbone.up(fused))

    def message_bytes(self, *, points: float, boxes: float) -> float:
        d = self.detector
        return _dense_map_bytes([(c, d.ny // s, d.nx // s) for c, s in
                                 zip(d.backbone.level_channels, d.backbone.level_strides)], self.message_bits)
