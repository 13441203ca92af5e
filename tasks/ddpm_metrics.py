"""Scores of generated LiDAR sets against held-out real ones, with bootstrap intervals.

Four numbers per set, all from point clouds (LiDAR DDPM §IV-1, after LiDM):

- JSD, MMD: :func:`typ.metrics.jsd_bev` / :func:`typ.metrics.mmd_bev` under the ``r2dm`` preset
  (``typ.metrics.PRESETS["r2dm"].convention``), computed here from per-scan BEV histograms so
  that the bootstrap can resample scans; the full-set values equal the typ.metrics functions'
  (tests/unit/tasks/test_ddpm.py). A generated scan with no point in the field adds nothing to the JSD
  and counts as an all-zero grid in the MMD (r2dm's code would divide by zero).
- FRID, FPVD: Fréchet distances (:mod:`typ.metrics.frechet`) between real and generated features
  of typ's own range-image and voxel networks (:mod:`tasks.lidar_features`): comparable within
  typ only.

Intervals: :func:`typ.metrics.intervals.hierarchical_bootstrap` over training seeds and samples.
``spread``: sqrt(tr Σ_gen / tr Σ_real) of the FRID features: 1 = as varied as the real scans,
0 = every sample the same.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial.distance import jensenshannon

from typ.errors import TypError
from typ.metrics import PRESETS, bev_histogram
from typ.metrics.frechet import frechet_from_features
from typ.metrics.intervals import hierarchical_bootstrap

PRESET = "r2dm"


@dataclass
class SetStats:
    """Per-scan statistics of one set of N clouds."""

    hist: np.ndarray     #: (N, cells²) float64 BEV point counts under the preset
    grids: np.ndarray    #: (N, cells²) each row divided by its own total (zeros when empty)
    frid: np.ndarray     #: (N, D) range-network features
    fpvd: np.ndarray     #: (N, D) voxel-network features
    empty: int           #: scans with no point in the preset's BEV field

    def __len__(self) -> int:
        return len(self.hist)


def set_stats(clouds: list[np.ndarray], nets, preset: str = PRESET) -> SetStats:
    """Statistics of (M_i, >=3) point clouds; ``nets``: :class:`tasks.lidar_features.FeatureNets`."""
    if preset != PRESET:
        raise TypError("ddpm", "preset", f"{PRESET!r} (its MMD is a kernel over per-scan grids, which the "
                       "bootstrap resamples)", preset)
    if not clouds:
        raise TypError("ddpm", "clouds", "at least one point cloud", "an empty set")
    hist = np.stack([bev_histogram(c if len(c) else np.zeros((0, 3), np.float32), preset).reshape(-1)
                     for c in clouds])
    totals = hist.sum(axis=1, keepdims=True)
    grids = np.divide(hist, totals, out=np.zeros_like(hist), where=totals > 0)
    feats = nets.features(clouds)
    return SetStats(hist, grids, feats["frid"], feats["fpvd"], int((totals[:, 0] == 0).sum()))


def _kernel(a: np.ndarray, b: np.ndarray, sigma: float) -> np.ndarray:
    d2 = np.einsum("ij,ij->i", a, a)[:, None] + np.einsum("ij,ij->i", b, b)[None, :] - 2.0 * (a @ b.T)
    return np.exp(-np.maximum(d2, 0.0) / (2.0 * sigma ** 2))


def _jsd(real_hist: np.ndarray, gen_hist: np.ndarray) -> float:
    pa, pb = real_hist.sum(axis=0), gen_hist.sum(axis=0)
    if pa.sum() == 0 or pb.sum() == 0:
        return float("nan")
    return float(jensenshannon(pa / pa.sum(), pb / pb.sum()))


#: a metric on a resample: ``fn(seed_index, generated scan indices, real scan indices)``
Resampled = Callable[[int, np.ndarray, np.ndarray], float]


def _jsd_of(real: SetStats, generated: list[SetStats]) -> Resampled:
    return lambda s, gi, ri: _jsd(real.hist[ri], generated[s].hist[gi])


def _mmd_of(real: SetStats, generated: list[SetStats]) -> Resampled:
    sigma = PRESETS[PRESET].sigma
    k_rr = _kernel(real.grids, real.grids, sigma)
    k_gg = [_kernel(g.grids, g.grids, sigma) for g in generated]
    k_rg = [_kernel(real.grids, g.grids, sigma) for g in generated]

    def mmd(s, gi, ri):
        return float(k_rr[np.ix_(ri, ri)].mean() + k_gg[s][np.ix_(gi, gi)].mean() - 2.0 * k_rg[s][np.ix_(ri, gi)].mean())
    return mmd


def _frechet_of(features: str) -> Callable[[SetStats, list[SetStats]], Resampled]:
    def prepare(real: SetStats, generated: list[SetStats]) -> Resampled:
        return lambda s, gi, ri: frechet_from_features(getattr(real, features)[ri], getattr(generated[s], features)[gi])
    return prepare


@dataclass(frozen=True)
class SetMetric:
    """A figure of a generated set against the real one (lower is better): ``prepare(real,
    generated)`` gives its value on any resample of both; the report prints ``value × scale`` with
    ``digits`` decimals under ``label``."""

    label: str
    prepare: Callable[[SetStats, list[SetStats]], Resampled]
    scale: float = 1.0
    digits: int = 3


#: every figure of a generated set, in the table's order (each bootstrap's seed is ``seed + its
#: position``). A new figure is one entry here (and its per-scan statistic in :class:`SetStats`).
METRICS: dict[str, SetMetric] = {
    "jsd": SetMetric("JSD", _jsd_of),
    "mmd": SetMetric("MMD ×10⁵", _mmd_of, scale=1e5, digits=1),   # x 10^5, as LiDAR DDPM Table II prints it
    "frid": SetMetric("FRID†", _frechet_of("frid"), digits=2),
    "fpvd": SetMetric("FPVD†", _frechet_of("fpvd"), digits=2),
}


def score(real: SetStats, generated: list[SetStats], *, n_boot: int, seed: int) -> dict:
    """Each metric's ``[estimate, low, high]`` for ``generated`` (one set per training seed) against
    ``real``, plus ``spread`` (mean over seeds), ``empty`` (summed) and ``samples`` (per seed)."""
    sizes = [len(g) for g in generated]
    out: dict = {}
    for i, (name, metric) in enumerate(METRICS.items()):
        iv = hierarchical_bootstrap(metric.prepare(real, generated), sizes, len(real), n_boot=n_boot, seed=seed + i)
        out[name] = [iv.value, iv.low, iv.high]
    real_var = np.trace(np.atleast_2d(np.cov(real.frid, rowvar=False)))
    out["spread"] = float(np.mean([np.sqrt(np.trace(np.atleast_2d(np.cov(g.frid, rowvar=False))) / real_var)
                                   for g in generated]))
    out["empty"] = sum(g.empty for g in generated)
    out["samples"] = sizes
    return out


def overlaps(a: list[float], b: list[float]) -> bool:
    """Whether two ``[estimate, low, high]`` intervals overlap (NaN: treated as overlapping)."""
    if any(np.isnan(v) for v in (*a, *b)):
        return True
    return not (a[2] < b[1] or b[2] < a[1])
