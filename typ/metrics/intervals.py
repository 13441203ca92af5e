"""Bootstrap confidence intervals for figures pooled over held-out scenes and training seeds.

Views of one scene (its frames, its (ego, reference) pairs) are correlated, so the unit that
is resampled is the scene, not the view: a cluster bootstrap. Where several training seeds
exist, seeds are resampled too, and each replicate's figure is the mean over its seeds of
the figure pooled over its scenes. The interval is the percentile interval of ``n_boot``
replicates (Efron & Tibshirani, ch. 13); the point estimate is the figure on the data as
observed. "A beats B" is claimed only when A's and B's intervals do not overlap.

:func:`hierarchical_bootstrap` is the same for a set metric of generated samples against a
reference set (JSD, MMD, Fréchet distance), where each training seed has its own samples:
seeds are resampled, then each drawn seed's samples and the reference samples.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from typ.errors import TypError


@dataclass(frozen=True)
class Interval:
    """A figure with its bootstrap interval: ``value`` [``low``, ``high``] at ``level``."""

    value: float
    low: float
    high: float
    level: float = 0.95

    def above(self, other: "Interval") -> bool:
        """True when this interval lies wholly above ``other``'s (no overlap)."""
        return self.low > other.high

    def to_dict(self) -> dict[str, float]:
        return {"value": self.value, "low": self.low, "high": self.high}

    def text(self, digits: int = 3) -> str:
        """``value [low, high]`` (:func:`interval_cell`, the one way reports print it)."""
        return interval_cell(self, digits)


#: a figure that does not exist (not finite)
NOT_A_NUMBER = "–"


def interval_cell(cell, digits: int = 3, *, scale: float = 1.0, missing: str = "–", adaptive: bool = False) -> str:
    """A figure with its bootstrap interval as a report cell: ``value [low, high]`` to ``digits``.

    cell: an :class:`Interval`, its dict (``{"value", "low", "high"}``, as the
    metrics JSON holds it) or a ``(value, low, high)`` tuple, each multiplied by ``scale``; None
    (the figure does not apply) gives ``missing``, a value that is not finite ``–``, bounds that are
    absent or not finite the value alone. adaptive: 5 digits for a value under 0.01 (but not 0), so
    that small figures keep their digits.
    """
    if cell is None:
        return missing
    if isinstance(cell, dict):
        value, low, high = cell.get("value"), cell.get("low"), cell.get("high")
    elif isinstance(cell, tuple):
        value, low, high = cell
    else:
        value, low, high = cell.value, cell.low, cell.high
    if value is None:
        return missing
    value = value * scale
    if not math.isfinite(value):
        return NOT_A_NUMBER
    if adaptive and value != 0 and abs(value) < 0.01:
        digits = 5
    if low is None or high is None or not (math.isfinite(low * scale) and math.isfinite(high * scale)):
        return f"{value:.{digits}f}"
    return f"{value:.{digits}f} [{low * scale:.{digits}f}, {high * scale:.{digits}f}]"


METHODS = ("percentile", "basic", "recentred")


def _check(level: float, method: str) -> None:
    if not 0 < level < 1:
        raise TypError("bootstrap", "level", "a probability in (0, 1)", level)
    if method not in METHODS:
        raise TypError("bootstrap", "method", " or ".join(METHODS), method)


def _interval(value: float, reps: np.ndarray, level: float, method: str) -> Interval:
    """The ``level`` interval of the replicates ``reps`` around the figure ``value``.

    method: ``"percentile"`` — the replicates' quantiles; ``"basic"`` — the quantiles
    reflected about the figure, [2 v - q_high, 2 v - q_low]; ``"recentred"`` — the quantiles
    shifted by (v - median of the replicates). The last two are for a statistic a resample
    biases: a JSD of pooled histograms or a Fréchet distance grows when a resampled set holds
    repeats (fewer distinct scans), so the percentile interval can lie wholly above the figure
    itself; "basic" reflects that bias back, "recentred" keeps the replicates' spread around
    the figure.
    """
    if len(reps) == 0:
        return Interval(value, float("nan"), float("nan"), level)
    tail = (1 - level) / 2 * 100
    low, high = np.percentile(reps, [tail, 100 - tail])
    if method == "basic":
        low, high = 2 * value - high, 2 * value - low
    elif method == "recentred":
        shift = float(np.median(reps)) - value
        low, high = low - shift, high - shift
    return Interval(value, float(low), float(high), level)


def bootstrap(stat: Callable[[np.ndarray, np.ndarray], float], n_clusters: int, n_seeds: int = 1, *,
              n_boot: int = 1000, level: float = 0.95, seed: int = 0, method: str = "percentile") -> Interval:
    """``stat(cluster_index, seed_index)`` -> figure, evaluated on ``n_boot`` resamples of the
    clusters (and of the seeds when ``n_seeds > 1``), each drawn with replacement.

    method: one of :data:`METHODS` (see :func:`_interval`); ``"basic"`` for a pooled JSD.

    ``stat`` receives index arrays (repeats allowed) and must pool over them as it pools over
    the whole set, e.g. ``IoU = sum(tp[c]) / sum(tp[c] + fp[c] + fn[c])``. Replicates whose
    figure is undefined (NaN, e.g. no true voxel drawn) are left out of the percentiles.
    """
    return bootstrap_figures(lambda c, s: (stat(c, s),), n_clusters, n_seeds, n_boot=n_boot, level=level,
                             seed=seed, method=method)[0]


