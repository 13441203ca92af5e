"""BEV voxel grids (TYP §3.2): point clouds -> occupancy ``x``, boxes -> box maps ``y``.

A :class:`Grid` is an axis-aligned box in one agent's sensor frame (x forward, y left,
z up, metres) cut into ``shape = (H, W, C)`` voxels: H along x, W along y and C height
channels along z. The paper's grid is 512×512×20 over [-51.2, 51.2] m in x and y and
4 m in z, e.g. ``Grid((-51.2, 51.2), (-51.2, 51.2), (-3.0, 1.0), (512, 512, 20))``
(:data:`PAPER_GRID`); the tiny profile uses 128×128×8 over the same box (:data:`TINY_GRID`).

Bin convention, per axis with ``n`` bins over ``[lo, hi)`` and ``size = (hi - lo) / n``:
bin ``i`` is the half-open interval ``[e_i, e_{i+1})`` with edges ``e_i = lo + i*size``
evaluated in float64, intersected with ``[lo, hi)``. The lower edge of every bin is
included and ``hi`` is excluded; a point on the last edge ``e_n`` (or in the ulp-sized gap
between ``e_n`` and ``hi`` when rounding puts them apart) is dropped, as is a point with any
coordinate outside ``[lo, hi)``. :func:`voxelize` computes ``floor((p - lo) / size)`` in
float64 and then compares the point with that bin's ``e_i`` and ``e_{i+1}``, so a point within
rounding of an edge lands where the interval definition puts it, not where the division
happens to round (plain floor division misplaces about 1 in 10 exact edges of PAPER_GRID).
"""
from __future__ import annotations

import functools
import math
import numbers
from dataclasses import dataclass

import numpy as np

from typ import geometry
from typ.errors import TypError
from typ.io import hash_obj

# A box-map cell centre within this distance (metres) of a box edge counts as inside:
# cos/sin of the yaw are rounded, so a centre exactly on a rotated edge would otherwise
# fall in or out by a few ulps.
BOX_EDGE_SLACK = 1e-9


def _check_range(value, field: str) -> tuple[float, float]:
    try:
        lo, hi = value
    except (TypeError, ValueError):
        raise TypError("grid", field, "a pair (min, max) of finite metres", value) from None
    for v in (lo, hi):
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v):
            raise TypError("grid", field, "a pair (min, max) of finite metres", value)
    if not lo < hi:
        raise TypError("grid", field, "min < max", value)
    return float(lo), float(hi)


#: voxels of a grid: the paper's is 512 x 512 x 20 = 5.2 M; every stage holds a few grids of them
MAX_VOXELS = 1 << 26


def _check_shape(value) -> tuple[int, int, int]:
    try:
        dims = tuple(value)
    except TypeError:
        raise TypError("grid", "shape", "three positive ints (H, W, C)", value) from None
    if len(dims) != 3 or any(isinstance(d, bool) or not isinstance(d, numbers.Integral) or d < 1 for d in dims):
        raise TypError("grid", "shape", "three positive ints (H, W, C)", value)
    if math.prod(int(d) for d in dims) > MAX_VOXELS:
        raise TypError("grid", "shape", f"at most {MAX_VOXELS} voxels (H x W x C)", value)
    return int(dims[0]), int(dims[1]), int(dims[2])


