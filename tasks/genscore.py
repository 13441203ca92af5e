"""Scores of generated reference views against the truth, per pair, pooled with intervals.

Every method turns a held-out (ego, reference) pair into an occupancy grid of the reference
view (and a point cloud, for the object hit rate); :func:`score_pair` compares it with the
true reference view and keeps what each figure needs of that pair, so that :func:`summarize`
can pool them over any resample of scenes and training seeds (:mod:`typ.metrics.intervals`).
:data:`METRICS` declares every figure once: its per-pair value, its pooling, its label and
whether lower is better; the scorer, the metrics and the report's table all read it.

Figures (all pooled over the voxels / boxes / scans of the set, not averaged per view):
- ``iou``, ``precision``, ``recall`` over the whole grid; ``iou_<lo>-<hi>`` over the BEV cells
  at that planar distance from the reference sensor; ``iou_seen`` / ``iou_unseen`` over the
  cells the ego's cloud did / did not cover (:func:`typ.resim.coverage_mask`);
- ``iou_above_ground``: over voxels more than 0.3 m above the true view's local ground
  (:func:`typ.metrics.generation.above_ground`), where walls, vehicles and vegetation are;
- ``object_hit_rate``: of the labelled vehicles within 50 m of the reference sensor, the share
  with at least 10 of the method's points inside their box (what a detector needs);
- ``chamfer_m``: mean over views of the symmetric Chamfer distance of occupied voxel centres;
- ``jsd_r2dm``: BEV Jensen–Shannon distance (r2dm preset) between the set of true views and
  the set of generated ones, both as occupied voxel centres, with the bootstrap replicates'
  spread re-centred on it; ``mmd_r2dm`` likewise (a point estimate: its pairwise cost rules out
  a bootstrap).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import numpy as np
from scipy.spatial.distance import jensenshannon

from typ.metrics.bev import bev_histogram, mmd_bev
from typ.metrics.intervals import Interval, mean_of_means, pooled_ratio, bootstrap
from typ.metrics.generation import above_ground, object_hits
from typ.metrics.truth import chamfer_distance
from typ.voxel import Grid, voxel_centers

#: range bands (metres from the reference sensor) inside the ±51.2 m grid; its corners reach 72 m
BANDS = ((0.0, 20.0), (20.0, 40.0), (40.0, 80.0))
HIT_DISTANCE = 50.0
HIT_POINTS = 10
PRESET = "r2dm"


def band_label(lo: float, hi: float) -> str:
    return f"{lo:g}-{hi:g}"


def cell_distance(grid: Grid) -> np.ndarray:
    """(H, W) planar distance of each BEV cell centre from the sensor at the grid's origin."""
    return np.hypot(grid.centers(0)[:, None], grid.centers(1)[None, :])


def true_view_stats(truth: np.ndarray, grid: Grid) -> dict:
    """What every method's score of one pair shares: the true view's masks, centres and histogram.

    truth: (C, H, W) bool, the reference view on the reference sensor's grid.
    """
    hwc = truth.transpose(1, 2, 0)
    centres = voxel_centers(hwc, grid)
    return {"above": above_ground(hwc, grid).transpose(2, 0, 1), "centres": centres,
            "histogram": bev_histogram(centres, PRESET) if len(centres) else None}


@dataclass
class Pair:
    """One method's view of one held-out pair, as a metric reads it.

    occupancy, truth: (C, H, W) bool on the reference sensor's ``grid``; points: (N, >=3) the
    method's cloud in the reference frame; seen: (H, W) bool cells the ego saw; boxes: (K, 7) the
    reference view's labelled vehicles; stats: :func:`true_view_stats` of ``truth``.
    """

    occupancy: np.ndarray
    points: np.ndarray
    truth: np.ndarray
    seen: np.ndarray
    boxes: np.ndarray
    grid: Grid
    stats: dict
    _counts: dict = field(default_factory=dict, repr=False)

    @cached_property
    def centres(self) -> np.ndarray:
        """(M, 3) the occupied voxel centres of the method's view."""
        return voxel_centers(self.occupancy.transpose(1, 2, 0), self.grid)

    @cached_property
    def distance(self) -> np.ndarray:
        """(H, W) planar distance of each BEV cell from the reference sensor (:func:`cell_distance`)."""
        return cell_distance(self.grid)

    def counts(self, mask: str) -> tuple[int, int, int]:
        """(true positives, false positives, false negatives) over the voxels of ``MASKS[mask]``."""
        if mask not in self._counts:
            where = MASKS[mask](self)
            o, t = (self.occupancy, self.truth) if where is None else (self.occupancy[where], self.truth[where])
            tp = int(np.count_nonzero(o & t))
            self._counts[mask] = (tp, int(np.count_nonzero(o)) - tp, int(np.count_nonzero(t)) - tp)
        return self._counts[mask]


