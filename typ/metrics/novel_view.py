"""A generated LiDAR view against the real scan taken at that pose: LiDAR novel-view synthesis metrics.

Conventions are LiDAR4D's (Zheng et al., CVPR 2024; ``ispc-lab/LiDAR4D`` ``utils/metrics.py`` and
``utils/convert.py``), which LiDAR-NeRF and GS-LiDAR share:

- points within :data:`MAX_RANGE` (80 m) of the sensor only (LiDAR4D drops depths >= 80 m when it
  makes its range images);
- Chamfer distance: the mean *squared* nearest-neighbour distance from each cloud to the other,
  the two means *added* (``dist1.mean() + dist2.mean()`` of ``chamfer_3DDist``), m²;
- F-score at :data:`FSCORE_THRESHOLD` = 0.05 m² of squared distance (0.224 m): precision is the
  share of predicted points whose nearest true point is nearer than that, recall the share of
  true points with a predicted point that near, F = 2PR / (P + R), 0 where P + R = 0;
- on the reference sensor's range image (one row per beam, one column per azimuth step, each
  pixel the nearest return): depth RMSE and median absolute error. LiDAR4D takes them over every
  pixel with empty pixels as depth 0; here, as the benchmark asks, over the pixels where both
  images have a return, so that they measure depth and :func:`raydrop_accuracy` measures returns;
- ray-drop accuracy: the share of pixels where both images agree on return / no return
  (LiDAR4D's ``RaydropMeter`` accuracy with its 0.5 threshold on a 0/1 mask).

Two figures of the scan pattern (not LiDAR4D's): the share of points within :data:`ON_BEAM_DEG`
of one of the sensor's beams seen from the beam's origin (:func:`typ.sensors.fit.beam_residuals`),
and the row-occupancy L1 (per beam row, the share of azimuth bins with a return; the mean absolute
difference over rows). And precision / recall restricted to a set of BEV cells (the cells the ego's
scan covered, or the others): :func:`masked_precision_recall`.

Every function is a pure function of arrays; clouds are (N, >=3) float, one sensor frame, metres.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from typ.errors import TypError
from typ.metrics.truth import check_points
from typ.sensors.fit import beam_residuals

#: LiDAR4D's range cut (metres): points this far or further are left out of every figure
MAX_RANGE = 80.0
#: LiDAR4D's F-score threshold on *squared* distances (m²): 0.05 m² = (0.224 m)²
FSCORE_THRESHOLD = 0.05
#: a point is on a beam within this angle of its elevation (the generation targets' tolerance)
ON_BEAM_DEG = 0.05
_WHERE = "typ.metrics.novel_view"


def within_range(points, max_range: float = MAX_RANGE) -> np.ndarray:
    """(M, 3) float64: the points of (N, >=3) ``points`` nearer than ``max_range`` to the origin."""
    xyz = check_points(points, _WHERE, "points")[:, :3].astype(np.float64)
    return xyz[np.linalg.norm(xyz, axis=1) < max_range]


def nearest_squared(a, b, *, tree: cKDTree | None = None) -> np.ndarray:
    """(len(a),) float64: the squared distance from each point of ``a`` to its nearest point of
    ``b`` (both (N, 3) float); all ``inf`` when ``b`` is empty. ``tree``: ``cKDTree(b)`` when the
    caller holds one (a truth scored against several views)."""
    a, b = np.asarray(a, dtype=np.float64)[:, :3], np.asarray(b, dtype=np.float64)[:, :3]
    if len(b) == 0:
        return np.full(len(a), np.inf)
    if len(a) == 0:
        return np.zeros(0)
    d, _ = (tree or cKDTree(b)).query(a, k=1, workers=-1)
    return d * d


def chamfer(pred_to_true_sq, true_to_pred_sq) -> float:
    """LiDAR4D's Chamfer distance (m²) from the two directions' squared nearest distances:
    ``mean(pred_to_true_sq) + mean(true_to_pred_sq)``; NaN when either cloud is empty."""
    a, b = np.asarray(pred_to_true_sq, np.float64), np.asarray(true_to_pred_sq, np.float64)
    if len(a) == 0 or len(b) == 0 or not (np.isfinite(a).all() and np.isfinite(b).all()):
        return float("nan")
    return float(a.mean() + b.mean())


def fscore(pred_to_true_sq, true_to_pred_sq, threshold: float = FSCORE_THRESHOLD) -> tuple[float, float, float]:
    """(F-score, precision, recall) at ``threshold`` m² of squared distance, LiDAR4D's ``fscore``:
    precision = share of ``pred_to_true_sq`` below it, recall = share of ``true_to_pred_sq`` below it,
    F = 2PR / (P + R) and 0 where P + R = 0. An empty cloud scores precision (or recall) 0."""
    a, b = np.asarray(pred_to_true_sq, np.float64), np.asarray(true_to_pred_sq, np.float64)
    precision = float(np.mean(a < threshold)) if len(a) else 0.0
    recall = float(np.mean(b < threshold)) if len(b) else 0.0
    f = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return f, precision, recall


def masked_precision_recall(pred_to_true_sq, true_to_pred_sq, pred_in, true_in,
                            threshold: float = FSCORE_THRESHOLD) -> tuple[float, float]:
    """(precision, recall) within a set of cells: precision over the predicted points where
    ``pred_in`` (N,) bool is True, recall over the true points where ``true_in`` (M,) is True,
    each against the whole other cloud; NaN where the set holds no such point."""
    a, b = np.asarray(pred_to_true_sq, np.float64), np.asarray(true_to_pred_sq, np.float64)
    pa, pb = np.asarray(pred_in, bool), np.asarray(true_in, bool)
    if pa.shape != a.shape or pb.shape != b.shape:
        raise TypError(_WHERE, "pred_in/true_in", f"one flag per point ({a.shape}, {b.shape})", (pa.shape, pb.shape))
    precision = float(np.mean(a[pa] < threshold)) if pa.any() else float("nan")
    recall = float(np.mean(b[pb] < threshold)) if pb.any() else float("nan")
    return precision, recall


def beams(points, elevations_deg, beam_heights_m=()) -> tuple[np.ndarray, np.ndarray]:
    """((N,) the beam nearest each point, (N,) its angle from that beam in degrees), seen from the
    beam's origin (:func:`typ.sensors.fit.beam_residuals`); ``elevations_deg`` ascending, as
    :class:`typ.sim.SensorSpec` lists them. The rows of :func:`sensor_range_image` and the
    residuals of :func:`on_beam`."""
    xyz = check_points(points, _WHERE, "points")[:, :3].astype(np.float64)
    if len(xyz) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    return beam_residuals(xyz, elevations_deg, beam_heights_m)


def sensor_range_image(points, rows, *, n_beams: int, azimuth_bins: int, max_range: float = MAX_RANGE,
                       min_range: float = 0.0) -> np.ndarray:
    """(n_beams, W) float64 range image of a cloud on its sensor's own layout: point n goes to row
    ``rows[n]`` (its beam, :func:`beams`) and to column c when its azimuth lies in
    ``[-pi + c 2pi/W, -pi + (c + 1) 2pi/W)``; each pixel holds the depth ``|p|`` of its nearest
    point, 0 where none. Depths outside ``[min_range, max_range)`` are left out."""
    xyz = check_points(points, _WHERE, "points")[:, :3].astype(np.float64)
    row = np.asarray(rows, dtype=np.int64)
    if row.shape != (len(xyz),) or (len(row) and (row.min() < 0 or row.max() >= n_beams)):
        raise TypError(_WHERE, "rows", f"one beam index in [0, {n_beams}) per point", row.shape)
    if isinstance(azimuth_bins, bool) or not isinstance(azimuth_bins, (int, np.integer)) or azimuth_bins < 1:
        raise TypError(_WHERE, "azimuth_bins", "an integer >= 1", azimuth_bins)
    image = np.zeros((int(n_beams), int(azimuth_bins)))
    depth = np.linalg.norm(xyz, axis=1)
    keep = (depth >= min_range) & (depth < max_range) & (np.hypot(xyz[:, 0], xyz[:, 1]) > 0)
    xyz, depth, row = xyz[keep], depth[keep], row[keep]
    col = np.floor((np.arctan2(xyz[:, 1], xyz[:, 0]) + np.pi) / (2 * np.pi) * azimuth_bins).astype(np.int64)
    col = np.clip(col, 0, azimuth_bins - 1)
    order = np.argsort(-depth, kind="stable")   # nearest written last: each pixel keeps its nearest return
    image[row[order], col[order]] = depth[order]
    return image


def _images(pred_image, true_image) -> tuple[np.ndarray, np.ndarray]:
    p, t = np.asarray(pred_image, np.float64), np.asarray(true_image, np.float64)
    if p.shape != t.shape or p.ndim != 2:
        raise TypError(_WHERE, "pred_image", f"a 2-D image of the true image's shape {t.shape}", p.shape)
    return p, t


def depth_errors(pred_image, true_image) -> tuple[float, float]:
    """(RMSE, median absolute error) of depth, metres, over the pixels where both range images
    have a return (> 0); NaN where there is none."""
    p, t = _images(pred_image, true_image)
    both = (p > 0) & (t > 0)
    if not both.any():
        return float("nan"), float("nan")
    diff = p[both] - t[both]
    return float(np.sqrt(np.mean(diff * diff))), float(np.median(np.abs(diff)))


def raydrop_accuracy(pred_image, true_image) -> float:
    """The share of pixels on which both range images agree: a return (> 0) in both or in neither."""
    p, t = _images(pred_image, true_image)
    return float(np.mean((p > 0) == (t > 0)))


def row_occupancy(image) -> np.ndarray:
    """(B,) the share of each row's pixels (azimuth bins) that hold a return."""
    return np.mean(np.asarray(image) > 0, axis=1)


def row_l1(pred_image, true_image) -> float:
    """Row-occupancy L1: mean over rows of ``|row_occupancy(pred) - row_occupancy(true)|``; 0 when
    every beam fills as many azimuth bins as the real scan's."""
    p, t = _images(pred_image, true_image)
    return float(np.mean(np.abs(row_occupancy(p) - row_occupancy(t))))


def on_beam(points, residuals_deg, *, tolerance_deg: float = ON_BEAM_DEG, min_range: float = 0.0) -> tuple[int, int]:
    """(on, counted): of the points at least ``min_range`` away horizontally, how many lie within
    ``tolerance_deg`` of their beam (``residuals_deg``: each point's angle from it, :func:`beams`)."""
    xyz = check_points(points, _WHERE, "points")
    r = np.asarray(residuals_deg, dtype=np.float64)
    if r.shape != (len(xyz),):
        raise TypError(_WHERE, "residuals_deg", f"one angle per point ({len(xyz)})", r.shape)
    counted = np.hypot(xyz[:, 0], xyz[:, 1]) >= max(min_range, 1e-9)
    return int(np.count_nonzero(np.abs(r[counted]) <= tolerance_deg)), int(np.count_nonzero(counted))
