"""Semantic occupancy ground truth (V2VSSC): the grid, its classes, rasterizing scene geometry, storage.

**Grid** (V2VSSC §IV-C): x, y in [-50, 50) m, z in [-3, 5) m in the agent's LiDAR frame, 128 x 128
x 20 voxels of 0.78125 x 0.78125 x 0.4 m (the paper's "0.78 m" is 100 m / 128), indexed
``[ix, iy, iz]`` with ``ix = floor((x + 50) / 0.78125)`` etc. Classes (:data:`SSC_CLASSES`):
0 empty, 1 road (drivable), 2 car (every vehicle), 3 terrain (open ground, sidewalks),
4 building, 5 vegetation, 6 pole (poles, signs, tree trunks).

**Ground truth from geometry, not points** (V2VSSC §III: each element's 3D extent is taken from
the simulator, projected into the CAV frame and voxelized): a voxel holds a class when one of
that class's solids contains any of the voxel's :data:`SUBSAMPLE` (4 x 4 x 2) sub-cell centres.
Solids are the town's (:mod:`typ.sim.solids`, world frame) plus every vehicle's box. Thin
solids (poles of 4-11 cm radius, sign plates) are widened to at least :data:`MIN_WIDTH` across
in x and y and :data:`MIN_HEIGHT` in z before the test, which is what guarantees that the
sub-cell lattice (0.195 m x 0.2 m) cannot step over them at any yaw. Overlaps go to the
highest class in :data:`PRIORITY` (V2VSSC: cars, drivable, poles, vegetation, buildings,
terrain). Tree trunks are pole below the canopy's lowest point and vegetation above it.

**Storage** (:func:`write_occupancy` / :func:`read_occupancy`): beside each agent's cloud in the
OPV2V layout, ``<scenario>/<agent>/<timestamp>_semantic_occupancy.npz`` (:data:`SUFFIX`), an
``np.savez_compressed`` archive (no pickles) holding:

- ``shape`` (3,) int64, the grid's voxel counts ``(X, Y, Z)``;
- ``index`` (N,) int64, flat C-order indices ``(ix * Y + iy) * Z + iz`` of the non-empty voxels, ascending;
- ``label`` (N,) uint8, their class ids in 1 .. 6;
- ``lower``, ``upper`` (3,) float64, the grid's bounds in metres (checked against the reader's grid).

Every voxel not listed is empty (0). Any folder with this layout and files reads the same way.
"""
from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from typ.errors import TypError
from typ.io import atomic_path
from typ.metrics.ssc import SSC_CLASSES, SSC_CODE
from typ.scene import SEMANTIC_CODE
from typ.sim.solids import Solids

__all__ = ["MIN_HEIGHT", "MIN_WIDTH", "PRIORITY", "SSC_CLASSES", "SSC_CODE", "SSC_GRID", "SUBSAMPLE", "SUFFIX",
           "SscGrid", "occupancy_path", "rasterize", "read_occupancy", "scene_occupancy", "write_occupancy"]

#: classes from the highest priority down: on overlap, the first wins (V2VSSC §III)
PRIORITY: tuple[str, ...] = ("car", "road", "pole", "vegetation", "building", "terrain")
#: sub-cell centres tested per voxel along x, y, z
SUBSAMPLE = (4, 4, 2)
#: solids are widened to at least this (m) across in x and y ...
MIN_WIDTH = 0.28
#: ... and this tall (m), so that the sub-cell lattice cannot miss them
MIN_HEIGHT = 0.2
#: file name of a frame's map, after the timestamp
SUFFIX = "_semantic_occupancy.npz"
#: the simulator's semantic codes (typ.scene) -> SSC class ids
_FROM_SEMANTIC = {SEMANTIC_CODE["ground"]: SSC_CODE["terrain"], SEMANTIC_CODE["road"]: SSC_CODE["road"],
                  SEMANTIC_CODE["building"]: SSC_CODE["building"], SEMANTIC_CODE["vegetation"]: SSC_CODE["vegetation"],
                  SEMANTIC_CODE["pole"]: SSC_CODE["pole"], SEMANTIC_CODE["vehicle"]: SSC_CODE["car"]}


