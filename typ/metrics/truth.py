"""Agreement of one generated scan with its ground truth: voxel IoU and Chamfer distance.

Where :mod:`typ.metrics.bev` compares *sets* of scans as distributions, these compare a
generated reference-view scan ``x_r`` with the real one captured there (when the data has
it, e.g. OPV2V): same frame, same grid, point for point.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from typ.errors import TypError
from typ.voxel import Grid, voxelize


def check_points(value, where: str, field: str) -> np.ndarray:
    """``value`` as an (N, >=3) float32/float64 array with finite x, y, z, else TypError(where, field).

    N may be 0. Columns past z are not checked (intensity may be anything).
    """
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):
        raise TypError(where, field, "an (N, >=3) float array [x, y, z, ...]", type(value).__name__) from None
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise TypError(where, field, "an (N, >=3) float array [x, y, z, ...]", arr.shape)
    if arr.dtype not in (np.float32, np.float64):
        raise TypError(where, field, "dtype float32 or float64", arr.dtype)
    bad = ~np.isfinite(arr[:, :3]).all(axis=1)
    if bad.any():
        raise TypError(where, field, "finite x, y, z (no NaN/Inf)", f"{int(bad.sum())} rows with NaN/Inf")
    return arr


def _ratio(num: int, den: int) -> float:
    return num / den if den else float("nan")


def occupancy_iou(pred, true) -> dict[str, float]:
    """IoU, precision and recall of a predicted occupancy against the true one.

    pred, true: bool arrays of the same shape (e.g. (H, W, C) from :func:`typ.voxel.voxelize`).
    With TP = |pred & true|: ``iou = TP / |pred | true|``, ``precision = TP / |pred|``,
    ``recall = TP / |true|``. A ratio whose denominator is 0 is NaN (undefined, e.g. IoU of
    two empty grids, precision of an empty prediction), so averages over scans must skip it
    explicitly (``np.nanmean``) rather than count it as 0 or 1.
    """
    p, t = np.asarray(pred), np.asarray(true)
    for name, arr in (("pred", p), ("true", t)):
        if arr.dtype != bool:
            raise TypError("occupancy_iou", name, "a bool occupancy array", arr.dtype)
    if p.shape != t.shape:
        raise TypError("occupancy_iou", "true", f"the shape of pred {p.shape}", t.shape)
    tp = int(np.count_nonzero(p & t))
    n_pred, n_true = int(np.count_nonzero(p)), int(np.count_nonzero(t))
    return {"iou": _ratio(tp, n_pred + n_true - tp), "precision": _ratio(tp, n_pred),
            "recall": _ratio(tp, n_true)}


def voxel_iou(pred_points, true_points, grid: Grid) -> dict[str, float]:
    """:func:`occupancy_iou` of two point clouds voxelized on ``grid`` (:func:`typ.voxel.voxelize`).

    pred_points, true_points: (N, >=3) float32/float64 in the grid's sensor frame; points
    outside the grid are dropped, a voxel is occupied when any point falls in it (bins as in
    :mod:`typ.voxel`). Returns ``{"iou", "precision", "recall"}``, NaN where undefined.
    """
    pred = check_points(pred_points, "voxel_iou", "pred_points")
    true = check_points(true_points, "voxel_iou", "true_points")
    return occupancy_iou(voxelize(pred, grid), voxelize(true, grid))


def chamfer_distance(a, b) -> float:
    """Symmetric Chamfer distance, metres: ``(mean_{p in a} d(p, b) + mean_{q in b} d(q, a)) / 2``.

    a, b: (N, >=3) float32/float64 point clouds in the same frame; only x, y, z are used.
    ``d(p, B)`` is the plain (not squared) Euclidean distance from p to its nearest point of
    B (scipy cKDTree, float64). So a set against itself gives 0 and two single points at
    distance d give d. Note LiDM's and most completion papers' "CD" use squared distances;
    this one does not. Either set empty raises TypError naming it: the nearest neighbour in
    an empty set does not exist, and returning inf or 0 would hide a failed generation.
    """
    pa = check_points(a, "chamfer_distance", "a")
    pb = check_points(b, "chamfer_distance", "b")
    for name, arr in (("a", pa), ("b", pb)):
        if len(arr) == 0:
            raise TypError("chamfer_distance", name, "at least one point", "an empty point set")
    xa, xb = pa[:, :3].astype(np.float64), pb[:, :3].astype(np.float64)
    a_to_b, _ = cKDTree(xb).query(xa, k=1)
    b_to_a, _ = cKDTree(xa).query(xb, k=1)
    return float((a_to_b.mean() + b_to_a.mean()) / 2.0)