def bootstrap_figures(stat: Callable[[np.ndarray, np.ndarray], Sequence[float]], n_clusters: int, n_seeds: int = 1,
                      *, n_boot: int = 1000, level: float = 0.95, seed: int = 0,
                      method: str = "percentile") -> list[Interval]:
    """:func:`bootstrap` of several figures of the same resamples: ``stat`` returns one value per
    figure, called once per replicate. Figure i's interval is exactly :func:`bootstrap`'s for
    ``lambda c, s: stat(c, s)[i]`` with the same ``seed`` (the draws do not depend on the figure),
    for one evaluation of what the figures share (a pooled confusion matrix, say) instead of one
    per figure."""
    if n_clusters < 1:
        raise TypError("bootstrap", "n_clusters", "at least one scene", n_clusters)
    if n_seeds < 1:
        raise TypError("bootstrap", "n_seeds", "at least one seed", n_seeds)
    _check(level, method)
    clusters, seeds = np.arange(n_clusters), np.arange(n_seeds)
    values = np.asarray(stat(clusters, seeds), dtype=np.float64)
    rng = np.random.default_rng(seed)
    reps = np.empty((n_boot, len(values)))
    for b in range(n_boot):
        c = rng.integers(0, n_clusters, n_clusters)
        s = rng.integers(0, n_seeds, n_seeds) if n_seeds > 1 else seeds
        reps[b] = stat(c, s)
    return [_interval(float(v), r[np.isfinite(r)], level, method) for v, r in zip(values, reps.T)]


def hierarchical_bootstrap(metric: Callable[[int, np.ndarray, np.ndarray], float], n_generated: Sequence[int],
                           n_reference: int, *, n_boot: int = 1000, level: float = 0.95, seed: int = 0,
                           method: str = "recentred") -> Interval:
    """A set metric of generated samples against a reference set, over training seeds.

    metric(s, gen_index, ref_index): the metric of seed s's generated samples ``gen_index``
    against reference samples ``ref_index`` (index arrays, repeats allowed). n_generated[s]:
    how many samples seed s generated; n_reference: the reference set's size. The figure is
    the mean over seeds of the metric on the full sets. Each replicate draws the seeds with
    replacement, then, for every drawn seed, its generated samples and the reference samples
    with replacement, and averages the metric over the drawn seeds. The default method,
    ``"recentred"``, keeps the replicates' spread around the figure (a repeat-biased set
    metric, see :func:`_interval`). Unlike :func:`bootstrap`, a NaN replicate is kept, so an
    undefined metric on any resample gives a NaN interval.
    """
    _check(level, method)
    n_seeds = len(n_generated)
    if n_seeds < 1 or min(n_generated) < 1 or n_reference < 1:
        raise TypError("bootstrap", "sizes", "at least one seed with >= 1 sample and a non-empty reference",
                       [list(n_generated), n_reference])
    every_ref = np.arange(n_reference)
    value = float(np.mean([metric(s, np.arange(n), every_ref) for s, n in enumerate(n_generated)]))
    rng = np.random.default_rng(seed)
    reps = np.empty(n_boot)
    for b in range(n_boot):
        seeds = rng.integers(0, n_seeds, n_seeds)
        reps[b] = np.mean([metric(int(s), rng.integers(0, n_generated[s], n_generated[s]),
                                  rng.integers(0, n_reference, n_reference)) for s in seeds])
    return _interval(value, reps, level, method)


def pooled_ratio(num: np.ndarray, den: np.ndarray, **kw) -> Interval:
    """Interval of ``mean over seeds of sum(num) / sum(den)`` over scenes.

    num, den: (S, K) per seed and scene (a (K,) array is one seed), e.g. true positives and
    |pred ∪ true| per scene for a pooled IoU, hits and boxes for the object hit rate.
    """
    num, den = np.atleast_2d(np.asarray(num, np.float64)), np.atleast_2d(np.asarray(den, np.float64))
    if num.shape != den.shape:
        raise TypError("pooled_ratio", "den", f"the shape of num {num.shape}", den.shape)

    def stat(c: np.ndarray, s: np.ndarray) -> float:
        n, d = num[s][:, c].sum(axis=1), den[s][:, c].sum(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return float(np.mean(n / d)) if (d > 0).all() else float("nan")

    return bootstrap(stat, num.shape[1], num.shape[0], **kw)


def mean_of_means(values: np.ndarray, **kw) -> Interval:
    """Interval of ``mean over seeds of mean over scenes`` of a per-scene figure (S, K) or (K,)
    (e.g. a mean Chamfer distance per scene); NaN entries are skipped."""
    v = np.atleast_2d(np.asarray(values, np.float64))

    def stat(c: np.ndarray, s: np.ndarray) -> float:
        with np.errstate(invalid="ignore"), np.testing.suppress_warnings() as sup:
            sup.filter(RuntimeWarning)
            return float(np.nanmean(np.nanmean(v[s][:, c], axis=1)))

    return bootstrap(stat, v.shape[1], v.shape[0], **kw)