@dataclass(frozen=True)
class SscGrid:
    """An axis-aligned voxel grid in the agent's sensor frame: ``lower``/``upper`` bounds (m), ``shape``."""

    lower: tuple[float, float, float] = (-50.0, -50.0, -3.0)
    upper: tuple[float, float, float] = (50.0, 50.0, 5.0)
    shape: tuple[int, int, int] = (128, 128, 20)

    @property
    def voxel(self) -> np.ndarray:
        """(3,) float64 voxel size (m)."""
        return (np.array(self.upper) - np.array(self.lower)) / np.array(self.shape)

    def centres(self, axis: int) -> np.ndarray:
        """(shape[axis],) float64 voxel centres along ``axis``."""
        return self.lower[axis] + (np.arange(self.shape[axis]) + 0.5) * self.voxel[axis]


#: V2VSSC's grid
SSC_GRID = SscGrid()


def _sub_centres(grid: SscGrid, axis: int, i0: int, i1: int) -> np.ndarray:
    """Sub-cell centres of voxels ``[i0, i1)`` along ``axis``, (i1 - i0, SUBSAMPLE[axis]) float64."""
    s, v = SUBSAMPLE[axis], grid.voxel[axis]
    return grid.lower[axis] + (np.arange(i0, i1)[:, None] + (np.arange(s)[None] + 0.5) / s) * v


def _rasterize_solid(hit: np.ndarray, grid: SscGrid, pose: np.ndarray, inv: np.ndarray,
                     world_lo: np.ndarray, world_hi: np.ndarray, inside) -> None:
    """Mark in ``hit`` (X, Y, Z) bool the voxels with a sub-cell centre for which ``inside(x, y, z)``
    (world coordinates, broadcast arrays) is True; ``world_lo``/``world_hi`` bound the solid."""
    corners = np.array(np.meshgrid(*zip(world_lo, world_hi), indexing="ij")).reshape(3, -1)
    local = inv[:3, :3] @ corners + inv[:3, 3:4]
    lo = np.floor((local.min(axis=1) - grid.lower) / grid.voxel).astype(int)
    hi = np.floor((local.max(axis=1) - grid.lower) / grid.voxel).astype(int) + 1
    lo, hi = np.maximum(lo, 0), np.minimum(hi, grid.shape)
    if (hi <= lo).any():
        return
    cx, cy, cz = (_sub_centres(grid, a, lo[a], hi[a]).reshape(-1) for a in range(3))
    x, y, z = cx[:, None, None], cy[None, :, None], cz[None, None, :]
    r, t = pose[:3, :3], pose[:3, 3]
    wx = r[0, 0] * x + r[0, 1] * y + r[0, 2] * z + t[0]
    wy = r[1, 0] * x + r[1, 1] * y + r[1, 2] * z + t[1]
    wz = r[2, 0] * x + r[2, 1] * y + r[2, 2] * z + t[2]
    inn = inside(wx, wy, wz)
    n = hi - lo
    inn = np.broadcast_to(inn, (len(cx), len(cy), len(cz))).reshape(n[0], SUBSAMPLE[0], n[1], SUBSAMPLE[1],
                                                                   n[2], SUBSAMPLE[2])
    hit[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] |= inn.any(axis=(1, 3, 5))


