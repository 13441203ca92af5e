"""Anchors, OpenCOOD's residual box encoding, target assignment and decoding (before NMS).

Conventions from ``opencood/data_utils/post_processor/voxel_postprocessor.py`` (the code is ours):
- anchors (H, W, A, 7) on the head's feature map, rows y and columns x, one per yaw in
  ``anchor_yaws_deg`` (OpenCOOD: l 3.9, w 1.6, h 1.56, z -1, yaws 0 and 90 degrees). Centres are
  the feature cells' centres ``min + (i + 0.5) * voxel_size * feature_stride``, which is exactly
  OpenCOOD's ``linspace(min + vw, max - vw, W // 2)`` for its stride 2.
- residuals (``generate_label`` / ``delta_to_boxes3d``): ``dx, dy`` over the anchor's BEV
  diagonal ``sqrt(l² + w²)``, ``dz`` over the anchor height, ``log`` size ratios, ``yaw - yaw_a``.
  Boxes here are typ's ``[x, y, z, l, w, h, yaw]`` (OpenCOOD stores ``hwl``; same maths).
- assignment: axis-aligned BEV IoU of the anchors' and boxes' standup rectangles, with the
  "+1" widths of OpenCOOD's Fast R-CNN ``bbox_overlaps`` (``pixel_offset=1.0``, even in metres);
  positives IoU > 0.6 plus the best anchor of every box, negatives IoU < 0.45 for all boxes.
- direction bins (OpenCOOD v2 / HEAL ``point_pillar_loss.get_direction_target`` and their
  post-processors): ``floor(limit_period(yaw - dir_offset, 0, 2π) / (2π / bins))``, offset π/4.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from typ.errors import TypError


def limit_period(val: torch.Tensor, offset: float = 0.5, period: float = 2 * math.pi) -> torch.Tensor:
    """OpenPCDet's ``val - floor(val / period + offset) * period``: into ``[-offset, 1 - offset) * period``."""
    return val - torch.floor(val / period + offset) * period


def standup_boxes(boxes: torch.Tensor) -> torch.Tensor:
    """(K, 7) ``[x, y, z, l, w, h, yaw]`` -> (K, 4) ``[x1, y1, x2, y2]`` BEV rectangle around the box."""
    c, s = torch.cos(boxes[:, 6]).abs(), torch.sin(boxes[:, 6]).abs()
    half_x = (boxes[:, 3] * c + boxes[:, 4] * s) / 2
    half_y = (boxes[:, 3] * s + boxes[:, 4] * c) / 2
    return torch.stack([boxes[:, 0] - half_x, boxes[:, 1] - half_y, boxes[:, 0] + half_x, boxes[:, 1] + half_y], 1)


def axis_aligned_iou(a: torch.Tensor, b: torch.Tensor, *, pixel_offset: float = 1.0) -> torch.Tensor:
    """(N, 4), (K, 4) ``[x1, y1, x2, y2]`` -> (N, K) IoU; widths are ``x2 - x1 + pixel_offset``."""
    iw = (torch.minimum(a[:, None, 2], b[None, :, 2]) - torch.maximum(a[:, None, 0], b[None, :, 0]) + pixel_offset)
    ih = (torch.minimum(a[:, None, 3], b[None, :, 3]) - torch.maximum(a[:, None, 1], b[None, :, 1]) + pixel_offset)
    inter = iw.clamp(min=0) * ih.clamp(min=0)
    area_a = (a[:, 2] - a[:, 0] + pixel_offset) * (a[:, 3] - a[:, 1] + pixel_offset)
    area_b = (b[:, 2] - b[:, 0] + pixel_offset) * (b[:, 3] - b[:, 1] + pixel_offset)
    return inter / (area_a[:, None] + area_b[None, :] - inter)