def _band(lo: float, hi: float) -> Callable[[Pair], np.ndarray]:
    def where(p: Pair) -> np.ndarray:
        return np.broadcast_to((p.distance >= lo) & (p.distance < hi), p.truth.shape)
    return where


#: where an IoU is counted: name -> a pair's (C, H, W) bool selection of voxels (None: all of them).
#: ``seen`` / ``unseen``: the BEV cells the ego's cloud did / did not cover
#: (:func:`typ.resim.coverage_mask`); ``above_ground``: voxels more than 0.3 m above the true
#: view's local ground (:func:`typ.metrics.generation.above_ground`), where walls, vehicles and vegetation are
MASKS: dict[str, Callable[[Pair], np.ndarray | None]] = {
    "all": lambda p: None,
    **{band_label(lo, hi): _band(lo, hi) for lo, hi in BANDS},
    "seen": lambda p: np.broadcast_to(p.seen, p.truth.shape),
    "unseen": lambda p: np.broadcast_to(~p.seen, p.truth.shape),
    "above_ground": lambda p: p.stats["above"],
}


@dataclass
class Pooling:
    """What pooling a figure over a set of pairs sees: the pairs' scenes (the resampled unit), the
    number of training seeds, the true views and the bootstrap's options."""

    cluster: np.ndarray                 # (pairs,) the scene index of each pair
    scenes: int
    seeds: int
    truth_histograms: list[np.ndarray]
    truth_centres: list[np.ndarray]
    kw: dict

    def per_scene(self, values: np.ndarray) -> np.ndarray:
        """(S, pairs, ...) -> (S, K, ...): each scene's sum."""
        out = np.zeros((self.seeds, self.scenes, *values.shape[2:]))
        for k in range(self.scenes):
            out[:, k] = values[:, self.cluster == k].sum(axis=1)
        return out


def pool_ratio(values: list[list], pool: Pooling) -> Interval:
    """Per-pair (numerator, denominator) counts summed over each scene's pairs, then the ratio
    of the sums (:func:`typ.metrics.intervals.pooled_ratio`): a figure pooled over voxels or boxes."""
    c = pool.per_scene(np.array(values, dtype=np.float64))
    return pooled_ratio(c[..., 0], c[..., 1], **pool.kw)


def pool_scene_mean(values: list[list], pool: Pooling) -> Interval:
    """Per-pair figures (NaN: undefined) averaged per scene, then over scenes and seeds."""
    v = np.array(values, dtype=np.float64)
    per_scene = np.stack([np.array([np.nanmean(v[s, pool.cluster == k]) if np.isfinite(v[s, pool.cluster == k]).any()
                                    else np.nan for k in range(pool.scenes)]) for s in range(pool.seeds)])
    return mean_of_means(per_scene, **pool.kw)


def pool_jsd(values: list[list], pool: Pooling) -> Interval:
    """BEV Jensen–Shannon distance between the set of true views and the set of generated ones
    (per-pair BEV histograms summed), with the bootstrap replicates' spread re-centred on it."""
    gen_h = pool.per_scene(np.array([[h.ravel() for h in row] for row in values]))
    true_h = pool.per_scene(np.array([h.ravel() for h in pool.truth_histograms])[None])[0]

    def jsd(c: np.ndarray, s: np.ndarray) -> float:
        a, b = true_h[c].sum(0), gen_h[s][:, c].sum(1)
        if a.sum() == 0 or (b.sum(axis=1) == 0).any():
            return float("nan")
        return float(np.mean([jensenshannon(a / a.sum(), g / g.sum()) for g in b]))

    # resampled scenes bias a pooled JSD upwards (repeats make a set less varied): the replicates'
    # spread, re-centred on the figure. "basic" reflected the bias into an interval wholly below
    # the figure (0.219 [0.166, 0.207] in a fresh run)
    j = bootstrap(jsd, pool.scenes, pool.seeds, method="recentred", **pool.kw)
    return Interval(j.value, max(0.0, j.low), j.high, j.level)


def pool_mmd(values: list[list], pool: Pooling) -> Interval:
    """BEV MMD between the true and the generated sets of occupied voxel centres, mean over seeds
    (a point estimate: its pairwise cost rules out a bootstrap)."""
    mmd = [mmd_bev([c for c in pool.truth_centres if len(c)], [c for c in row if len(c)] or [np.zeros((1, 3))],
                   preset=PRESET) for row in values]
    return Interval(float(np.mean(mmd)), float("nan"), float("nan"))


