"""Pipeline cost: per-stage time and memory, fixed cost per stage, incremental runs, skipping,
paper scale, fusion inference.

    python bench/pipeline.py [--only pipeline,overhead,skipping,paper,fusion] [--scale N]
        [--out reports] [--repeats R] [--noop-repeats R] [--baseline REV] [--keep]

Run from the repository root. Each section is one function; a run measures the sections named
by --only (default: all), stores their raw numbers in <out>/bench_pipeline.json beside those
of earlier runs, and rewrites <out>/bench_pipeline.md and .png from every section stored, each
stamped with when and on which machine it was measured.

- pipeline: a throwaway copy of the project in /tmp (git-tracked and untracked files, .venv
  linked, `git init`; as tests/test_pipeline_e2e.py does; the stages import the copy's code,
  through PYTHONPATH) with the e2e test's small params and N = --scale scenarios in every
  split they use. Three `dvc repro` runs, one after another: from nothing (full), again with
  nothing changed (no-op), and after adding one scenario to target/test (incremental; a split
  the models are not trained on, so no model needs retraining, only evaluating and
  generating), all under one Prefect server as `make run` has. Every `typ run <stage>` process that dvc starts is followed with psutil every
  50 ms together with its descendants (Prefect's temporary server, worker processes): wall
  time from the first to the last poll that sees it, plus one interval; peak RSS as the
  largest sampled sum over the tree; the largest single process's peak from the kernel's
  high-water mark (VmHWM, exact); CPU seconds as user + system of every process of the tree
  as last seen (other sessions on the machine stretch wall times, much less CPU times).
  "dvc" is the rest of the wall time: dvc's start, hashing, lock and checks between stages.
  Work reported: the seconds a stage's metrics give for its own work (seconds_total, else
  seconds_training). Target for the incremental run: at most 1.5 / N of the full run's time.
- overhead: what a stage costs beyond its work, all in one run, on a throwaway copy
  of the project with its own params.yaml, the tiny pipeline `make run` runs: one local Prefect
  server started (timed), then `dvc repro` from nothing with PREFECT_API_URL pointing at it,
  each stage's process tree followed as above. A stage's work is its Prefect flow run (from
  its Running state to its final one, read from the server: the flow's body, which reads the
  stage's inputs, trains or computes, logs and writes) less MLflow's start inside it (the
  run's `typ.mlflow_start_s` tag: import, store, stale-run check); its fixed cost is the rest
  of its wall time: interpreter start, imports, params, the Prefect flow run's creation and
  end, MLflow's start, exit. The fixed costs of all stages plus the server's start, over the
  pipeline's wall time (server start + `dvc repro`): target ≤ 10 %.
  Then, after the pipeline, `typ run <stage>` with nothing to do (simulate and voxelize: every
  scene unchanged), --noop-repeats times each, with the shared server and (voxelize) with
  Prefect's temporary server per process: wall time from process start to exit (exact) and CPU
  of the process tree; target ≤ 4 s wall. `typ --help` and `typ check`: wall, target < 1 s.
  With --baseline REV, that revision's code (`git archive`, same params and venv) runs
  simulate and voxelize once, then the same no-op voxelize and CLI commands.
- skipping: from metrics/generate.json of the default data (the last `make run`) and of the
  bench's own runs. A reference view is skipped when its vehicle (or CAV) lies outside
  generate's [min_distance, max_distance] band (reference_too_close, reference_out_of_range;
  counted per frame and vehicle; fraction = skipped / (skipped + generated): vehicles inside
  the band but not drawn, references_per_frame being reached, are counted nowhere); a scenario
  when no vehicle stays inside the band in all its frames (scenario_without_candidate_vehicle);
  a scenario whose inputs, params and models are unchanged is not regenerated
  (skipped_unchanged). Compute saved = seconds_per_reference x the views not generated,
  against generating one at every skipped vehicle (band) or references_per_frame per frame
  (scenario without candidate); the unchanged scenarios' views are their references minus
  the references generated in that run.
- paper: the paper profile's models (typ/profiles.yaml `paper`, built by tasks/vqvae.py and
  tasks/stage1.py / tasks/stage2.py `build`) on random inputs of the paper's shapes, on this
  CPU at batch 1: a few real training steps of each (forward, loss, backward, optimizer step),
  and one denoising step (one step of the DDIM sampler: a UNet forward with adapter features
  plus the scheduler step). --repeats calls each (at least 2 training steps) after a warm-up
  call, which counts when it takes more than 5 s; the table gives their median, torch on the
  threads it was given (the stamp says how many). Extrapolated, linearly in the samples seen (a CPU does
  not get faster per sample at larger batches):
  training = s/step(batch 1) x epochs x N_train; generation = N_gen x (E_x(x_e') + E_y(y_r) +
  F_AD(x^f_e') + S x denoising step + G_x decoding), S = the paper profile's DDIM steps (200).
  N_train = 17,400 WOD training samples and N_gen = 36,000 generated samples (TYP §4.5); the
  paper gives no pair count for stage 2 and self-training, which are taken at N_train too.
  Not measured: the adaptation stage (its step is about the VQ-VAE x step plus two encoder passes).
- fusion: inference time per frame of each fusion method (tasks/fusion_train.py build_model on
  models/fusion.py + models/pointpillars.py, untrained weights) at the tiny and the paper
  profile's detector sizes, on one frame of --agents agents (the ego and cooperating agents
  up to 30 m away, random poses) with --points random points each (64-beam-like: ground
  rings and obstacle hits within 60 m). Per frame: tasks/fusion_score.py `predict` on fresh inputs
  (pillarizing every cloud, or the merged one for early fusion, the network, box decoding,
  late fusion's move into the ego frame, rotated NMS); network: the forward pass alone on
  prepared pillars. Methods take turns call by call, one warm-up call each (counted when it
  takes more than 5 s); median of --repeats. x none: time over no fusion's.
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import datetime as dt
import json
import math
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Iterator

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

from bench.report import machine, machine_line  # noqa: E402
from typ.io import atomic_path, read_json_or_none, write_json, write_text  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SECTIONS = ("pipeline", "overhead", "skipping", "paper", "fusion")
def _e2e_params() -> dict:
    """The e2e test's small params (tests/test_pipeline_e2e.py ``SMALL``), read from the test itself
    so that the two cannot drift apart: a copy kept here lost the fusion robustness and ddpm
    settings the stages gained since, and its fusion stage then failed on 2-frame sequences."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("_typ_e2e", REPO / "tests" / "test_pipeline_e2e.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return copy.deepcopy(module.SMALL)


#: every split's count is multiplied by --scale (real_cav/test: the fusion stage evaluates on it)
SMALL = _e2e_params()
ADDED = ("target", "test")          # where the incremental run adds its scenario
STAGE_CMD = re.compile(r"\btyp\s+run\s+(\w+)")
POLL_S = 0.05
N_TRAIN, N_GEN = 17_400, 36_000    # TYP §4.5: WOD samples the generator is trained on / generates
PROFILE_ORDER = ("tiny", "paper")
WARMUP_S = 5.0                      # a first call longer than this counts: its warm-up share is small
NOOP_STAGES = ("simulate", "voxelize")  # per-scene stages: a rerun with nothing changed has nothing to do
NOOP_TARGET_S, FIXED_TARGET, STARTUP_TARGET_S = 4.0, 0.10, 1.0   # targets: no-op stage, fixed share, CLI start


# ---------------------------------------------------------------- pure helpers


