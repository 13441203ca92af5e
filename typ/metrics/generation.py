"""Figures of generated views that only the evaluation needs (ground dominates a LiDAR grid).

- :func:`local_ground` / :func:`above_ground`: voxels more than 0.3 m over the true view's
  local ground, where walls, vehicles and vegetation are, so an IoU over them is not the
  IoU of ground cells that happen to overlap;
- :func:`object_hits`: whether a labelled vehicle holds enough of a cloud's points to be
  found by a detector trained on it (the object hit rate).
"""
from __future__ import annotations

import numpy as np

from typ.errors import TypError
from typ.metrics.truth import check_points
from typ.voxel import Grid

#: side (m) of the neighbourhood a cell's ground is taken from: wider than a car, so that a cell
#: whose only return is a car's roof reaches the road beside the car on any grid
GROUND_WINDOW_M = 4.0


def ground_window(grid: Grid) -> int:
    """The odd number of cells nearest :data:`GROUND_WINDOW_M` on ``grid``: 5 on 0.8 m cells, 21 on 0.2 m."""
    return 2 * int(np.floor((GROUND_WINDOW_M / float(min(grid.voxel_size[:2])) - 1) / 2 + 0.5)) + 1


def local_ground(truth, grid: Grid, *, window: int | None = None) -> np.ndarray:
    """(H, W) float64 ground height (z, the grid's frame) under every BEV cell of one true view.

    truth: (H, W, C) bool occupancy on ``grid``. The ground of a cell is the lowest occupied
    voxel centre among the cells within ``window // 2`` cells of it (a ``window`` x ``window``
    neighbourhood, by default :func:`ground_window`: about 4 m), so a cell whose ground is
    hidden under a car or a wall takes its neighbours' ground; a neighbourhood with no occupied
    voxel at all takes the median of the view's per-cell lowest heights (the ground of a flat
    scene); an empty view takes the grid's lowest bin centre.
    """
    occ = np.asarray(truth)
    if occ.shape != grid.shape or occ.dtype != bool:
        raise TypError("local_ground", "truth", f"{grid.shape} bool array", f"{occ.shape} {occ.dtype}")
    window = ground_window(grid) if window is None else window
    if window < 1 or window % 2 == 0:
        raise TypError("local_ground", "window", "an odd number of cells >= 1", window)
    z = grid.centers(2)
    any_occ = occ.any(axis=2)
    lowest = np.where(any_occ, z[np.argmax(occ, axis=2)], np.inf)
    if not any_occ.any():
        return np.full(occ.shape[:2], z[0])
    from scipy.ndimage import minimum_filter
    ground = minimum_filter(lowest, size=window, mode="constant", cval=np.inf)
    return np.where(np.isfinite(ground), ground, float(np.median(lowest[any_occ])))


def above_ground(truth, grid: Grid, *, margin: float = 0.3, window: int | None = None) -> np.ndarray:
    """(H, W, C) bool: voxels whose centre is more than ``margin`` m over :func:`local_ground` of
    the true view ``truth`` (H, W, C). Ground dominates a LiDAR grid, so IoU restricted to this
    mask measures walls, vehicles and vegetation, the structure a detector needs."""
    ground = local_ground(truth, grid, window=window)
    return grid.centers(2)[None, None, :] > ground[:, :, None] + margin


def object_hits(points, boxes, *, max_distance: float = 50.0, min_points: int = 10) -> tuple[int, int]:
    """(hit, total): of the boxes whose centre lies within ``max_distance`` m (planar) of the
    sensor, how many hold at least ``min_points`` of ``points`` (closed upright boxes,
    :func:`typ.geometry.points_in_boxes`). points: (N, >=3), boxes: (K, 7), one sensor frame.
    The object hit rate of a set of views is the pooled ``sum(hit) / sum(total)``."""
    from typ.geometry import points_in_boxes
    pts = check_points(points, "object_hits", "points")
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    near = b[np.hypot(b[:, 0], b[:, 1]) <= max_distance]
    if len(near) == 0:
        return 0, 0
    if len(pts) == 0:
        return 0, len(near)
    counts = np.zeros(len(near), dtype=np.int64)
    for start in range(0, len(pts), 200_000):  # bounded (N, K) masks on dense clouds
        counts += points_in_boxes(pts[start:start + 200_000], near).sum(axis=0)
    return int((counts >= min_points).sum()), len(near)