@dataclass(frozen=True)
class Grid:
    """A BEV voxel grid in a sensor frame (x forward, y left, z up, metres).

    x_range, y_range, z_range: ``(min, max)`` metres, finite, min < max.
    shape: ``(H, W, C)``: H bins along x, W along y, C height channels along z.
    """

    x_range: tuple[float, float]
    y_range: tuple[float, float]
    z_range: tuple[float, float]
    shape: tuple[int, int, int]

    def __post_init__(self) -> None:
        # Normalise to plain floats/ints so equality, hashing and digest() are stable.
        object.__setattr__(self, "x_range", _check_range(self.x_range, "x_range"))
        object.__setattr__(self, "y_range", _check_range(self.y_range, "y_range"))
        object.__setattr__(self, "z_range", _check_range(self.z_range, "z_range"))
        object.__setattr__(self, "shape", _check_shape(self.shape))
        # voxelize() corrects the float64 division by at most one bin; that is exact as long
        # as rounding of the edges (~1e-16 of the coordinates) stays far below one voxel.
        for axis, field in enumerate(("x_range", "y_range", "z_range")):
            lo, hi = getattr(self, field)
            if (hi - lo) / self.shape[axis] < 1e-9 * max(abs(lo), abs(hi)):
                raise TypError("grid", field, "voxels at least 1e-9 of the coordinate magnitude",
                               ((lo, hi), self.shape[axis]))

    @property
    def lower(self) -> np.ndarray:
        """(3,) float64 ``[x_min, y_min, z_min]``."""
        return np.array([self.x_range[0], self.y_range[0], self.z_range[0]])

    @property
    def upper(self) -> np.ndarray:
        """(3,) float64 ``[x_max, y_max, z_max]``."""
        return np.array([self.x_range[1], self.y_range[1], self.z_range[1]])

    @property
    def voxel_size(self) -> np.ndarray:
        """(3,) float64 voxel edge lengths ``(max - min) / n`` along x, y, z (metres)."""
        return (self.upper - self.lower) / np.array(self.shape, dtype=np.float64)

    def edges(self, axis: int) -> np.ndarray:
        """(n + 1,) float64 bin edges ``min + i*size`` along ``axis`` (0 = x, 1 = y, 2 = z)."""
        return self.lower[axis] + np.arange(self.shape[axis] + 1, dtype=np.float64) * self.voxel_size[axis]

    def centers(self, axis: int) -> np.ndarray:
        """(n,) float64 bin centres ``min + (i + 0.5)*size`` along ``axis``."""
        return self.lower[axis] + (np.arange(self.shape[axis], dtype=np.float64) + 0.5) * self.voxel_size[axis]

    def to_dict(self) -> dict:
        """JSON-able ``{"x_range": [min, max], ..., "shape": [H, W, C]}``."""
        return {"x_range": list(self.x_range), "y_range": list(self.y_range),
                "z_range": list(self.z_range), "shape": list(self.shape)}

    @classmethod
    def from_dict(cls, d, where: str = "grid") -> Grid:
        """Inverse of :meth:`to_dict`; a missing or unknown key raises TypError naming ``where``."""
        keys = {"x_range", "y_range", "z_range", "shape"}
        if not isinstance(d, dict) or set(d) != keys:
            got = sorted(d) if isinstance(d, dict) else type(d).__name__
            raise TypError(where, "grid", f"a mapping with exactly the keys {sorted(keys)}", got)
        return cls(tuple(d["x_range"]), tuple(d["y_range"]), tuple(d["z_range"]), tuple(d["shape"]))

    def for_sensor(self, mount_height: float) -> Grid:
        """This grid, whose z range is height above the ground under the sensor, expressed in
        the frame of a sensor ``mount_height`` m above that ground (TYP §4.1: the z range is
        dataset-dependent). Every domain's ground then falls in the same height channel, and
        ``voxel_centers`` on the returned grid gives points in that sensor's own frame."""
        if isinstance(mount_height, bool) or not isinstance(mount_height, numbers.Real) \
                or not math.isfinite(mount_height) or mount_height < 0:
            raise TypError("grid", "mount_height", "a finite height >= 0 in metres", mount_height)
        lo, hi = self.z_range
        return Grid(self.x_range, self.y_range, (lo - float(mount_height), hi - float(mount_height)), self.shape)

    def digest(self) -> str:
        """Stable 16-hex-digit id of the grid (sha256 of :meth:`to_dict`), for cache keys."""
        return hash_obj(self.to_dict())[:16]


PAPER_GRID = Grid((-51.2, 51.2), (-51.2, 51.2), (-3.0, 1.0), (512, 512, 20))
TINY_GRID = Grid((-51.2, 51.2), (-51.2, 51.2), (-3.0, 1.0), (128, 128, 8))


@functools.cache
def _scatter():
    """:func:`_scatter_points` compiled, on first use: importing numba takes a few tenths of a
    second that a stage which voxelizes nothing (every scene unchanged) should not pay."""
    import numba

    return numba.njit(cache=True, nogil=True, boundscheck=False, error_model="numpy")(_scatter_points)