def small_params(scale: int) -> dict:
    """The e2e test's small params with ``scale`` scenarios in each split they use."""
    params = copy.deepcopy(SMALL)
    scenarios = params["simulate"]["scenarios"]
    for splits in scenarios.values():
        for split, n in splits.items():
            splits[split] = n * scale
    return params


def with_added_scenario(params: dict) -> dict:
    out = copy.deepcopy(params)
    domain, split = ADDED
    out["simulate"]["scenarios"][domain][split] += 1
    return out


def pipeline_stages(dvc_yaml: dict) -> list[str]:
    """typ's stages in pipeline order (Config.STAGES) that dvc.yaml declares."""
    from typ.config import Config

    declared = set((dvc_yaml or {}).get("stages", {}))
    return [s for s in Config.STAGES if s in declared]


def ordered(keys, order: tuple[str, ...]) -> list[str]:
    """``keys`` in ``order`` first, then the rest sorted (the JSON store sorts its keys)."""
    keys = list(keys)
    return [k for k in order if k in keys] + sorted(k for k in keys if k not in order)


def fmt(value, spec: str, missing: str = "–") -> str:
    return missing if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, spec)


def duration(seconds: float) -> str:
    """Seconds as the largest sensible unit: '42 s', '3.5 h', '12 d', '4.1 y'."""
    for unit, size in (("y", 365.25 * 86400), ("d", 86400), ("h", 3600), ("min", 60)):
        if seconds >= 2 * size:
            return f"{seconds / size:,.1f} {unit}"
    return f"{seconds:,.1f} s"


def work_run(result: dict) -> tuple[str, dict]:
    """(label, stage -> reported work s) of the first run whose stages report their work."""
    for label, key in (("full", "full"), ("+1", "incremental")):
        work = {k: v for k, v in result[key].get("work", {}).items() if v is not None}
        if work:
            return label, work
    return "full", {}


def stage_table(result: dict) -> str:
    """Per-stage table of the pipeline section: full run, its memory, the incremental run."""
    full, inc = result["full"], result["incremental"]
    label, work = work_run(result)
    head = (f"| stage | full: wall s | share | CPU s | work reported s ({label}) | peak RSS, tree MB "
            "| largest process MB | +1 scenario: wall s | CPU s | wall × full | CPU × full |")
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for stage in result["stages"]:
        f, i = full["stages"].get(stage), inc["stages"].get(stage)
        if i is None:
            inc_cells = "skipped | | 0 | 0"
        elif f is None:
            inc_cells = f"{i['seconds']:.1f} | {i['cpu_s']:.1f} | |"
        else:
            inc_cells = (f"{i['seconds']:.1f} | {i['cpu_s']:.1f} | {i['seconds'] / f['seconds']:.2f} "
                         f"| {i['cpu_s'] / f['cpu_s']:.2f}")
        if f is None:
            lines.append(f"| {stage} | not run | | | | | | {inc_cells} |")
            continue
        lines.append(f"| {stage} | {f['seconds']:.1f} | {f['seconds'] / full['seconds']:.0%} | {f['cpu_s']:.1f} "
                     f"| {fmt(work.get(stage), '.1f')} | {f['peak_rss_mb']:,.0f} | {f['peak_process_mb']:,.0f} "
                     f"| {inc_cells} |")
    rest, rest_i = (run["seconds"] - sum(v["seconds"] for v in run["stages"].values()) for run in (full, inc))
    lines.append(f"| dvc (start, hashing, checks) | {rest:.1f} | {rest / full['seconds']:.0%} | | | | "
                 f"| {rest_i:.1f} | | {rest_i / rest:.2f} | |")

    def cpu(run: dict) -> float:
        return sum(v["cpu_s"] for v in run["stages"].values())

    lines.append(f"| **total** | **{full['seconds']:.1f}** | 100% | {cpu(full):.1f} "
                 f"| {fmt(sum(work.values()) if work else None, '.1f')} "
                 f"| {max(v['peak_rss_mb'] for v in full['stages'].values()):,.0f} "
                 f"| {max(v['peak_process_mb'] for v in full['stages'].values()):,.0f} "
                 f"| **{inc['seconds']:.1f}** | {cpu(inc):.1f} | **{inc['seconds'] / full['seconds']:.2f}** "
                 f"| {cpu(inc) / cpu(full):.2f} |")
    return "\n".join(lines)


def incremental_verdicts(result: dict) -> list[str]:
    """'- **...**' lines: the incremental run against its 1.5 / N target, the no-op run, fixed costs."""
    n, full, inc, noop = result["scale"], result["full"], result["incremental"], result["noop"]
    ratio, target = inc["seconds"] / full["seconds"], 1.5 / n
    cpu_ratio = sum(v["cpu_s"] for v in inc["stages"].values()) / sum(v["cpu_s"] for v in full["stages"].values())
    domain, split = result["added"]
    redone = ", ".join(f"{k} {v['redone']} of {v['scenarios']}" for k, v in inc["scenario_counts"].items())
    met = "met" if ratio <= target else "**not met**"
    if n == 1:
        met += " (vacuous at N = 1: --scale 2 or more makes it bite)"
    lines = [f"- **incremental**: one scenario added to {domain}/{split} (N = {n} per split): `dvc repro` took "
             f"{inc['seconds']:.1f} s = {ratio:.2f} × the full run ({full['seconds']:.1f} s; CPU time "
             f"{cpu_ratio:.2f} ×); target ≤ 1.5/N = {target:.2f}: {met}. Stages rerun: {len(inc['ran'])} of "
             f"{len(result['stages'])}; scenarios recomputed: {redone or 'none reported'}.",
             f"- **no-op**: `dvc repro` with nothing changed took {noop['seconds']:.1f} s "
             f"({noop['seconds'] / full['seconds']:.1%} of the full run) and "
             + ("ran no stage." if noop["noop"] else f"**ran stages {', '.join(noop['ran'])}**.")]
    label, work = work_run(result)
    if work:
        run = full if label == "full" else inc
        fixed = statistics.median(run["stages"][k]["cpu_s"] - w for k, w in work.items())
        wall = sum(run["stages"][k]["seconds"] for k in work)
        lines.append(f"- **fixed cost per stage** ({label} run): the {len(work)} stages that report their own work "
                     f"(seconds_total, else seconds_training) report {sum(work.values()):.1f} s of it in {wall:.1f} s "
                     f"wall; the median stage spends {fixed:.1f} CPU s beyond its reported work: process start and "
                     "imports, Prefect's flow run, MLflow, reading inputs, evaluation.")
    return lines


