"""Real scans at other poses: every view generated for pose j from scan i of a real drive, scored
against the real scan j (LiDAR novel-view synthesis, at TYP's distances).

A drive in the KITTI odometry layout (:mod:`typ.formats.kitti_odometry`) has what simulated pairs
have: the scan a LiDAR took at pose j is what a LiDAR there sees. For every ordered pair of scans
(ego frame i, reference frame j) whose LiDAR origins are :data:`MIN_DISTANCE`-:data:`MAX_DISTANCE`
m apart (:func:`build_pairs`), each method of :data:`METHODS` makes j's view from scan i and the
pose j alone (:class:`PairInput` holds nothing else; the map oracle's map leaves scan j out), and
:func:`score_view` scores it against scan j with LiDAR4D's metrics (:mod:`typ.metrics.novel_view`).
Figures are means over the pairs of a distance band (:data:`BANDS`, and ``all``), with 95 %
bootstrap intervals that resample ego frames (pairs of one ego share its scan), and paired
differences against the floor (copy), re-simulation and the cast without TYP's cells
(:func:`summarize`).

One car, two times: at time j the drive's own car has left pose i, so the reference's box map y_r
does not hold it (:func:`reference_for`), unlike ``typ generate``'s simultaneous references. The
drive has no labels, so y_r is empty. Other traffic moves between i and j; no method can know
how, and the truth keeps it.
"""
from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipelines.typ import Reference, reference_at
from tasks.generate import Generator
from typ.config import CastConfig
from typ.errors import TypError
from typ.formats.kitti_odometry import Sequence as Drive, read_sequence
from typ.geometry import invert, points_in_boxes, transform_points
from typ.metrics import novel_view as nv
from typ.metrics.intervals import Interval, bootstrap_figures
from typ.resim import EGO_CAR_LWH, build_surface, coverage_mask, in_mask
from typ.scene import AgentView, vehicle_mask
from typ.sim.sensor import SensorSpec
from typ.voxel import Grid, box_map

#: the pair rule: ordered pairs of scans whose LiDAR origins are this far apart (metres, inclusive)
MIN_DISTANCE, MAX_DISTANCE = 2.0, 40.0
#: distance bands (metres): [low, high), the last one closed at MAX_DISTANCE
BANDS = (("0-10", 0.0, 10.0), ("10-20", 10.0, 20.0), ("20-40", 20.0, 40.0))
ALL = "all"
BAND_NAMES = tuple(b for b, _, _ in BANDS) + (ALL,)


@dataclass(frozen=True)
class Figure:
    label: str
    lower_is_better: bool = False


#: every figure of a pair, in the JSON's order (the first nine are the benchmark's headline figures)
METRICS: dict[str, Figure] = {
    "chamfer": Figure("Chamfer (m²)", True), "fscore": Figure("F-score"), "precision": Figure("precision"),
    "recall": Figure("recall"), "depth_rmse": Figure("depth RMSE (m)", True),
    "depth_medae": Figure("depth MedAE (m)", True), "raydrop_acc": Figure("ray-drop acc."),
    "on_beam": Figure(f"on a beam ±{nv.ON_BEAM_DEG}°"), "row_l1": Figure("row L1", True),
    "precision_seen": Figure("precision, seen cells"), "recall_seen": Figure("recall, seen cells"),
    "precision_unseen": Figure("precision, unseen cells"), "recall_unseen": Figure("recall, unseen cells"),
}
#: the paired differences reported: method - baseline, for every method
BASELINES = ("copy", "resim", "cast_no_typ")
#: the map oracle: a scan's surfel this near (m) to a surfel of a scan seen from nearer is dropped
MAP_OVERLAP = 1.0


@dataclass(frozen=True)
class Pair:
    """Ego frame ``ego`` (the scan a method sees), reference frame ``reference`` (the pose it
    generates for and the scan it is scored against), ``distance`` m apart."""

    ego: int
    reference: int
    distance: float

    @property
    def band(self) -> str:
        return next(name for name, lo, hi in BANDS if lo <= self.distance < hi or
                    (hi == MAX_DISTANCE and self.distance == hi))