def _scatter_points(points, lo, hi, inv, ex, ey, ez, flat, nx, ny, nz):
    """Set ``flat[(i*ny + j)*nz + k]`` for every in-range point; returns the non-finite row count."""
    lx, ly, lz = lo[0], lo[1], lo[2]
    hx, hy, hz = hi[0], hi[1], hi[2]
    one, unx, uny, unz = np.uint64(1), np.uint64(nx), np.uint64(ny), np.uint64(nz)
    bad = 0
    for row in range(points.shape[0]):
        x = np.float64(points[row, 0])
        y = np.float64(points[row, 1])
        z = np.float64(points[row, 2])
        # Bitwise & keeps this to one branch; NaN fails every comparison and so lands in
        # the out-of-range path, where it is counted instead of binned.
        if not ((x >= lx) & (x < hx) & (y >= ly) & (y < hy) & (z >= lz) & (z < hz)):
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                bad += 1
            continue
        # The division picks the bin; one comparison with each of its edges moves a point
        # that lies within rounding of an edge to where [e_i, e_{i+1}) puts it (Grid keeps
        # voxels coarse enough that rounding is far below one bin). Unsigned indices skip
        # numba's negative-index wraparound; e_0 == lo <= p, so i - 1 never underflows.
        i = np.uint64(min(np.int64((x - lx) * inv[0]), nx - 1))
        j = np.uint64(min(np.int64((y - ly) * inv[1]), ny - 1))
        k = np.uint64(min(np.int64((z - lz) * inv[2]), nz - 1))
        i = i - np.uint64(x < ex[i]) + np.uint64(x >= ex[i + one])
        j = j - np.uint64(y < ey[j]) + np.uint64(y >= ey[j + one])
        k = k - np.uint64(z < ez[k]) + np.uint64(z >= ez[k + one])
        if (i < unx) & (j < uny) & (k < unz):
            flat[(i * uny + j) * unz + k] = True
    return bad


def _check_points(points, field: str = "points") -> np.ndarray:
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise TypError(None, field, "array of shape (N, >=3) [x, y, z, ...]", arr.shape)
    if arr.dtype not in (np.float32, np.float64):
        raise TypError(None, field, "dtype float32 or float64", arr.dtype)
    return arr


def voxelize(points, grid: Grid) -> np.ndarray:
    """Occupancy ``x`` (TYP §3.2): (N, >=3) points -> (H, W, C) bool, same sensor frame as ``grid``.

    points: (N, >=3) float32 or float64 ``[x, y, z, ...]`` in the grid's sensor frame; columns
    past z are ignored. A voxel is True when at least one point falls in it (bins as in the
    module doc; points outside the grid are dropped). Indices are computed in float64 whatever
    the input dtype. NaN/Inf in x, y or z raises TypError (field ``points``) with the number of
    bad rows. Runs as one compiled pass over the points with O(1) extra memory, so 10 M points
    cost only the output grid.
    """
    arr = _check_points(points)
    out = np.zeros(grid.shape, dtype=bool)
    lo, hi = grid.lower, grid.upper
    bad = _scatter()(arr, lo, hi, 1.0 / grid.voxel_size, grid.edges(0), grid.edges(1), grid.edges(2),
                     out.reshape(-1), *grid.shape)
    if bad:
        raise TypError(None, "points", "finite x, y, z (no NaN/Inf)", f"{bad} rows with NaN/Inf")
    return out


def voxel_centers(occupancy, grid: Grid) -> np.ndarray:
    """Occupied voxels -> points (TYP §3.5): (H, W, C) bool -> (M, 3) float64 voxel centres.

    Centres are ``min + (i + 0.5)*size`` per axis in the grid's sensor frame, in C order of
    (i, j, k), so ``voxelize(voxel_centers(x, grid), grid) == x``.
    """
    occ = np.asarray(occupancy)
    if occ.shape != grid.shape or occ.dtype != bool:
        raise TypError(None, "occupancy", f"{grid.shape} bool array", f"{occ.shape} {occ.dtype}")
    i, j, k = np.nonzero(occ)
    idx = np.stack([i, j, k], axis=1).astype(np.float64)
    return grid.lower + (idx + 0.5) * grid.voxel_size