def median(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def overhead_stage_rows(result: dict) -> list[dict]:
    """Per stage of the full run: wall; its Prefect flow run (the stage's body: reading inputs, its
    MLflow run, the work); MLflow's start inside it; fixed = wall − flow run + MLflow's start;
    then the Prefect server's start (once per pipeline)."""
    full = result["full"]
    rows = []
    for stage, m in full["stages"].items():
        flow, mlflow_start = full["flow_s"].get(stage), full["mlflow_start_s"].get(stage, 0.0)
        rows.append({"name": stage, "wall": m["seconds"], "flow": flow, "mlflow": mlflow_start, "cpu": m["cpu_s"],
                     "fixed": m["seconds"] - flow + mlflow_start if flow is not None else None})
    rows.append({"name": "Prefect server start (once)", "wall": result["server_s"], "flow": None, "mlflow": None,
                 "cpu": None, "fixed": result["server_s"]})
    return rows


def overhead_totals(result: dict) -> dict:
    """The pipeline's wall time (server start + `dvc repro`), the stages' fixed cost together, their ratio."""
    rows = overhead_stage_rows(result)
    wall = result["full"]["seconds"] + result["server_s"]
    fixed = sum(r["fixed"] for r in rows if r["fixed"] is not None)
    return {"wall": wall, "fixed": fixed, "ratio": fixed / wall, "unmeasured": [r["name"] for r in rows
                                                                             if r["fixed"] is None]}


def overhead_table(result: dict) -> str:
    head = ("| stage | wall s | its flow run s | of which MLflow's start s | fixed s (wall − flow run + MLflow's "
            "start) | fixed / pipeline wall | CPU s |")
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    totals = overhead_totals(result)
    for r in overhead_stage_rows(result):
        share = f"{r['fixed'] / totals['wall']:.1%}" if r["fixed"] is not None else "–"
        lines.append(f"| {r['name']} | {r['wall']:.1f} | {fmt(r['flow'], '.1f')} | {fmt(r['mlflow'], '.2f')} "
                     f"| {fmt(r['fixed'], '.1f')} | {share} | {fmt(r['cpu'], '.1f')} |")
    rest = result["full"]["seconds"] - sum(m["seconds"] for m in result["full"]["stages"].values())
    lines.append(f"| dvc (start, hashing, checks) | {rest:.1f} | | | | | |")
    lines.append(f"| **pipeline** | **{totals['wall']:.1f}** | | | **{totals['fixed']:.1f}** | **{totals['ratio']:.1%}** "
                 f"| {sum(m['cpu_s'] for m in result['full']['stages'].values()):.1f} |")
    return "\n".join(lines)


def noop_table(result: dict) -> str:
    head = (f"| code | `typ run` with nothing to do | wall s, median of {result['repeats']} | min – max "
            f"| CPU s (process tree) | × the {NOOP_TARGET_S:.0f} s target |")
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    runs = [("this branch", k, v) for k, v in result["noop"].items()]
    if result.get("baseline"):
        b = result["baseline"]
        runs += [(f"{b['rev']} ({b['sha']})", k, v) for k, v in b["noop"].items()]
    for code, what, r in runs:
        wall = median(r["wall_s"])
        lines.append(f"| {code} | {what} | {wall:.2f} | {min(r['wall_s']):.2f} – {max(r['wall_s']):.2f} "
                     f"| {median(r['cpu_s']):.2f} | {wall / NOOP_TARGET_S:.2f} |")
    return "\n".join(lines)


def startup_table(result: dict) -> str:
    head = f"| code | command | wall s, median of {result['repeats']} | × the {STARTUP_TARGET_S:.0f} s target |"
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    runs = [("this branch", result["startup"])]
    if result.get("baseline"):
        runs.append((f"{result['baseline']['rev']} ({result['baseline']['sha']})", result["baseline"]["startup"]))
    for code, startup in runs:
        for name, walls in startup.items():
            lines.append(f"| {code} | `{name}` | {median(walls):.2f} | {median(walls) / STARTUP_TARGET_S:.2f} |")
    return "\n".join(lines)


def overhead_verdicts(result: dict) -> list[str]:
    """'- **...**' lines: the no-op stage against 4 s, the fixed cost against 10 %, the CLI against 1 s."""
    def met(ok: bool) -> str:
        return "met" if ok else "**not met**"

    noop = median(result["noop"]["voxelize, shared server"]["wall_s"])
    totals = overhead_totals(result)
    lines = [f"- **no-op stage**: `typ run voxelize` with every scene unchanged took {noop:.2f} s wall (median of "
             f"{result['repeats']}) = {noop / NOOP_TARGET_S:.2f} × the {NOOP_TARGET_S:.0f} s target: "
             f"{met(noop <= NOOP_TARGET_S)}."]
    if result.get("baseline"):
        before = median(result["baseline"]["noop"]["voxelize, temporary server"]["wall_s"])
        lines[0] += (f" {result['baseline']['rev']}'s code took {before:.2f} s with its temporary Prefect server per "
                     f"stage ({before / noop:.1f} × as long).")
    unmeasured = f" (not measured: {', '.join(totals['unmeasured'])})" if totals["unmeasured"] else ""
    lines.append(f"- **fixed cost**: the stages' fixed costs together with the one Prefect server's start are "
                 f"{totals['fixed']:.1f} s of the tiny pipeline's {totals['wall']:.1f} s wall = {totals['ratio']:.1%}; "
                 f"target ≤ {FIXED_TARGET:.0%}: {met(totals['ratio'] <= FIXED_TARGET)}{unmeasured}.")
    worst = max(median(w) for w in result["startup"].values())
    lines.append(f"- **start-up**: " + ", ".join(f"`{k}` {median(w):.2f} s" for k, w in result["startup"].items())
                 + f"; target < {STARTUP_TARGET_S:.0f} s: {met(worst < STARTUP_TARGET_S)}.")
    return lines


def skip_rows(name: str, metrics: dict, references_per_frame: int) -> list[dict]:
    """Skipped reference views and scenarios of one generate.json, and the seconds they saved."""
    per_ref = metrics.get("seconds_per_reference")
    refs = metrics.get("references", 0)
    band = metrics.get("reference_too_close", 0) + metrics.get("reference_out_of_range", 0)
    scenarios = metrics.get("scenarios", 0)
    frames_per_scenario = metrics.get("frames", 0) / scenarios if scenarios else 0.0
    no_candidate = metrics.get("scenario_without_candidate_vehicle", 0)
    unchanged = metrics.get("skipped_unchanged", 0)
    done = round(metrics.get("seconds_generating", 0.0) / per_ref) if per_ref else 0
    rows = [
        {"data": name, "what": "reference views outside the distance band", "skipped": band, "of": refs + band,
         "views": band},
        {"data": name, "what": "scenarios without a candidate vehicle", "skipped": no_candidate, "of": scenarios,
         "views": no_candidate * frames_per_scenario * references_per_frame},
        {"data": name, "what": "scenarios unchanged since the last run", "skipped": unchanged, "of": scenarios,
         "views": max(refs - done, 0) if unchanged else 0},
    ]
    for row in rows:
        row["seconds_per_reference"] = per_ref
        row["saved_s"] = row["views"] * per_ref if per_ref is not None else None
    return rows


def skip_table(rows: list[dict]) -> str:
    head = "| data | skipped | count | fraction | views not generated | s/reference | compute saved |"
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for r in rows:
        frac = f"{r['skipped'] / r['of']:.1%}" if r["of"] else "–"
        saved = duration(r["saved_s"]) if r["saved_s"] is not None else "– (nothing generated)"
        lines.append(f"| {r['data']} | {r['what']} | {r['skipped']:,} of {r['of']:,} | {frac} | {r['views']:,.0f} "
                     f"| {fmt(r['seconds_per_reference'], '.3f')} | {saved} |")
    return "\n".join(lines)


GENERATION_PARTS = ("E_x encode", "E_y encode", "F_AD features", "G_x decode")


def extrapolate(result: dict) -> list[dict]:
    """Training rows x epochs x samples, and generation per sample x samples generated."""
    t = {r["name"]: r["seconds"] for r in result["rows"]}
    steps = result["sample_steps"]
    per_gen = sum(t[n] for n in GENERATION_PARTS) + steps * t["denoising step"]
    out = [{"name": r["name"], "per_sample": r["seconds"], "total": r["seconds"] * r["epochs"] * r["n"],
            "formula": f"{r['epochs']} epochs × {r['n']:,}" + (" (assumed)" if r.get("assumed") else "")}
           for r in result["rows"] if r.get("epochs")]
    out += [{"name": "self-training pseudo references", "per_sample": per_gen,
             "total": per_gen * result["pseudo_references"],
             "formula": f"{result['pseudo_references']:,} samples × generation"},
            {"name": "generation (ColWaymo)", "per_sample": per_gen, "total": per_gen * result["n_gen"],
             "formula": f"{result['n_gen']:,} samples × (E_x + E_y + F_AD + {steps} × denoising step + G_x)"}]
    return out


def paper_table(result: dict) -> str:
    head = "| component | what | params M | s per call, batch 1 |"
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for r in result["rows"]:
        lines.append(f"| {r['name']} | {r['what']} | {fmt(r['params_m'], '.1f')} | {r['seconds']:.3f} |")
    head = "| cost | s per sample | × | CPU time on this machine |"
    lines += ["", head, "|" + "---|" * head.count(" | ") + "---|"]
    rows = extrapolate(result)
    for r in rows:
        lines.append(f"| {r['name']} | {r['per_sample']:.3f} | {r['formula']} | {duration(r['total'])} |")
    lines.append(f"| **total** | | | **{duration(sum(r['total'] for r in rows))}** |")
    return "\n".join(lines)


def fusion_table(result: dict) -> str:
    head = "| profile | detector | method | ms / frame | × none | network ms | × none |"
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for profile in ordered(result["profiles"], PROFILE_ORDER):
        res = result["profiles"][profile]
        base = res["methods"]["none"]
        for method in ordered(res["methods"], fusion_order()):
            r = res["methods"][method]
            lines.append(f"| {profile} | {res['detector']} | {method} | {1e3 * r['frame_s']:.1f} "
                         f"| {r['frame_s'] / base['frame_s']:.2f}× | {1e3 * r['network_s']:.1f} "
                         f"| {r['network_s'] / base['network_s']:.2f}× |")
    return "\n".join(lines)


def stamp(section: dict) -> str:
    load = f"; 1-minute load average {section['load']:.1f} at the start" if "load" in section else ""
    return f"Measured {section['when']} on {machine_line(section['machine'])}{load}."


def render(store: dict) -> str:
    """The whole report from the stored sections."""
    doc = __doc__.split("\n\n", 2)[2]
    parts = ["# Pipeline cost: stages, incremental runs, skipping, paper scale, fusion inference", "", doc]
    pipe = store.get("pipeline")
    if pipe:
        params = pipe["params"]["simulate"]
        parts += [f"## Per-stage time and memory of `dvc repro` (tiny profile, N = {pipe['scale']})", "",
                  f"{stamp(pipe)} Scenarios per split: {json.dumps(params['scenarios'])}, {params['frames']} frames "
                  f"each; stages in dvc.yaml: {', '.join(pipe['stages'])}.", "",
                  stage_table(pipe), "", *incremental_verdicts(pipe), ""]
    over = store.get("overhead")
    if over:
        params_used = over.get("params_file") or "the project's params.yaml (the tiny pipeline `make run` runs)"
        parts += ["## Fixed cost per stage: the tiny pipeline, stages with nothing to do, the CLI", "",
                  f"{stamp(over)} Params: {params_used}; from nothing, under one Prefect server.", "",
                  overhead_table(over), "", noop_table(over), "", startup_table(over), "",
                  *overhead_verdicts(over), ""]
    skip = store.get("skipping")
    if skip or pipe:
        rows = []
        if skip and skip.get("default"):
            rows += skip_rows("default data", skip["default"], skip["references_per_frame"])
        if pipe:
            rpf = pipe["params"]["generate"]["references_per_frame"]
            rows += skip_rows(f"bench N = {pipe['scale']}, full run", pipe["full"]["generate"], rpf)
            rows += skip_rows(f"bench N = {pipe['scale']}, +1 scenario", pipe["incremental"]["generate"], rpf)
        note = (f"{stamp(skip)} Default data: {skip['source']}." if skip and skip.get("default")
                else "No metrics/generate.json of the default data: run `make run` first.")
        parts += ["## Skipping", "", note, "", skip_table(rows), ""]
    paper = store.get("paper")
    if paper:
        parts += ["## Paper profile: per-sample cost extrapolated from real steps", "",
                  f"{stamp(paper)} Median of {paper['steps']} timed calls per row.", "", paper_table(paper), ""]
    fusion = store.get("fusion")
    if fusion:
        parts += ["## Fusion inference time per frame", "",
                  f"{stamp(fusion)} {fusion['agents']} agents, {fusion['points']:,} points each, median of "
                  f"{fusion['repeats']} calls.", "", fusion_table(fusion), ""]
    return "\n".join(parts)


def plot(store: dict, path: Path) -> None:
    from typ.reporting import subplots
    import numpy as np

    panels = [k for k in ("pipeline", "paper", "fusion") if store.get(k)]
    if not panels:
        return
    fig, axes = subplots(1, len(panels), figsize=(6.2 * len(panels), 4.8), squeeze=False)
    for ax, key in zip(axes[0], panels):
        res = store[key]
        if key == "pipeline":
            names = res["stages"] + ["dvc"]
            runs = {"full": res["full"], "+1 scenario": res["incremental"], "no-op": res["noop"]}
            x = np.arange(len(names))
            for k, (label, run) in enumerate(runs.items()):
                secs = [run["stages"].get(s, {}).get("seconds", 0.0) for s in res["stages"]]
                secs.append(run["seconds"] - sum(secs))
                ax.bar(x + (k - 1) * 0.27, secs, 0.27, label=f"{label} ({run['seconds']:.0f} s)")
            ax.set_xticks(x, names, rotation=30, fontsize=8)
            ax.set_ylabel("wall time, s")
            ax.set_title(f"dvc repro per stage, tiny profile, N = {res['scale']}", fontsize=10)
            ax2 = ax.twinx()
            ax2.plot(x[:-1], [res["full"]["stages"].get(s, {}).get("peak_rss_mb", np.nan) for s in res["stages"]],
                     "k.--", lw=0.8, label="peak RSS, full run")
            ax2.set_ylabel("peak RSS of the stage's process tree, MB")
            ax2.set_ylim(bottom=0)
            handles = [h for a in (ax, ax2) for h in a.get_legend_handles_labels()[0]]
            ax.legend(handles, [h.get_label() for h in handles], fontsize=8, ncol=2, loc="upper left",
                      bbox_to_anchor=(0.0, -0.2))
        elif key == "paper":
            totals = extrapolate(res)
            ax.barh([r["name"] for r in totals], [r["total"] / 86400 for r in totals], color="tab:purple")
            ax.set_xscale("log")
            ax.set_xlabel("extrapolated CPU time on this machine, days (log)")
            ax.set_title("paper profile: per-sample cost × paper epochs and samples", fontsize=10)
            ax.invert_yaxis()
        else:
            profiles = ordered(res["profiles"], PROFILE_ORDER)
            methods = ordered(next(iter(res["profiles"].values()))["methods"], fusion_order())
            x = np.arange(len(methods))
            width = 0.8 / len(profiles)
            for k, profile in enumerate(profiles):
                m = res["profiles"][profile]["methods"]
                ax.bar(x + (k - (len(profiles) - 1) / 2) * width, [m[n]["frame_s"] / m["none"]["frame_s"]
                                                                   for n in methods], width, label=profile)
            ax.axhline(1.0, color="k", lw=0.8)
            ax.set_xticks(x, methods)
            ax.set_ylabel("time per frame / no fusion's")
            ax.set_title(f"fusion inference, {res['agents']} agents, same frame", fontsize=10)
            ax.legend(fontsize=8)
        ax.grid(axis="y" if key != "paper" else "x", which="both", alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)


def write_report(store: dict, out: Path) -> None:
    write_json(out / "bench_pipeline.json", store)
    write_text(out / "bench_pipeline.md", render(store))
    plot(store, out / "bench_pipeline.png")


def section_stamp() -> dict:
    """When, on what, and how busy the machine was (other processes stretch wall times, not CPU times)."""
    return {"when": dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z"), "machine": machine(),
            "load": os.getloadavg()[0]}


# ---------------------------------------------------------------- process-tree measurement


def _hwm_mb(pid: int) -> float:
    """The kernel's peak resident set size of ``pid`` (VmHWM), MB; 0 when unreadable."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError):
        pass
    return 0.0


class StageMonitor(threading.Thread):
    """Follows the descendants of ``pid`` and charges each to the `typ run <stage>` process above it.

    Per stage: ``start``/``end`` (perf_counter s), ``peak_rss_mb`` (largest sampled tree sum),
    ``peak_process_mb`` (largest VmHWM seen), ``cpu_s`` (user + system, processes as last seen).
    """

    def __init__(self, pid: int, *, interval: float = POLL_S, label: str | None = None):
        super().__init__(daemon=True)
        import psutil

        self._psutil, self.root, self.interval = psutil, psutil.Process(pid), interval
        self.fixed_label = label  # charge the root and its whole tree to this label
        self._halt = threading.Event()
        self._stage_of: dict[tuple[int, float], str | None] = {}
        self._cpu: dict[tuple[int, float], tuple[str, float]] = {}
        self.stages: dict[str, dict] = {}

    def run(self) -> None:
        while not self._halt.is_set():
            self.poll()
            self._halt.wait(self.interval)

    def stop(self) -> dict[str, dict]:
        self._halt.set()
        self.join()
        for stage, cpu in self._cpu.values():
            self.stages[stage]["cpu_s"] += cpu
        return {s: {"seconds": v["end"] - v["start"], **{k: v[k] for k in ("peak_rss_mb", "peak_process_mb",
                                                                         "cpu_s")}}
                for s, v in self.stages.items()}

    def _label(self, proc, parent_label: str | None) -> str | None:
        key = (proc.pid, proc.create_time())
        if key not in self._stage_of:
            match = STAGE_CMD.search(" ".join(proc.cmdline()))
            self._stage_of[key] = match.group(1) if match else None
        return parent_label or self._stage_of[key]

    def poll(self) -> None:
        psutil = self._psutil
        now = time.perf_counter()
        try:
            procs = self.root.children(recursive=True)
        except psutil.Error:
            return
        if self.fixed_label is not None:
            procs.append(self.root)
        by_pid = {p.pid: p for p in procs}
        labels: dict[int, str | None] = {}

        def label(p) -> str | None:  # the outermost `typ run <stage>` at or above p
            if self.fixed_label is not None:
                return self.fixed_label
            if p.pid not in labels:
                labels[p.pid] = None  # cycle guard
                try:
                    parent = by_pid.get(p.ppid())
                    labels[p.pid] = self._label(p, label(parent) if parent is not None else None)
                except psutil.Error:
                    pass
            return labels[p.pid]

        rss: dict[str, float] = {}
        for p in procs:
            stage = label(p)
            if stage is None:
                continue
            try:
                with p.oneshot():
                    key = (p.pid, p.create_time())
                    mem, cpu = p.memory_info().rss / 2**20, p.cpu_times()
            except psutil.Error:
                continue
            # seen between two polls: charge half an interval on either side (create_time is
            # relative to a boot time the kernel gives in whole seconds: too coarse)
            entry = self.stages.setdefault(stage, {"start": now - self.interval / 2, "peak_rss_mb": 0.0,
                                                   "peak_process_mb": 0.0, "cpu_s": 0.0})
            entry["end"] = now + self.interval / 2
            entry["peak_process_mb"] = max(entry["peak_process_mb"], _hwm_mb(p.pid), mem)
            self._cpu[key] = (stage, cpu.user + cpu.system)
            rss[stage] = rss.get(stage, 0.0) + mem
        for stage, total in rss.items():
            self.stages[stage]["peak_rss_mb"] = max(self.stages[stage]["peak_rss_mb"], total)


def measured(cmd: list[str], cwd: Path, env: dict, *, label: str | None = None) -> dict:
    """Run ``cmd``; its wall time, stdout, and per-stage numbers of the `typ run` processes it starts
    (``label``: the whole process tree of ``cmd``, itself included, counts as that one stage)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    monitor = StageMonitor(proc.pid, label=label)
    monitor.start()
    stdout, stderr = proc.communicate()
    seconds = time.perf_counter() - t0
    stages = monitor.stop()
    if proc.returncode != 0:
        done = ", ".join(f"{k} {v['seconds']:.1f} s" for k, v in stages.items())
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}) in {cwd} after {seconds:.1f} s "
                           f"({done}):\n{stdout[-3000:]}\n{stderr[-5000:]}")
    return {"seconds": seconds, "stages": stages, "ran": list(stages), "noop": "Running stage" not in stdout}


