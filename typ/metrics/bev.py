"""BEV distribution metrics for generated LiDAR (TYP §4.5, Tables 4-5): JSD and MMD.

Both compare two *sets* of scans (real vs generated) through bird's-eye-view grids of
point counts or occupancy, the way LiDAR generation papers report them. Each published code
base fixes the grid, the range filter and the distance a little differently, and the numbers
only carry over under the same convention, so every function takes a ``preset`` naming one
of them (:data:`PRESETS`; each preset's ``convention`` is the paragraph a report can quote):

- ``"r2dm"`` - kazuto1011/r2dm ``metrics/bev.py`` (used by ``evaluate.py``).
- ``"lidargen"`` - vzyrianov/lidargen ``metrics/histogram/`` (``histogram.py``,
  ``hist_utils.py``, ``jsd.py``, ``mmd.py``, ``dist_helper.py``).
- ``"lidm64"``, ``"lidm32"`` - hancyran/LiDAR-Diffusion ``lidm/eval/`` (``__init__.py``,
  ``eval_utils.py``, ``metric_utils.py``), data types ``'64'`` and ``'32'``. Its "MMD" is
  the *minimum matching distance*, a different function from the maximum mean discrepancy.

Scans are (N, >=3) float32/float64 ``[x, y, z, ...]`` arrays in their own sensor frame
(sensor at the origin, metres); columns past z are ignored. Where the published code's
rounding depends on the dtype (bin edges, cell division, the range filter) the input's dtype
is used, as it would be had the same array been handed to that code; sums, normalisation and
kernels are float64 (the published code reduces in float32, so results agree with it to
float32 rounding, ~1e-6 relative, not bit for bit).

Not reproduced, because they happen before these metrics in the published scripts: R2DM
keeps a random 10,000 of the real scans; LiDARGen and LiDM re-project real scans through a
range image and back before binning (LiDM's README asks for reference point clouds
"projected back from range images"). Do those upstream if the numbers must match.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from functools import lru_cache
from typing import Literal

import numpy as np
from scipy import ndimage
from scipy.spatial.distance import jensenshannon

from typ.errors import TypError
from typ.metrics.truth import check_points

# Scans (or matrix rows) handled per block in the pairwise terms: bounds memory to a few
# hundred MB whatever the set sizes.
_BLOCK = 256


@dataclass(frozen=True, kw_only=True)
class BevPreset:
    """One published BEV JSD/MMD convention; the fields are the numbers the code here uses."""

    name: str
    source: str
    """Repository and files the convention was read from."""
    half_width: float
    """The BEV field is ``[-half_width, half_width]`` metres in x and in y."""
    cells: int
    """Cells per axis of the JSD grid (and of the MMD grid of ``squared-mmd``)."""
    depth_range: tuple[float, float] | None
    """Keep points with ``min < |xyz| < max`` (strict); None: no range filter."""
    binning: Literal["torch-linspace", "numpy-linspace", "floor"]
    """``*-linspace``: histogram edges as torch/numpy build them, bins ``[e_i, e_{i+1})``, last
    bin closed, field inclusive. ``floor``: open field ``-hw < x, y < hw``, cell
    ``floor(x / cell) - ceil(-hw / cell)``."""
    cell_value: Literal["count", "occupancy"]
    """What a scan puts in a cell: its number of points, or 1 if it has any."""
    mmd: Literal["squared-mmd", "minimum-matching"]
    mmd_distance: Literal["frobenius", "spectral", "squared-chamfer"]
    sigma: float | None
    """Gaussian kernel width of ``squared-mmd``."""
    mmd_cells: int | None
    """``minimum-matching``: cells per axis of its coarser (0.5 m) grid."""
    convention: str
    """The convention in words, for reports."""

    @property
    def cell(self) -> float:
        """Cell edge of the JSD grid, metres."""
        return 2.0 * self.half_width / self.cells


_R2DM_TEXT = (
    "R2DM (kazuto1011/r2dm, metrics/bev.py as called by evaluate.py). Filter: keep points with "
    "3 < |xyz| < 70 m (strict). Grid: x and y binned into 100x100 cells over [-80, 80]^2 m "
    "(1.6 m cells), z unused, cell value = point count, with torch.histogramdd's rules: edges "
    "torch.linspace(-80, 80, 101) in the input dtype, bin i = [e_i, e_(i+1)), last bin closed. "
    "JSD: per-scan counts summed over each set, divided by the set total, then "
    "scipy.spatial.distance.jensenshannon (natural log; the square root of the JS divergence in "
    "nats, 0 to sqrt(ln 2) = 0.8326). MMD: each scan's grid divided by its own total and "
    "flattened; kernel k(p, q) = exp(-||p - q||_F^2 / (2 sigma^2)), sigma = 0.5, Frobenius "
    "(Euclidean) distance; biased estimate of squared MMD, mean k(A, A) + mean k(B, B) - "
    "2 mean k(A, B) over all pairs, diagonal included."
)
_LIDARGEN_TEXT = (
    "LiDARGen (vzyrianov/lidargen, metrics/histogram/histogram.py, hist_utils.py, jsd.py, "
    "mmd.py, dist_helper.py). Filter: 3 < |xyz| < 70 m (strict; LiDARGen applies it when it "
    "turns range images back into points). Grid: 100x100 cells over [-80, 80]^2 m, z unused, "
    "point counts, with numpy.histogramdd's rules: edges np.linspace(-80, 80, 101) in float64, "
    "coordinates compared in float64, bin i = [e_i, e_(i+1)), last bin closed. JSD: as R2DM "
    "(set-summed counts, normalised, scipy jensenshannon, nats, square root). MMD: each scan's "
    "100x100 grid divided by its own total; kernel k(p, q) = exp(-||p - q||_2^2 / (2 sigma^2)), "
    "sigma = 0.5, where ||.||_2 is the spectral norm (largest singular value; what "
    "numpy.linalg.norm(x - y, 2) gives for 2-D arrays); biased squared MMD over all pairs, "
    "diagonal included."
)


def _lidm_text(kind: str, hw: int, cells: int, mmd_cells: int) -> str:
    return (
        f"LiDAR-Diffusion / LiDM (hancyran/LiDAR-Diffusion, lidm/eval/__init__.py, eval_utils.py, "
        f"metric_utils.py; data type '{kind}'). Filter: keep points with -{hw} < x < {hw} and "
        f"-{hw} < y < {hw} m (strict); no |xyz| or z filter; z unused. JSD grid: 0.05 m cells, "
        f"{cells}x{cells}, cell = floor(x / 0.05) + {cells // 2} (the division in the input dtype); "
        f"a scan marks each cell it has any point in (occupancy), the marks are summed over the "
        f"set, divided by the set total, then scipy jensenshannon (nats, square root). 'MMD' is "
        f"LiDM's minimum matching distance, not a maximum mean discrepancy: each scan becomes the "
        f"set of its occupied cells on a 0.5 m grid ({mmd_cells}x{mmd_cells}, cell = floor(x / 0.5) "
        f"+ {mmd_cells // 2}) as 2-D points at (cell index) / {mmd_cells}; MMD = mean over reference "
        f"scans a in set_a of min over scans b in set_b of the squared-L2 Chamfer distance "
        f"CD(a, b) = (mean_(p in a) min_(q in b) |p - q|^2 + mean_(q in b) min_(p in a) |p - q|^2) / 2 "
        f"(LiDM's CUDA chamfer kernel returns squared distances). Not symmetric: set_a is the "
        f"reference (real) set."
    )


def _lidm(kind: str, hw: int) -> BevPreset:
    # LiDM sizes its grids as ceil((hi - lo) / cell) in float64; both divisions are exact here.
    cells, mmd_cells = math.ceil(2 * hw / 0.05), math.ceil(2 * hw / 0.5)
    return BevPreset(
        name=f"lidm{kind}", source="hancyran/LiDAR-Diffusion lidm/eval/{__init__,eval_utils,metric_utils}.py",
        half_width=float(hw), cells=cells, depth_range=None, binning="floor", cell_value="occupancy",
        mmd="minimum-matching", mmd_distance="squared-chamfer", sigma=None, mmd_cells=mmd_cells,
        convention=_lidm_text(kind, hw, cells, mmd_cells))


PRESETS: dict[str, BevPreset] = {
    "r2dm": BevPreset(
        name="r2dm", source="kazuto1011/r2dm metrics/bev.py (+ evaluate.py)",
        half_width=80.0, cells=100, depth_range=(3.0, 70.0), binning="torch-linspace",
        cell_value="count", mmd="squared-mmd", mmd_distance="frobenius", sigma=0.5, mmd_cells=None,
        convention=_R2DM_TEXT),
    "lidargen": BevPreset(
        name="lidargen",
        source="vzyrianov/lidargen metrics/histogram/{histogram,hist_utils,jsd,mmd,dist_helper}.py",
        half_width=80.0, cells=100, depth_range=(3.0, 70.0), binning="numpy-linspace",
        cell_value="count", mmd="squared-mmd", mmd_distance="spectral", sigma=0.5, mmd_cells=None,
        convention=_LIDARGEN_TEXT),
    "lidm64": _lidm("64", 50),
    "lidm32": _lidm("32", 30),
}


def _preset(name, where: str) -> BevPreset:
    if not isinstance(name, str) or name not in PRESETS:
        raise TypError(where, "preset", f"one of {sorted(PRESETS)}", name)
    return PRESETS[name]


def _scan_list(value, where: str, field: str) -> list[np.ndarray]:
    if isinstance(value, np.ndarray) and value.ndim == 3:
        value = list(value)
    if not isinstance(value, (list, tuple)):
        raise TypError(where, field, "a list of (N, >=3) point arrays, one per scan",
                       f"{type(value).__name__} {getattr(value, 'shape', '')}".strip())
    if len(value) == 0:
        raise TypError(where, field, "at least one scan", "an empty list")
    return [check_points(scan, where, f"{field}[{i}]") for i, scan in enumerate(value)]


@lru_cache(maxsize=None)
def _torch_edges(half_width: float, cells: int, dtype: type) -> np.ndarray:
    """Edges as torch.linspace(-hw, hw, cells + 1) builds them on CPU, in ``dtype``.

    torch computes ``start + step*i`` for the first half and ``end - step*(cells - i)`` for
    the rest, with ``step = (end - start) / cells`` in ``dtype`` and a fused multiply-add
    (one rounding); exact rational arithmetic reproduces that rounding on any machine.
    """
    start, end = dtype(-half_width), dtype(half_width)
    step = Fraction(float((end - start) / dtype(cells)))
    half = (cells + 1) // 2
    exact = [Fraction(float(start)) + step * i if i < half else Fraction(float(end)) - step * (cells - i)
             for i in range(cells + 1)]
    # float(Fraction) rounds once to float64; for float32 the exact value already fits in
    # float64 (24-bit step times a small integer, plus +-hw), so the cast is the one rounding.
    edges = np.array([float(v) for v in exact]).astype(dtype)
    edges.setflags(write=False)
    return edges


def _edge_bins(v: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Histogram bins of ``v`` against ``edges`` (compared in the edges' dtype): (inside, index)."""
    v = v.astype(edges.dtype, copy=False)
    inside = (v >= edges[0]) & (v <= edges[-1])
    idx = np.minimum(np.searchsorted(edges, v, side="right") - 1, len(edges) - 2)
    return inside, idx