def build_pairs(poses: np.ndarray, *, min_distance: float = MIN_DISTANCE,
                max_distance: float = MAX_DISTANCE) -> list[Pair]:
    """Every ordered pair (i, j), i != j, of the (N, 4, 4) LiDAR poses whose origins lie
    ``[min_distance, max_distance]`` m apart, both directions, sorted by (i, j)."""
    t = np.asarray(poses, dtype=np.float64)[:, :3, 3]
    d = np.linalg.norm(t[:, None] - t[None], axis=2)
    return [Pair(i, j, float(d[i, j])) for i in range(len(t)) for j in range(len(t))
            if i != j and min_distance <= d[i, j] <= max_distance]


# ---------------------------------------------------------------- what a method sees


@dataclass(frozen=True)
class PairInput:
    """Everything a method may use to make reference frame j's view: scan i and poses, never scan j.

    reference: x_e', y_r and scan i in j's sensor frame (:func:`reference_for`); sensor: the
    drive's LiDAR, cast at pose j; grid: the generator's grid in that LiDAR's frame; seed: the
    pair's sampling seed; map_surfels: the oracle's map in j's frame, built without scan j.
    """

    reference: Reference
    sensor: SensorSpec
    grid: Grid
    seed: int
    generator: Generator | None = None
    cast: CastConfig = CastConfig()
    map_surfels: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None


def reference_for(ego: AgentView, reference_pose: np.ndarray, grid: Grid) -> Reference:
    """:func:`pipelines.typ.reference_at` at ``reference_pose``, without the ego's own car, which
    :func:`reference_at` adds to y_r for a reference beside the ego at the same time: on one drive
    the car has moved on to pose j (module doc)."""
    ref = reference_at(ego, reference_pose, "reference", None, grid)
    boxes, labels, ids = ref.boxes[:-1], ref.labels[:-1], ref.ids[:-1]
    return dataclasses.replace(ref, boxes=boxes, labels=labels, ids=ids,
                               y_r=box_map(boxes, grid).transpose(2, 0, 1))


def copy_view(p: PairInput) -> np.ndarray:
    """The floor: scan i moved into j's frame."""
    return p.reference.ego_points[:, :3]


def resim_view(p: PairInput) -> np.ndarray:
    """Scan i as surfels, cast from pose j with the drive's LiDAR (:mod:`typ.resim`)."""
    from typ.resim import resimulated_points

    return resimulated_points(p.reference.ego_points, p.sensor, EGO_CAR_LWH)


def compose_view(compose: str) -> Callable[[PairInput], np.ndarray]:
    """What ``typ generate`` writes with ``generate.compose: <compose>`` (:meth:`pipelines.typ.TYPPipeline.generate`)."""
    def view(p: PairInput) -> np.ndarray:
        if p.generator is None:
            raise TypError("typ novel-view", "generator", f"a trained generator for compose {compose!r}", None)
        return p.generator.pipe.generate([p.reference], p.grid, p.seed, sensor=p.sensor, compose=compose,
                                         cast=p.cast)[0][:, :3]

    view.__name__ = f"{compose}_view"
    return view


def cast_no_typ_view(p: PairInput) -> np.ndarray:
    """The cast view with no generated cell: scan i's surfels, the road, y_r's boxes, cast from
    pose j exactly as ``compose: cast`` casts them (same random draws), so that ``cast`` minus
    this is what the learned generator adds."""
    from typ.resim import own_car_box
    from typ.castview import cast_view

    r = p.reference
    empty = np.zeros((p.grid.shape[2], *p.grid.shape[:2]), dtype=bool)
    # carving removes generated cells the ego saw empty: with none, it changes nothing and takes seconds
    params = dataclasses.replace(p.cast, carve=False)
    return cast_view(r.ego_points, empty, p.grid, p.sensor, np.random.default_rng([p.seed, 0, 2]), params=params,
                     ego_origin=r.ego_origin, label_boxes=r.boxes[vehicle_mask(r.labels)],
                     exclude_boxes=own_car_box(p.sensor, EGO_CAR_LWH))


