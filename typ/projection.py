"""LiDAR images for pixel-space diffusion (LiDAR DDPM §III-C): the BEV image and the
equirectangular range image, each with its inverse back to points.

Both are pure functions of arrays. Points are (N, >=3) float32/float64 ``[x, y, z, ...]`` in
the sensor frame (x forward, y left, z up, metres, sensor at the origin); columns past z
are ignored except where a function takes per-point ``values`` (e.g. semantic codes).

**Range image** (:class:`RangeLayout`, :func:`range_image`, :func:`range_to_points`): rows
are the sensor's beams, top row = highest beam; columns are ``W`` equal azimuth bins, bin
``c`` centred on ``φ_c = -π + c·2π/W`` (the simulator's azimuth grid when W matches its
step). A point at depth ``d = |xyz|``, elevation ``ε = asin(z/d)`` and azimuth
``φ = atan2(y, x)`` goes to the beam whose elevation is nearest and the bin whose centre is
nearest; the pixel keeps the *nearest* point (what a LiDAR would have returned), and its
value is ``d`` in metres (0 = no return). Points with ``d`` outside
``[min_range, max_range)`` or an elevation more than half the outer beam gap beyond the
outermost beams are dropped. The inverse puts a point at ``d`` along the pixel-centre ray.

*Error bound* of the round trip, per kept point (the nearest of its pixel): with α the
angle between its ray and the pixel-centre ray, the reconstruction is ``2·d·sin(α/2) <= d·α``
from it, and α <= ``half_gap[row] + π/W`` (elevation off by at most half the gap to the
neighbouring beam, azimuth by half a bin, the latter shrunk by cos ε on the sphere); float32
storage adds at most ``4e-7·d`` (:meth:`RangeLayout.error_bound`). Points that lie on the
layout's rays (the simulator's, with W = its azimuth count) come back to float32 rounding.
Points that shared a pixel with a nearer one are not reconstructed; :func:`range_image`
reports how many.

**BEV image** (:func:`bev_image`, :func:`bev_to_points`): an orthographic projection along z
onto the (H, W) cells of a :class:`typ.voxel.Grid` with ``shape (H, W, 1)`` (bins as in
:mod:`typ.voxel`: ``[e_i, e_{i+1})``, points outside x/y/z ranges dropped). Two channels:
occupancy (1 where any point fell) and the height of the highest point in the cell (``z_min``
of the grid where empty). The inverse puts one point per occupied cell at the cell centre
and that height. *Error bound*: every input point has a reconstructed point in its own
column at most half a cell away in x and in y and not below it; the highest point of each
column comes back within ``sqrt(sx² + sy²)/2`` in xy and exactly in z.

Both inverses are exact on images: ``range_image(range_to_points(R)) == R`` (to float32
rounding of the depth) and ``bev_image(bev_to_points(B)) == B`` for any image in canonical
form (depths 0 or in [min_range, max_range); occupancy 0/1, heights in the z range).

:func:`to_unit` / :func:`from_unit` map the images to and from the [-1, 1] pixels a
diffusion model sees (from_unit also canonicalises generated images). A range image's depth is
encoded linearly or, as R2DM and LiDARGen do, on a log scale (``depth="log"``); both send "no
return" to -1, and both round-trip a canonical image to float32 rounding.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from typ.errors import TypError
from typ.metrics.truth import check_points
from typ.voxel import Grid

__all__ = ["DEPTH_ENCODINGS", "HDL32E", "HDL64E", "RangeLayout", "RangePixels", "bev_image", "bev_to_points",
           "from_unit", "no_return_threshold", "range_image", "range_pixels", "range_to_points", "to_unit",
           "voxel_indices"]

#: float32 storage of depth and coordinates: relative error of the round trip beyond the angles
FLOAT32_SLACK = 4e-7


def _cloud(points, where: str) -> np.ndarray:
    """(N >= 1, >=3) finite float points, else TypError naming ``where`` (NaN points, empty cloud)."""
    arr = check_points(points, where, "points")
    if len(arr) == 0:
        raise TypError(where, "points", "at least one point", "an empty cloud (0 points)")
    return arr


def _values(values, n: int, where: str) -> np.ndarray:
    arr = np.asarray(values)
    if arr.shape != (n,):
        raise TypError(where, "values", f"one value per point, shape ({n},)", arr.shape)
    return arr


@dataclass(frozen=True)
class RangeLayout:
    """Rows and columns of an equirectangular range image.

    elevations_deg: beam elevations, ascending (as :class:`typ.sim.SensorSpec` lists them);
    row 0 of the image is the last (highest) one. azimuth_bins: W. max_range, min_range:
    depths kept, metres (``min_range`` > 0, so that 0 can mean "no return").
    """

    elevations_deg: tuple[float, ...]
    azimuth_bins: int
    max_range: float
    min_range: float = 0.5
    name: str = ""

    def __post_init__(self) -> None:
        where = f"range layout {self.name}".strip()
        e = np.asarray(self.elevations_deg, dtype=np.float64)
        if e.ndim != 1 or len(e) < 2 or not np.all(np.isfinite(e)) or not np.all(np.abs(e) < 90) \
                or not np.all(np.diff(e) > 0):
            raise TypError(where, "elevations_deg", ">= 2 ascending beam elevations in (-90, 90) degrees",
                           self.elevations_deg)
        object.__setattr__(self, "elevations_deg", tuple(float(v) for v in e))
        if isinstance(self.azimuth_bins, bool) or not isinstance(self.azimuth_bins, (int, np.integer)) \
                or self.azimuth_bins < 4:
            raise TypError(where, "azimuth_bins", "an integer >= 4", self.azimuth_bins)
        object.__setattr__(self, "azimuth_bins", int(self.azimuth_bins))
        if not (math.isfinite(self.min_range) and math.isfinite(self.max_range) and 0 < self.min_range < self.max_range):
            raise TypError(where, "min_range/max_range", "0 < min_range < max_range metres",
                           [self.min_range, self.max_range])

    @classmethod
    def from_sensor(cls, sensor, azimuth_bins: int | None = None) -> "RangeLayout":
        """The layout of a :class:`typ.sim.SensorSpec`: its beams, its azimuth count unless
        ``azimuth_bins`` is given, its ranges (min_range at least 0.5 m so that 0 stays "empty")."""
        return cls(tuple(sensor.elevations_deg), azimuth_bins or sensor.n_azimuths, float(sensor.max_range),
                   max(float(sensor.min_range), 0.5), sensor.name)

    @property
    def height(self) -> int:
        return len(self.elevations_deg)

    @property
    def width(self) -> int:
        return self.azimuth_bins

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    def row_elevations(self) -> np.ndarray:
        """(H,) float64 radians, row 0 = highest beam."""
        return np.radians(np.asarray(self.elevations_deg[::-1]))

    def column_azimuths(self) -> np.ndarray:
        """(W,) float64 radians, bin centres ``-π + c·2π/W``."""
        return -math.pi + np.arange(self.width, dtype=np.float64) * (2.0 * math.pi / self.width)

    def half_gaps(self) -> np.ndarray:
        """(H,) float64 radians per row: the largest elevation error a point of that row can have
        (half the gap to a neighbouring beam; the outer rows accept as far outside as inside)."""
        e = np.radians(np.asarray(self.elevations_deg))
        gaps = np.diff(e) / 2.0
        per_beam = np.maximum(np.r_[gaps[0], gaps], np.r_[gaps, gaps[-1]])
        return per_beam[::-1]

    def error_bound(self, depth, row) -> np.ndarray:
        """Largest distance (metres) between a kept point of depth ``depth`` in ``row`` and its
        reconstruction: ``d·(half_gap[row] + π/W) + 4e-7·d`` (see the module doc)."""
        d = np.asarray(depth, dtype=np.float64)
        return d * (self.half_gaps()[np.asarray(row)] + math.pi / self.width) + FLOAT32_SLACK * d + 1e-6

    def to_dict(self) -> dict:
        return {"elevations_deg": list(self.elevations_deg), "azimuth_bins": self.width,
                "max_range": self.max_range, "min_range": self.min_range, "name": self.name}

    @classmethod
    def from_dict(cls, d: dict, where: str = "range layout") -> "RangeLayout":
        keys = {"elevations_deg", "azimuth_bins", "max_range", "min_range", "name"}
        if not isinstance(d, dict) or set(d) != keys:
            raise TypError(where, "layout", f"a mapping with the keys {sorted(keys)}",
                           sorted(d) if isinstance(d, dict) else d)
        return cls(tuple(d["elevations_deg"]), d["azimuth_bins"], d["max_range"], d["min_range"], d["name"])


#: Velodyne HDL-64E as in KITTI: 64 beams over its nominal +2.0 .. -24.8 deg (uniform here;
#: the real per-laser table differs, which the error bound absorbs), 120 m.
HDL64E = RangeLayout(tuple(float(v) for v in np.linspace(-24.8, 2.0, 64)), 1024, 120.0, 0.5, "hdl64e")
#: Velodyne HDL-32E as in nuScenes: 32 beams, -30.67 .. +10.67 deg in steps of 4/3 deg, 100 m.
HDL32E = RangeLayout(tuple(float(v) for v in np.linspace(-30.67, 10.67, 32)), 1024, 100.0, 0.5, "hdl32e")


@dataclass(frozen=True)
class RangePixels:
    """Where each point of a cloud lands: ``row``/``col`` (N,) int64, -1 for dropped points;
    ``depth`` (N,) float64; ``winner`` (N,) bool: the nearest point of its pixel."""

    row: np.ndarray
    col: np.ndarray
    depth: np.ndarray
    winner: np.ndarray

    @property
    def kept(self) -> int:
        return int(self.winner.sum())

    @property
    def inside(self) -> int:
        return int((self.row >= 0).sum())


def range_pixels(points, layout: RangeLayout, *, where: str = "range_image") -> RangePixels:
    """Each point's pixel in ``layout`` (see the module doc for the rules)."""
    arr = _cloud(points, where)
    xyz = arr[:, :3].astype(np.float64)
    depth = np.sqrt(np.einsum("ij,ij->i", xyz, xyz))
    ok = (depth >= layout.min_range) & (depth < layout.max_range)
    elevation = np.arcsin(np.clip(xyz[:, 2] / np.where(depth > 0, depth, 1.0), -1.0, 1.0))
    beams = np.radians(np.asarray(layout.elevations_deg))
    mids = (beams[1:] + beams[:-1]) / 2.0
    beam = np.searchsorted(mids, elevation)  # nearest beam, ascending index
    margin_low, margin_high = (beams[1] - beams[0]) / 2.0, (beams[-1] - beams[-2]) / 2.0
    ok &= (elevation >= beams[0] - margin_low) & (elevation <= beams[-1] + margin_high)
    step = 2.0 * math.pi / layout.width
    azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
    col = np.floor((azimuth + math.pi) / step + 0.5).astype(np.int64) % layout.width
    row = np.where(ok, layout.height - 1 - beam, -1)
    col = np.where(ok, col, -1)
    # nearest point per pixel: sort by (pixel, depth, index) and keep the first of each pixel
    flat = np.where(ok, row * layout.width + col, -1)
    idx = np.flatnonzero(ok)
    order = idx[np.lexsort((idx, depth[idx], flat[idx]))]
    first = np.ones(len(order), dtype=bool)
    first[1:] = flat[order][1:] != flat[order][:-1]
    winner = np.zeros(len(arr), dtype=bool)
    winner[order[first]] = True
    return RangePixels(row, col, depth, winner)