# ---------------------------------------------------------------- sections


def copy_project(dst: Path) -> None:
    """The files git tracks or would track (not ignored) into ``dst``, with .venv linked."""
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True,
                           text=True, check=True).stdout.splitlines()
    for rel in files:
        src = REPO / rel
        if src.is_file():
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / rel)
    (dst / "dvc.lock").unlink(missing_ok=True)  # a full run from nothing
    (dst / ".venv").symlink_to(REPO / ".venv")


def project_env(proj: Path) -> dict:
    # PYTHONPATH: the copy's typ/flows/tasks/models, not the checkout's that the editable
    # install points at (the checkout may change while the bench runs)
    return {**os.environ, "PATH": f"{REPO / '.venv' / 'bin'}:{os.environ['PATH']}", "PYTHONPATH": str(proj),
            "MLFLOW_TRACKING_URI": f"sqlite:///{proj / 'mlruns.db'}", "PREFECT_HOME": str(proj / ".prefect"),
            "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DVC_NO_ANALYTICS": "1", "DO_NOT_TRACK": "1",
            "PREFECT_LOGGING_LEVEL": "WARNING", "GIT_AUTHOR_NAME": "bench", "GIT_AUTHOR_EMAIL": "bench@localhost",
            "GIT_COMMITTER_NAME": "bench", "GIT_COMMITTER_EMAIL": "bench@localhost"}