class AnchorBoxCoder:
    """Anchors of one feature map and the residual coding between anchors and boxes."""

    def __init__(self, *, lidar_range: Sequence[float] = (-140.8, -40.0, -3.0, 140.8, 40.0, 1.0),
                 voxel_size: float = 0.4, feature_stride: int = 2,
                 anchor_size: Sequence[float] = (3.9, 1.6, 1.56), anchor_yaws_deg: Sequence[float] = (0.0, 90.0),
                 anchor_z: float = -1.0, pos_threshold: float = 0.6, neg_threshold: float = 0.45,
                 pixel_offset: float = 1.0, num_dir_bins: int = 2, dir_offset: float = math.pi / 4):
        """lidar_range: the detector's [x_min, y_min, z_min, x_max, y_max, z_max] m; voxel_size: pillar side (m);
        feature_stride: pillars per head cell (the model's ``feature_stride``); anchor_size: (l, w, h) m;
        anchor_yaws_deg: one anchor per yaw; anchor_z: anchor centre height (m, sensor frame);
        pos_threshold / neg_threshold: IoU for positives / negatives; pixel_offset: OpenCOOD's +1 in IoU widths;
        num_dir_bins: direction classes (0: none); dir_offset: start of the first direction bin (rad)."""
        r = [float(v) for v in lidar_range]
        cell = float(voxel_size) * int(feature_stride)
        w, h = (r[3] - r[0]) / cell, (r[4] - r[1]) / cell
        if len(r) != 6 or abs(w - round(w)) > 1e-6 or abs(h - round(h)) > 1e-6 or w < 1 or h < 1:
            raise TypError(None, "lidar_range",
                           f"an x/y extent that is a multiple of voxel_size * feature_stride = {cell}", r)
        if not 0 <= neg_threshold <= pos_threshold:
            raise TypError(None, "neg_threshold", f"0 <= neg_threshold <= pos_threshold={pos_threshold}", neg_threshold)
        self.shape = (int(round(h)), int(round(w)))
        self.num_anchors = len(anchor_yaws_deg)
        self.pos_threshold, self.neg_threshold, self.pixel_offset = pos_threshold, neg_threshold, pixel_offset
        self.num_dir_bins, self.dir_offset = int(num_dir_bins), float(dir_offset)
        xs = r[0] + (np.arange(self.shape[1]) + 0.5) * cell
        ys = r[1] + (np.arange(self.shape[0]) + 0.5) * cell
        cy, cx = np.meshgrid(ys, xs, indexing="ij")
        a = np.zeros((*self.shape, self.num_anchors, 7))
        a[..., 0], a[..., 1], a[..., 2] = cx[..., None], cy[..., None], anchor_z
        a[..., 3:6] = np.asarray(anchor_size, dtype=np.float64)
        a[..., 6] = np.radians(np.asarray(anchor_yaws_deg, dtype=np.float64))
        self.anchors = torch.from_numpy(a).float()          # (H, W, A, 7)

    # ------------------------------------------------------------------ coding
    @staticmethod
    def encode(boxes: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
        """(..., 7) boxes and anchors -> (..., 7) residuals
        ``[dx/d, dy/d, dz/h_a, log l/l_a, log w/w_a, log h/h_a, yaw - yaw_a]``, d = anchor BEV diagonal."""
        d = torch.sqrt(anchors[..., 3] ** 2 + anchors[..., 4] ** 2)
        return torch.stack([(boxes[..., 0] - anchors[..., 0]) / d, (boxes[..., 1] - anchors[..., 1]) / d,
                            (boxes[..., 2] - anchors[..., 2]) / anchors[..., 5],
                            torch.log(boxes[..., 3] / anchors[..., 3]), torch.log(boxes[..., 4] / anchors[..., 4]),
                            torch.log(boxes[..., 5] / anchors[..., 5]), boxes[..., 6] - anchors[..., 6]], -1)

    @staticmethod
    def decode(deltas: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`encode` (OpenCOOD's ``delta_to_boxes3d``)."""
        d = torch.sqrt(anchors[..., 3] ** 2 + anchors[..., 4] ** 2)
        return torch.stack([deltas[..., 0] * d + anchors[..., 0], deltas[..., 1] * d + anchors[..., 1],
                            deltas[..., 2] * anchors[..., 5] + anchors[..., 2],
                            torch.exp(deltas[..., 3]) * anchors[..., 3], torch.exp(deltas[..., 4]) * anchors[..., 4],
                            torch.exp(deltas[..., 5]) * anchors[..., 5], deltas[..., 6] + anchors[..., 6]], -1)

    def direction_bin(self, yaw: torch.Tensor) -> torch.Tensor:
        """Yaw (rad) -> direction class in ``[0, num_dir_bins)``."""
        period = 2 * math.pi / self.num_dir_bins
        return torch.floor(limit_period(yaw - self.dir_offset, 0.0, 2 * math.pi) / period).long().clamp(
            0, self.num_dir_bins - 1)

    # -------------------------------------------------------------- assignment
    def assign_targets(self, gt_boxes) -> dict[str, torch.Tensor]:
        """(K, 7) boxes in the sensor frame -> OpenCOOD's label dict for one sample.

        ``pos_equal_one`` / ``neg_equal_one`` (H, W, A) float, ``targets`` (H, W, 7A) residuals
        (zero off positives), ``dir_targets`` (H, W, A) long direction bins of the matched box.
        """
        gt = torch.as_tensor(np.asarray(gt_boxes, dtype=np.float64).reshape(-1, 7), dtype=torch.float32)
        anchors = self.anchors.reshape(-1, 7)
        n, hw = len(anchors), (*self.shape, self.num_anchors)
        pos = torch.zeros(n, dtype=torch.bool)
        matched = torch.zeros(n, dtype=torch.long)
        if len(gt) == 0:
            neg = torch.ones(n, dtype=torch.bool)
        else:
            iou = axis_aligned_iou(standup_boxes(anchors), standup_boxes(gt), pixel_offset=self.pixel_offset)
            best_anchor = iou.argmax(0)                       # the best anchor of every box ...
            has_overlap = iou[best_anchor, torch.arange(len(gt))] > 0
            best_anchor, best_gt = best_anchor[has_overlap], torch.arange(len(gt))[has_overlap]
            best_iou, best_of_anchor = iou.max(1)
            pos = best_iou > self.pos_threshold
            matched = best_of_anchor.clone()
            pos[best_anchor] = True                           # ... is positive whatever its IoU
            matched[best_anchor] = best_gt
            neg = (iou < self.neg_threshold).all(1)
            neg[best_anchor] = False
        targets = torch.zeros(n, 7)
        dirs = torch.zeros(n, dtype=torch.long)
        if pos.any():
            targets[pos] = self.encode(gt[matched[pos]], anchors[pos])
            if self.num_dir_bins:
                dirs[pos] = self.direction_bin(gt[matched[pos], 6])
        return {"pos_equal_one": pos.float().view(hw), "neg_equal_one": neg.float().view(hw),
                "targets": targets.view(*self.shape, 7 * self.num_anchors), "dir_targets": dirs.view(hw)}

    def assign_batch(self, gt_boxes_per_sample: Sequence) -> dict[str, torch.Tensor]:
        """:meth:`assign_targets` of every sample, stacked along a new batch dim (OpenCOOD's collate)."""
        labels = [self.assign_targets(g) for g in gt_boxes_per_sample]
        return {k: torch.stack([lab[k] for lab in labels]) for k in labels[0]}

    # ---------------------------------------------------------------- decoding
    def decode_head(self, output: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """Head output -> boxes (B, H*W*A, 7) in the sensor frame and scores (B, H*W*A), before NMS.

        With a ``dm`` entry the yaw is folded into ``[dir_offset, dir_offset + π)`` and moved to
        the predicted direction bin, then wrapped into ``[-π, π)`` (HEAL's post-processor).
        """
        psm, rm = output["psm"], output["rm"]
        b = psm.shape[0]
        scores = torch.sigmoid(psm.permute(0, 2, 3, 1).reshape(b, -1))
        deltas = rm.permute(0, 2, 3, 1).reshape(b, -1, 7)
        boxes = self.decode(deltas, self.anchors.to(deltas).reshape(1, -1, 7))
        if "dm" in output and self.num_dir_bins:
            labels = output["dm"].permute(0, 2, 3, 1).reshape(b, -1, self.num_dir_bins).argmax(-1)
            period = 2 * math.pi / self.num_dir_bins
            yaw = limit_period(boxes[..., 6] - self.dir_offset, 0.0, period) + self.dir_offset + period * labels
            boxes = torch.cat([boxes[..., :6], limit_period(yaw, 0.5, 2 * math.pi)[..., None]], -1)
        return boxes, scores

    def decode_predictions(self, output: dict[str, torch.Tensor], *, score_threshold: float = 0.2,
                           max_boxes: int | None = None) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Per sample (boxes (K, 7), scores (K,)) with score > threshold, best first, at most
        ``max_boxes``; NMS is the caller's (``typ.boxes_bev``)."""
        boxes, scores = self.decode_head(output)
        out = []
        for bx, sc in zip(boxes, scores):
            keep = sc > score_threshold
            bx, sc = bx[keep], sc[keep]
            order = torch.argsort(sc, descending=True)[:max_boxes]
            out.append((bx[order], sc[order]))
        return out