def range_image(points, layout: RangeLayout, *, values=None, fill=0, where: str = "range_image"):
    """Equirectangular range image: (N, >=3) points -> (H, W) float32 depth in metres, 0 = no return.

    values: optional (N,) per-point values (e.g. uint8 semantic codes); then returns
    ``(depth, value_image)`` with each pixel's value taken from the point it kept and ``fill``
    where empty. Raises TypError for NaN/Inf points or an empty cloud.
    """
    arr = _cloud(points, where)
    px = range_pixels(arr, layout, where=where)
    image = np.zeros(layout.shape, dtype=np.float32)
    w = px.winner
    image[px.row[w], px.col[w]] = px.depth[w].astype(np.float32)
    if values is None:
        return image
    vals = _values(values, len(arr), where)
    out = np.full(layout.shape, fill, dtype=vals.dtype)
    out[px.row[w], px.col[w]] = vals[w]
    return image, out


def _check_image(image, shape: tuple[int, ...], where: str, what: str) -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim != len(shape):
        raise TypError(where, "image", f"a {len(shape)}-D {what} of shape {shape}", arr.shape)
    if arr.shape[-2] != shape[-2]:
        raise TypError(where, "image", f"height {shape[-2]} = the layout's {what} rows (beam layout mismatch)",
                       arr.shape)
    if arr.shape != shape:
        raise TypError(where, "image", f"shape {shape}", arr.shape)
    if not np.issubdtype(arr.dtype, np.floating) or not np.isfinite(arr).all():
        raise TypError(where, "image", "finite floating-point pixels", str(arr.dtype))
    return arr