def reported_work(metrics: dict) -> float | None:
    """The seconds a stage reports for its own work: ``seconds_total``, else its ``seconds_training``s."""
    if "seconds_total" in metrics:
        return metrics["seconds_total"]

    def training(d: dict) -> list[float]:
        return [v for k, v in d.items() if k == "seconds_training"] + \
            [t for v in d.values() if isinstance(v, dict) for t in training(v)]

    found = training(metrics)
    return sum(found) if found else None


def scenario_counts(proj: Path) -> dict:
    """stage -> {'redone', 'scenarios'} from the per-scene stages' metrics."""
    out = {}
    for stage in ("simulate", "voxelize", "generate"):
        m = read_json_or_none(proj / "metrics" / f"{stage}.json") or {}
        if "scenarios" in m:
            out[stage] = {"redone": m["scenarios"] - m.get("skipped_unchanged", 0), "scenarios": m["scenarios"]}
    return out


def bench_pipeline(scale: int, *, keep: bool = False) -> dict:
    """Full, no-op and incremental `dvc repro` of a throwaway project copy with small params."""
    import yaml

    work = Path(tempfile.mkdtemp(prefix="typ-bench-pipeline-"))
    proj = work / "project"
    try:
        copy_project(proj)
        params = small_params(scale)
        (proj / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
        git_snapshot(proj, project_env(proj))
        stages = pipeline_stages(yaml.safe_load((proj / "dvc.yaml").read_text()))
        runs = {}
        with shared_server(proj, project_env(proj)) as (env, _):
            for name in ("full", "noop", "incremental"):
                if name == "incremental":
                    (proj / "params.yaml").write_text(yaml.safe_dump(with_added_scenario(params), sort_keys=False))
                print(f"pipeline: dvc repro ({name}) in {proj}", file=sys.stderr)
                runs[name] = measured(["dvc", "repro"], proj, env)
                runs[name]["scenario_counts"] = scenario_counts(proj)
                runs[name]["generate"] = read_json_or_none(proj / "metrics" / "generate.json") or {}
                runs[name]["work"] = {s: reported_work(read_json_or_none(proj / "metrics" / f"{s}.json") or {})
                                      for s in runs[name]["stages"]}
                ran = ", ".join(f"{k} {v['seconds']:.1f} s" for k, v in runs[name]["stages"].items())
                print(f"  {runs[name]['seconds']:.1f} s; stages run: {ran or 'none'}", file=sys.stderr)
    finally:
        if keep:
            print(f"pipeline: kept {proj}", file=sys.stderr)
        else:
            shutil.rmtree(work, ignore_errors=True)
    return {"scale": scale, "params": params, "added": list(ADDED), "stages": stages, **runs}


def git_snapshot(proj: Path, env: dict) -> None:
    for cmd in (["git", "init", "-q"], ["git", "add", "-A"], ["git", "commit", "-qm", "bench snapshot"]):
        subprocess.run(cmd, cwd=proj, env=env, check=True, capture_output=True)


@contextlib.contextmanager
def shared_server(proj: Path, env: dict) -> Iterator[tuple[dict, float]]:
    """(env with the server's PREFECT_API_URL and secret, seconds the server took to start): one
    local Prefect server for everything run inside, as `make run` (`typ with-server dvc repro`)
    has; stopped on the way out."""
    from flows.server import LocalServer

    t0 = time.perf_counter()
    with LocalServer.running(proj / ".prefect", ui=False, env=env, timeout=600) as server:
        started = time.perf_counter() - t0
        yield {**env, **server.client_env}, started


def mlflow_starts(proj: Path, since: float) -> dict[str, float]:
    """stage -> seconds MLflow took to start in its runs created after ``since`` (epoch s): the
    ``typ.mlflow_start_s`` tag (import, store, stale-run check, until the run exists)."""
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{proj / 'mlruns.db'}")
    starts: dict[str, float] = {}
    for exp in client.search_experiments():
        for run in client.search_runs([exp.experiment_id], max_results=10_000):
            tags = run.data.tags
            if tags.get("typ.stage") and "typ.mlflow_start_s" in tags and run.info.start_time / 1e3 >= since:
                starts[tags["typ.stage"]] = starts.get(tags["typ.stage"], 0.0) + float(tags["typ.mlflow_start_s"])
    return starts


#: prints {flow name: [seconds of each flow run that ended]} of the Prefect API in PREFECT_API_URL
FLOW_RUNS = """
import json
from prefect.client.orchestration import get_client
with get_client(sync_client=True) as client:
    names = {f.id: f.name for f in client.read_flows()}
    out = {}
    for run in client.read_flow_runs(limit=200):
        if run.start_time and run.end_time:
            out.setdefault(names.get(run.flow_id, "?"), []).append((run.end_time - run.start_time).total_seconds())
print(json.dumps(out))
"""


def flow_run_seconds(env: dict) -> dict[str, float]:
    """flow name -> seconds its flow runs took in the Prefect API of ``env``: from the flow run's
    Running state (its body starts) to its final state, the stage's work with its inputs read."""
    proc = subprocess.run([str(REPO / ".venv" / "bin" / "python"), "-c", FLOW_RUNS], env=env, capture_output=True,
                          text=True, check=True)
    return {name: sum(runs) for name, runs in json.loads(proc.stdout.strip().splitlines()[-1]).items()}


def typ_command(proj: Path) -> list[str]:
    """How to start the `typ` console script of the code in ``proj`` (its pyproject's entry point)
    with the checkout's interpreter: the code of another revision runs unchanged."""
    import tomllib

    entry = tomllib.loads((proj / "pyproject.toml").read_text())["project"]["scripts"]["typ"]
    module, func = entry.split(":")
    return [str(REPO / ".venv" / "bin" / "python"), "-c",
            f"import sys; sys.argv[0] = 'typ'; from {module} import {func}; sys.exit({func}())"]


def noop_runs(typ: list[str], stage: str, proj: Path, env: dict, repeats: int) -> dict:
    """``typ run <stage>`` ``repeats`` times with nothing to do: wall s (exact, process start to
    exit) and CPU s of the process tree (a temporary Prefect server included) of each."""
    walls, cpus = [], []
    for _ in range(repeats):
        r = measured([*typ, "run", stage], proj, env, label=stage)
        walls.append(r["seconds"])
        cpus.append(r["stages"].get(stage, {}).get("cpu_s", float("nan")))
    return {"wall_s": walls, "cpu_s": cpus}


def command_walls(cmd: list[str], proj: Path, env: dict, repeats: int) -> list[float]:
    walls = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(cmd, cwd=proj, env=env, check=True, capture_output=True)
        walls.append(time.perf_counter() - t0)
    return walls


def bench_overhead(*, repeats: int, baseline: str | None = None, params: Path | None = None,
                   keep: bool = False) -> dict:
    """The tiny pipeline (the checkout's params.yaml) from nothing under one Prefect server, each
    stage's fixed cost (wall − time in its MLflow run), no-op stages, `typ --help` / `typ check`;
    with ``baseline`` (a git revision) the same no-op stage of that revision's code."""
    work = Path(tempfile.mkdtemp(prefix="typ-bench-overhead-"))
    proj = work / "project"
    try:
        copy_project(proj)
        if params is not None:
            shutil.copy2(params, proj / "params.yaml")
        env = project_env(proj)
        git_snapshot(proj, env)
        typ = typ_command(proj)
        result: dict = {"repeats": repeats, "params": (proj / "params.yaml").read_text(),
                        "params_file": str(params) if params is not None else None,
                        "startup": {name: command_walls([*typ, *argv], proj, env, repeats)
                                    for name, argv in (("typ --help", ["--help"]), ("typ check", ["check"]))}}
        with shared_server(proj, env) as (api, server_s):
            print(f"overhead: dvc repro (tiny pipeline) in {proj}", file=sys.stderr)
            since = time.time()
            full = measured(["dvc", "repro"], proj, api)
            full["flow_s"] = flow_run_seconds(api)          # before the no-op runs add theirs
            full["mlflow_start_s"] = mlflow_starts(proj, since)
            result.update(server_s=server_s, full=full, noop={})
            for stage in NOOP_STAGES:
                result["noop"][f"{stage}, shared server"] = noop_runs(typ, stage, proj, api, repeats)
        result["noop"]["voxelize, temporary server"] = noop_runs(typ, "voxelize", proj, env, repeats)
        if baseline:
            result["baseline"] = {"rev": baseline, **bench_baseline(baseline, work, proj, repeats)}
    finally:
        if keep:
            print(f"overhead: kept {work}", file=sys.stderr)
        else:
            shutil.rmtree(work, ignore_errors=True)
    return result


def bench_baseline(rev: str, work: Path, proj: Path, repeats: int) -> dict:
    """``rev``'s code on the same params: simulate + voxelize once, then its no-op voxelize with a
    temporary Prefect server per stage (as its `make run` had) and with a shared one."""
    base = work / "baseline"
    base.mkdir()
    archive = subprocess.run(["git", "archive", rev], cwd=REPO, capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(base)], input=archive, check=True)
    shutil.copy2(proj / "params.yaml", base / "params.yaml")
    (base / ".venv").symlink_to(REPO / ".venv")
    env = project_env(base)
    typ = typ_command(base)
    sha = subprocess.run(["git", "rev-parse", "--short", rev], cwd=REPO, capture_output=True, text=True,
                         check=True).stdout.strip()
    out = {"sha": sha, "startup": {name: command_walls([*typ, *argv], base, env, repeats)
                                   for name, argv in (("typ --help", ["--help"]), ("typ check", ["check"]))},
           "noop": {}}
    with shared_server(base, env) as (api, _):
        for stage in NOOP_STAGES:   # its own data first: a change to the readers' code redoes every scene
            measured([*typ, "run", stage], base, api, label=stage)
        out["noop"]["voxelize, shared server"] = noop_runs(typ, "voxelize", base, api, repeats)
    out["noop"]["voxelize, temporary server"] = noop_runs(typ, "voxelize", base, env, repeats)
    return out


