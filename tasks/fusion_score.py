"""Scoring trained fusion detectors on held-out data: TYP Tables 1–3, robustness, AP by range, PR.

:func:`score` is what a stage calls: trained networks (per run, one per training seed), the
test split and the cells to fill -> a JSON-able dict. Nothing here trains or writes files.

Conventions:
- Predictions (:func:`predict`): the module's detections above ``score_threshold`` (late fusion:
  every agent's boxes moved into the ego frame), inside the detection range in x/y (OpenCOOD
  drops the others), after rotated NMS (``typ.boxes_bev.nms_bev``).
- AP by range with OpenCOOD's conventions (:mod:`typ.metrics.detection`) at IoU 0.5 and 0.7,
  overall and for 0–30 / 30–50 / 50–100 m. OpenCOOD's default ranks the detections in frame
  order (each frame's by score, frames one after another), as the OPV2V, V2V4Real and TYP tables
  do; Table 1's cells also carry ``ap50_global`` / ``ap70_global`` (overall), with the detections
  of all frames ranked by score (OpenCOOD's ``--global_sort_detections``, the mainstream AP),
  which frame order penalises for every low-score detection wherever it sits.
- Method against method (:func:`paired_difference`): the AP difference with a paired interval,
  both methods scored on the same resampled scenarios and seeds, so the scenarios' shared
  difficulty cancels; the marginal intervals stay the rule for "beats".
- Every cell is ``value [low, high]``: ``value`` the mean over training seeds of the AP on all
  test frames; ``[low, high]`` the 95 % cluster-bootstrap interval (:mod:`typ.metrics.intervals`)
  resampling test scenarios (a scenario's frames are correlated) and training seeds; a
  replicate's AP pools the frames of its scenarios, in the drawn order, and averages its seeds.
- Robustness (V2VSSC §IV): the same networks on perturbed copies of the test split: pose noise
  of the cooperating agents, time delay, and (features) quantisation of the messages. Every
  delay level is scored on the same frames, those with ``t >= the largest delay`` (no message is
  clamped at the sequence start), and the delay actually applied is reported beside it.
- Bytes per message: ``FusionModule.message_bytes`` — points (16 bytes each) for early fusion,
  boxes with scores (32 bytes each) for late fusion, dense maps (``C * h * w * bits / 8`` plus
  a float32 (min, step) per channel when quantised) for intermediate fusion.
"""
from __future__ import annotations

import copy
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from models.fusion import METHODS, compressed
from tasks.fusion_batch import Inputs
from tasks.fusion_data import FusionDataset, boxes_in_range
from tasks.fusion import TABLE3_PAIRS, TRAINING_JSON, Benchmark, Cell, generated_compose, load_networks
from tasks.fusion_train import Trained
from typ import distributed
from typ.boxes_bev import nms_bev
from typ.config import FusionConfig
from typ.io import read_json_or_none
from typ.metrics.detection import FrameMatches, ap_of_frames, frame_matches, pr_curves
from typ.metrics.intervals import Interval, bootstrap, bootstrap_figures

#: the AP figures, by name: the BEV IoU a detection must reach. A new one is an entry here (and
#: its column in the reports and metrics follows)
IOU_THRESHOLDS = {"ap50": 0.5, "ap70": 0.7}
#: typ.metrics.detection.frame_matches' bands: overall, then its default ranges
BANDS = ("overall", "0-30", "30-50", "50-100")
#: the bands robustness curves keep (AP@0.5)
ROBUSTNESS_BANDS = ("overall", "50-100")