def _widen(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Grow an interval box about its centre to at least MIN_WIDTH x MIN_WIDTH x MIN_HEIGHT."""
    need = np.array([MIN_WIDTH, MIN_WIDTH, MIN_HEIGHT])
    grow = np.maximum(need - (hi - lo), 0.0) / 2.0
    return lo - grow, hi + grow


def rasterize(solids: Solids, vehicle_boxes: np.ndarray, pose: np.ndarray, grid: SscGrid = SSC_GRID) -> np.ndarray:
    """(X, Y, Z) uint8 semantic occupancy of one agent (:data:`SSC_CLASSES` ids) on ``grid``.

    solids: the static town in world coordinates, codes from :data:`typ.scene.SEMANTIC_CODE`;
    vehicle_boxes: (M, 7) world ``[x, y, z, l, w, h, yaw]`` (z the box centre), all class car;
    pose: (4, 4) float64 the agent's sensor-to-world. Rules in the module docstring.
    """
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise TypError("typ.ssc.rasterize", "pose", "a finite (4, 4) sensor-to-world matrix", pose.shape)
    inv = np.linalg.inv(pose)
    hits = {name: np.zeros(grid.shape, dtype=bool) for name in PRIORITY}
    names = {SSC_CODE[n]: n for n in PRIORITY}
    for (x0, y0, z0, x1, y1, z1), code in zip(solids.boxes, solids.box_code):
        lo, hi = _widen(np.array([x0, y0, z0]), np.array([x1, y1, z1]))
        _rasterize_solid(hits[names[_FROM_SEMANTIC[int(code)]]], grid, pose, inv, lo, hi,
                         lambda x, y, z, lo=lo, hi=hi: ((x >= lo[0]) & (x < hi[0]) & (y >= lo[1]) & (y < hi[1])
                                                        & (z >= lo[2]) & (z < hi[2])))
    for (x, y, z0, z1, rad), code in zip(solids.cylinders, solids.cylinder_code):
        lo, hi = _widen(np.array([x - rad, y - rad, z0]), np.array([x + rad, y + rad, z1]))
        rr = (hi[0] - lo[0]) / 2.0
        _rasterize_solid(hits[names[_FROM_SEMANTIC[int(code)]]], grid, pose, inv, lo, hi,
                         lambda wx, wy, wz, c=(x, y), rr=rr, lo=lo, hi=hi:
                         ((wx - c[0]) ** 2 + (wy - c[1]) ** 2 < rr * rr) & (wz >= lo[2]) & (wz < hi[2]))
    for (cx, cy, cz, rx, ry, rz), code in zip(solids.ellipsoids, solids.ellipsoid_code):
        r = np.maximum([rx, ry, rz], [MIN_WIDTH / 2, MIN_WIDTH / 2, MIN_HEIGHT / 2])
        c = np.array([cx, cy, cz])
        _rasterize_solid(hits[names[_FROM_SEMANTIC[int(code)]]], grid, pose, inv, c - r, c + r,
                         lambda x, y, z, c=c, r=r: ((x - c[0]) / r[0]) ** 2 + ((y - c[1]) / r[1]) ** 2
                         + ((z - c[2]) / r[2]) ** 2 < 1.0)
    for x, y, z, length, width, height, yaw in np.asarray(vehicle_boxes, dtype=np.float64).reshape(-1, 7):
        half = np.maximum([length / 2, width / 2, height / 2], [MIN_WIDTH / 2, MIN_WIDTH / 2, MIN_HEIGHT / 2])
        reach = np.hypot(half[0], half[1])
        cos, sin = np.cos(yaw), np.sin(yaw)
        _rasterize_solid(hits["car"], grid, pose, inv, np.array([x - reach, y - reach, z - half[2]]),
                         np.array([x + reach, y + reach, z + half[2]]),
                         lambda wx, wy, wz, c=(x, y, z), h=half, cs=(cos, sin):
                         (np.abs((wx - c[0]) * cs[0] + (wy - c[1]) * cs[1]) < h[0])
                         & (np.abs(-(wx - c[0]) * cs[1] + (wy - c[1]) * cs[0]) < h[1])
                         & (wz >= c[2] - h[2]) & (wz < c[2] + h[2]))
    labels = np.zeros(grid.shape, dtype=np.uint8)
    for name in reversed(PRIORITY):  # lowest priority first, higher ones overwrite it
        labels[hits[name]] = SSC_CODE[name]
    return labels


def scene_occupancy(*, domain: str, seed: int, n_frames: int, n_agents: int, comm_range: float = 70.0,
                    dt: float = 0.1, grid: SscGrid = SSC_GRID) -> list[list[np.ndarray]]:
    """Semantic occupancy of every agent at every frame of the scenario that
    :func:`typ.sim.simulate_scenario` builds from the same arguments: ``[frame][agent]`` (X, Y, Z)
    uint8, agents in the scenario's order (ego first), from its true geometry."""
    from typ.sim import scenario_world  # the simulator only where maps are made, not where they are read

    town, traffic, poses = scenario_world(domain=domain, seed=seed, n_frames=n_frames, n_agents=n_agents,
                                          comm_range=comm_range, dt=dt)
    return [[rasterize(town.solids, traffic.boxes(f), poses[f, a], grid) for a in range(poses.shape[1])]
            for f in range(n_frames)]


def occupancy_path(scenario_dir: str | os.PathLike, agent: str, timestamp: str) -> Path:
    """``<scenario_dir>/<agent>/<timestamp>_semantic_occupancy.npz``."""
    return Path(scenario_dir) / str(agent) / f"{timestamp}{SUFFIX}"


def write_occupancy(path: str | os.PathLike, labels: np.ndarray, grid: SscGrid = SSC_GRID) -> Path:
    """Write one (X, Y, Z) map of class ids in the sparse format of the module docstring, atomically."""
    labels = np.asarray(labels)
    _check_labels(labels, grid, "typ.ssc.write_occupancy", "labels")
    flat = labels.reshape(-1)
    index = np.flatnonzero(flat)
    path = Path(path)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, shape=np.array(grid.shape, dtype=np.int64), index=index.astype(np.int64),
                                label=flat[index].astype(np.uint8), lower=np.array(grid.lower, dtype=np.float64),
                                upper=np.array(grid.upper, dtype=np.float64))
    return path