def range_to_points(image, layout: RangeLayout, *, where: str = "range_to_points") -> np.ndarray:
    """Inverse of :func:`range_image`: (H, W) depths -> (M, 3) float32 points on the pixel-centre rays.

    Pixels with depth outside ``[min_range, max_range)`` (0 = no return) give no point. An
    image whose height is not the layout's beam count raises TypError (beam layout mismatch).
    Points come in row-major pixel order.
    """
    img = _check_image(image, layout.shape, where, "beam")
    rows, cols = np.nonzero((img >= layout.min_range) & (img < layout.max_range))
    d = img[rows, cols].astype(np.float64)
    e, a = layout.row_elevations()[rows], layout.column_azimuths()[cols]
    xyz = np.stack([d * np.cos(e) * np.cos(a), d * np.cos(e) * np.sin(a), d * np.sin(e)], axis=1)
    return xyz.astype(np.float32)


def _bev_grid(grid: Grid, where: str) -> Grid:
    if not isinstance(grid, Grid) or grid.shape[2] != 1:
        raise TypError(where, "grid", "a typ.voxel.Grid with shape (H, W, 1)", getattr(grid, "shape", grid))
    return grid


def voxel_indices(points, grid: Grid) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per point: its voxel ``(i, j, k)`` in ``grid`` and whether it is inside, with
    :mod:`typ.voxel`'s bins (``floor``, then one comparison with each edge of that bin), so a
    point lands in the voxel :func:`typ.voxel.voxelize` marks. Indices of outside points are
    clipped into the grid; mask them with ``inside``."""
    xyz = np.asarray(points)[:, :3].astype(np.float64)
    lo, hi = grid.lower, grid.upper
    inside = np.all((xyz >= lo) & (xyz < hi), axis=1)
    out = []
    for axis in range(3):
        edges, n = grid.edges(axis), grid.shape[axis]
        v = xyz[:, axis]
        k = np.clip(np.floor((v - lo[axis]) / grid.voxel_size[axis]), 0, n - 1).astype(np.int64)
        k = k - (v < edges[k]) + (v >= edges[k + 1])
        inside &= (k >= 0) & (k < n)
        out.append(np.clip(k, 0, n - 1))
    return out[0], out[1], out[2], inside


def bev_image(points, grid: Grid, *, values=None, fill=0, where: str = "bev_image"):
    """BEV image: (N, >=3) points -> (2, H, W) float32 ``[occupancy 0/1, height of the highest point]``.

    grid: a :class:`typ.voxel.Grid` of shape (H, W, 1) in the points' frame; empty cells get
    height ``grid.z_range[0]``. values: optional (N,) per-point values; then returns
    ``(image, value_image)`` with each cell's value from its highest point (``fill`` where
    empty). Raises TypError for NaN/Inf points or an empty cloud.
    """
    grid = _bev_grid(grid, where)
    arr = _cloud(points, where)
    xyz = arr[:, :3].astype(np.float64)
    i, j, _, inside = voxel_indices(xyz, grid)
    H, W, _ = grid.shape
    image = np.zeros((2, H, W), dtype=np.float32)
    image[1] = grid.z_range[0]
    idx = np.flatnonzero(inside)
    # highest point per cell: sort by (cell, z, index), the last of each cell wins
    flat = i[idx] * W + j[idx]
    order = idx[np.lexsort((idx, xyz[idx, 2], flat))]
    flat_sorted = i[order] * W + j[order]
    last = np.ones(len(order), dtype=bool)
    last[:-1] = flat_sorted[1:] != flat_sorted[:-1]
    top = order[last]
    image[0, i[top], j[top]] = 1.0
    image[1, i[top], j[top]] = xyz[top, 2].astype(np.float32)
    if values is None:
        return image
    vals = _values(values, len(arr), where)
    out = np.full((H, W), fill, dtype=vals.dtype)
    out[i[top], j[top]] = vals[top]
    return image, out


def bev_to_points(image, grid: Grid, *, where: str = "bev_to_points") -> np.ndarray:
    """Inverse of :func:`bev_image`: (2, H, W) -> (M, 3) float32, one point per cell with
    occupancy >= 0.5, at the cell centre in x, y and the cell's height (clipped into the grid's
    z range) in z. Row-major cell order."""
    grid = _bev_grid(grid, where)
    H, W, _ = grid.shape
    img = _check_image(image, (2, H, W), where, "BEV")
    i, j = np.nonzero(img[0] >= 0.5)
    z_lo, z_hi = grid.z_range
    top = np.nextafter(np.float32(z_hi), np.float32(z_lo))  # z_hi itself is outside the grid
    z = np.clip(img[1, i, j].astype(np.float32), np.float32(z_lo), top)
    return np.stack([grid.centers(0)[i], grid.centers(1)[j], z.astype(np.float64)], axis=1).astype(np.float32)


# ---------------------------------------------------------------- model pixels


#: how a range image's depth becomes a pixel (:func:`to_unit`); see the module doc
DEPTH_ENCODINGS = ("linear", "log")


def _depth_to_unit(d: np.ndarray, layout: RangeLayout, depth: str) -> np.ndarray:
    """Depth (metres, 0 = no return) -> [-1, 1]: no return is -1 under either encoding."""
    if depth == "linear":
        return 2.0 * d / layout.max_range - 1.0
    scale = math.log2(layout.max_range + 1.0)
    return np.where(d > 0, 2.0 * np.log2(np.maximum(d, 0.0) + 1.0) / scale - 1.0, -1.0)


def no_return_threshold(layout: RangeLayout, depth: str = "linear") -> float:
    """Pixel value below which :func:`from_unit` reads "no return": linear, the pixel of
    ``min_range`` itself (less 1e-6, the float32 rounding of a stored pixel); log, half way
    between -1 (no return) and the pixel of ``min_range`` (the log scale leaves a gap of
    ``2·log2(min_range + 1)/log2(max_range + 1)`` there, ~0.17 for 120 m, that a sample's
    residual noise must not cross)."""
    vmin = float(_depth_to_unit(np.array(layout.min_range), layout, depth))
    return vmin - 1e-6 if depth == "linear" else (vmin - 1.0) / 2.0


def _unit_to_depth(v: np.ndarray, layout: RangeLayout, depth: str) -> np.ndarray:
    """Inverse of :func:`_depth_to_unit` on [-1, 1] (no threshold: see :func:`from_unit`)."""
    if depth == "linear":
        return (v + 1.0) / 2.0 * layout.max_range
    return np.exp2((v + 1.0) / 2.0 * math.log2(layout.max_range + 1.0)) - 1.0


def _check_depth(depth: str, layout, where: str) -> None:
    """A known encoding, and ``linear`` unless ``layout`` is a range image (BEV has no depth)."""
    if depth not in DEPTH_ENCODINGS:
        raise TypError(where, "depth", f"one of {list(DEPTH_ENCODINGS)}", depth)
    if depth != "linear" and not isinstance(layout, RangeLayout):
        raise TypError(where, "depth", "'linear' for a BEV image (it has no depth channel)", depth)


def to_unit(image, layout, *, depth: str = "linear") -> np.ndarray:
    """Physical image -> the [-1, 1] pixels a diffusion model sees, float32, with a channel axis.

    Range layout: (H, W) depth -> (1, H, W); no return is -1. ``depth="linear"``:
    ``2·d/max_range - 1``; ``depth="log"`` (R2DM's, LiDARGen's log scaling):
    ``2·log2(d + 1)/log2(max_range + 1) - 1``, which gives near objects, where most returns and
    most detail lie, most of the pixel range. BEV grid: (2, H, W) ->
    ``[2·occ - 1, 2·(z - z_min)/(z_max - z_min) - 1]`` (empty: height -1); ``depth`` must be linear.
    """
    _check_depth(depth, layout, "to_unit")
    if isinstance(layout, RangeLayout):
        img = _check_image(image, layout.shape, "to_unit", "beam")
        return _depth_to_unit(img.astype(np.float64), layout, depth).astype(np.float32)[None]
    grid = _bev_grid(layout, "to_unit")
    H, W, _ = grid.shape
    img = _check_image(image, (2, H, W), "to_unit", "BEV")
    z_lo, z_hi = grid.z_range
    return np.stack([2.0 * img[0] - 1.0, 2.0 * (img[1] - z_lo) / (z_hi - z_lo) - 1.0]).astype(np.float32)


def from_unit(pixels, layout, *, depth: str = "linear") -> np.ndarray:
    """Inverse of :func:`to_unit` for model output: values are clipped to [-1, 1] and the image
    is made canonical — range: pixels below :func:`no_return_threshold` become 0 (no return),
    the rest a depth in ``[min_range, max_range)``; BEV: occupancy thresholded at 0.5, height of
    empty cells set to ``z_min``. Accepts (C, H, W) float pixels."""
    _check_depth(depth, layout, "from_unit")
    px = np.clip(np.asarray(pixels, dtype=np.float64), -1.0, 1.0)
    if isinstance(layout, RangeLayout):
        if px.shape != (1, *layout.shape):
            raise TypError("from_unit", "pixels", f"shape (1, {layout.height}, {layout.width})", px.shape)
        below_max = np.nextafter(np.float32(layout.max_range), np.float32(0))  # max_range itself is not kept
        d = np.clip(_unit_to_depth(px[0], layout, depth).astype(np.float32), np.float32(layout.min_range), below_max)
        return np.where(px[0] >= no_return_threshold(layout, depth), d, 0).astype(np.float32)
    grid = _bev_grid(layout, "from_unit")
    H, W, _ = grid.shape
    if px.shape != (2, H, W):
        raise TypError("from_unit", "pixels", f"shape (2, {H}, {W})", px.shape)
    z_lo, z_hi = grid.z_range
    occ = (px[0] >= 0.0).astype(np.float32)
    z = z_lo + (px[1] + 1.0) / 2.0 * (z_hi - z_lo)
    return np.stack([occ, np.where(occ > 0, z, z_lo)]).astype(np.float32)
