"""Pipeline cost: per-stage time and memory, fixed cost per stage, incremental runs, skipping,
paper scale, fusion inference. Its parts: bench/pipeline_report.py (constants, tables, the page
and plot), bench/process_tree.py (the measurement), bench/model_cost.py (the paper and fusion
sections); the pipeline, overhead and skipping sections and the CLI are here.

    python bench/pipeline.py [--only pipeline,overhead,skipping,paper,fusion] [--scale N]
        [--out reports] [--repeats R] [--noop-repeats R] [--baseline REV] [--keep]

Run from the repository root. Each section is one function; a run measures the sections named
by --only (default: all), stores their raw numbers in <out>/bench_pipeline.json beside those
of earlier runs, and rewrites <out>/bench_pipeline.md and .png from every section stored, each
stamped with when and on which machine it was measured.

- pipeline: a throwaway copy of the project in /tmp (git-tracked and untracked files, .venv
  linked, `git init`; as tests/e2e/test_pipeline_e2e.py does; the stages import the copy's code,
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
  models/fusion/ + models/pointpillars.py, untrained weights) at the tiny and the paper
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
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Iterator

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

# the bench's parts by job; what tests and callers read through this module is re-exported
from bench.model_cost import (bench_fusion, bench_paper, call_seconds, fusion_frame,  # noqa: E402,F401
                              synthetic_cloud, time_fusion)
from bench.pipeline_report import (ADDED, FIXED_TARGET, GENERATION_PARTS, NOOP_STAGES,  # noqa: E402,F401
                                   NOOP_TARGET_S, N_GEN, N_TRAIN, POLL_S, PROFILE_ORDER, REPO, SECTIONS, SMALL,
                                   STAGE_CMD, STARTUP_TARGET_S, WARMUP_S, _e2e_params, duration, extrapolate, fmt,
                                   fusion_order, fusion_table, incremental_verdicts, median, noop_table, ordered,
                                   overhead_stage_rows, overhead_table, overhead_totals, overhead_verdicts,
                                   paper_table, pipeline_stages, plot, render, section_stamp, skip_rows, skip_table,
                                   small_params, stage_table, stamp, startup_table, with_added_scenario, work_run,
                                   write_report)
from bench.process_tree import StageMonitor, _hwm_mb, measured  # noqa: E402,F401
from typ.io import read_json_or_none  # noqa: E402


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