def bench_skipping(root: Path) -> dict:
    """The default data's generate metrics (the last `make run`), with its references_per_frame."""
    from typ.config import load_config

    path = root / "metrics" / "generate.json"
    default = read_json_or_none(path)
    rpf = load_config(root / "params.yaml").generate.references_per_frame
    return {"source": f"{path.relative_to(root)} of the last `make run`",
            "default": default, "references_per_frame": rpf}


def call_seconds(fn, *, repeats: int, min_calls: int = 1) -> float:
    """Median wall seconds of ``fn()`` over ``max(repeats, min_calls)`` calls after a warm-up call;
    a first call slower than WARMUP_S counts as one of them (its warm-up share is small)."""
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    times = [first] if first > WARMUP_S else []
    while len(times) < max(repeats, min_calls):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_paper(steps: int) -> dict:
    """Seconds per training step (batch 1) and per generation component of the paper profile's models."""
    import numpy as np
    import torch
    import torch.nn.functional as F

    from models.samplers import make_scheduler, sample
    from models.schedules import alphas_cumprod, betas
    from tasks import stage1, stage2, vqvae
    from tasks.training import noised_batch
    from typ.config import config_from_dict

    cfg = config_from_dict({"profile": "paper"})
    H, W, C = cfg.voxelize.grid.shape
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    rows: list[dict] = []

    def add(name: str, what: str, modules: list, fn, *, training: bool, **extra) -> None:
        seconds = call_seconds(fn, repeats=steps, min_calls=2 if training else 1)
        params = sum(p.numel() for m in modules for p in m.parameters()) / 1e6
        rows.append({"name": name, "what": what, "params_m": params, "seconds": seconds, **extra})
        print(f"  paper {name}: {seconds:.3f} s", file=sys.stderr)

    def train_step(model_fn, opt):
        def step():
            loss = model_fn()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        return step

    occupancy = (torch.rand(1, C, H, W) < 0.04).float()     # about the tiny data's 3.7 % occupied voxels
    boxes = (torch.rand(1, 1, H, W) < 0.01).float()
    vq = {}
    for kind, x in (("y", boxes), ("x", occupancy)):
        ae = getattr(cfg.vqvae, kind)
        model = vqvae.build(kind, ae, C).train()
        opt = torch.optim.Adam(model.parameters(), lr=cfg.vqvae.lr)
        add(f"VQ-VAE {kind}", f"train step, input {tuple(x.shape[1:])}", [model],
            train_step(lambda model=model, x=x, g=ae.gamma: model.loss(x, gamma=g)[0], opt), training=True,
            epochs=ae.epochs, n=N_TRAIN)
        vq[kind] = model.eval()

    with torch.no_grad():
        x_lat, y_lat = vq["x"].encode_pre_quant(occupancy), vq["y"].encode_pre_quant(boxes)
    s1 = cfg.stage1
    ldm = stage1.build(s1, x_lat.shape[1], y_lat.shape[1], x_lat.shape[-1]).train()
    ldm.set_statistics(torch.randn(4, *x_lat.shape[1:]), torch.randn(4, *y_lat.shape[1:]))
    abar = torch.from_numpy(alphas_cumprod(betas(s1.schedule, s1.train_timesteps))).float()
    z0, c, ce = torch.randn(1, *x_lat.shape[1:]), torch.randn(1, *y_lat.shape[1:]), torch.randn(1, *x_lat.shape[1:])

    def eps_loss(adapter=None):
        index, t, eps, z_t = noised_batch(rng, z0, abar, 1)
        features = list(adapter(ce[index])) if adapter is not None else None
        return F.mse_loss(ldm(z_t, t, c[index], features), eps)

    add("stage-1 UNet", f"train step, x^f {tuple(x_lat.shape[1:])}, y^f {tuple(y_lat.shape[1:])}", [ldm],
        train_step(eps_loss, torch.optim.AdamW(ldm.parameters(), lr=s1.lr)), training=True, epochs=s1.epochs,
        n=N_TRAIN)
    ldm.eval().requires_grad_(False)
    adapter = stage2.build_adapter(ldm, res_blocks=cfg.stage2.adapter_res_blocks, seed=0).train()
    add("stage-2 adapter", "train step of F_AD, UNet frozen", [adapter],
        train_step(lambda: eps_loss(adapter), torch.optim.AdamW(adapter.parameters(), lr=cfg.stage2.lr)),
        training=True, epochs=cfg.stage2.epochs, n=N_TRAIN, assumed=True)
    rows.append({**rows[-1], "name": "self-training adapter", "epochs": cfg.selftrain.epochs})
    adapter.eval()

    with torch.no_grad():
        features = stage2.adapter_features(adapter, ldm, x_lat)
        scheduler = make_scheduler("ddim", betas(s1.schedule, s1.train_timesteps))
        gen = torch.Generator().manual_seed(0)
        add("E_x encode", "x_e' -> x^f_e'", [vq["x"].net.encoder, vq["x"].net.quant_conv],
            lambda: vq["x"].encode_pre_quant(occupancy), training=False)
        add("E_y encode", "y_r -> y^f_r", [vq["y"].net.encoder, vq["y"].net.quant_conv],
            lambda: vq["y"].encode_pre_quant(boxes), training=False)
        add("F_AD features", "once per sample", [adapter], lambda: stage2.adapter_features(adapter, ldm, x_lat),
            training=False)
        add("denoising step", "UNet forward with adapter features + DDIM step", [ldm],
            lambda: sample(ldm, scheduler, shape=tuple(x_lat.shape), num_steps=1, generator=gen,
                           cond=ldm.normalize_cond(y_lat), adapter_features=features), training=False)
        add("G_x decode", f"x^f -> logits {(1, C, H, W)}", [vq["x"].net.post_quant_conv, vq["x"].net.decoder],
            lambda: vq["x"].decode_latents(x_lat), training=False)
    return {"steps": steps, "sample_steps": cfg.generate.sample_steps, "n_gen": N_GEN,
            "pseudo_references": cfg.selftrain.pseudo_references, "rows": rows}


