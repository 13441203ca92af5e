"""bench/pipeline.py's constants and pure parts: the e2e params it scales, the tables and verdicts of
each section, the markdown page and the plot (no dvc, no torch)."""
from __future__ import annotations

import copy
import datetime as dt
import json
import math
import os
import re
import statistics
import sys
from pathlib import Path

from bench.report import machine, machine_line
from typ.io import atomic_path, write_json, write_text


REPO = Path(__file__).resolve().parents[1]
SECTIONS = ("pipeline", "overhead", "skipping", "paper", "fusion")


def _e2e_params() -> dict:
    """The e2e test's small params (tests/e2e/test_pipeline_e2e.py ``SMALL``), read from the test itself
    so that the two cannot drift apart: a copy kept here lost the fusion robustness and ddpm
    settings the stages gained since, and its fusion stage then failed on 2-frame sequences."""
    import importlib.util

    helpers = str(REPO / "tests" / "helpers")   # the module's own imports (tests/conftest.py adds it under pytest)
    if helpers not in sys.path:
        sys.path.insert(0, helpers)
    spec = importlib.util.spec_from_file_location("_typ_e2e", REPO / "tests" / "e2e" / "test_pipeline_e2e.py")
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


def fusion_order() -> tuple[str, ...]:
    """The fusion methods in bench order (the registry's)."""
    from typ.registry import METHODS

    return tuple(METHODS)


def stamp(section: dict) -> str:
    load = f"; 1-minute load average {section['load']:.1f} at the start" if "load" in section else ""
    return f"Measured {section['when']} on {machine_line(section['machine'])}{load}."


def _pipeline_doc() -> str:
    """bench/pipeline.py's docstring (the page's method section), read without importing it."""
    import ast

    return ast.get_docstring(ast.parse(Path(__file__).with_name("pipeline.py").read_text()), clean=False)


def render(store: dict) -> str:
    """The whole report from the stored sections."""
    doc = _pipeline_doc().split("\n\n", 2)[2]
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