def _depth_keep(arr: np.ndarray, depth_range: tuple[float, float]) -> np.ndarray:
    xyz = arr[:, :3].astype(np.float64)
    # |xyz| as the published code's norm returns it: accurate, then in the input's dtype.
    depth = np.sqrt(np.einsum("ij,ij->i", xyz, xyz)).astype(arr.dtype)
    return (depth > depth_range[0]) & (depth < depth_range[1])


def _floor_cells(arr: np.ndarray, half_width: float, cell: float, cells: int) -> np.ndarray:
    """LiDM's cells: flat ``i*cells + j`` of every point strictly inside the field (repeats kept)."""
    x, y = arr[:, 0], arr[:, 1]
    keep = (x > -half_width) & (x < half_width) & (y > -half_width) & (y < half_width)
    # numpy divides a float32 array by a Python float in float32; do the same.
    ij = np.floor(arr[keep, :2] / arr.dtype.type(cell)).astype(np.int64) - math.ceil(-half_width / cell)
    return ij[:, 0] * cells + ij[:, 1]


def _scan_cells(arr: np.ndarray, p: BevPreset) -> np.ndarray:
    """Flat JSD-grid cells of one scan's points: one entry per point, or per occupied cell."""
    if p.binning == "floor":
        return np.unique(_floor_cells(arr, p.half_width, p.cell, p.cells))
    keep = _depth_keep(arr, p.depth_range)
    if p.binning == "torch-linspace":
        edges = _torch_edges(p.half_width, p.cells, arr.dtype.type)
    else:
        edges = np.linspace(-p.half_width, p.half_width, p.cells + 1)
    in_x, ix = _edge_bins(arr[keep, 0], edges)
    in_y, iy = _edge_bins(arr[keep, 1], edges)
    inside = in_x & in_y
    return ix[inside] * p.cells + iy[inside]