def _check_labels(labels: np.ndarray, grid: SscGrid, where, field: str) -> None:
    if labels.shape != tuple(grid.shape):
        raise TypError(where, field, f"a semantic occupancy map of shape {tuple(grid.shape)}", labels.shape)
    if not np.issubdtype(labels.dtype, np.integer) or labels.dtype == bool:
        raise TypError(where, field, "integer class ids", labels.dtype)
    bad = (labels < 0) | (labels >= len(SSC_CLASSES))
    if bad.any():
        raise TypError(where, field, f"class ids in 0..{len(SSC_CLASSES) - 1} {SSC_CLASSES}", int(labels[bad][0]))


def read_occupancy(path: str | os.PathLike, grid: SscGrid = SSC_GRID) -> np.ndarray:
    """(X, Y, Z) uint8 map written by :func:`write_occupancy`; TypError naming the file and field
    when it is missing, unreadable, of another grid shape or bounds, or holds an unknown class id."""
    path = Path(path)
    if not path.is_file():
        raise TypError(path, "file", f"a semantic occupancy map ({SUFFIX}, made by the ssc stage's ground truth)",
                       "missing")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in ("shape", "index", "label", "lower", "upper") if k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise TypError(path, "file", "an .npz archive", f"{type(e).__name__}: {e}") from None
    for key in ("shape", "index", "label", "lower", "upper"):
        if key not in data:
            raise TypError(path, key, "an array (keys shape, index, label, lower, upper)", "missing")
    shape = tuple(int(v) for v in np.asarray(data["shape"]).reshape(-1))
    if shape != tuple(grid.shape):
        raise TypError(path, "shape", f"a semantic occupancy map of shape {tuple(grid.shape)}", shape)
    for key, want in (("lower", grid.lower), ("upper", grid.upper)):
        if np.asarray(data[key]).shape != (3,) or not np.allclose(data[key], want):
            raise TypError(path, key, f"grid bounds {want}", np.asarray(data[key]).tolist())
    index, label = np.asarray(data["index"]), np.asarray(data["label"])
    if index.ndim != 1 or label.shape != index.shape or not np.issubdtype(index.dtype, np.integer):
        raise TypError(path, "index", "(N,) integer indices with (N,) labels", (index.shape, label.shape))
    size = int(np.prod(shape))
    if index.size and (index.min() < 0 or index.max() >= size):
        raise TypError(path, "index", f"flat indices in [0, {size})", int(index.max()))
    bad = (label < 1) | (label >= len(SSC_CLASSES))
    if bad.any():
        raise TypError(path, "label", f"class ids in 1..{len(SSC_CLASSES) - 1} {SSC_CLASSES[1:]}", int(label[bad][0]))
    out = np.zeros(size, dtype=np.uint8)
    out[index] = label
    return out.reshape(shape)
