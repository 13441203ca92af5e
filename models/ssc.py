"""Semantic scene completion on the detector's backbone (V2VSSC §IV): an occupancy head and late fusion.

V2VSSC keeps its detector (VoxelNet there, typ's PointPillars here) and swaps the detection head
for a semantic occupancy head. :func:`ssc_detector` builds the PointPillars of ``models/
pointpillars.py`` on the SSC grid (pillars of 0.78125 m over x, y in [-50, 50) m, z in [-3, 5) m,
so its BEV has the grid's 128 x 128 cells) and puts an :class:`OccupancyHead` where its anchor
head was. The fusion modules of ``models/fusion`` that call ``detector.head`` (``NoFusion``,
``EarlyFusion``, ``LateFusion``, ``AttFuse``) then output ``{"occ": (B, K, X, Y, Z) logits}``
unchanged; ``V2XViT`` builds its head with the detector head's :meth:`OccupancyHead.like` on its
transformer's width and stride. Late fusion's map merge is :func:`merge_max_confidence` after :func:`warp_to_ego`.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from models.pointpillars import PointPillars
from typ.errors import TypError

#: PointPillars ``lidar_range`` of V2VSSC's grid, and its pillar side (= the voxel's x/y size)
SSC_LIDAR_RANGE = (-50.0, -50.0, -3.0, 50.0, 50.0, 5.0)
SSC_PILLAR = 0.78125


class OccupancyHead(nn.Module):
    """BEV features (B, C, H, W) at ``feature_stride`` -> semantic occupancy logits (B, K, X, Y, Z).

    A transposed conv brings the features back to one cell per voxel column, a 1 x 1 conv gives
    ``num_heights * num_classes`` logits per cell (V2VSSC: 20 height bins x 7 classes). BEV rows
    are y and columns x (``scatter_to_bev``); the output is indexed ``[b, k, ix, iy, iz]`` like
    :mod:`typ.ssc`'s maps.
    """

    def __init__(self, *, in_channels: int, num_classes: int = 7, num_heights: int = 20, feature_stride: int = 2,
                 hidden: int = 64):
        """in_channels: C of the fused BEV map; num_classes: K (0 empty); num_heights: Z bins;
        feature_stride: BEV cells per voxel column side; hidden: width after the upsampling."""
        super().__init__()
        self.num_classes, self.num_heights = int(num_classes), int(num_heights)
        self.up = nn.Sequential(nn.ConvTranspose2d(in_channels, hidden, feature_stride, stride=feature_stride, bias=False),
                                nn.BatchNorm2d(hidden, eps=1e-3, momentum=0.01), nn.ReLU())
        self.out = nn.Conv2d(hidden, self.num_heights * self.num_classes, 1)

    def like(self, *, in_channels: int, feature_stride: int) -> "OccupancyHead":
        """A fresh head of the same classes, heights and width on a ``in_channels`` map at
        ``feature_stride`` (V2X-ViT's shrunk map)."""
        return OccupancyHead(in_channels=in_channels, num_classes=self.num_classes, num_heights=self.num_heights,
                             feature_stride=feature_stride, hidden=self.out.in_channels)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        logits = self.out(self.up(x))                              # (B, Z*K, Y, X)
        b, _, h, w = logits.shape
        logits = logits.view(b, self.num_heights, self.num_classes, h, w)
        return {"occ": logits.permute(0, 2, 4, 3, 1).contiguous()}  # (B, K, X, Y, Z)


def ssc_detector(*, num_classes: int = 7, num_heights: int = 20, layer_nums: Sequence[int] = (3, 5, 8),
                 num_filters: Sequence[int] = (64, 128, 256), num_upsample_filters: Sequence[int] = (128, 128, 128),
                 pillar_channels: int = 64, max_pillars: int = 16384, head_hidden: int = 64) -> PointPillars:
    """PointPillars on V2VSSC's grid with an :class:`OccupancyHead` as its ``head`` (see module doc);
    the backbone arguments are :class:`models.pointpillars.PointPillars`'s."""
    det = PointPillars(lidar_range=SSC_LIDAR_RANGE, voxel_size=SSC_PILLAR, max_pillars=max_pillars,
                       pillar_channels=pillar_channels, layer_nums=layer_nums, num_filters=num_filters,
                       num_upsample_filters=num_upsample_filters, upsample_strides=(1, 2, 4))
    det.head = OccupancyHead(in_channels=det.backbone.out_channels, num_classes=num_classes, num_heights=num_heights,
                             feature_stride=det.feature_stride, hidden=head_hidden)
    return det


def class_weights(counts, *, eps: float = 1.02) -> np.ndarray:
    """(K,) float64 class-balanced cross-entropy weights from voxel counts per class:
    ``1 / ln(eps + f_k)`` with ``f_k`` the class's share (ENet's / MonoScene's weighting), so
    rare classes (poles, cars) weigh up to ~50x as much as empty space; a class never seen gets
    the largest weight. Normalised to mean 1."""
    counts = np.asarray(counts, dtype=np.float64)
    if counts.ndim != 1 or (counts < 0).any() or counts.sum() <= 0:
        raise TypError("models.ssc.class_weights", "counts", "(K,) non-negative voxel counts, not all 0", counts)
    w = 1.0 / np.log(eps + counts / counts.sum())
    return w / w.mean()


def class_argmax(logits: torch.Tensor) -> torch.Tensor:
    """Argmax over dim 0 of (C, ...) class logits, ties to the first class as ``torch.argmax``.
    Reduced with the classes as the last, contiguous axis: torch's CPU argmax over a leading
    axis of a (7, 128, 128, 20) map takes 5x as long."""
    return logits.movedim(0, -1).contiguous().argmax(-1)


def warp_to_ego(labels: torch.Tensor, confidence: torch.Tensor, transform, *, lower: Sequence[float],
                voxel: Sequence[float]) -> tuple[torch.Tensor, torch.Tensor]:
    """One agent's predicted map resampled into the ego's grid, nearest voxel.

    labels (X, Y, Z) long and confidence (X, Y, Z) float in the agent's frame; transform (4, 4)
    agent->ego (float64); lower, voxel: the grid's lower corner and voxel size (m). Each ego voxel
    centre is mapped into the agent's frame and takes the label and confidence of the agent voxel
    containing it; ego voxels outside the agent's grid get label 0 and confidence -1 (no vote).
    """
    shape = labels.shape
    dev = labels.device
    t = torch.as_tensor(transform, dtype=torch.float64, device=dev)
    lo = torch.as_tensor(lower, dtype=torch.float64, device=dev)
    v = torch.as_tensor(voxel, dtype=torch.float64, device=dev)
    axes = [lo[a] + (torch.arange(shape[a], dtype=torch.float64, device=dev) + 0.5) * v[a] for a in range(3)]
    centres = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inv = torch.linalg.inv(t)
    src = centres @ inv[:3, :3].T + inv[:3, 3]
    idx = torch.floor((src - lo) / v).long()
    size = torch.tensor(shape, device=dev)
    ok = ((idx >= 0) & (idx < size)).all(1)
    idx = idx.clamp(min=torch.zeros_like(size), max=size - 1)
    out_l = labels[idx[:, 0], idx[:, 1], idx[:, 2]].where(ok, torch.zeros((), dtype=labels.dtype, device=dev))
    out_c = confidence[idx[:, 0], idx[:, 1], idx[:, 2]].where(ok, torch.full((), -1.0, dtype=confidence.dtype,
                                                                             device=dev))
    return out_l.reshape(shape), out_c.reshape(shape)


def merge_max_confidence(labels: torch.Tensor, confidence: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """V2VSSC's late fusion: per voxel, the label of the agent with the greatest confidence.

    labels (L, X, Y, Z) long, confidence (L, X, Y, Z) float, all in the ego frame, agent 0 the
    ego (ties go to the lowest agent index, so the ego keeps a voxel it is as sure of). Returns
    (labels (X, Y, Z), confidence (X, Y, Z)).
    """
    if labels.shape != confidence.shape or labels.dim() != 4 or labels.shape[0] < 1:
        raise TypError("models.ssc.merge_max_confidence", "labels", "(L, X, Y, Z) labels and confidences of one shape",
                       (tuple(labels.shape), tuple(confidence.shape)))
    best = confidence.argmax(0, keepdim=True)  # first maximum on ties
    return labels.gather(0, best)[0], confidence.gather(0, best)[0]