def bev_histogram(points, preset: str = "r2dm") -> np.ndarray:
    """One scan's BEV grid under ``preset``: (N, >=3) points -> (cells, cells) float64.

    Indexed ``[x cell, y cell]``, x and y ascending from ``-half_width``. Values are point
    counts (``r2dm``, ``lidargen``) or 0/1 occupancy (``lidm*``), after the preset's range
    filter; this is the per-scan grid that :func:`jsd_bev` sums (see ``PRESETS[preset]``).
    """
    p = _preset(preset, "bev_histogram")
    arr = check_points(points, "bev_histogram", "points")
    return np.bincount(_scan_cells(arr, p), minlength=p.cells ** 2).astype(np.float64).reshape(p.cells, p.cells)


def _summed_grid(scans: list[np.ndarray], p: BevPreset, where: str, field: str) -> np.ndarray:
    total = np.zeros(p.cells ** 2)
    pending, size = [], 0
    for scan in scans:
        cells = _scan_cells(scan, p)
        pending.append(cells)
        size += len(cells)
        if size > 1 << 22:  # flush so one bincount covers many scans without holding them all
            total += np.bincount(np.concatenate(pending), minlength=p.cells ** 2)
            pending, size = [], 0
    if pending:
        total += np.bincount(np.concatenate(pending), minlength=p.cells ** 2)
    if total.sum() == 0:
        raise TypError(where, field, f"at least one point inside the {p.name} BEV field (see PRESETS)",
                       "no point in any scan")
    return total