def synthetic_cloud(rng, n: int) -> "np.ndarray":
    """(n, 4) float32 64-beam-like scan: ground rings thinning with range, 35 % obstacle hits within 60 m."""
    import numpy as np

    elev = np.radians(rng.choice(np.linspace(-24.9, 2.0, 64), n))
    az = rng.uniform(-np.pi, np.pi, n)
    r = np.where(elev < 0, 1.73 / np.tan(-np.minimum(elev, -1e-3)), 120.0)
    r = np.where(rng.random(n) < 0.35, np.minimum(r, rng.uniform(3.0, 60.0, n)), np.minimum(r, 120.0))
    xyz = np.stack([r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az), r * np.sin(elev) - 0.2], 1)
    return np.column_stack([xyz, rng.random(n)]).astype(np.float32)


def fusion_frame(rng, *, agents: int, points: int):
    """One FusionSample of ``agents`` random clouds, the others within 30 m of the ego, no labels."""
    import numpy as np

    from tasks.fusion_data import FusionSample
    from typ.geometry import pose_to_matrix

    poses = [np.eye(4)] + [pose_to_matrix([*rng.uniform(-30, 30, 2), 0.0, 0.0, rng.uniform(-180, 180), 0.0])
                           for _ in range(agents - 1)]
    transforms = np.stack(poses)
    empty = np.zeros((0, 7))
    return FusionSample("bench", "000000", tuple(str(i) for i in range(agents)),
                        tuple(synthetic_cloud(rng, points) for _ in range(agents)), transforms, transforms,
                        np.zeros(agents, np.int64), empty, np.zeros(0, np.int64), tuple(empty for _ in range(agents)))