def map_oracle_view(p: PairInput) -> np.ndarray:
    """The ceiling: the surfels of every other scan of the drive (never j's), cast from pose j
    without noise or drop. Rays start ``min_range`` out (:func:`typ.castview.cast`): another scan
    may have seen a car or cyclist where the LiDAR stands at j, and a surfel around the sensor
    would blind every ray through it."""
    from typ.castview import cast

    if p.map_surfels is None:
        raise TypError("typ novel-view", "map_oracle", "the drive's other scans", None)
    ideal = dataclasses.replace(p.sensor, dropout=0.0, range_noise_std=0.0)
    return cast(*p.map_surfels(), ideal, np.random.default_rng(p.seed))


@dataclass(frozen=True)
class Method:
    label: str
    view: Callable[[PairInput], np.ndarray]
    #: needs the trained generator (``selftrain``'s)
    learned: bool = False


#: every method, in the report's order; keys are ``compose`` names where ``typ generate`` has one
METHODS: dict[str, Method] = {
    "copy": Method("copy (scan i moved to pose j: the floor)", copy_view),
    "resim": Method("re-simulation (scan i's surfels cast)", resim_view),
    "hybrid": Method("hybrid (re-simulation where i saw, TYP elsewhere)", compose_view("hybrid"), learned=True),
    "cast": Method("cast (scan i's surfels + TYP's cells, cast once)", compose_view("cast"), learned=True),
    "typ": Method("TYP's sample alone (compose: generated)", compose_view("generated"), learned=True),
    "cast_no_typ": Method("cast without TYP's cells", cast_no_typ_view),
    "map_oracle": Method("map oracle (every other scan's surfels cast: the ceiling)", map_oracle_view),
}


# ---------------------------------------------------------------- the drive and its scans


