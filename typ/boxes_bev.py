"""Rotated bird's-eye-view (BEV) box geometry in plain numpy: corners, IoU, NMS.

Boxes are ``(K, 7)`` ``[x, y, z, l, w, h, yaw]`` (see :mod:`typ.geometry`); only x, y, l,
w and yaw matter here. A box's BEV footprint is the bottom face of
:func:`typ.geometry.box_corners`, i.e. OpenCOOD's ``(N, 8, 3)[:, :4, :2]`` polygon that
``common_utils.convert_format`` hands to shapely, in counter-clockwise order.

Which IoU OpenCOOD uses where (DerrickXuNu/OpenCOOD, main branch):

- Evaluation (``utils/eval_utils.py``) and NMS (``utils/box_utils.py::nms_rotated``) use the
  exact intersection of the BEV polygons (shapely) -> :func:`rotated_iou_bev`, :func:`nms_bev`.
- PointPillars anchor targets (``data_utils/post_processor/voxel_postprocessor.py::
  generate_label``) do *not*: they take the axis-aligned "standup" rectangles around the
  rotated boxes (``box_utils.corner2d_to_standup_box``) and Fast R-CNN's ``bbox_overlaps``
  (``utils/box_overlaps.pyx``), float32, with its pixel-style ``+1`` on every width and
  height -> :func:`standup_iou_bev`. No torch version is needed: targets are built in numpy
  on the data side there too.
"""
from __future__ import annotations

import numpy as np

from typ.errors import TypError
from typ.geometry import box_corners

_MAX_VERTS = 8  # a convex quad clipped by a convex quad has at most 8 vertices
_SNAP = 1e-9  # metres: a vertex this close to a clip line counts as on it (robust ties)
_CHUNK = 65536  # pairs clipped at once; bounds memory to a few tens of MB


