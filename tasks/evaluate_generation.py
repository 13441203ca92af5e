"""Generation accuracy on held-out simulated target scenes: every method, every seed, with intervals.

Held-out (ego, reference) pairs come from the target domain's test split: only the ego's
cloud and the reference's labelled boxes go in; the reference's own cloud is the hidden
truth. Each method produces the reference view as an occupancy grid and a point cloud:

- ``naive copy``: the ego's cloud moved into the reference frame (x_e');
- ``re-simulation``: the ego's cloud as surfels, ray-cast from the reference pose with the
  reference sensor's beams (:mod:`typ.resim`);
- ``stage 1 only``: P(x_r | y_r), no ego cloud;
- ``stage 2 without adaptation`` / ``stage 2 (adapted source encoder)`` / ``+ self-training`` /
  ``TYP``: TYP Table 4's rows (:mod:`tasks.selftrain`);
- ``TYP + re-simulated conditioning``: the adapter sees the re-simulated view beside x_e';
- ``one-stage``: TYP Table 5's baseline, UNet and adapter trained together on source tuples;
- ``hybrid``: re-simulation where the ego saw, TYP elsewhere;
- ``cast``: one scene of the ego's surfels and TYP's cells, cast once with the reference LiDAR
  (:mod:`typ.castview`, ``generate.cast``).

Learned methods are sampled once per training seed (replica); every figure is pooled over
pairs and given with a bootstrap interval over scenes and seeds (:mod:`tasks.genscore`).
"""
from __future__ import annotations

import dataclasses
import itertools
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipelines.typ.pipeline_typ import TYPPipeline
from tasks import genscore, realism, stage1, stage2
from tasks.pairs import iter_pairs
from tasks.selftrain import base_pipeline, resim_variant, variant_of, variants_to_run
from typ.distributed import threaded_map
from typ.metrics.intervals import Interval
from typ.registry import GENERATION_METHODS
from typ.resim import EGO_CAR_LWH, coverage_mask, hybrid, hybrid_points, own_car_box, resimulated_points
from typ.voxel import Grid, voxelize

#: method key -> row label, in the report's order
METHODS = {k: m.label for k, m in GENERATION_METHODS.items()}


@dataclass
class EvalSet:
    """The held-out pairs, as every method needs them."""

    grid: Grid
    scenes: list[str]
    x_r: np.ndarray          # (P, C, H, W) bool truth
    y_r: np.ndarray          # (P, 1, H, W) float32
    x_e: np.ndarray          # (P, C, H, W) float32
    resim: np.ndarray        # (P, C, H, W) float32
    seen: np.ndarray         # (P, H, W) bool
    boxes: list[np.ndarray]  # (K, 7) reference vehicles per pair
    ego_points: list[np.ndarray]
    resim_points: list[np.ndarray]
    ego_origins: list[np.ndarray] = field(default_factory=list)   # (3,) the ego sensor in each reference frame
    ref_points: list[np.ndarray] = field(default_factory=list)    # (M, 4) the true reference scans
    sensor: object = None    # the reference LiDAR (SensorSpec) the pairs were re-simulated with
    truth_stats: list[dict] = field(default_factory=list)
    resim_seconds: float = 0.0

    def __len__(self) -> int:
        return len(self.scenes)