class DriveScans:
    """A drive's scans, each read once, and the oracle's per-scan surfels, each built once in the
    first scan's frame (the world) and reused for every reference frame."""

    def __init__(self, drive: Drive, read: Callable[[int], np.ndarray] | None = None):
        self.drive = drive
        self.scan = Once(read or drive.points)
        self._surfels = Once(self._build_surfels)

    def view(self, k: int) -> AgentView:
        return AgentView("ego", self.scan(k), self.drive.poses[k].copy(), where=str(self.drive.scans[k]))

    def surfels(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Scan k's surfels (:func:`typ.resim.build_surface`), vertices in the world frame."""
        return self._surfels(k)

    def _build_surfels(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        verts, tris = build_surface(self.scan(k)[:, :3])
        return transform_points(self.drive.poses[k], verts.astype(np.float64)), tris

    def map_without(self, j: int, sensor: SensorSpec) -> tuple[np.ndarray, np.ndarray]:
        """Every scan's surfels but scan j's, in j's sensor frame: the drive's map without j.

        Where two scans saw one place, the surfels of the scan whose LiDAR was nearer are kept
        (finer: a surfel's size grows with the gaps between its points) and the other's within
        :data:`MAP_OVERLAP` m of them dropped; a plain union lets the coarse surfels of far scans
        stand in front of the surfaces (on KITTI seq 00: F-score 0.69-0.71 against 0.72-0.78).
        The surfels inside j's own car (its LiDAR does not see its body) are left out too."""
        from scipy.spatial import cKDTree

        from typ.resim import own_car_box

        others = [k for k in range(len(self.drive)) if k != j]
        origins = self.drive.poses[:, :3, 3]
        quads = {k: self.surfels(k)[0].reshape(-1, 4, 3) for k in others}
        centres = {k: q.mean(axis=1) for k, q in quads.items()}
        trees = {k: cKDTree(c) for k, c in centres.items()}
        kept = []
        for k in others:
            c = centres[k]
            own = np.linalg.norm(c - origins[k], axis=1)
            keep = np.ones(len(c), dtype=bool)
            for other in (o for o in others if o != k):
                nearer = np.flatnonzero(np.linalg.norm(c - origins[other], axis=1) < own)
                if len(nearer):
                    dist, _ = trees[other].query(c[nearer], distance_upper_bound=MAP_OVERLAP)
                    keep[nearer[np.isfinite(dist)]] = False
            kept.append(quads[k][keep])
        v = transform_points(invert(self.drive.poses[j]), np.concatenate(kept).reshape(-1, 3)).reshape(-1, 4, 3)
        v = v[~points_in_boxes(v.mean(axis=1), own_car_box(sensor, EGO_CAR_LWH))[:, 0]]
        base = 4 * np.arange(len(v), dtype=np.int64)[:, None]
        t = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
        return v.reshape(-1, 3).astype(np.float32), t.astype(np.uint32)


# ---------------------------------------------------------------- scoring


def evaluation_grid(grid: Grid, max_range: float = nv.MAX_RANGE) -> Grid:
    """The BEV cells the seen / unseen split is made on: ``grid``'s cell size and height range
    over ``[-max_range, max_range]`` in x and y (the metrics' reach, beyond the generator's grid)."""
    cells = [int(np.ceil(2 * max_range / s)) for s in grid.voxel_size[:2]]
    half = [c * s / 2 for c, s in zip(cells, grid.voxel_size[:2])]
    return Grid((-half[0], half[0]), (-half[1], half[1]), grid.z_range, (cells[0], cells[1], grid.shape[2]))


@dataclass
class Truth:
    """Scan j as every figure needs it: its points within range and its range image."""

    points: np.ndarray
    image: np.ndarray
    tree: object = None      # cKDTree(points), built once for every view scored against it


def truth_of(points: np.ndarray, sensor: SensorSpec) -> Truth:
    from scipy.spatial import cKDTree

    xyz = nv.within_range(points)
    return Truth(xyz, range_image(xyz, sensor)[0], cKDTree(xyz))


def range_image(points: np.ndarray, sensor: SensorSpec) -> tuple[np.ndarray, np.ndarray]:
    """(the range image on ``sensor``'s own layout, each point's angle from its beam in degrees)."""
    rows, residuals = nv.beams(points, sensor.elevations_deg, sensor.beam_heights_m)
    return nv.sensor_range_image(points, rows, n_beams=len(sensor.elevations_deg), azimuth_bins=sensor.n_azimuths,
                                 min_range=sensor.min_range), residuals


def score_view(points: np.ndarray, truth: Truth, sensor: SensorSpec, seen: np.ndarray, eval_grid: Grid) -> dict:
    """Every figure of :data:`METRICS` for one view (points in j's frame) against the truth;
    ``seen``: (H, W) the cells of ``eval_grid`` scan i covered."""
    pred = nv.within_range(points)
    to_true, to_pred = nv.nearest_squared(pred, truth.points, tree=truth.tree), nv.nearest_squared(truth.points, pred)
    f, precision, recall = nv.fscore(to_true, to_pred)
    image, residuals = range_image(pred, sensor)
    rmse, medae = nv.depth_errors(image, truth.image)
    on, counted = nv.on_beam(pred, residuals, min_range=sensor.min_range)
    pred_seen, true_seen = in_mask(pred, seen, eval_grid), in_mask(truth.points, seen, eval_grid)
    p_seen, r_seen = nv.masked_precision_recall(to_true, to_pred, pred_seen, true_seen)
    p_unseen, r_unseen = nv.masked_precision_recall(to_true, to_pred, ~pred_seen, ~true_seen)
    return {"chamfer": nv.chamfer(to_true, to_pred), "fscore": f, "precision": precision, "recall": recall,
            "depth_rmse": rmse, "depth_medae": medae, "raydrop_acc": nv.raydrop_accuracy(image, truth.image),
            "on_beam": on / counted if counted else float("nan"), "row_l1": nv.row_l1(image, truth.image),
            "precision_seen": p_seen, "recall_seen": r_seen, "precision_unseen": p_unseen,
            "recall_unseen": r_unseen}


@dataclass
class PairResult:
    pair: Pair
    scores: dict[str, dict[str, float]] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)       # making the view
    score_seconds: dict[str, float] = field(default_factory=dict)  # scoring it
    views: dict[str, np.ndarray] = field(default_factory=dict)    # kept for the pictures only


def pair_seed(seed: int, pair: Pair) -> int:
    return int(seed) * 1_000_003 + 1009 * pair.ego + pair.reference


def pair_input(scans: DriveScans, pair: Pair, sensor: SensorSpec, grid: Grid, *, generator: Generator | None = None,
               cast: CastConfig = CastConfig(), seed: int = 0) -> PairInput:
    """What the methods get for ``pair``: scan i and pose j (:class:`PairInput`), the map without j."""
    reference = reference_for(scans.view(pair.ego), scans.drive.poses[pair.reference], grid)
    return PairInput(reference, sensor, grid, pair_seed(seed, pair), generator, cast,
                     lambda: scans.map_without(pair.reference, sensor))


def run_pairs(scans: DriveScans, pairs: Sequence[Pair], sensor: SensorSpec, grid: Grid, methods: Sequence[str], *,
              generator: Generator | None = None, cast: CastConfig = CastConfig(), seed: int = 0,
              keep_views: Sequence[Pair] = (), workers: int = 1,
              log: Callable[[str], None] | None = None) -> list[PairResult]:
    """Every method's view of every pair, scored, ``workers`` pairs at a time (the results do not
    depend on it); the views of ``keep_views`` kept for pictures.

    The oracle's view of reference j does not depend on the ego frame: it is cast once per j
    (and counted against the first pair that needed it)."""
    from typ.distributed import threaded_map

    eval_grid = evaluation_grid(grid)
    truths = Once(lambda j: truth_of(scans.scan(j), sensor))
    first = {p.reference: p for p in reversed(pairs)}     # the first pair of each reference frame
    oracles = Once(lambda j: METHODS["map_oracle"].view(pair_input(scans, first[j], sensor, grid, seed=seed)))

    def one(item: tuple[int, Pair]) -> PairResult:
        n, pair = item
        t0 = time.perf_counter()
        truth = truths(pair.reference)
        p = pair_input(scans, pair, sensor, grid, generator=generator, cast=cast, seed=seed)
        seen = coverage_mask(p.reference.ego_points, eval_grid)
        setup = time.perf_counter() - t0
        result = PairResult(pair)
        for name in methods:
            t0 = time.perf_counter()
            points = oracles(pair.reference) if name == "map_oracle" else METHODS[name].view(p)
            t1 = time.perf_counter()
            result.scores[name] = score_view(points, truth, sensor, seen, eval_grid)
            result.seconds[name] = t1 - t0
            result.score_seconds[name] = time.perf_counter() - t1 + setup / len(methods)
            if pair in keep_views:
                result.views[name] = np.asarray(points)[:, :3]
        if log is not None:
            log(f"pair {n + 1}/{len(pairs)} ({pair.ego} -> {pair.reference}, {pair.distance:.1f} m): " +
                ", ".join(f"{m} F {result.scores[m]['fscore']:.3f}" for m in methods))
        return result

    return list(threaded_map(one, enumerate(pairs), workers=workers))


class Once:
    """``make(key)`` computed once per key, also when several threads ask for it at once."""

    def __init__(self, make: Callable):
        self.make, self.values, self.locks, self.lock = make, {}, {}, threading.Lock()

    def __call__(self, key):
        with self.lock:
            lock = self.locks.setdefault(key, threading.Lock())
        with lock:
            if key not in self.values:
                self.values[key] = self.make(key)
            return self.values[key]


# ---------------------------------------------------------------- figures with intervals


def _nanmean(values: np.ndarray, axis: int = 0) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        counts = np.sum(np.isfinite(values), axis=axis)
        sums = np.nansum(values, axis=axis)
        return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def summarize(results: Sequence[PairResult], methods: Sequence[str], *, n_boot: int = 1000,
              seed: int = 0) -> dict:
    """Per band (and ``all``): each method's mean of each figure over the band's pairs, its ratio of
    F-score to the map oracle's, and its paired differences against each of :data:`BASELINES` run,
    each with a 95 % bootstrap interval that resamples the ego frames of the band's pairs (one
    resampling serves every figure of the band: :func:`typ.metrics.intervals.bootstrap_figures`);
    a band whose pairs share one ego frame gets no interval (NaN bounds).

    Returns ``{"methods": {m: {band: {metric: Interval}}}, "differences": {"vs_<b>": {m: {band:
    {metric: Interval}}}}, "ratios_to_map_oracle": {m: {band: {"fscore": Interval}}}}``; a band
    without pairs is left out.
    """
    keys = list(METRICS)
    baselines = [b for b in BASELINES if b in methods]
    oracle = methods.index("map_oracle") if "map_oracle" in methods else None
    out: dict = {"methods": {m: {} for m in methods}, "differences": {f"vs_{b}": {m: {} for m in methods if m != b}
                                                                      for b in baselines},
                 "ratios_to_map_oracle": {m: {} for m in methods if oracle is not None and m != "map_oracle"}}
    for band in BAND_NAMES:
        rows = [r for r in results if band == ALL or r.pair.band == band]
        if not rows:
            continue
        values = np.array([[[r.scores[m][k] for k in keys] for m in methods] for r in rows], dtype=np.float64)
        egos = sorted({r.pair.ego for r in rows})
        members = [np.flatnonzero([r.pair.ego == e for r in rows]) for e in egos]
        diffs = [values - values[:, [methods.index(b)]] for b in baselines]
        f = keys.index("fscore")

        def stat(c: np.ndarray, s: np.ndarray) -> np.ndarray:
            idx = np.concatenate([members[k] for k in c])
            means = _nanmean(values[idx])                                   # (M, K)
            parts = [means.ravel(), *(_nanmean(d[idx]).ravel() for d in diffs)]
            if oracle is not None:
                with np.errstate(invalid="ignore", divide="ignore"):
                    parts.append(means[:, f] / means[oracle, f])
            return np.concatenate(parts)

        figures = bootstrap_figures(stat, len(egos), n_boot=n_boot, seed=seed)
        if len(egos) < 2:   # one ego frame: every resample is the same, and the spread unknown
            figures = [Interval(iv.value, float("nan"), float("nan")) for iv in figures]
        figures = iter(figures)
        for m in methods:
            out["methods"][m][band] = {k: next(figures) for k in keys}
        for b in baselines:
            for m in methods:
                row = {k: next(figures) for k in keys}
                if m != b:
                    out["differences"][f"vs_{b}"][m][band] = row
        if oracle is not None:
            for m in methods:
                iv = next(figures)
                if m != "map_oracle":
                    out["ratios_to_map_oracle"][m][band] = {"fscore": iv}
    return out


def beats(diff: Interval, metric: str) -> bool:
    """Whether a paired difference (method - baseline) says the method is better: its interval
    excludes 0 on the better side of ``metric`` (never without an interval)."""
    return bool(diff.high < 0 if METRICS[metric].lower_is_better else diff.low > 0)


def intervals_json(tree):
    """Intervals in a nested dict as ``{"value", "low", "high"}`` (NaN as None), rounded."""
    if isinstance(tree, Interval):
        return {k: (round(float(v), 6) if np.isfinite(v) else None) for k, v in tree.to_dict().items()}
    return {k: intervals_json(v) for k, v in tree.items()}


# ---------------------------------------------------------------- one drive, end to end


@dataclass
class BenchmarkResult:
    """What :func:`run_benchmark` measured on one drive (the report writer's input)."""

    drive: Drive
    sensor_name: str
    sensor_note: str
    pairs: list[Pair]
    methods: list[str]
    skipped: dict[str, str]
    results: list[PairResult]
    summary: dict
    model: str
    grid: Grid
    split_rule: str = ""
    picture_pairs: list[Pair] = field(default_factory=list)


def trained_generator(root: Path, cfg, folder: str | None = None) -> tuple[Generator | None, str]:
    """(the generator ``typ generate`` uses, as :func:`flows.generate.load_generator` loads it, or
    None when ``make run`` has made none; which one it is, in words, for the report's rows).
    folder: the selftrain output holding it (default: params' ``generate.generator``)."""
    from pipelines.typ.pipeline_typ import TYPPipeline
    from pipelines.typ.pipeline_typ import generator_dir
    from typ.io import hash_files

    path = generator_dir(root / (folder or cfg.generate.generator), cfg.stage1.seed)
    if not (path / "pipeline.json").is_file():
        return None, f"none: {path} holds no trained generator"
    pipe = dataclasses.replace(TYPPipeline.from_pretrained(path), sampler=cfg.generate.sampler,
                               num_inference_steps=cfg.generate.sample_steps)
    digest = hash_files(sorted(p for p in path.rglob("*") if p.is_file()))[:16]
    generator = Generator(pipe, dict(cfg.voxelize.mount_height), digest, cfg.simulate.azimuth_step_deg)
    return generator, f"{path} (replica seed {cfg.stage1.seed}, files {digest}; {training_data(cfg)})"


def training_data(cfg) -> str:
    """Where the generator's target domain came from, as params say (TYP §3.4: stage 1 and
    self-training learn the target domain; the source domain is the simulator's)."""
    domain = cfg.selftrain.target_domain
    blocks = cfg.simulate.source_blocks(domain)
    if not blocks:
        return f"profile {cfg.profile}, target domain '{domain}' simulated: the sim-trained generator"
    drives = "; ".join(f"{b.format} {b.root}" + (f" scans {dict(b.frame_ranges)}" if b.frame_ranges else "")
                       for b in blocks)
    return f"profile {cfg.profile}, target domain '{domain}' read from {drives}: trained on that real data"


def drive_sensor(drive: Drive, sensor: str | None) -> tuple[str, SensorSpec, str]:
    """(preset name, SensorSpec, how it was chosen) of a drive: ``sensor`` (``--sensor``) or the
    estimate from its first scan (:func:`typ.formats.kitti_odometry.estimate_sensor`)."""
    from typ.formats.kitti_odometry import estimate_sensor
    from typ.sensors import resolve

    if sensor:
        return sensor, resolve(sensor, where="typ novel-view", field="--sensor"), "named (--sensor)"
    name, shares = estimate_sensor(drive.points(0), where=drive.scans[0])
    text = ", ".join(f"{k} {v:.2f}" for k, v in sorted(shares.items(), key=lambda kv: -kv[1]))
    return name, resolve(name), f"estimated from scan 0 (share of points within 0.1° of each preset's beams: {text})"


def picture_pairs(pairs: Sequence[Pair]) -> list[Pair]:
    """The pairs drawn: the first (in (i, j) order) of each band. By rule, never by hand."""
    return [next(p for p in pairs if p.band == band) for band, _, _ in BANDS if any(p.band == band for p in pairs)]


def run_benchmark(root: Path, sequence: str, *, sensor: str | None, grid: Grid, generator: Generator | None,
                  model: str, cast: CastConfig = CastConfig(), methods: Sequence[str] | None = None,
                  frames: tuple[int, int] | None = None, max_pairs: int = 0, n_boot: int = 1000, seed: int = 0,
                  workers: int = 1, log: Callable[[str], None] | None = None) -> BenchmarkResult:
    """Score every method on every pair of drive ``sequence`` under ``root`` (module doc).

    grid: the generator's grid (ground-relative z, as params' ``voxelize.grid``; moved here into
    the LiDAR's frame when the generator is None). generator: the trained generator, or None
    (the learned methods are then skipped, with the reason). model: which generator, in words,
    for the report. frames: ``[first, stop)`` the pairs' scans (both ends of a pair) are taken
    from (a held-out range), None: every scan. max_pairs: score the first this many pairs (0: all).
    workers: pairs made and scored at once (threads; the figures do not depend on it).
    """
    drive = read_sequence(root, sequence)
    name, spec, note = drive_sensor(drive, sensor)
    wanted = list(methods or METHODS)
    for m in wanted:
        if m not in METHODS:
            raise TypError("typ novel-view", "--methods", f"names from {list(METHODS)}", m)
    skipped = {}
    if generator is None:
        skipped = {m: "no trained generator (selftrain's output; run `make run` first)" for m in wanted
                   if METHODS[m].learned}
        wanted = [m for m in wanted if m not in skipped]
    sensor_grid = generator.grid(name) if generator is not None else grid.for_sensor(spec.mount_height)
    pairs = build_pairs(drive.poses)
    rule = ""
    if frames is not None:
        first, stop = frames
        pairs = [p for p in pairs if first <= p.ego < stop and first <= p.reference < stop]
        rule = f"pairs within scans [{first}, {stop}) only"
    if max_pairs:
        pairs = pairs[:max_pairs]
    if not pairs:
        raise TypError(drive.folder, "poses", f"scans {MIN_DISTANCE:g}-{MAX_DISTANCE:g} m apart (the pair rule)",
                       "no pair")
    shown = picture_pairs(pairs)
    results = run_pairs(DriveScans(drive), pairs, spec, sensor_grid, wanted, generator=generator, cast=cast,
                        seed=seed, keep_views=shown, workers=workers, log=log)
    return BenchmarkResult(drive, name, note, pairs, wanted, skipped, results,
                           summarize(results, wanted, n_boot=n_boot, seed=seed), model, sensor_grid, rule, shown)