def jsd_bev(set_a, set_b, preset: str = "r2dm") -> float:
    """BEV Jensen-Shannon distance between two sets of scans, as ``preset``'s code computes it.

    set_a, set_b: lists of (N, >=3) float32/float64 point arrays, sensor at the origin. Each
    set's per-scan grids (:func:`bev_histogram`) are summed and divided by their total, and
    the two distributions go to ``scipy.spatial.distance.jensenshannon`` with its default
    natural log: the result is the *square root* of the JS divergence in nats, 0 for identical
    distributions and sqrt(ln 2) = 0.8326 for disjoint ones. Symmetric in (a, b).

    - ``r2dm``: 100x100 cells over [-80, 80]^2 m (torch.histogramdd edges), 3 < |xyz| < 70 m, counts.
    - ``lidargen``: the same grid with numpy.histogramdd edges (float64), same filter, counts.
    - ``lidm64`` / ``lidm32``: 0.05 m cells over (-50, 50)^2 / (-30, 30)^2 m, no range filter,
      per-scan occupancy summed over the set.

    Full wording in ``PRESETS[preset].convention``. A scan with no point in the field adds
    nothing; a set with none at all raises TypError naming the set.
    """
    p = _preset(preset, "jsd_bev")
    a = _scan_list(set_a, "jsd_bev", "set_a")
    b = _scan_list(set_b, "jsd_bev", "set_b")
    pa = _summed_grid(a, p, "jsd_bev", "set_a")
    pb = _summed_grid(b, p, "jsd_bev", "set_b")
    # Normalise first, as the published code does; scipy normalises again (a no-op up to rounding).
    return float(jensenshannon(pa / pa.sum(), pb / pb.sum()))


