"""Stage ``ssc``: collaborative semantic scene completion (V2VSSC §III–IV, Table I, Figs. 4–5).

Data: the fusion samples of :class:`tasks.fusion_data.FusionDataset` (OPV2V layout, 70 m
communication range, delay and pose noise as there) on V2VSSC's grid, each with the semantic
occupancy maps the simulate stage writes beside the clouds (:mod:`typ.ssc`).

Networks (:func:`models.ssc.ssc_detector`, PointPillars with an occupancy head) are reached through
the fusion-method registry (:data:`typ.registry.METHODS`), as the detectors are:

- ``single``: under :class:`models.fusion.NoFusion`, trained on every agent's own cloud against its
  own map. No fusion runs it on the ego's cloud; late fusion runs it on every agent in range and
  merges the maps in the ego frame, keeping per voxel the most confident agent
  (:func:`models.ssc.merge_max_confidence`), as V2VSSC does.
- ``early``, ``attfuse`` and ``v2xvit``: :class:`~models.fusion.EarlyFusion` (the agents' clouds
  merged in the ego frame), :class:`~models.fusion.AttFuse` (features warped and attended in the
  ego frame) and :class:`~models.fusion.V2XViT` (its transformer, the block ``ssc.v2xvit``, on the
  backbone's features, with an occupancy head on its width), warm-started from the single-agent
  network and trained on the ego's map.

Loss: cross-entropy weighted ``1 / ln(eps + share)`` (:func:`models.ssc.class_weights`, the shares
of the training maps' classes), Adam with cosine decay, one view or sample a step in a seeded order,
on the shared resumable loop (:func:`tasks.training.run_loop`, checkpoints every
``ssc.checkpoint_every`` steps under ``<out>/checkpoints/<data>/<network>-seed<s>/<key>/``, removed
once the network is saved).
Every network is saved (safetensors + JSON) with a key of its training config, seed, init and
data, and a rerun loads instead of training when the key matches: a stage killed mid-way loads the
networks it finished and resumes the one it was training from its newest checkpoint. Each (data,
seed) pair's networks train on one thread, the pairs on as many spawned processes as torch has
threads (:func:`tasks.ssc_train.train_arms`), as the fusion stage's runs do: on 2 cores two
one-thread trainings do 1.9x the steps per second of one on both, and the bytes do not depend on
how many run at once.

Scores: :func:`typ.metrics.ssc_scores` of the ego's maps against the ego's truth, counts pooled
over the test frames (SemanticKITTI), intervals from a bootstrap over test scenarios and seeds.

By job: :mod:`tasks.ssc_data` (samples, maps, training sets), :mod:`tasks.ssc_train` (the
networks), this module (prediction, scores, the stage), :mod:`tasks.ssc_report` (the report).
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from models.fusion import NoFusion, compressed, get_method
from models.ssc import class_argmax, class_weights, merge_max_confidence, warp_to_ego
from tasks.fusion_data import FusionDataset, FusionSample, unavailable
from tasks.ssc_data import FIGURES, NETWORK, N_CLASSES, ego_map, ssc_dataset
from tasks.ssc_train import SscNetworks, _inputs, generated_root, train_arms, train_seed, training_set
from tasks.scene_stage import StageResult
from tasks.training import Trainings
from typ.config import SscConfig
from typ.errors import TypError
from typ.io import write_json
from typ.metrics.intervals import bootstrap, bootstrap_figures
from typ.metrics.ssc import SSC_CLASSES, figure_of, ssc_confusion, ssc_scores
from typ.ssc import SSC_GRID
# the stage's data and training, re-exported: ``tasks.ssc`` is the stage's one module for its callers
from tasks.ssc_data import (DISPLAY, FOOTPRINT_CELLS, IGNORE, STAGE, TrainingSet, footprint,  # noqa: F401
                            model_kwargs, sample_maps)
from tasks.ssc_train import network_options, train_fused, train_single  # noqa: F401
from typ.registry import declare

#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare("ssc", data=("data/sim/real_cav/train", "data/sim/real_cav/test", "data/generated/real_cav/train"),
                      outs=("artifacts/ssc",), reports=("reports/ssc.md",),
                      images=("reports/ssc_robustness.png", "reports/ssc_gallery.png"))


# ---------------------------------------------------------------- prediction and scores


@torch.no_grad()
def _predict_own(model: NoFusion, clouds: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """(L, X, Y, Z) labels and max-softmax confidences of each cloud in its own frame."""
    det = model.detector
    mask = torch.ones(len(clouds), 1, dtype=torch.bool)
    probs = model(det.pillarize(list(clouds)), agent_mask=mask)["occ"].softmax(1)
    conf, labels = probs.max(1)
    return labels, conf


@torch.no_grad()
def predict(nets: SscNetworks, sample: FusionSample, method: str, *, bits: int | None = None) -> np.ndarray:
    """(X, Y, Z) uint8 ego-frame map of ``sample`` by ``method`` (:data:`NETWORK`); ``bits``: AttFuse's
    messages quantised to that many bits."""
    if method not in NETWORK:
        raise TypError("tasks.ssc.predict", "method", f"one of {list(NETWORK)}", method)
    module = nets.for_method(method)
    if method in ("none", "late"):
        clouds = sample.clouds[:1] if method == "none" else sample.clouds
        labels, conf = _predict_own(module, clouds)
        if method == "none":
            return labels[0].numpy().astype(np.uint8)
        kw = dict(lower=SSC_GRID.lower, voxel=SSC_GRID.voxel.tolist())
        warped = [warp_to_ego(labels[j], conf[j], sample.transforms[j], **kw) for j in range(len(clouds))]
        merged, _ = merge_max_confidence(torch.stack([w[0] for w in warped]), torch.stack([w[1] for w in warped]))
        return merged.numpy().astype(np.uint8)
    pillars, kw = _inputs(nets.networks["single"].detector, method, sample)
    with compressed(module, bits):
        logits = module(pillars, **kw)["occ"]
    return class_argmax(logits[0]).numpy().astype(np.uint8)


def confusions(nets: SscNetworks, ds: FusionDataset, method: str, *, bits: int | None = None) -> tuple[np.ndarray, dict]:
    """Per-scenario (S, K, K) confusion matrices of ``method``'s ego maps against the ego's truth over
    ``ds`` (rows truth, columns prediction), and what was scored (frames, mean message age)."""
    conf = np.zeros((len(ds.scenarios), N_CLASSES, N_CLASSES), dtype=np.int64)
    ages = []
    for i in range(len(ds)):
        sample = ds[i]
        pred = predict(nets, sample, method, bits=bits)
        conf[ds.index[i][0]] += ssc_confusion(pred, ego_map(ds, i, sample), N_CLASSES)
        ages += [100.0 * float(d) for d in sample.time_delay[1:]]
    return conf, {"frames": len(ds), "applied_delay_ms": float(np.mean(ages)) if ages else 0.0}


def intervals(conf: np.ndarray, *, n_boot: int, seed: int = 0,
              figures: Sequence[str] = FIGURES) -> dict[str, dict[str, float]]:
    """Each of ``figures`` (:data:`FIGURES`) with its bootstrap interval, from (seeds, scenarios, K, K)
    confusion matrices: the mean over seeds of the figure pooled over scenarios, scenarios and seeds
    resampled."""
    conf = np.asarray(conf)
    if conf.ndim == 3:
        conf = conf[None]

    def stat(c: np.ndarray, s: np.ndarray) -> list[float]:
        scores = [ssc_scores(conf[k][c].sum(0)) for k in s]
        return [float(np.mean([figure_of(sc, name) for sc in scores])) for name in figures]

    ivs = bootstrap_figures(stat, conf.shape[1], conf.shape[0], n_boot=n_boot, seed=seed)
    return {name: iv.to_dict() for name, iv in zip(figures, ivs)}


#: the figures given per seed and at each robustness level
HEADLINE_FIGURES = ("iou", "miou", "ciou")


def scored(conf: np.ndarray, *, n_boot: int, seed: int) -> dict:
    """A table row of (seeds, scenarios, K, K) confusions: every figure's interval, and IoU, mIoU and
    cIoU of each seed."""
    return {"figures": intervals(conf, n_boot=n_boot, seed=seed),
            "per_seed": {f: [round(figure_of(ssc_scores(c.sum(0)), f), 6) for c in conf] for f in HEADLINE_FIGURES}}


def ratio_interval(num: np.ndarray, den: np.ndarray, figure: str, *, n_boot: int, seed: int = 0) -> dict[str, float]:
    """``figure`` of ``num``'s networks over ``figure`` of ``den``'s (each the mean over seeds of the
    figure pooled over scenarios), from (seeds, scenarios, K, K) confusion matrices of the same test
    scenarios and training seeds: both are resampled together (paired), seed k of each side drawn
    as one (modulo its seed count)."""
    num, den = np.asarray(num), np.asarray(den)
    if num.shape[1:] != den.shape[1:]:
        raise TypError("tasks.ssc.ratio_interval", "den", f"matrices of the same scenarios as num {num.shape[1:]}",
                       den.shape[1:])
    n_seeds = max(len(num), len(den))

    def stat(c: np.ndarray, s: np.ndarray) -> float:
        a = np.mean([figure_of(ssc_scores(num[k % len(num)][c].sum(0)), figure) for k in s])
        b = np.mean([figure_of(ssc_scores(den[k % len(den)][c].sum(0)), figure) for k in s])
        return float(a / b) if b > 0 else float("nan")

    return bootstrap(stat, num.shape[1], n_seeds, n_boot=n_boot, seed=seed).to_dict()


# ---------------------------------------------------------------- the stage


def run(cfg, root: Path, *, run, trainings: Trainings = Trainings()) -> StageResult:
    """The stage (:mod:`flows.generic`): :func:`run_benchmark`, the report, and ``results.json`` /
    ``losses.json`` beside the networks, all kept with the MLflow ``run``."""
    from tasks import ssc_report

    block = cfg.ssc
    out = Path(root) / block.out
    t0 = time.perf_counter()
    results = run_benchmark(block, root, log_fn=run.metrics, trainings=trainings)
    paths = ssc_report.write_report(results, block, Path(root) / block.reports, results["gallery"])
    metrics = metrics_of(results, time.perf_counter() - t0)
    write_json(out / "results.json", metrics)
    write_json(out / "losses.json", results["losses"])
    return StageResult(metrics, artifacts=[out / "results.json", out / "losses.json", *paths])


def run_benchmark(block: SscConfig, root: Path, *, log: Callable[[str], None] = print,
                  log_fn: Callable[[dict, int | None], None] | None = None, trainings: Trainings = Trainings()) -> dict:
    """Train every seed's networks (each (arm, seed) reported to ``trainings``), score Table I
    (perfect and noisy), the networks trained on generated cooperators against the oracle ones,
    and the robustness sweeps; returns the results the report and the metrics are made of."""
    sim = Path(root) / block.sim / block.domain
    out = Path(root) / block.out
    test_ds = ssc_dataset(sim / block.test_split, comm_range=block.comm_range, max_scenarios=block.test_scenarios)
    data = training_set(block, root, "oracle")
    weights = class_weights(data.class_counts(), eps=block.class_weight_eps)
    skipped: dict[str, str] = {}
    # why the generated arm cannot run (None: it runs), asked once for training and for scoring
    gen_unavailable = unavailable(generated_root(block, root)) if "generated" in block.data else None
    generated = "generated" in block.data and gen_unavailable is None
    train_arms(block, root, ["oracle", "generated"] if generated else ["oracle"], weights, log, trainings,
               sets={"oracle": data})
    noisy_ds = test_ds.with_options(position_std=block.noisy.position_std,
                                    heading_std_deg=block.noisy.heading_std_deg,
                                    delay_frames=block.noisy.delay_ms // 100, seed=block.seed)
    trained = [train_seed(block, data, weights, seed, out, log) for seed in block.training_seeds]
    losses = {f"oracle/{n}-seed{t.seed}": t.losses[n] for t in trained for n in t.losses}
    for nets in trained:
        if log_fn is not None:
            for name, curve in nets.losses.items():
                if curve:
                    log_fn({f"loss_{name}_seed{nets.seed}_last": float(np.mean(curve[-20:]))}, None)
    tables: dict[str, dict] = {}
    perfect: dict[str, np.ndarray] = {}     # the oracle networks' confusions, for the generated ratios
    for setting, ds in (("perfect", test_ds), ("noisy", noisy_ds)):
        rows = {}
        for method in block.methods:
            per_seed = [confusions(nets, ds, method) for nets in trained]
            conf = np.stack([c for c, _ in per_seed])
            if setting == "perfect":
                perfect[method] = conf
            rows[method] = {**scored(conf, n_boot=block.bootstrap, seed=block.seed), **per_seed[0][1]}
        tables[setting] = rows
    if "generated" in block.data:   # TYP Table 1 for SSC: the cooperating clouds of training generated
        if generated:
            gen = training_set(block, root, "generated")
            gen_trained = [train_seed(block, gen, weights, seed, out, log, data_name="generated")
                           for seed in block.training_seeds]
            losses.update({f"generated/{n}-seed{t.seed}": t.losses[n] for t in gen_trained for n in t.losses})
            rows = {}
            for method in block.methods:
                if method == "none":      # the ego's cloud is never generated: no fusion is the oracle row
                    continue
                conf = np.stack([confusions(nets, test_ds, method)[0] for nets in gen_trained])
                oracle = perfect[method]
                boot = dict(n_boot=block.bootstrap, seed=block.seed)
                rows[method] = {**scored(conf, **boot), "ratio_miou": ratio_interval(conf, oracle, "miou", **boot),
                                "ratio_iou": ratio_interval(conf, oracle, "iou", **boot), "frames": len(test_ds)}
            tables["generated"] = rows
        else:
            skipped["generated"] = gen_unavailable
            log(f"ssc: the generated rows are skipped: {gen_unavailable}")
    robustness = robustness_curves(block, trained[0], test_ds)
    sample = test_ds[0]     # the gallery: the first test frame by every method, first seed
    gallery = (ego_map(test_ds, 0, sample), {m: predict(trained[0], sample, m) for m in block.methods},
               f"{sample.scenario} frame {sample.timestamp}, ego {sample.agent_ids[0]}, "
               f"{len(sample.agent_ids) - 1} cooperating agent(s); seed {trained[0].seed}")
    return {"tables": tables, "robustness": robustness, "skipped": skipped, "gallery": gallery,
            "class_weights": dict(zip(SSC_CLASSES, weights.round(4).tolist())),
            "train": {"samples": len(data.samples), "views": len(data.views),
                      "scenarios": len({s.scenario for s in data.samples})},
            "test": {"samples": len(test_ds), "scenarios": len(test_ds.scenarios)},
            "seeds": list(block.training_seeds), "losses": losses, "networks": trained}


def robustness_curves(block: SscConfig, nets: SscNetworks, test_ds: FusionDataset) -> dict:
    """mIoU / IoU of every method against pose noise, delay and (AttFuse, V2X-ViT) message bits, first seed, on
    the test frames t >= the longest delay; each level a bootstrap interval over scenarios (no fusion:
    the reference, unperturbed)."""
    rob = block.robustness
    methods = list(block.methods)
    max_delay = max(rob.delay_ms, default=0) // 100
    # every sweep on the same frames, t >= the longest delay (the delays need them; the zero level
    # of each sweep is then one score, and the sweeps cost a quarter of tiny's test frames)
    frames = test_ds.with_options(first_frame=max_delay)
    sweeps = {"position_std": [dict(position_std=v) for v in rob.position_std],
              "heading_std_deg": [dict(heading_std_deg=v) for v in rob.heading_std_deg],
              "delay_ms": [dict(delay_frames=v // 100) for v in rob.delay_ms]}
    levels = {"position_std": list(rob.position_std), "heading_std_deg": list(rob.heading_std_deg),
              "delay_ms": list(rob.delay_ms)}
    curves: dict[str, dict] = {m: {} for m in methods}
    applied = {}
    cache: dict[tuple, dict] = {}
    for sweep, options in sweeps.items():
        for method in methods:
            cells = []
            for opt in options:
                ds = frames.with_options(seed=block.seed, **opt)
                # no fusion never reads a cooperating agent, and a zero level is no perturbation
                level = tuple(sorted((n, v) for n, v in opt.items() if v))
                k = (method, level if method != "none" else ())
                if k not in cache:
                    conf, info = confusions(nets, ds, method)
                    cache[k] = {**intervals(conf, n_boot=block.bootstrap, seed=block.seed, figures=HEADLINE_FIGURES),
                                **info}
                cells.append(cache[k])
            curves[method][sweep] = cells
            if sweep == "delay_ms" and method != "none":
                applied = [c["applied_delay_ms"] for c in cells]
    bits: dict[str, dict] = {}
    for method in methods:          # the methods whose cooperating agents send features
        if get_method(method).message == "features":
            bits[method] = {}
            for b in rob.quantization_bits:
                conf, info = confusions(nets, frames, method, bits=b)
                bits[method][str(b)] = {**intervals(conf, n_boot=block.bootstrap, seed=block.seed,
                                                    figures=HEADLINE_FIGURES), **info}
    return {"levels": levels, "methods": curves, "applied_delay_ms": applied or list(map(float, rob.delay_ms)),
            "quantization": bits}


def metrics_of(results: dict, seconds: float) -> dict:
    """metrics/ssc.json: Table I's figures with intervals, the robustness curves' mIoU, the sizes."""
    tables = {setting: {m: {**row["figures"], "per_seed": row["per_seed"], "frames": row["frames"]}
                        for m, row in rows.items()} for setting, rows in results["tables"].items()}
    perfect = results["tables"]["perfect"]
    targets = {}
    if "none" in perfect:
        none = perfect["none"]["figures"]
        targets["none_iou_ge_0.50"] = none["iou"]["value"] >= 0.50
        targets["none_miou_ge_0.35"] = none["miou"]["value"] >= 0.35
        for m, row in perfect.items():
            if m != "none":
                f = row["figures"]
                targets[f"{m}_beats_none_iou"] = f["iou"]["low"] > none["iou"]["high"]
                targets[f"{m}_beats_none_miou"] = f["miou"]["low"] > none["miou"]["high"]
    for m, row in results["tables"].get("generated", {}).items():
        targets[f"{m}_generated_ge_0.85_oracle_miou"] = row["ratio_miou"]["value"] >= 0.85
        tables["generated"][m].update(ratio_miou=row["ratio_miou"], ratio_iou=row["ratio_iou"])
    rob = results["robustness"]
    curves = {m: {sweep: [c["miou"]["value"] for c in cells] for sweep, cells in entry.items()}
              for m, entry in rob["methods"].items()}
    return {"tables": tables, "targets": targets, "robustness_miou": curves, "levels": rob["levels"],
            "applied_delay_ms": rob["applied_delay_ms"],
            "quantization_miou": {m: {b: v["miou"]["value"] for b, v in per.items()}
                                  for m, per in rob["quantization"].items()},
            "class_weights": results["class_weights"], "train": results["train"], "test": results["test"],
            "skipped": results["skipped"],
            "seeds": results["seeds"], "seconds_total": round(seconds, 3)}
