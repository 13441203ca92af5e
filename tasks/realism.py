"""Scan-pattern realism of generated reference views: is it a scan of the reference LiDAR?

IoU says whether a view has the right voxels; a detector trained on generated views also sees
how the points lie. Per method, on the same held-out pairs as :mod:`tasks.evaluate_generation`,
against the true reference scans:

- ``on_beam``: the fraction of the view's points within ±0.05° of one of the reference sensor's
  beam elevations, seen from the beam's origin (:func:`typ.sensors.fit.beam_residuals`). A scan
  cast with the sensor lies on its beams; voxel centres and another pose's scan do not.
- ``row_profile_l1``: the range-image row-occupancy profile (per beam row, the fraction of the
  sensor's azimuth bins with a return, :func:`typ.projection.range_image` on the sensor's own
  layout), averaged over the set's views; the figure is the mean absolute difference, over rows,
  between the method's profile and the truth's. 0: the rows fill as the real sensor's do.
- ``frid`` / ``fpvd``: Fréchet distances between the true and the generated views in the feature
  spaces of the networks the ``ddpm`` stage trains (:mod:`tasks.lidar_features`: a range-image
  and a voxel segmentation network). Without them (no ``ddpm`` stage run) the two are left out,
  with the reason.

Every figure is pooled over the pairs and given with a bootstrap interval over scenes and
training seeds, as the accuracy table is: a resample draws scenes, and both the truth and the
method's views are those of the drawn scenes' pairs (set distances use the "recentred" interval,
a repeat-biased set figure's, :func:`typ.metrics.intervals.bootstrap`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from typ.metrics.frechet import frechet_from_features
from typ.metrics.intervals import Interval, bootstrap, pooled_ratio
from typ.projection import RangeLayout, range_image
from typ.sensors.fit import beam_residuals

#: a point is on a beam within this many degrees of its elevation (the tolerance the generation targets use)
ON_BEAM_DEG = 0.05
FEATURES = ("frid", "fpvd")
#: figure -> True where lower is better
LOWER_IS_BETTER = {"on_beam": False, "row_profile_l1": True, "frid": True, "fpvd": True}
#: the realism table's columns (the generation report's), in order: (figure, label with its direction)
COLUMNS = [(figure, f"{label} {'↓' if LOWER_IS_BETTER[figure] else '↑'}")
           for figure, label in (("on_beam", f"on a beam ±{ON_BEAM_DEG}°"), ("row_profile_l1", "row profile L1"),
                                 ("frid", "FRID†"), ("fpvd", "FPVD†"))]


@dataclass
class ViewPattern:
    """What one view contributes to the pooled scan-pattern figures."""

    on_beam: int        # points within ON_BEAM_DEG of a beam
    points: int         # points at or beyond the sensor's minimum range
    rows: np.ndarray    # (H,) int64 occupied pixels per range-image row (row 0 = highest beam)


def view_pattern(points: np.ndarray, sensor, layout: RangeLayout) -> ViewPattern:
    """The scan pattern of (N, >=3) ``points`` in the reference sensor's frame."""
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    xyz = xyz[np.hypot(xyz[:, 0], xyz[:, 1]) >= max(float(sensor.min_range), 1e-9)]
    if len(xyz) == 0:
        return ViewPattern(0, 0, np.zeros(layout.height, dtype=np.int64))
    _, residual = beam_residuals(xyz, sensor.elevations_deg, getattr(sensor, "beam_heights_m", ()))
    rows = (range_image(xyz, layout) > 0).sum(axis=1).astype(np.int64)
    return ViewPattern(int(np.count_nonzero(np.abs(residual) <= ON_BEAM_DEG)), len(xyz), rows)


def layout_of(sensor) -> RangeLayout:
    """The sensor's own range-image layout: one row per beam, one column per azimuth step."""
    return RangeLayout.from_sensor(sensor)


def load_feature_nets(folder: Path):
    """The FRID / FPVD networks the ``ddpm`` stage saved under ``folder`` (``features/``), or the
    reason they cannot be used (a str)."""
    from models.lidar_features import SegmentationFeatureNet
    from typ.artifacts import CONFIG, load_module
    from tasks.lidar_features import FeatureNets
    from typ.voxel import Grid

    missing = [k for k in ("range", "voxel") if not (folder / k / CONFIG).is_file()]
    if missing:
        return (f"{folder}/{missing[0]} holds no trained network (the ddpm stage trains the FRID / FPVD "
                "feature networks)")
    range_net, meta = load_module(folder / "range", SegmentationFeatureNet.from_config, "ddpm")
    voxel_net, vmeta = load_module(folder / "voxel", SegmentationFeatureNet.from_config, "ddpm")
    return FeatureNets(range_net, voxel_net, RangeLayout.from_dict(meta["layout"], f"{folder}/range"),
                       Grid.from_dict(vmeta["voxel_grid"], f"{folder}/voxel"))


