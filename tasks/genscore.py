"""Scores of generated reference views against the truth, per pair, pooled with intervals.

Every method turns a held-out (ego, reference) pair into an occupancy grid of the reference
view (and a point cloud, for the object hit rate); :func:`score_pair` compares it with the
true reference view and keeps the counts a pooled figure needs, so that :func:`summarize`
can pool them over any resample of scenes and training seeds (:mod:`typ.metrics.intervals`).

Figures (all pooled over the voxels / boxes / scans of the set, not averaged per view):
- ``iou``, ``precision``, ``recall`` over the whole grid; ``iou_<lo>-<hi>`` over the BEV cells
  at that planar distance from the reference sensor; ``iou_seen`` / ``iou_unseen`` over the
  cells the ego's cloud did / did not cover (:func:`typ.resim.coverage_mask`);
- ``iou_above_ground``: over voxels more than 0.3 m above the true view's local ground
  (:func:`typ.metrics.truth.above_ground`), where walls, vehicles and vegetation are;
- ``object_hit_rate``: of the labelled vehicles within 50 m of the reference sensor, the share
  with at least 10 of the method's points inside their box (what a detector needs);
- ``chamfer_m``: mean over views of the symmetric Chamfer distance of occupied voxel centres;
- ``jsd_r2dm``: BEV Jensen–Shannon distance (r2dm preset) between the set of true views and
  the set of generated ones, both as occupied voxel centres, with the basic (bias-reflected)
  bootstrap interval; ``mmd_r2dm`` likewise (a point estimate: its pairwise cost rules out a
  bootstrap).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.distance import jensenshannon

from typ.metrics.bev import bev_histogram, mmd_bev
from typ.metrics.intervals import Interval, mean_of_means, pooled_ratio, bootstrap
from typ.metrics.generation import above_ground, object_hits
from typ.metrics.truth import chamfer_distance
from typ.voxel import Grid, voxel_centers

#: range bands (metres from the reference sensor) inside the ±51.2 m grid; its corners reach 72 m
BANDS = ((0.0, 20.0), (20.0, 40.0), (40.0, 80.0))
MASKS = ("all", *(f"{lo:g}-{hi:g}" for lo, hi in BANDS), "seen", "unseen", "above_ground")
HIT_DISTANCE = 50.0
HIT_POINTS = 10
PRESET = "r2dm"


def band_label(lo: float, hi: float) -> str:
    return f"{lo:g}-{hi:g}"


def cell_distance(grid: Grid) -> np.ndarray:
    """(H, W) planar distance of each BEV cell centre from the sensor at the grid's origin."""
    return np.hypot(grid.centers(0)[:, None], grid.centers(1)[None, :])


@dataclass
class PairScore:
    """What one method's view of one pair contributes to the pooled figures."""

    counts: dict[str, tuple[int, int, int]]   # mask -> (tp, fp, fn)
    hits: tuple[int, int]                    # (vehicles hit, vehicles within HIT_DISTANCE)
    chamfer: float                           # NaN when either view is empty
    histogram: np.ndarray                    # (cells, cells) BEV histogram of the occupied voxel centres
    centres: np.ndarray = field(repr=False)  # (M, 3) occupied voxel centres (for MMD)


def true_view_stats(truth: np.ndarray, grid: Grid) -> dict:
    """What every method's score of one pair shares: the true view's masks, centres and histogram.

    truth: (C, H, W) bool, the reference view on the reference sensor's grid.
    """
    hwc = truth.transpose(1, 2, 0)
    centres = voxel_centers(hwc, grid)
    return {"above": above_ground(hwc, grid).transpose(2, 0, 1), "centres": centres,
            "histogram": bev_histogram(centres, PRESET) if len(centres) else None}


def score_pair(occupancy: np.ndarray, points: np.ndarray, truth: np.ndarray, seen: np.ndarray, boxes: np.ndarray,
               grid: Grid, truth_stats: dict) -> PairScore:
    """Counts of one generated view against its truth.

    occupancy, truth: (C, H, W) bool on the reference sensor's ``grid``; points: (N, >=3) the
    method's cloud in the reference frame (for the hit rate); seen: (H, W) bool cells the ego
    saw; boxes: (K, 7) the reference view's labelled vehicles; truth_stats: :func:`true_view_stats`.
    """
    dist = cell_distance(grid)
    columns = {"all": np.ones_like(seen), "seen": seen, "unseen": ~seen,
               **{band_label(lo, hi): (dist >= lo) & (dist < hi) for lo, hi in BANDS}}
    counts = {}
    for name, cols in columns.items():
        o, t = occupancy[:, cols], truth[:, cols]
        counts[name] = _tpfpfn(o, t)
    above = truth_stats["above"]
    counts["above_ground"] = _tpfpfn(occupancy[above], truth[above])
    centres = voxel_centers(occupancy.transpose(1, 2, 0), grid)
    true_centres = truth_stats["centres"]
    chamfer = chamfer_distance(centres, true_centres) if len(centres) and len(true_centres) else float("nan")
    histogram = bev_histogram(centres, PRESET) if len(centres) else np.zeros_like(truth_stats["histogram"])
    return PairScore(counts, object_hits(points, boxes, max_distance=HIT_DISTANCE, min_points=HIT_POINTS),
                     chamfer, histogram, centres)