def _boxes(value, field: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0:
        return arr.reshape(0, 7)
    if arr.ndim != 2 or arr.shape[1] != 7:
        raise TypError(None, field, "a (K, 7) array [x, y, z, l, w, h, yaw]", arr.shape)
    if not np.isfinite(arr).all():
        raise TypError(None, field, "finite values (no NaN/Inf)", "non-finite entries")
    if (arr[:, 3:6] < 0).any():
        raise TypError(None, field, "non-negative sizes l, w, h", "negative sizes")
    return arr


def bev_corners(boxes) -> np.ndarray:
    """``(K, 7)`` boxes -> ``(K, 4, 2)`` BEV corners, OpenCOOD order (counter-clockwise)."""
    b = _boxes(boxes, "boxes")
    return box_corners(b)[:, :4, :2] if len(b) else np.zeros((0, 4, 2))


def _shoelace(poly: np.ndarray, count: np.ndarray) -> np.ndarray:
    slots = np.arange(poly.shape[1])
    nxt = np.take_along_axis(poly, ((slots + 1) % np.maximum(count, 1)[:, None])[..., None], axis=1)
    term = poly[..., 0] * nxt[..., 1] - nxt[..., 0] * poly[..., 1]
    return 0.5 * np.where(slots < count[:, None], term, 0.0).sum(axis=1)


def _intersection_area(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Area of ``subject & clip`` for (P, 4, 2) counter-clockwise convex quads (Sutherland-Hodgman).

    All P pairs are clipped at once: each polygon lives in a fixed (P, 8, 2) buffer with a
    vertex count; each clip step emits, per vertex, the vertex itself (if inside) and the
    crossing with the clip line (if the edge to the next vertex crosses it), then compacts
    the emitted points to the front with a stable sort so that their order is kept.
    """
    p = len(subject)
    poly = np.zeros((p, _MAX_VERTS, 2))
    poly[:, :4] = subject
    count = np.full(p, 4)
    slots = np.arange(_MAX_VERTS)
    for k in range(4):
        origin = clip[:, k]
        direction = clip[:, (k + 1) % 4] - origin
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        rel = poly - origin[:, None, :]
        # signed distance to the clip line, positive on the left (inside a CCW polygon)
        dist = direction[:, None, 0] * rel[..., 1] - direction[:, None, 1] * rel[..., 0]
        dist[np.abs(dist) < _SNAP] = 0.0
        nxt_idx = (slots[None, :] + 1) % np.maximum(count, 1)[:, None]
        nxt = np.take_along_axis(poly, nxt_idx[..., None], axis=1)
        dist_nxt = np.take_along_axis(dist, nxt_idx, axis=1)
        valid = slots[None, :] < count[:, None]
        inside = dist >= 0.0
        crosses = valid & (inside != (dist_nxt >= 0.0))
        t = dist / np.where(crosses, dist - dist_nxt, 1.0)
        hit = poly + t[..., None] * (nxt - poly)
        emitted = np.stack([poly, hit], axis=2).reshape(p, 2 * _MAX_VERTS, 2)
        keep = np.stack([valid & inside, crosses], axis=2).reshape(p, 2 * _MAX_VERTS)
        order = np.argsort(~keep, axis=1, kind="stable")[:, :_MAX_VERTS]
        poly = np.take_along_axis(emitted, order[..., None], axis=1)
        count = np.minimum(keep.sum(axis=1), _MAX_VERTS)
    return np.maximum(_shoelace(poly, count), 0.0)


def rotated_iou_bev(a, b) -> np.ndarray:
    """Exact BEV IoU of rotated boxes: ``(N, 7)``, ``(M, 7)`` -> ``(N, M)`` float64.

    Intersection of the two footprint polygons over their union, as OpenCOOD's
    ``common_utils.compute_iou`` does with shapely (there in float32). Pairs whose
    axis-aligned footprint bounds do not overlap are 0 without being clipped; so are pairs
    with a zero-area box (shapely would divide 0 by 0 when both are).
    """
    box_a, box_b = _boxes(a, "a"), _boxes(b, "b")
    out = np.zeros((len(box_a), len(box_b)))
    if out.size == 0:
        return out
    ca, cb = bev_corners(box_a), bev_corners(box_b)
    area_a, area_b = box_a[:, 3] * box_a[:, 4], box_b[:, 3] * box_b[:, 4]
    lo_a, hi_a, lo_b, hi_b = ca.min(axis=1), ca.max(axis=1), cb.min(axis=1), cb.max(axis=1)
    near = ((lo_a[:, None, :] <= hi_b[None, :, :]) & (lo_b[None, :, :] <= hi_a[:, None, :])).all(axis=2)
    near &= (area_a[:, None] > 0) & (area_b[None, :] > 0)
    ia, ib = np.nonzero(near)
    for s in range(0, len(ia), _CHUNK):
        i, j = ia[s:s + _CHUNK], ib[s:s + _CHUNK]
        inter = np.minimum(_intersection_area(ca[i], cb[j]), np.minimum(area_a[i], area_b[j]))
        out[i, j] = inter / (area_a[i] + area_b[j] - inter)
    return out


def standup_iou_bev(a, b) -> np.ndarray:
    """OpenCOOD's anchor-assignment IoU: ``(N, 7)``, ``(M, 7)`` -> ``(N, M)`` float32.

    Each box is replaced by the axis-aligned rectangle around its BEV corners
    (``corner2d_to_standup_box``); overlaps follow ``box_overlaps.pyx::bbox_overlaps``
    in float32, including its ``+1`` on widths, heights and intersections (a Fast R-CNN
    pixel convention that OpenCOOD applies to metres unchanged — kept so that positive
    and negative anchors come out the same as there).
    """
    ra, rb = (np.concatenate([c.min(axis=1), c.max(axis=1)], axis=1).astype(np.float32)
              for c in (bev_corners(a), bev_corners(b)))
    one = np.float32(1.0)
    iw = np.minimum(ra[:, None, 2], rb[None, :, 2]) - np.maximum(ra[:, None, 0], rb[None, :, 0]) + one
    ih = np.minimum(ra[:, None, 3], rb[None, :, 3]) - np.maximum(ra[:, None, 1], rb[None, :, 1]) + one
    area_a = (ra[:, 2] - ra[:, 0] + one) * (ra[:, 3] - ra[:, 1] + one)
    area_b = (rb[:, 2] - rb[:, 0] + one) * (rb[:, 3] - rb[:, 1] + one)
    inter = np.where((iw > 0) & (ih > 0), iw * ih, np.float32(0.0))
    return (inter / (area_a[:, None] + area_b[None, :] - inter)).astype(np.float32)


def nms_bev(boxes, scores, iou_threshold: float, max_candidates: int | None = 1000) -> np.ndarray:
    """Greedy rotated NMS: indices into ``boxes`` of the kept boxes, by descending score.

    As OpenCOOD's ``box_utils.nms_rotated``: only the ``max_candidates`` best-scoring boxes
    are considered (their ``top = 1000``; ``None`` for all), and a box is dropped when its
    BEV IoU with a kept, higher-ranked box is strictly greater than ``iou_threshold``.
    Equal scores rank by index, lower first (OpenCOOD's ``argsort()[::-1]`` puts the
    higher index first, so exact ties may keep the other box of the pair there).
    """
    b = _boxes(boxes, "boxes")
    s = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(s) != len(b):
        raise TypError(None, "scores", f"one score per box ({len(b)})", len(s))
    if not np.isfinite(s).all():
        raise TypError(None, "scores", "finite values (no NaN/Inf)", "non-finite entries")
    if not 0.0 <= float(iou_threshold) <= 1.0:
        raise TypError(None, "iou_threshold", "a number in [0, 1]", iou_threshold)
    if max_candidates is not None and max_candidates < 1:
        raise TypError(None, "max_candidates", "None or a positive int", max_candidates)
    order = np.argsort(-s, kind="stable")[:max_candidates]
    iou = rotated_iou_bev(b[order], b[order])
    suppressed = np.zeros(len(order), dtype=bool)
    kept = []
    for k in range(len(order)):
        if suppressed[k]:
            continue
        kept.append(order[k])
        suppressed |= iou[k] > iou_threshold
    return np.asarray(kept, dtype=np.int64)