@dataclass(frozen=True)
class Metric:
    """A generation figure: its value for one pair and how the pairs' values pool into an
    :class:`~typ.metrics.intervals.Interval`, with the report's column label."""

    label: str
    of_pair: Callable[[Pair], object]
    pool: Callable[[list[list], Pooling], Interval]
    lower_is_better: bool = False
    in_table: bool = True               # a column of the generation table (else metrics only)


def _iou(mask: str) -> Callable[[Pair], tuple[int, int]]:
    def of_pair(p: Pair) -> tuple[int, int]:
        tp, fp, fn = p.counts(mask)
        return tp, tp + fp + fn
    return of_pair


def _chamfer(p: Pair) -> float:
    true_centres = p.stats["centres"]
    return chamfer_distance(p.centres, true_centres) if len(p.centres) and len(true_centres) else float("nan")


def _histogram(p: Pair) -> np.ndarray:
    return bev_histogram(p.centres, PRESET) if len(p.centres) else np.zeros_like(p.stats["histogram"])


_MASK_LABELS = {"seen": "IoU seen", "unseen": "IoU unseen", "above_ground": "IoU above ground",
                **{band_label(lo, hi): f"IoU {lo:g}–{hi:g} m" for lo, hi in BANDS}}

#: every generation figure, by its name in the metrics, in the generation table's column order.
#: A new figure is one entry here (its per-pair function may live in :mod:`typ.metrics`).
METRICS: dict[str, Metric] = {
    "iou": Metric("IoU", _iou("all"), pool_ratio),
    **{f"iou_{mask}": Metric(_MASK_LABELS.get(mask, f"IoU {mask}"), _iou(mask), pool_ratio)
       for mask in MASKS if mask != "all"},
    "precision": Metric("precision", lambda p: (p.counts("all")[0], sum(p.counts("all")[:2])), pool_ratio,
                        in_table=False),
    "recall": Metric("recall", lambda p: (p.counts("all")[0], p.counts("all")[0] + p.counts("all")[2]), pool_ratio,
                     in_table=False),
    "object_hit_rate": Metric("object hit rate", lambda p: object_hits(p.points, p.boxes, max_distance=HIT_DISTANCE,
                                                                       min_points=HIT_POINTS), pool_ratio),
    "chamfer_m": Metric("Chamfer m", _chamfer, pool_scene_mean, lower_is_better=True),
    "jsd_r2dm": Metric("JSD", _histogram, pool_jsd, lower_is_better=True),
    "mmd_r2dm": Metric("MMD", lambda p: p.centres, pool_mmd, lower_is_better=True),
}


class PairScore(dict):
    """One method's view of one pair, scored: metric name -> its per-pair value (:data:`METRICS`)."""


def score_pair(occupancy: np.ndarray, points: np.ndarray, truth: np.ndarray, seen: np.ndarray, boxes: np.ndarray,
               grid: Grid, truth_stats: dict) -> PairScore:
    """Every metric's per-pair value of one generated view against its truth (:class:`Pair`'s
    arguments, in its order)."""
    pair = Pair(occupancy, points, truth, seen, boxes, grid, truth_stats)
    return PairScore((name, metric.of_pair(pair)) for name, metric in METRICS.items())


def summarize(scores: list[list[PairScore]], scenes: list[str], truth_histograms: list[np.ndarray],
              truth_centres: list[np.ndarray], *, n_boot: int = 1000, seed: int = 0) -> dict[str, Interval]:
    """Pooled figures with bootstrap intervals over scenes (and seeds).

    scores[s][i]: the method's score of pair i under training seed s (every seed scores the
    same pairs); scenes[i]: the scene of pair i (the resampled unit); truth_histograms[i] /
    truth_centres[i]: the true view of pair i.
    """
    names = sorted(set(scenes))
    pool = Pooling(np.array([names.index(s) for s in scenes]), len(names), len(scores), truth_histograms,
                   truth_centres, {"n_boot": n_boot, "seed": seed})
    return {name: metric.pool([[p[name] for p in row] for row in scores], pool) for name, metric in METRICS.items()}


def lower_is_better(figure: str) -> bool:
    return figure in METRICS and METRICS[figure].lower_is_better


def pairwise_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Pooled IoU between two sets of samples of the same pairs (N, C, H, W) bool: how much two
    draws of the generator agree. 1 means the sample ignores its noise."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else float("nan")