def _tpfpfn(o: np.ndarray, t: np.ndarray) -> tuple[int, int, int]:
    tp = int(np.count_nonzero(o & t))
    return tp, int(np.count_nonzero(o)) - tp, int(np.count_nonzero(t)) - tp


def summarize(scores: list[list[PairScore]], scenes: list[str], truth_histograms: list[np.ndarray],
              truth_centres: list[np.ndarray], *, n_boot: int = 1000, seed: int = 0) -> dict[str, Interval]:
    """Pooled figures with bootstrap intervals over scenes (and seeds).

    scores[s][i]: the method's score of pair i under training seed s (every seed scores the
    same pairs); scenes[i]: the scene of pair i (the resampled unit); truth_histograms[i] /
    truth_centres[i]: the true view of pair i.
    """
    names = sorted(set(scenes))
    cluster = np.array([names.index(s) for s in scenes])
    K, S = len(names), len(scores)

    def per_scene(values: np.ndarray) -> np.ndarray:  # (S, pairs, ...) -> (S, K, ...)
        out = np.zeros((S, K, *values.shape[2:]))
        for k in range(K):
            out[:, k] = values[:, cluster == k].sum(axis=1)
        return out

    out: dict[str, Interval] = {}
    kw = {"n_boot": n_boot, "seed": seed}
    for mask in MASKS:
        c = per_scene(np.array([[p.counts[mask] for p in row] for row in scores], dtype=np.float64))
        tp, fp, fn = c[..., 0], c[..., 1], c[..., 2]
        key = "iou" if mask == "all" else f"iou_{mask}"
        out[key] = pooled_ratio(tp, tp + fp + fn, **kw)
        if mask == "all":
            out["precision"] = pooled_ratio(tp, tp + fp, **kw)
            out["recall"] = pooled_ratio(tp, tp + fn, **kw)
    hits = per_scene(np.array([[p.hits for p in row] for row in scores], dtype=np.float64))
    out["object_hit_rate"] = pooled_ratio(hits[..., 0], hits[..., 1], **kw)
    chamfer = np.array([[p.chamfer for p in row] for row in scores])
    chamfer_scene = np.stack([np.array([np.nanmean(chamfer[s, cluster == k]) if np.isfinite(chamfer[s, cluster == k]).any()
                                        else np.nan for k in range(K)]) for s in range(S)])
    out["chamfer_m"] = mean_of_means(chamfer_scene, **kw)
    gen_h = per_scene(np.array([[p.histogram.ravel() for p in row] for row in scores]))
    true_h = per_scene(np.array([h.ravel() for h in truth_histograms])[None])[0]

    def jsd(c: np.ndarray, s: np.ndarray) -> float:
        a, b = true_h[c].sum(0), gen_h[s][:, c].sum(1)
        if a.sum() == 0 or (b.sum(axis=1) == 0).any():
            return float("nan")
        return float(np.mean([jensenshannon(a / a.sum(), g / g.sum()) for g in b]))

    # resampled scenes bias a pooled JSD upwards (repeats make a set less varied): the replicates'
    # spread, re-centred on the figure. "basic" reflected the bias into an interval wholly below
    # the figure (0.219 [0.166, 0.207] in a fresh run)
    j = bootstrap(jsd, K, S, method="recentred", **kw)
    out["jsd_r2dm"] = Interval(j.value, max(0.0, j.low), j.high, j.level)
    mmd = [mmd_bev([c for c in truth_centres if len(c)], [p.centres for p in row if len(p.centres)] or [np.zeros((1, 3))],
                   preset=PRESET) for row in scores]
    out["mmd_r2dm"] = Interval(float(np.mean(mmd)), float("nan"), float("nan"))
    return out


def pairwise_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Pooled IoU between two sets of samples of the same pairs (N, C, H, W) bool: how much two
    draws of the generator agree. 1 means the sample ignores its noise."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else float("nan")