@torch.no_grad()
def predict(trained: Trained, inputs: Inputs, cfg: FusionConfig, *, bits: int | None = None,
            batch_size: int = 4) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per sample (boxes (K, 7) float64 in the ego frame, scores (K,)) (module doc)."""
    model = trained.model.eval()
    out = []
    with compressed(model, bits), distributed.on_device(model) as dev:
        for start in range(0, len(inputs), batch_size):
            batch = inputs.batch(trained.method, range(start, min(start + batch_size, len(inputs))))
            head = {k: v.cpu() for k, v in batch.to(dev).run(model).items()}   # decoded on the CPU
            per = model.detections(head, trained.coder, agent_mask=batch.agent_mask, transforms=batch.transforms,
                                   score_threshold=cfg.score_threshold, max_boxes=cfg.max_boxes)
            for boxes, scores in per:
                b, s = boxes.double().numpy(), scores.double().numpy()
                inside = boxes_in_range(b, cfg.detector.lidar_range, xy_only=True)
                b, s = b[inside], s[inside]
                keep = nms_bev(b, s, cfg.nms_threshold)[:cfg.max_boxes] if len(b) else np.zeros(0, np.int64)
                out.append((b[keep], s[keep]))
    return out


def matches(preds, inputs: Inputs) -> dict[str, FrameMatches]:
    """:func:`typ.metrics.detection.frame_matches` at each IoU of :data:`IOU_THRESHOLDS`."""
    gts = [s.gt_boxes for s in inputs.samples]
    return {key: frame_matches(preds, gts, iou_thr=thr) for key, thr in IOU_THRESHOLDS.items()}


def _finite(v: float) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), 4)


def _frames_of(scenarios: Sequence[str]) -> list[np.ndarray]:
    """Frame indices of each scenario, scenarios in sorted order (the bootstrap's clusters)."""
    return [np.flatnonzero(np.asarray(scenarios) == n) for n in sorted(set(scenarios))]


def _cell(iv: Interval) -> dict | None:
    return None if not math.isfinite(iv.value) else \
        {"value": _finite(iv.value), "low": _finite(iv.low), "high": _finite(iv.high)}


def _interval(stat: Callable[[np.ndarray, np.ndarray], float], n_scenarios: int, n_seeds: int, *, n_boot: int,
              seed: int) -> dict | None:
    return _cell(bootstrap(stat, n_scenarios, n_seeds, n_boot=n_boot, seed=seed))


def ap_cell(per_seed: Sequence[Mapping[str, FrameMatches]], scenarios: Sequence[str], *, n_boot: int,
            seed: int = 0, keys: Sequence[str] = tuple(IOU_THRESHOLDS),
            bands: Sequence[str] = BANDS, global_sort: bool = False) -> dict:
    """``{key: {band: {"value", "low", "high"}}}`` over the seeds' matches of one test set whose
    frame ``i`` belongs to ``scenarios[i]`` (module doc); None where a band has no gt. Also
    ``"per_seed"``: each seed's AP@0.5 overall, and with ``global_sort`` ``"<key>_global"``:
    ``{"overall": ...}`` with the detections of all frames ranked by score."""
    frames_of = _frames_of(scenarios)
    ranked = [(key, key, False) for key in keys] + ([(f"{key}_global", key, True) for key in keys]
                                                    if global_sort else [])
    figures = [(name, key, band, by_score) for name, key, by_score in ranked
               for band in (bands if not by_score else ("overall",))]

    def stat(c: np.ndarray, s: np.ndarray) -> list[float]:   # every figure of one resample of scenarios
        frames = np.concatenate([frames_of[j] for j in c])
        return [float(np.mean([ap_of_frames(per_seed[k][key], band, frames, by_score) for k in s]))
                for _, key, band, by_score in figures]

    out: dict = {name: {} for name, _, _ in ranked}
    for (name, _, band, _), iv in zip(figures, bootstrap_figures(stat, len(frames_of), len(per_seed),
                                                                  n_boot=n_boot, seed=seed)):
        out[name][band] = _cell(iv)
    all_frames = np.arange(len(scenarios))
    out["per_seed"] = [_finite(ap_of_frames(m["ap50"], "overall", all_frames)) for m in per_seed]
    return out


def paired_difference(a: Sequence[Mapping[str, FrameMatches]], b: Sequence[Mapping[str, FrameMatches]],
                      scenarios: Sequence[str], *, n_boot: int, seed: int = 0, key: str = "ap50",
                      band: str = "overall", global_sort: bool = False) -> dict | None:
    """AP of ``a`` minus AP of ``b`` (each per seed, seed k against seed k) on one test set, with
    the 95 % interval of the same cluster bootstrap as :func:`ap_cell` where both sides are scored
    on each replicate's scenarios and seeds (module doc). None where the band has no gt."""
    if len(a) != len(b):
        raise ValueError(f"paired seeds: {len(a)} against {len(b)}")
    frames_of = _frames_of(scenarios)

    def stat(c: np.ndarray, s: np.ndarray) -> float:
        frames = np.concatenate([frames_of[j] for j in c])
        return float(np.mean([ap_of_frames(a[k][key], band, frames, global_sort)
                              - ap_of_frames(b[k][key], band, frames, global_sort) for k in s]))

    return _interval(stat, len(frames_of), len(a), n_boot=n_boot, seed=seed)


def pr_curve(preds, inputs: Inputs, iou_thr: float = 0.5) -> dict[str, list[float]]:
    """Overall precision (interpolated: OpenCOOD's ``mpre``) against recall after each detection of
    the ranking; without OpenCOOD's padding point (recall 1, precision 0), which no detection reached."""
    c = pr_curves(preds, [s.gt_boxes for s in inputs.samples], iou_thr=iou_thr)["overall"]
    return {"recall": c.mrec[1:-1].round(4).tolist(), "precision": c.mpre[1:-1].round(4).tolist()}


def _effective(perturbation: dict) -> dict:
    """The perturbation without its zero entries (no noise, no delay, from frame 0: the clean split)."""
    return {k: v for k, v in perturbation.items() if v}


class Scorer:
    """Predictions and matches of (run, method, test variant), each computed once."""

    def __init__(self, cfg: FusionConfig, test: FusionDataset, networks: Mapping[str, Sequence[Trained]]):
        self.cfg, self.test, self.networks = cfg, test, networks
        self._inputs: dict[tuple, Inputs] = {}
        self._preds: dict[tuple, list] = {}
        self._cells: dict[tuple, dict] = {}
        self._matches: dict[tuple, list[dict]] = {}

    def inputs(self, **perturbation) -> Inputs:
        perturbation = _effective(perturbation)
        key = tuple(sorted(perturbation.items()))
        if key not in self._inputs:
            ds = self.test.with_options(**perturbation) if perturbation else self.test
            self._inputs[key] = Inputs(list(ds), self.cfg)
        return self._inputs[key]

    def predictions(self, run: str, method: str, *, bits: int | None = None, **perturbation) -> list[list]:
        """Per seed of ``run``: :func:`predict` of ``method`` on the (perturbed) test split."""
        perturbation = _effective(perturbation)
        key = (run, method, bits, tuple(sorted(perturbation.items())))
        if key not in self._preds:
            inputs = self.inputs(**perturbation)
            self._preds[key] = [predict(t.as_method(method), inputs, self.cfg, bits=bits) for t in self.networks[run]]
        return self._preds[key]

    def matches(self, run: str, method: str, *, bits: int | None = None, **perturbation) -> list[dict]:
        """Per seed of ``run``: :func:`matches` of ``method`` on the (perturbed) test split."""
        perturbation = _effective(perturbation)
        key = (run, method, bits, tuple(sorted(perturbation.items())))
        if key not in self._matches:
            inputs = self.inputs(**perturbation)
            self._matches[key] = [matches(p, inputs) for p in self.predictions(run, method, bits=bits,
                                                                                 **perturbation)]
        return self._matches[key]

    def cell(self, run: str, method: str, *, bits: int | None = None, keys=tuple(IOU_THRESHOLDS), bands=BANDS,
             global_sort: bool = False, **perturbation) -> dict:
        """:func:`ap_cell` of ``method`` with ``run``'s networks on the (perturbed) test split."""
        perturbation = _effective(perturbation)
        key = (run, method, bits, tuple(keys), tuple(bands), global_sort, tuple(sorted(perturbation.items())))
        if key not in self._cells:
            inputs = self.inputs(**perturbation)
            self._cells[key] = ap_cell(self.matches(run, method, bits=bits, **perturbation), inputs.scenarios,
                                       n_boot=self.cfg.bootstrap, seed=self.cfg.seed, keys=keys, bands=bands,
                                       global_sort=global_sort)
        return copy.deepcopy(self._cells[key])


def fill_tables(scorer: Scorer, cells: Sequence[Cell], *, pr_tables: Sequence[str] = ("table1",)) -> dict:
    """``{table: {method: {row: cell or {column: cell}}}}`` for ``cells``; cells of ``pr_tables``
    keep the PR curve (AP@0.5, overall) of their first seed."""
    out: dict = {}
    for c in cells:
        value = scorer.cell(c.run, c.method, global_sort=c.table == "table1")
        if c.table in pr_tables:
            value["pr"] = pr_curve(scorer.predictions(c.run, c.method)[0], scorer.inputs())
        row = out.setdefault(c.table, {}).setdefault(c.method, {})
        if c.column is None:
            row[c.row] = value
        else:
            row.setdefault(c.row, {})[c.column] = value
    return out


def differences(scorer: Scorer, cells: Sequence[Cell]) -> dict:
    """Table 1, each fusion method's oracle row against no fusion: :func:`paired_difference` of
    AP@0.5 overall and 50–100 m (frame order) and overall with global ranking,
    ``{method: {"overall", "50-100", "overall_global"}}``; empty without a no-fusion cell."""
    table1 = {(c.method, c.row): c.run for c in cells if c.table == "table1"}
    base = table1.get(("none", "ego"))
    if base is None:
        return {}
    scenarios, kw = scorer.inputs().scenarios, {"n_boot": scorer.cfg.bootstrap, "seed": scorer.cfg.seed}
    out = {}
    for (method, row), run in table1.items():
        if row != "oracle" or method == "none":
            continue
        a, b = scorer.matches(run, method), scorer.matches(base, "none")
        out[method] = {"overall": paired_difference(a, b, scenarios, **kw),
                       "50-100": paired_difference(a, b, scenarios, band="50-100", **kw),
                       "overall_global": paired_difference(a, b, scenarios, global_sort=True, **kw)}
    return out


def applied_delay_ms(inputs: Inputs) -> float:
    """Mean age (ms, 100 a frame) of the messages cooperating agents sent in ``inputs``."""
    ages = [d for s in inputs.samples for d in s.time_delay[1:]]
    return float(np.mean(ages) * 100.0) if ages else 0.0


def message_sizes(scorer: Scorer, run: str, method: str) -> tuple[float, float]:
    """Mean points of a cooperating agent's cloud, and mean boxes above the score threshold a
    cooperating agent's single-agent detector finds (seed 0), on the clean test split."""
    inputs = scorer.inputs()
    points = [len(s.clouds[k]) for s in inputs.samples for k in range(1, s.num_agents)]
    boxes = 0.0
    if METHODS[method].message == "boxes":
        trained = scorer.networks[run][0].as_method(method)
        counts = []
        with torch.no_grad():
            for start in range(0, len(inputs), 4):
                batch = inputs.batch(method, range(start, min(start + 4, len(inputs))))
                head = trained.model(batch.pillars, agent_mask=batch.agent_mask, transforms=batch.transforms)
                per = trained.coder.decode_predictions(head, score_threshold=scorer.cfg.score_threshold,
                                                       max_boxes=scorer.cfg.max_boxes)
                slots = batch.agent_mask.nonzero()[:, 1].tolist()
                counts += [len(b) for slot, (b, _) in zip(slots, per) if slot > 0]
        boxes = float(np.mean(counts)) if counts else 0.0
    return (float(np.mean(points)) if points else 0.0), boxes


def robustness(scorer: Scorer, runs: Mapping[str, str]) -> dict:
    """V2VSSC §IV for ``runs`` (method -> run): AP@0.5 (overall, 50–100 m, with intervals) against
    the cooperating agents' position noise σ (m), heading noise σ (deg) and time delay (ms), and
    for feature messages against quantisation, with the bytes of each message (module doc)."""
    r = scorer.cfg.robustness
    last = max(r.delay_ms) // 100
    sweeps: dict[str, list[tuple[float, dict]]] = {
        "position_std": [(v, {"position_std": v}) for v in r.position_std],
        "heading_std_deg": [(v, {"heading_std_deg": v}) for v in r.heading_std_deg],
        "delay_ms": [(v, {"delay_frames": v // 100, "first_frame": last}) for v in r.delay_ms]}
    delay_inputs = [scorer.inputs(**kw) for _, kw in sweeps["delay_ms"]]
    out: dict = {"levels": {k: [v for v, _ in levels] for k, levels in sweeps.items()},
                 "applied_delay_ms": [round(applied_delay_ms(i), 1) for i in delay_inputs],
                 "delay_frames_scored": len(delay_inputs[0]), "quantization_bits": [32, *r.quantization_bits],
                 "methods": {}}
    kw = {"keys": ("ap50",), "bands": ROBUSTNESS_BANDS}
    for method, run in runs.items():
        entry: dict = {sweep: [scorer.cell(run, method, **kw, **p) for _, p in levels]
                       for sweep, levels in sweeps.items()}
        points, boxes = message_sizes(scorer, run, method)
        module = scorer.networks[run][0].as_method(method).model
        entry["bytes_per_message"] = module.message_bytes(points=points, boxes=boxes)
        if METHODS[method].message == "features":
            entry["quantization"] = []
            for bits in [None, *r.quantization_bits]:
                with compressed(module, bits):
                    size = module.message_bytes(points=points, boxes=boxes)
                entry["quantization"].append({"bits": bits or 32, "bytes_per_message": size,
                                              **scorer.cell(run, method, bits=bits, **kw)})
        out["methods"][method] = entry
    return out


def table3_differences(scorer: Scorer, cells: Sequence[Cell]) -> dict:
    """Table 3's paired differences (:data:`tasks.fusion.TABLE3_PAIRS`: each pre-training against
    scratch on the same fine-tuning scenes, the generated target and both against source sim):
    :func:`paired_difference` of AP@0.5 overall (frame order), ``{method: {"<row>-<base>": {column:
    interval}}}`` for every pair whose two rows were trained."""
    table3 = {(c.method, c.row, c.column): c.run for c in cells if c.table == "table3"}
    scenarios, kw = scorer.inputs().scenarios, {"n_boot": scorer.cfg.bootstrap, "seed": scorer.cfg.seed}
    out: dict = {}
    for (method, row, column), run in table3.items():
        for base in (b for r, b in TABLE3_PAIRS if r == row):
            other = table3.get((method, base, column))
            if other is not None:
                out.setdefault(method, {}).setdefault(f"{row}-{base}", {})[column] = paired_difference(
                    scorer.matches(run, method), scorer.matches(other, method), scenarios, **kw)
    return out


def test_summary(inputs: Inputs) -> dict:
    """Frames, scenarios and vehicles of the test split, vehicles per band."""
    s = inputs.samples
    dist = [np.hypot(x.gt_boxes[:, 0], x.gt_boxes[:, 1]) for x in s]
    return {"test_frames": len(s), "test_scenarios": len(set(inputs.scenarios)),
            "test_gt_boxes": int(sum(len(x.gt_boxes) for x in s)),
            "test_gt_boxes_by_band": {b: int(sum(((lo < d) & (d < hi)).sum() for d in dist))
                                      for b, (lo, hi) in (("0-30", (0, 30)), ("30-50", (30, 50)),
                                                          ("50-100", (50, 100)))}}


def score(cfg: FusionConfig, test: FusionDataset, networks: Mapping[str, Sequence[Trained]], cells: Sequence[Cell],
          robustness_runs: Mapping[str, str], *, progress: Callable[[str], None] | None = None) -> dict:
    """Every table of the benchmark for trained ``networks`` (run -> one per seed) on ``test``:
    ``{"tables": fill_tables(...), "robustness": robustness(...), **test_summary}``."""
    scorer = Scorer(cfg, test, networks)
    if progress:
        progress(f"scoring {len(cells)} cells")
    tables = fill_tables(scorer, cells)
    if progress:
        progress(f"robustness of {len(robustness_runs)} methods")
    return {**test_summary(scorer.inputs()), "seeds": cfg.seeds, "tables": tables,
            "differences": differences(scorer, cells), "table3_differences": table3_differences(scorer, cells),
            "robustness": robustness(scorer, robustness_runs)}


def score_benchmark(bench: Benchmark, progress: Callable[[str], None] | None = None) -> dict:
    """:func:`score` of ``bench``'s trained networks on its test split, with what the stage ran."""
    results = score(bench.cfg, bench.test, bench.networks, bench.plan.cells, bench.plan.robustness, progress=progress)
    real = bench.inputs("real")
    return {**results, "skipped": dict(bench.plan.skipped),
            "finetune_sets": {k: ("all" if v is None else v) for k, v in bench.plan.finetune_sets.items()},
            "train_frames": len(real), "train_scenarios": len(set(real.scenarios)),
            "runs": len(bench.plan.runs), "trainings": len(bench.plan.runs) * bench.cfg.seeds,
            "seconds_per_run": dict(bench.seconds), "generated_compose": generated_compose(bench.roots.generated_cavs)}


def score_trained(cfg: FusionConfig, root: Path) -> dict:
    """:func:`score_benchmark` of the networks the fusion stage saved under ``root / cfg.out``
    (what the evaluate stage scores), with the training stage's times; a missing or damaged
    network raises naming its file and the fusion stage."""
    from tasks.fusion import Roots

    roots, out = Roots.from_config(cfg, root), root / cfg.out
    bench = Benchmark(cfg, roots, out)
    bench.networks = load_networks(cfg, roots, out)
    training = read_json_or_none(out / TRAINING_JSON) or {}
    return {**score_benchmark(bench), "seconds_total": training.get("seconds_total", 0.0),
            "seconds_training": training.get("seconds_training", 0.0),
            "seconds_per_run": training.get("seconds_per_run", {})}