def build_eval_set(split_root: Path, grid: Grid, spec, *, max_pairs: int | None = None) -> EvalSet:
    """Pairs (scenario ego -> every other agent) of every frame under ``split_root``."""
    rows: dict[str, list] = {k: [] for k in ("scenes", "x_r", "y_r", "x_e", "resim", "seen", "boxes", "ego_points",
                                              "resim_points", "ego_origins", "ref_points")}
    t0 = time.perf_counter()
    pairs = list(itertools.islice(iter_pairs(split_root, grid, ego_only=True), max_pairs))
    resims = threaded_map(lambda p: resimulated_points(p.ego_points, spec, EGO_CAR_LWH), pairs)
    for p, points in zip(pairs, resims):
        rows["scenes"].append(p.scenario)
        rows["x_r"].append(p.x_r)
        rows["y_r"].append(p.y_r.astype(np.float32))
        rows["x_e"].append(p.x_e.astype(np.float32))
        rows["resim"].append(voxelize(points, grid).transpose(2, 0, 1).astype(np.float32))
        rows["seen"].append(coverage_mask(p.ego_points, grid))
        rows["boxes"].append(p.ref_boxes)
        rows["ego_points"].append(p.ego_points)
        rows["resim_points"].append(points)
        rows["ego_origins"].append(p.ego_pose_in_ref[:3, 3].copy())
        rows["ref_points"].append(p.ref_points)
    seconds = (time.perf_counter() - t0) / max(len(rows["scenes"]), 1)
    stacked = {k: np.stack(rows[k]) for k in ("x_r", "y_r", "x_e", "resim", "seen")}
    out = EvalSet(grid, rows["scenes"], **stacked, boxes=rows["boxes"], ego_points=rows["ego_points"],
                  resim_points=rows["resim_points"], ego_origins=rows["ego_origins"],
                  ref_points=rows["ref_points"], sensor=spec,
                  resim_seconds=seconds)
    out.truth_stats = [genscore.true_view_stats(x, grid) for x in out.x_r]
    return out


def score_method(data: EvalSet, occupancy: np.ndarray, points: list[np.ndarray]) -> list[genscore.PairScore]:
    return [genscore.score_pair(occupancy[i].astype(bool), points[i], data.x_r[i], data.seen[i], data.boxes[i],
                                data.grid, data.truth_stats[i]) for i in range(len(data))]


def sample_method(pipe: TYPPipeline, data: EvalSet, seed: int) -> tuple[np.ndarray, list[np.ndarray], float]:
    """(occupancy, points, seconds per view) of ``pipe`` on every pair."""
    t0 = time.perf_counter()
    occ = pipe.occupancy(data.x_e, data.y_r, seed=seed, resim=data.resim if pipe.conditions == 2 else None)
    points = [pipe.points(o, data.grid, seed + i) for i, o in enumerate(occ)]
    return occ, points, (time.perf_counter() - t0) / max(len(data), 1)