def box_map(boxes, grid: Grid) -> np.ndarray:
    """Box map ``y`` (TYP §3.2): (K, 7) boxes -> (H, W, 1) bool BEV footprints.

    boxes: (K, 7) ``[x, y, z, l, w, h, yaw]`` in the grid's sensor frame (see
    :mod:`typ.geometry`); z and h are ignored, the map is the BEV footprint. Cell (i, j) is
    True when its centre ``(x_min + (i + 0.5)*sx, y_min + (j + 0.5)*sy)`` lies in the closed
    rotated rectangle of some box (with :data:`BOX_EDGE_SLACK` metres of slack). Boxes wholly
    or partly outside the grid are clipped to it. Each box tests only the cells in its
    axis-aligned bounding window.
    """
    b = np.asarray(boxes, dtype=np.float64)
    if b.size == 0:
        b = b.reshape(0, 7)
    if b.ndim != 2 or b.shape[1] != 7:
        raise TypError(None, "boxes", "array of shape (K, 7) [x, y, z, l, w, h, yaw]", b.shape)
    if not np.isfinite(b).all():
        raise TypError(None, "boxes", "finite box parameters", f"{int((~np.isfinite(b)).any(axis=1).sum())} bad rows")
    if (b[:, 3:5] <= 0).any():
        raise TypError(None, "boxes", "positive sizes l and w", b[(b[:, 3:5] <= 0).any(axis=1)][:1])
    H, W, _ = grid.shape
    out = np.zeros((H, W, 1), dtype=bool)
    (x0, y0, _), (sx, sy, _) = grid.lower, grid.voxel_size
    cx, cy = grid.centers(0), grid.centers(1)
    for x, y, _, length, width, _, yaw in b:
        c, s = math.cos(yaw), math.sin(yaw)
        hl, hw = length / 2.0 + BOX_EDGE_SLACK, width / 2.0 + BOX_EDGE_SLACK
        ax, ay = abs(c) * hl + abs(s) * hw, abs(s) * hl + abs(c) * hw  # half extents of the AABB
        # Index window of the centres inside the AABB (floor/ceil keep it a superset despite
        # rounding), clipped in float first so boxes far outside cannot overflow the int cast.
        i0, i1 = np.clip([math.floor((x - ax - x0) / sx - 0.5), math.ceil((x + ax - x0) / sx - 0.5)], -1, H)
        j0, j1 = np.clip([math.floor((y - ay - y0) / sy - 0.5), math.ceil((y + ay - y0) / sy - 0.5)], -1, W)
        i0, j0, i1, j1 = max(int(i0), 0), max(int(j0), 0), min(int(i1), H - 1), min(int(j1), W - 1)
        if i0 > i1 or j0 > j1:
            continue
        dx = cx[i0:i1 + 1, None] - x
        dy = cy[None, j0:j1 + 1] - y
        along = dx * c + dy * s     # centre in the box's own frame
        across = dy * c - dx * s
        out[i0:i1 + 1, j0:j1 + 1, 0] |= (np.abs(along) <= hl) & (np.abs(across) <= hw)
    return out


def points_to_reference(points, ego_pose, reference_pose) -> np.ndarray:
    """``x_{e'}``: ego points (N, >=3, ego sensor frame) -> the reference agent's sensor frame.

    ego_pose, reference_pose: sensor-to-world, as 6-vector poses or (4, 4) matrices (see
    :mod:`typ.geometry`). The move is float64 (``relative_transform(ego_pose,
    reference_pose)``); the result is cast back to the input's float dtype only afterwards.
    Columns past z (intensity, ...) are kept unchanged.
    """
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] < 3:
        raise TypError(None, "points", "array of shape (N, >=3) [x, y, z, ...]", arr.shape)
    moved = geometry.transform_points(geometry.relative_transform(ego_pose, reference_pose), arr)
    dtype = arr.dtype if np.issubdtype(arr.dtype, np.floating) else np.float64
    return moved.astype(dtype, copy=False)
