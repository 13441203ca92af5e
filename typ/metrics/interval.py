"""Bootstrap intervals for the numbers reports print as ``mean [low, high]``.

Two estimators, both percentile bootstraps with an explicit seed (same inputs, same interval):

- :func:`mean_interval`: the mean of per-run values (e.g. one number per training seed).
- :func:`hierarchical_interval`: a set-level metric (JSD, MMD, Fréchet distance) of generated
  samples against a reference set, with both sources of spread at once: each replicate draws
  the training seeds with replacement, then, for every drawn seed, its generated samples and the
  reference samples with replacement, and averages the metric over the drawn seeds; the
  interval is centred on the estimate (see the function).
"""
from __future__ import annotations

from typing import Callable, Sequence

import numpy as np

from typ.errors import TypError

__all__ = ["hierarchical_interval", "mean_interval"]

WHERE = "bootstrap interval"


def _check(level: float, n_boot: int) -> None:
    if not 0.0 < level < 1.0:
        raise TypError(WHERE, "level", "a coverage in (0, 1), e.g. 0.95", level)
    if isinstance(n_boot, bool) or not isinstance(n_boot, int) or n_boot < 10:
        raise TypError(WHERE, "n_boot", "an integer >= 10", n_boot)


def _percentiles(values: np.ndarray, level: float) -> tuple[float, float]:
    tail = (1.0 - level) / 2.0 * 100.0
    lo, hi = np.percentile(values, [tail, 100.0 - tail])
    return float(lo), float(hi)


def mean_interval(values, *, level: float = 0.95, n_boot: int = 10000, seed: int = 0) -> tuple[float, float, float]:
    """(mean, low, high): the mean of ``values`` and the percentile bootstrap interval of the mean.

    One value gives a zero-width interval (nothing to resample). NaN values raise TypError.
    """
    _check(level, n_boot)
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size == 0 or not np.isfinite(v).all():
        raise TypError(WHERE, "values", "at least one finite value", v.tolist()[:5])
    means = v[np.random.default_rng(seed).integers(0, v.size, (n_boot, v.size))].mean(axis=1)
    return float(v.mean()), *_percentiles(means, level)


def hierarchical_interval(metric: Callable[[int, np.ndarray, np.ndarray], float], n_generated: Sequence[int],
                          n_reference: int, *, level: float = 0.95, n_boot: int = 1000,
                          seed: int = 0) -> tuple[float, float, float]:
    """(estimate, low, high) of a set metric over training seeds.

    metric(s, gen_index, ref_index): the metric of seed s's generated samples ``gen_index``
    against reference samples ``ref_index`` (index arrays, repeats allowed). n_generated[s]:
    how many samples seed s generated; n_reference: the reference set's size. The estimate
    is the mean over seeds of the metric on the full sets; the interval resamples seeds,
    then samples (see the module doc), and is re-centred: set metrics such as a JSD or a
    Fréchet distance grow when a set holds repeats (fewer distinct scans), so the replicates'
    percentiles sit above the estimate; the interval keeps their spread around the estimate,
    ``[low, high] = percentiles - (median of the replicates - estimate)``.
    """
    _check(level, n_boot)
    n_seeds = len(n_generated)
    if n_seeds < 1 or min(n_generated) < 1 or n_reference < 1:
        raise TypError(WHERE, "sizes", "at least one seed with >= 1 sample and a non-empty reference",
                       [list(n_generated), n_reference])
    every_ref = np.arange(n_reference)
    estimate = float(np.mean([metric(s, np.arange(n), every_ref) for s, n in enumerate(n_generated)]))
    rng = np.random.default_rng(seed)
    reps = np.empty(n_boot)
    for b in range(n_boot):
        seeds = rng.integers(0, n_seeds, n_seeds)
        reps[b] = np.mean([metric(int(s), rng.integers(0, n_generated[s], n_generated[s]),
                                  rng.integers(0, n_reference, n_reference)) for s in seeds])
    shift = float(np.median(reps)) - estimate
    lo, hi = _percentiles(reps, level)
    return estimate, lo - shift, hi - shift