def fusion_order() -> tuple[str, ...]:
    """The fusion methods in bench order (the registry's)."""
    from models.fusion import METHODS

    return tuple(METHODS)


def time_fusion(cfg, *, agents: int, points: int, repeats: int, seed: int = 0) -> dict:
    """method -> {'frame_s', 'network_s'} for one frame, methods taking turns call by call."""
    import numpy as np
    import torch

    from models.fusion import METHODS
    from tasks.fusion_batch import Inputs
    from tasks.fusion_score import predict
    from tasks.fusion_train import Trained, box_coder, build_model

    sample = fusion_frame(np.random.default_rng(seed), agents=agents, points=points)
    trained, batches = {}, {}
    for method in cfg.methods:
        torch.manual_seed(seed)
        model = build_model(METHODS[method].network, cfg).eval()
        trained[method] = Trained(METHODS[method].network, model, box_coder(cfg, model), key="bench",
                                  steps=0).as_method(method)
        batches[method] = Inputs([sample], cfg).batch(method, [0])
    calls = {}
    for method in cfg.methods:
        calls[(method, "frame_s")] = lambda m=method: predict(trained[m], Inputs([sample], cfg), cfg, batch_size=1)
        calls[(method, "network_s")] = lambda m=method: batches[m].run(trained[m].model)
    times: dict = {k: [] for k in calls}
    with torch.no_grad():
        for rep in range(repeats + 1):      # the first round warms up, and counts for calls over WARMUP_S
            for key, fn in calls.items():
                if len(times[key]) == repeats:
                    continue
                t0 = time.perf_counter()
                fn()
                seconds = time.perf_counter() - t0
                if rep or seconds > WARMUP_S:
                    times[key].append(seconds)
    out: dict = {m: {} for m in cfg.methods}
    for (method, what), t in times.items():
        out[method][what] = statistics.median(t)
    return out


def bench_fusion(*, agents: int, points: int, repeats: int) -> dict:
    from typ.config import config_from_dict

    profiles = {}
    for profile in ("tiny", "paper"):
        cfg = config_from_dict({"profile": profile}).fusion
        d = cfg.detector
        nx, ny = (round((d.lidar_range[k + 3] - d.lidar_range[k]) / d.voxel_size) for k in (0, 1))
        detector = f"{d.voxel_size} m pillars, {nx}×{ny}, filters {list(d.num_filters)}"
        print(f"fusion: {profile} profile ({detector})", file=sys.stderr)
        profiles[profile] = {"detector": detector,
                             "methods": time_fusion(cfg, agents=agents, points=points, repeats=repeats)}
    return {"agents": agents, "points": points, "repeats": repeats, "profiles": profiles}


# ---------------------------------------------------------------- CLI


def parse_args(argv: list[str] | None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", default=",".join(SECTIONS), help=f"comma-separated sections of {list(SECTIONS)}")
    ap.add_argument("--scale", type=int, default=1, help="pipeline: scenarios per split (N)")
    ap.add_argument("--out", default="reports", help="folder for bench_pipeline.md/.png/.json")
    ap.add_argument("--repeats", type=int, default=2, help="paper: timed training steps; fusion: timed calls")
    ap.add_argument("--agents", type=int, default=3, help="fusion: agents per frame, the ego included")
    ap.add_argument("--points", type=int, default=30_000, help="fusion: points per agent's cloud")
    ap.add_argument("--keep", action="store_true", help="pipeline, overhead: keep the throwaway project (path on stderr)")
    ap.add_argument("--params", help="overhead: this params file instead of the project's (the tiny pipeline)")
    ap.add_argument("--noop-repeats", type=int, default=3, help="overhead: runs of each no-op stage and CLI command")
    ap.add_argument("--baseline", help="overhead: also time the no-op stage and the CLI of this git revision's code "
                                       "(e.g. main)")
    args = ap.parse_args(argv)
    only = [s.strip() for s in args.only.split(",") if s.strip()]
    bad = [s for s in only if s not in SECTIONS]
    if bad or not only:
        ap.error(f"--only: expected sections of {list(SECTIONS)}, got {bad or only}")
    if args.scale < 1 or args.repeats < 1 or args.agents < 1 or args.points < 1 or args.noop_repeats < 1:
        ap.error("--scale, --repeats, --agents, --points and --noop-repeats must be positive")
    return args, only


def main(argv: list[str] | None = None) -> int:
    args, only = parse_args(argv)
    out = Path(args.out)
    store = read_json_or_none(out / "bench_pipeline.json") or {}
    for section in SECTIONS:
        if section not in only:
            continue
        t0, started = time.perf_counter(), section_stamp()
        if section == "pipeline":
            result = bench_pipeline(args.scale, keep=args.keep)
        elif section == "overhead":
            result = bench_overhead(repeats=args.noop_repeats, baseline=args.baseline, keep=args.keep,
                                    params=Path(args.params).resolve() if args.params else None)
        elif section == "skipping":
            result = bench_skipping(Path.cwd())
        elif section == "paper":
            result = bench_paper(args.repeats)
        else:
            result = bench_fusion(agents=args.agents, points=args.points, repeats=args.repeats)
        store[section] = {**started, **result, "bench_seconds": round(time.perf_counter() - t0, 1)}
        print(f"{section}: {store[section]['bench_seconds']} s", file=sys.stderr)
        write_report(store, out)   # after every section, so a later failure keeps the earlier ones
    print(render(store))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