class RealismScorer:
    """Patterns (and features, with the networks) of every method's views, then their figures."""

    def __init__(self, sensor, scenes: list[str], truth_points: list[np.ndarray], nets=None):
        self.sensor, self.layout, self.nets, self.scenes = sensor, layout_of(sensor), nets, scenes
        self.patterns: dict[str, list[list[ViewPattern]]] = {}
        self.features: dict[str, list[dict[str, np.ndarray]]] = {}
        self.truth = [self.pattern(p) for p in truth_points]
        self.truth_features = self._features(truth_points)

    def pattern(self, points: np.ndarray) -> ViewPattern:
        return view_pattern(points, self.sensor, self.layout)

    def _features(self, clouds: list[np.ndarray]) -> dict[str, np.ndarray] | None:
        if self.nets is None:
            return None
        return self.nets.features([np.asarray(c, dtype=np.float32)[:, :3] for c in clouds])

    def add(self, method: str, points: list[np.ndarray]) -> None:
        """One training seed's views of every pair (in the pairs' order)."""
        self.patterns.setdefault(method, []).append([self.pattern(p) for p in points])
        if self.nets is not None:
            self.features.setdefault(method, []).append(self._features(points))

    def summarize(self, *, n_boot: int = 1000, seed: int = 0) -> dict[str, dict[str, Interval]]:
        """{"truth" and every method added: {figure: Interval}}."""
        out = {"truth": self._summarize([self.truth], [self.truth_features] if self.nets else None, n_boot, seed)}
        for method, rows in self.patterns.items():
            out[method] = self._summarize(rows, self.features.get(method), n_boot, seed)
        return out

    def truth_floor(self) -> dict[str, float]:
        """FRID / FPVD between the true views of one half of the scenes (alternate scenes in
        sorted order) and those of the other: what two sets of real scans of this size score."""
        if self.nets is None:
            return {}
        names = sorted(set(self.scenes))
        half = np.array([names.index(s) % 2 == 0 for s in self.scenes])
        if half.sum() < 2 or (~half).sum() < 2:
            return {}
        return {k: frechet_from_features(self.truth_features[k][half], self.truth_features[k][~half]) for k in FEATURES}

    def _summarize(self, rows: list[list[ViewPattern]], feats: list[dict] | None, n_boot: int,
                   seed: int) -> dict[str, Interval]:
        names = sorted(set(self.scenes))
        cluster = np.array([names.index(s) for s in self.scenes])
        K, S = len(names), len(rows)
        members = [np.flatnonzero(cluster == k) for k in range(K)]
        kw = {"n_boot": n_boot, "seed": seed}

        def per_scene(values: np.ndarray) -> np.ndarray:  # (S, pairs, ...) -> (S, K, ...)
            return np.stack([values[:, m].sum(axis=1) for m in members], axis=1)

        counts = per_scene(np.array([[(v.on_beam, v.points) for v in row] for row in rows], dtype=np.float64))
        out = {"on_beam": pooled_ratio(counts[..., 0], counts[..., 1], **kw)}
        width = self.layout.width
        gen_rows = per_scene(np.array([[v.rows for v in row] for row in rows], dtype=np.float64))   # (S, K, H)
        true_rows = per_scene(np.array([[v.rows for v in self.truth]], dtype=np.float64))[0]      # (K, H)
        views = np.array([len(m) for m in members], dtype=np.float64)

        def profile_l1(c: np.ndarray, s: np.ndarray) -> float:
            n = views[c].sum() * width
            truth = true_rows[c].sum(axis=0) / n
            return float(np.mean([np.abs(gen_rows[i][c].sum(axis=0) / n - truth).mean() for i in s]))

        out["row_profile_l1"] = _nonnegative(bootstrap(profile_l1, K, S, method="recentred", **kw))
        if feats is not None:
            for i, key in enumerate(FEATURES):
                truth_f, gen_f = self.truth_features[key], [f[key] for f in feats]

                def fd(c: np.ndarray, s: np.ndarray, truth_f=truth_f, gen_f=gen_f) -> float:
                    idx = np.concatenate([members[k] for k in c])
                    return float(np.mean([frechet_from_features(truth_f[idx], gen_f[j][idx]) for j in s]))

                out[key] = _nonnegative(bootstrap(fd, K, S, method="recentred", n_boot=n_boot, seed=seed + 1 + i))
        return out

    def profiles(self, methods: list[str]) -> dict[str, list[float]]:
        """Per method (first seed) and the truth: the mean fraction of azimuth bins with a return
        in each beam row, lowest beam first (for the plot)."""
        def profile(views: list[ViewPattern]) -> list[float]:
            total = np.sum([v.rows for v in views], axis=0) / (len(views) * self.layout.width)
            return [round(float(x), 6) for x in total[::-1]]

        return {"truth": profile(self.truth),
                **{m: profile(self.patterns[m][0]) if m in self.patterns else [float("nan")] * self.layout.height
                   for m in methods}}


def _nonnegative(iv: Interval) -> Interval:
    """A distance's interval: the recentred replicates may reach below 0, the distance cannot."""
    return Interval(iv.value, max(0.0, iv.low), iv.high, iv.level)