def cast_views(data: EvalSet, occupancy: np.ndarray, params, seed: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """(occupancy, points) of the cast views of every pair (:func:`typ.castview.cast_view`) built
    on the generated ``occupancy`` (P, C, H, W), as ``generate.compose: cast`` builds them."""
    from typ.castview import cast_view

    own = own_car_box(data.sensor, EGO_CAR_LWH)
    points = list(threaded_map(
        lambda i: cast_view(data.ego_points[i], occupancy[i], data.grid, data.sensor, np.random.default_rng([seed, i, 2]),
                            params=params, ego_origin=data.ego_origins[i], label_boxes=data.boxes[i],
                            exclude_boxes=own, mask=data.seen[i]), range(len(data))))
    return np.stack([voxelize(p, data.grid).transpose(2, 0, 1) for p in points]), points


def pipelines(cfg, root: Path, seed: int, x_vq, y_encoder, stats) -> dict[str, TYPPipeline]:
    """Every learned method of replica ``seed`` that the trained artifacts provide."""
    base = base_pipeline(cfg, root, seed, x_vq, y_encoder, stats)
    out = {"stage1_only": base}
    folder = stage1.replica_dir(root / cfg.selftrain.out, seed)
    # the variants selftrain trains under these params (every Table 4 row when ablation is on, and
    # the switches' own combination even when it is none of them); typ_resim when stage 2 re-simulates
    for v in variants_to_run(cfg.selftrain, resim=cfg.stage2.resim):
        if (folder / v.name / "config.json").is_file():
            out[v.name] = base.with_adapter(stage2.load_adapter(folder / v.name, "selftrain"))
    one = stage1.replica_dir(root / cfg.stage2.out, seed) / "one_stage"
    if (one / "unet" / "config.json").is_file():
        from typ.artifacts import load_module
        from models.ldm import LatentDiffusion

        unet, meta = load_module(one / "unet", LatentDiffusion.from_config, "stage2")
        # the sampler every other row has (steps, thresholds, selftrain.adapter_scale): Table 5
        # compares the training recipes alone
        out["one_stage"] = dataclasses.replace(base, unet=unet, adapter=stage2.load_adapter(one / "adapter"),
                                               schedule=meta["schedule"], train_timesteps=int(meta["train_timesteps"]))
    return out


def run(cfg, root: Path, data: EvalSet, x_vq, y_encoder, stats, *, n_boot: int = 1000, feature_nets=None) -> dict:
    """Scores and intervals of every method; the TYP variant the switches name is ``typ``.

    feature_nets: the ``ddpm`` stage's FRID / FPVD networks (:func:`tasks.realism.load_feature_nets`),
    or the reason there are none (a str): the realism table then leaves FRID / FPVD out.
    """
    seeds = stage1.replica_seeds(cfg.stage1.seed, cfg.stage1.replicas)
    scores: dict[str, list[list[genscore.PairScore]]] = {}
    seconds: dict[str, float] = {"re-simulation": data.resim_seconds}
    samples: dict[str, np.ndarray] = {}
    nets = None if isinstance(feature_nets, str) else feature_nets
    pattern = realism.RealismScorer(data.sensor, data.scenes, data.ref_points, nets)
    scores["naive_copy"] = [score_method(data, data.x_e > 0.5, data.ego_points)]
    scores["resim"] = [score_method(data, data.resim > 0.5, data.resim_points)]
    pattern.add("naive_copy", data.ego_points)
    pattern.add("resim", data.resim_points)
    typ_key = variant_of(cfg.selftrain).name
    spread = []
    for seed in seeds:
        for name, pipe in pipelines(cfg, root, seed, x_vq, y_encoder, stats).items():
            occ, points, sec = sample_method(pipe, data, seed)
            scores.setdefault(name, []).append(score_method(data, occ, points))
            pattern.add(name, points)
            seconds[name] = sec
            if seed == seeds[0]:
                samples[name] = occ
            if name == typ_key:
                hyb = hybrid(data.resim > 0.5, occ, data.seen)
                hyb_points = [hybrid_points(data.resim_points[i][:, :3], points[i][:, :3], data.seen[i], data.grid)
                              for i in range(len(data))]
                scores.setdefault("hybrid", []).append(score_method(data, hyb, hyb_points))
                pattern.add("hybrid", hyb_points)
                t0 = time.perf_counter()
                cast_occ, cast_points = cast_views(data, occ, cfg.generate.cast, seed)
                seconds["cast"] = (time.perf_counter() - t0) / max(len(data), 1)
                scores.setdefault("cast", []).append(score_method(data, cast_occ, cast_points))
                pattern.add("cast", cast_points)
                # sample-to-sample spread: the same pairs with other noise
                other, _, _ = sample_method(pipe, data, seed + 7919)
                spread.append(genscore.pairwise_iou(occ, other))
    truth_h = [s["histogram"] for s in data.truth_stats]
    truth_c = [s["centres"] for s in data.truth_stats]
    table = {name: genscore.summarize(rows, data.scenes, truth_h, truth_c, n_boot=n_boot) for name, rows in scores.items()}
    return {"table": table, "seconds": seconds, "samples": samples, "typ": typ_key, "seeds": seeds,
            "resim_key": resim_variant(cfg.selftrain).name, "spread_iou": float(np.mean(spread)) if spread else None,
            "pairs": len(data), "scenes": len(set(data.scenes)),
            "realism": pattern.summarize(n_boot=n_boot), "realism_floor": pattern.truth_floor(),
            "realism_missing": feature_nets if isinstance(feature_nets, str) else None,
            "row_profiles": pattern.profiles(list(METHODS)), "layout": pattern.layout}


def label(key: str) -> str:
    """A method key's row label; a selftrain switch combination outside Table 4 goes by its variant name."""
    return METHODS.get(key, f"TYP variant {key} (selftrain switches)")


def report_rows(result: dict) -> dict[str, dict[str, Interval]]:
    """The accuracy table's rows in :data:`METHODS` order, other variants after them (methods not
    run are left out)."""
    table = result["table"]
    return {label(k): table[k] for k in [*METHODS, *(k for k in table if k not in METHODS)] if k in table}
