"""Cast reference views: one scene model, cast once from the reference pose with its LiDAR.

A hybrid view (:func:`typ.resim.hybrid_points`) pastes two clouds side by side: the ego's
surfaces re-simulated where the ego saw, the generator's voxel centres elsewhere. Its points
off the ego's coverage lie on no beam of any sensor, and nothing stops a re-simulated ray
behind a generated wall. A cast view instead builds one scene and casts the reference
sensor into it once, so what the reference sees is a scan of its own LiDAR (every point on
one of its beams, ray drop and range noise included) and occlusion between the two parts is
physical:

- where the ego saw (:func:`typ.resim.coverage_mask`): the ego's points as surfels
  (:func:`typ.resim.build_surface`), the reference vehicle's own body left out;
- elsewhere, the generated occupancy as closed cells: each run of occupied voxels above the
  road one box over its cell, from the road (when the run stands on it) to its top; generated
  voxels the ego's rays crossed (:func:`free_space`: the ego saw them empty) are dropped first;
- the road as a height field at a sub-cell height (:func:`ground_heights`: the ego's lowest
  returns near the road, carried to the cells it did not see), under every cell or only under
  generated ground voxels;
- the labelled vehicles y_r (the generator's own condition) as closed boxes.

:class:`typ.config.CastConfig` switches the last three (``generate.cast``).
Everything is in the reference sensor's frame (x forward, y left, z up), lengths in metres.
``reports/generation_ablation.md`` has the measurements behind the choices.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from typ.config import CastConfig
from typ.errors import TypError
from typ.metrics.truth import check_points
from typ.resim import build_surface, coverage_mask
from typ.sim.raycast import cast_mesh
from typ.sim.sensor import SensorSpec
from typ.voxel import Grid

_WHERE = "typ.castview"
#: a return this far from the road level (m) at most may be the road (a kerb, a slope)
GROUND_BAND = 0.4
#: a cell's road height is the ego's lowest return in it; this many cells of median smoothing
SMOOTH_CELLS = 3


def ground_layer(grid: Grid, ground_z: float) -> int:
    """The height layer of ``grid`` that holds the road level ``ground_z`` (clipped into the grid)."""
    k = int(np.floor((ground_z - grid.lower[2]) / grid.voxel_size[2]))
    return int(np.clip(k, 0, grid.shape[2] - 1))


def ground_heights(ego_points_in_ref, grid: Grid, ground_z: float) -> np.ndarray:
    """(H, W) float64: the road's height under each BEV cell of ``grid``.

    In a cell the ego saw, the lowest of its returns within :data:`GROUND_BAND` of the road
    level ``ground_z`` (the reference sensor's ``-mount_height``); every other cell takes the
    nearest such cell's height, and with no road return at all the road is flat at
    ``ground_z``. A median filter over :data:`SMOOTH_CELLS` cells then removes single low
    outliers.
    """
    pts = check_points(ego_points_in_ref, _WHERE, "ego_points_in_ref")[:, :3].astype(np.float64)
    h, w = grid.shape[:2]
    ij = np.floor((pts[:, :2] - grid.lower[:2]) / grid.voxel_size[:2]).astype(np.int64)
    ok = (ij >= 0).all(axis=1) & (ij[:, 0] < h) & (ij[:, 1] < w) & (np.abs(pts[:, 2] - ground_z) <= GROUND_BAND)
    lowest = np.full(h * w, np.inf)
    np.minimum.at(lowest, ij[ok, 0] * w + ij[ok, 1], pts[ok, 2])
    lowest = lowest.reshape(h, w)
    known = np.isfinite(lowest)
    if not known.any():
        return np.full((h, w), float(ground_z))
    nearest = ndimage.distance_transform_edt(~known, return_distances=False, return_indices=True)
    return ndimage.median_filter(lowest[nearest[0], nearest[1]], size=SMOOTH_CELLS, mode="nearest")


def free_space(ego_points_in_ref, ego_origin, grid: Grid, *, margin: float = 0.5,
               chunk: int = 2_000_000) -> np.ndarray:
    """(C, H, W) bool: the voxels of ``grid`` an ego ray crossed before its return, which the
    ego therefore saw empty (the last ``margin`` m before each return excepted: the surface's
    own voxel and range noise).

    ego_points_in_ref: (N, >=3) the ego's returns in the reference frame; ego_origin: (3,) the
    ego sensor's position in that frame. Each ray is sampled every half of the smallest voxel
    edge.
    """
    pts = check_points(ego_points_in_ref, _WHERE, "ego_points_in_ref")[:, :3].astype(np.float64)
    o = np.asarray(ego_origin, dtype=np.float64)
    if o.shape != (3,) or not np.isfinite(o).all():
        raise TypError(_WHERE, "ego_origin", "the ego sensor's finite (3,) position in the reference frame", o.shape)
    step = 0.5 * float(np.min(grid.voxel_size))
    d = pts - o
    r = np.linalg.norm(d, axis=1)
    n = np.maximum(np.floor((r - margin) / step).astype(np.int64), 0)
    keep = n > 0
    d, r, n = d[keep], r[keep], n[keep]
    c, h, w = grid.shape[2], grid.shape[0], grid.shape[1]
    free = np.zeros(h * w * c, dtype=bool)
    first = np.cumsum(n) - n                               # each ray's first sample, counted over all rays
    per = max(1, chunk // max(int(n.max(initial=1)), 1))   # rays per chunk: at most ``chunk`` samples
    for lo in range(0, len(n), per):
        counts = n[lo:lo + per]
        ray = np.repeat(np.arange(lo, lo + len(counts)), counts)
        k = np.arange(int(counts.sum())) - np.repeat(first[lo:lo + per] - first[lo], counts) + 1
        at = o + d[ray] * (k * step / r[ray])[:, None]
        idx = np.floor((at - grid.lower) / grid.voxel_size).astype(np.int64)
        ok = ((idx >= 0) & (idx < np.array(grid.shape))).all(axis=1)
        idx = idx[ok]
        free[(idx[:, 2] * h + idx[:, 0]) * w + idx[:, 1]] = True
    return free.reshape(c, h, w)


def generated_solids(occupancy, mask, heights: np.ndarray, grid: Grid, ground_z: float, *,
                     road=None) -> tuple[np.ndarray, np.ndarray]:
    """The generated part of the scene: (V, 3) float32 vertices, (T, 3) uint32 triangles.

    occupancy: (C, H, W) bool on ``grid`` (as the generator gives it); only the BEV cells where
    ``mask`` (H, W) is True are built. A cell whose road layer (:func:`ground_layer`) or a layer
    below it is occupied gets a road quad whose corners lie at the mean of the four cells'
    ``heights`` around them, so neighbouring road cells join without steps. Each run of
    occupied layers above the road becomes one box over the whole cell, from the road (or the
    run's lowest voxel, when it floats) to the run's top.
    """
    occ = np.asarray(occupancy, dtype=bool)
    m = np.asarray(mask, dtype=bool)
    c, h, w = occ.shape
    if (h, w, c) != tuple(grid.shape) or m.shape != (h, w) or heights.shape != (h, w):
        raise TypError(_WHERE, "occupancy", f"(C, H, W) = {grid.shape[2], *grid.shape[:2]} with an (H, W) mask",
                       (occ.shape, m.shape, heights.shape))
    kg = ground_layer(grid, ground_z)
    verts, tris = [], []
    # road: a height field over the cell corners
    road = m & occ[:kg + 1].any(axis=0) if road is None else np.asarray(road, dtype=bool)
    if road.any():
        padded = np.pad(heights, 1, mode="edge")
        corner_z = (padded[:-1, :-1] + padded[1:, :-1] + padded[:-1, 1:] + padded[1:, 1:]) / 4.0   # (H+1, W+1)
        i, j = np.nonzero(road)
        xe, ye = grid.edges(0), grid.edges(1)
        quad = np.stack([np.stack([xe[i + di], ye[j + dj], corner_z[i + di, j + dj]], axis=1)
                         for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1))], axis=1)            # (N, 4, 3)
        base = 4 * np.arange(len(i))[:, None]
        verts.append(quad.reshape(-1, 3))
        tris.append(np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]))
    # above the road: one box per vertical run of occupied voxels
    above = occ[kg + 1:] & m[None]
    if above.any():
        start = above & ~np.concatenate([np.zeros((1, h, w), bool), above[:-1]])
        stop = above & ~np.concatenate([above[1:], np.zeros((1, h, w), bool)])
        # [i, j, k] sorted by column then layer: a column's runs alternate start, stop, so the
        # n-th start and the n-th stop are one run
        starts = np.argwhere(start.transpose(1, 2, 0))
        stops = np.argwhere(stop.transpose(1, 2, 0))
        i, j = starts[:, 0], starts[:, 1]
        ze = grid.edges(2)
        bottom = ze[starts[:, 2] + kg + 1]
        top = ze[stops[:, 2] + kg + 2]
        bottom = np.where(starts[:, 2] == 0, np.minimum(bottom, heights[i, j]), bottom)
        xe, ye = grid.edges(0), grid.edges(1)
        lo = np.stack([xe[i], ye[j], bottom], axis=1)
        hi = np.stack([xe[i + 1], ye[j + 1], top], axis=1)
        offset = sum(len(v) for v in verts)
        bv, bt = boxes_mesh(lo, hi)
        verts.append(bv)
        tris.append(bt + offset)
    if not verts:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint32)
    return np.concatenate(verts).astype(np.float32), np.concatenate(tris).astype(np.uint32)


_CUBE_TRIS = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])


#: corner v of a box is at the high end of x, y, z where bits 2, 1, 0 of v are set
_CORNER_BITS = np.array([[(v >> 2) & 1, (v >> 1) & 1, v & 1] for v in range(8)], dtype=bool)


def boxes_mesh(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed axis-aligned boxes between corners ``lo`` and ``hi`` (N, 3): (8N, 3) vertices and
    (12N, 3) triangles; box n owns vertices [8n, 8n + 8)."""
    corners = np.where(_CORNER_BITS[None], hi[:, None, :], lo[:, None, :])                  # (N, 8, 3)
    return corners.reshape(-1, 3), _box_triangles(len(lo))


def oriented_boxes_mesh(boxes) -> tuple[np.ndarray, np.ndarray]:
    """Closed boxes (K, 7) ``[x, y, z, l, w, h, yaw]`` (centre, OpenCOOD's convention) as
    (8K, 3) vertices and (12K, 3) triangles."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    local = (_CORNER_BITS[None] - 0.5) * b[:, None, 3:6]                                     # (K, 8, 3)
    c, s = np.cos(b[:, 6])[:, None], np.sin(b[:, 6])[:, None]
    corners = np.stack([c * local[..., 0] - s * local[..., 1], s * local[..., 0] + c * local[..., 1],
                        local[..., 2]], axis=-1) + b[:, None, :3]
    return corners.reshape(-1, 3), _box_triangles(len(b))


def _box_triangles(n: int) -> np.ndarray:
    return (_CUBE_TRIS[None] + 8 * np.arange(n)[:, None, None]).reshape(-1, 3)


def scene_model(ego_points_in_ref, occupancy, grid: Grid, spec: SensorSpec, *, params: CastConfig = CastConfig(),
                ego_origin=None, label_boxes=None, exclude_boxes=None, mask=None) -> tuple[np.ndarray, np.ndarray]:
    """The surface a cast view is cast from (module doc): (V, 3) float32, (T, 3) uint32.

    ego_points_in_ref: (N, >=3) the ego's cloud in the reference sensor's frame; occupancy:
    (C, H, W) bool, the generated view on ``grid`` (that sensor's grid); spec: the reference
    sensor, whose ``mount_height`` places the road; params: what goes in
    (:class:`typ.config.CastConfig`); ego_origin: (3,) the ego sensor in the reference frame,
    which ``params.carve`` needs; label_boxes: (K, 7) the labelled vehicles y_r holds;
    exclude_boxes: (K, 7) boxes whose ego points are dropped (the reference vehicle's own
    body); mask: (H, W) the cells the ego covers, by default :func:`typ.resim.coverage_mask`.
    """
    pts = check_points(ego_points_in_ref, _WHERE, "ego_points_in_ref")
    seen = coverage_mask(pts, grid) if mask is None else np.asarray(mask, dtype=bool)
    ground_z = -float(spec.mount_height)
    occ = np.asarray(occupancy, dtype=bool)
    if params.carve:
        if ego_origin is None:
            raise TypError(_WHERE, "ego_origin", "the ego sensor's (3,) position in the reference frame "
                           "(generate.cast.carve needs it)", None)
        occ = occ & ~free_space(pts, ego_origin, grid)
    road = {"generated": None, "unseen": ~seen, "everywhere": np.ones_like(seen)}[params.road]
    parts = [build_surface(pts[:, :3], exclude_boxes=exclude_boxes),
             generated_solids(occ, ~seen, ground_heights(pts, grid, ground_z), grid, ground_z, road=road)]
    if params.label_boxes > 0 and label_boxes is not None and len(label_boxes):
        b = np.asarray(label_boxes, dtype=np.float64).reshape(-1, 7).copy()
        b[:, 3:6] *= params.label_boxes
        parts.append(oriented_boxes_mesh(b))
    offsets = np.cumsum([0] + [len(v) for v, _ in parts])
    return (np.concatenate([v for v, _ in parts]).astype(np.float32),
            np.concatenate([t + o for (_, t), o in zip(parts, offsets)]).astype(np.uint32))


def cast(vertices, triangles, spec: SensorSpec, rng: np.random.Generator) -> np.ndarray:
    """Every ray of ``spec`` from its origin into the surface: (M, 3) float32 returns.

    :func:`typ.sim.raycast.cast_mesh` with the sensor's dropout and range noise (``rng`` draws
    both), rays starting ``min_range`` out: the sensor sees nothing nearer, and a surfel (up to
    1.5 m from the return that made it) or a cell that reaches around the sensor must not blind it.
    """
    if not isinstance(spec, SensorSpec):
        raise TypError(_WHERE, "spec", "a SensorSpec (typ.sensors.resolve)", type(spec).__name__)
    if not isinstance(rng, np.random.Generator):
        raise TypError(_WHERE, "rng", "a numpy.random.Generator", type(rng).__name__)
    return cast_mesh(vertices, triangles, spec, rng, start=spec.min_range)


def cast_view(ego_points_in_ref, occupancy, grid: Grid, spec: SensorSpec, rng: np.random.Generator, *,
              params: CastConfig = CastConfig(), ego_origin=None, label_boxes=None, exclude_boxes=None,
              mask=None) -> np.ndarray:
    """(M, 3) float32: what ``spec`` at the reference pose sees of :func:`scene_model`, cast with
    :func:`cast`. Arguments as theirs."""
    return cast(*scene_model(ego_points_in_ref, occupancy, grid, spec, params=params, ego_origin=ego_origin,
                             label_boxes=label_boxes, exclude_boxes=exclude_boxes, mask=mask), spec, rng)