def _normalised_grids(scans: list[np.ndarray], p: BevPreset, where: str, field: str) -> np.ndarray:
    """(N, cells^2) float64: each scan's count grid divided by its own total."""
    out = np.zeros((len(scans), p.cells ** 2))
    for i, scan in enumerate(scans):
        counts = np.bincount(_scan_cells(scan, p), minlength=p.cells ** 2)
        n = counts.sum()
        if n == 0:
            raise TypError(where, f"{field}[{i}]",
                           f"at least one point inside the {p.name} BEV field (per-scan grids are "
                           f"divided by their total)", "no point in the field")
        out[i] = counts / n
    return out


def _frobenius_sq(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """(len(P), len(Q)) squared Euclidean distances between flattened grids, float64."""
    d2 = np.einsum("ij,ij->i", P, P)[:, None] + np.einsum("ij,ij->i", Q, Q)[None, :] - 2.0 * (P @ Q.T)
    return np.maximum(d2, 0.0)  # the Gram form can round a zero distance to -1e-17


def _spectral_sq(P: np.ndarray, Q: np.ndarray, cells: int) -> np.ndarray:
    """(len(P), len(Q)) squared spectral norms of the (cells, cells) grid differences."""
    out = np.empty((len(P), len(Q)))
    for i, row in enumerate(P):
        for j in range(0, len(Q), _BLOCK):
            diff = (row - Q[j:j + _BLOCK]).reshape(-1, cells, cells)
            out[i, j:j + _BLOCK] = np.linalg.svd(diff, compute_uv=False)[:, 0] ** 2
    return out


def _kernel_mean(P: np.ndarray, Q: np.ndarray, p: BevPreset) -> float:
    """Mean of the Gaussian kernel over all (P row, Q row) pairs."""
    total = 0.0
    for i in range(0, len(P), _BLOCK):
        block = P[i:i + _BLOCK]
        d2 = _frobenius_sq(block, Q) if p.mmd_distance == "frobenius" else _spectral_sq(block, Q, p.cells)
        total += np.exp(-d2 / (2.0 * p.sigma ** 2)).sum()
    return total / (len(P) * len(Q))


def _mmd_cell_sets(scans: list[np.ndarray], p: BevPreset, where: str, field: str) -> list[np.ndarray]:
    out = []
    for i, scan in enumerate(scans):
        cells = np.unique(_floor_cells(scan, p.half_width, 0.5, p.mmd_cells))
        if len(cells) == 0:
            raise TypError(where, f"{field}[{i}]",
                           f"at least one point inside the {p.name} BEV field (the Chamfer distance "
                           f"of an empty scan is undefined)", "no point in the field")
        out.append(cells)
    return out


def _occupancy_and_sq_distance(cells: list[np.ndarray], n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per scan: (n*n,) 0/1 occupancy, and each cell's squared distance (in cells) to the
    nearest occupied cell, both float32 (exact: distances are integers <= 2 n^2)."""
    occ = np.zeros((len(cells), n * n), dtype=np.float32)
    dist2 = np.empty((len(cells), n * n), dtype=np.float32)
    grid = np.indices((n, n))
    for k, c in enumerate(cells):
        occ[k, c] = 1.0
        # Exact Euclidean feature transform: index of the nearest occupied cell for every cell.
        nearest = ndimage.distance_transform_edt(occ[k].reshape(n, n) == 0, return_distances=False,
                                                 return_indices=True)
        dist2[k] = ((grid - nearest) ** 2).sum(axis=0).reshape(-1)
    return occ, dist2


def _minimum_matching(a: list[np.ndarray], b: list[np.ndarray], n: int) -> float:
    """mean_a min_b squared-L2 Chamfer(a, b), points = occupied cells / n.

    Chamfer's one-way term sum_{p in a} min_{q in b} |p - q|^2 is the dot product of a's
    occupancy with b's squared distance transform, so all pairs are two matrix products.
    """
    occ_a, d2_a = _occupancy_and_sq_distance(a, n)
    occ_b, d2_b = _occupancy_and_sq_distance(b, n)
    size_a = np.array([len(c) for c in a], dtype=np.float64)
    size_b = np.array([len(c) for c in b], dtype=np.float64)
    best = np.full(len(a), np.inf)
    for i in range(0, len(a), _BLOCK):
        oa, da = occ_a[i:i + _BLOCK].astype(np.float64), d2_a[i:i + _BLOCK].astype(np.float64)
        for j in range(0, len(b), _BLOCK):
            ob, db = occ_b[j:j + _BLOCK].astype(np.float64), d2_b[j:j + _BLOCK].astype(np.float64)
            a_to_b = (oa @ db.T) / size_a[i:i + _BLOCK, None]
            b_to_a = (da @ ob.T) / size_b[None, j:j + _BLOCK]
            cd = (a_to_b + b_to_a) / (2.0 * n * n)
            best[i:i + _BLOCK] = np.minimum(best[i:i + _BLOCK], cd.min(axis=1))
    return float(best.mean())


def mmd_bev(set_a, set_b, preset: str = "r2dm") -> float:
    """The BEV "MMD" of ``preset``'s code between two sets of scans.

    set_a, set_b: lists of (N, >=3) float32/float64 point arrays, sensor at the origin;
    set_a is the reference (real) set. Every scan needs at least one point inside the
    preset's field (TypError naming the scan otherwise: the published code would divide by
    zero and return NaN).

    - ``r2dm``: squared maximum mean discrepancy, biased estimate (all pairs, diagonal
      included): mean k(A, A) + mean k(B, B) - 2 mean k(A, B) with k(p, q) =
      exp(-||p - q||^2 / (2 sigma^2)), sigma = 0.5, ||.|| the Frobenius norm, p, q each scan's
      100x100 count grid (as :func:`jsd_bev`) divided by its own total. Symmetric.
    - ``lidargen``: the same, except ||.|| is the spectral norm of the 100x100 difference
      (its largest singular value). Symmetric. O(N^2) SVDs of 100x100 matrices.
    - ``lidm64`` / ``lidm32``: LiDM's **minimum matching distance** (Achlioptas et al. 2018),
      not a maximum mean discrepancy: mean over a in set_a of min over b in set_b of the
      squared-L2 Chamfer distance between the scans' occupied 0.5 m cells (as 2-D points at
      cell index / cells-per-axis, 200 or 120), CD = (mean a->b + mean b->a) / 2.
      *Not symmetric* in (a, b).

    Full wording in ``PRESETS[preset].convention``. The pairwise terms are computed in
    blocks of 256 scans; the per-scan grids of both sets are held in memory (float64
    10,000 cells a scan for r2dm/lidargen, float32 2 x 40,000 for lidm64).
    """
    p = _preset(preset, "mmd_bev")
    a = _scan_list(set_a, "mmd_bev", "set_a")
    b = _scan_list(set_b, "mmd_bev", "set_b")
    if p.mmd == "minimum-matching":
        return _minimum_matching(_mmd_cell_sets(a, p, "mmd_bev", "set_a"),
                                 _mmd_cell_sets(b, p, "mmd_bev", "set_b"), p.mmd_cells)
    P = _normalised_grids(a, p, "mmd_bev", "set_a")
    Q = _normalised_grids(b, p, "mmd_bev", "set_b")
    return float(_kernel_mean(P, P, p) + _kernel_mean(Q, Q, p) - 2.0 * _kernel_mean(P, Q, p))
