"""One prepared run of typ on a GPU: the CUDA tests, throughput beside the CPU's, and the generator
trained at a size the CPU profile cannot reach, scored as the evaluate stage scores generation.

    python3 bench/gpu.py --out DIR [--minutes 7.5] [--device cuda] [--bundle .gpu]
                         [--phases tests,timings,train] [--quick] [--set KEY=VALUE ...]

Everything runs through typ's task-level functions (no Prefect, MLflow, DVC or open3d: the GPU
machine has none of them) on the data bench/gpu_data.py made on the CPU (``--bundle``). The run
keeps a deadline (``--minutes``): every phase and every training step checks the clock, and
``results.json`` is rewritten after every step, so a run stopped at its time limit still returns
what it measured. A phase that fails has its traceback kept in ``results.json``; the next runs.

Phases:
- ``tests``: tests/e2e/test_cuda.py under pytest in a subprocess (every test, ``-x`` off) ->
  ``tests.xml`` (JUnit) and its summary;
- ``timings``: training steps/s and samples/s of each network, through its stage's own training
  function (the generator's at bench/gpu.yaml's size, the detectors' and the pixel DDPM's at the
  tiny profile's; batches in :data:`TIMING_BATCH`), in fp32 and bf16; sampling views/s of the
  whole generator (encoders, adapter, DPM-Solver++ 10 or DDIM 200 steps, decoder);
  voxelization frames/s; and CUDA's run-to-run spread with the reproducibility flags on and
  off. ``--device cpu --quick`` measures the same on the CPU with fewer steps and small batches
  (DDIM 200 extrapolated from 10 and 20 steps): the CPU side of each ratio, read from ``--cpu``
  (reports/gpu/cpu/results.json);
- ``train``: the generator at bench/gpu.yaml's size for the time left (bench/gpu_train.py).

Writes to ``--out``: results.json, bench_gpu.md (the tables; reports/gpu/ keeps it for
``make bench``), README.md (how the run was made: command, commit, device, wall time, what was
cut), bench_gpu.png (the curves), tests.xml, log.txt and, when it fits in 15 MiB, generator.safetensors.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

import gpu_bundle  # noqa: E402
import gpu_train  # noqa: E402
from gpu_timers import (determinism, device_voxelize, difference_rate, generator_at_size,  # noqa: E402,F401
                        network_timers, per_step_rate)
from typ.io import write_json  # noqa: E402


ROOT = Path(__file__).resolve().parents[1]
PHASES = ("tests", "timings", "train")
#: the batch each network is timed at: on the GPU its training batch, on the CPU a small one (a
#: CPU's samples/s hardly depends on the batch; at the GPU's batches its side would take an hour).
#: The ratios compare samples/s.
TIMING_BATCH = {"cuda": {"vqvae": 16, "stage1": 32, "stage2": 32, "adapt": 8, "fusion": 1, "ssc": 1, "ddpm": 8},
                "cpu": {"vqvae": 1, "stage1": 2, "stage2": 2, "adapt": 1, "fusion": 1, "ssc": 1, "ddpm": 2}}
SAMPLING_BATCH = {"cuda": 16, "cpu": 1}
#: seconds kept for the final scores and the pages, before the first probe says what they cost
#: (at most a sixth of the run)
FINAL_RESERVE = {"cuda": 45.0, "cpu": 60.0}
#: the share of --minutes, from the start, by which each phase ends (what is left is then
#: recorded as skipped); training has the rest
PHASE_END = {"tests": 0.2, "timings": 0.42}
CPU_RESULTS = ROOT / "reports" / "gpu" / "cpu" / "results.json"


class Run:
    """The run's clock, its results (saved after every change) and its log."""

    def __init__(self, args):
        self.args, self.out = args, Path(args.out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.t0 = time.monotonic()
        self.end = self.t0 + 60.0 * args.minutes
        self.log_file = open(self.out / "log.txt", "a", buffering=1)
        self.results = {"run": header(args), "phases": {}}
        self.save()

    def left(self) -> float:
        return self.end - time.monotonic()

    def phase_left(self, name: str) -> float:
        """Seconds until ``name`` must end (:data:`PHASE_END`)."""
        return self.t0 + PHASE_END[name] * (self.end - self.t0) - time.monotonic()

    def log(self, line: str) -> None:
        stamp = f"[{time.monotonic() - self.t0:6.1f} s] {line}"
        print(stamp, flush=True)
        self.log_file.write(stamp + "\n")

    def save(self) -> None:
        self.results["run"]["wall_s"] = round(time.monotonic() - self.t0, 1)
        write_json(self.out / "results.json", self.results)

    @contextlib.contextmanager
    def phase(self, name: str):
        record = self.results["phases"].setdefault(name, {"status": "running"})
        t0 = time.monotonic()
        self.log(f"phase {name} ({self.left():.0f} s left)")
        try:
            yield record
            record["status"] = "ok" if record.get("status") == "running" else record["status"]
        except Exception as exc:  # one phase's failure must not lose the others
            record.update(status="failed", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc())
            self.log(f"phase {name} failed: {type(exc).__name__}: {exc}")
        finally:
            record["seconds"] = round(time.monotonic() - t0, 1)
            self.save()
            write_pages(self)


def header(args) -> dict:
    import torch

    cuda = args.device == "cuda" and torch.cuda.is_available()
    commit, dirty = args.commit or git("rev-parse", "HEAD"), None
    if not args.commit:
        status = git("status", "--porcelain", "--untracked-files=no")
        dirty = None if status is None else bool(status)
    return {"command": "python3 " + " ".join(shlex.quote(a) for a in sys.argv), "commit": commit,
            "dirty": dirty, "device": torch.cuda.get_device_name() if cuda else f"CPU: {cpu_model()}",
            "device_type": "cuda" if cuda else "cpu", "cores": os.cpu_count(), "torch": torch.__version__,
            "cuda": torch.version.cuda, "python": platform.python_version(), "numpy": np.__version__,
            "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "minutes": args.minutes, "quick": args.quick,
            "torch_threads": torch.get_num_threads(), "load_average_1min": round(os.getloadavg()[0], 2)}


def git(*args: str) -> str | None:
    """``git <args>`` in the checkout, stripped; None where there is no git or no repository
    (the GPU machine gets a copy of the working tree: pass --commit there)."""
    try:
        proc = subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout.strip() if proc.returncode == 0 else None


def cpu_model() -> str:
    from report import cpu_model as model

    return model()


# ------------------------------------------------------------------ phase: tests


def run_tests(run: Run, record: dict) -> None:
    xml = run.out / "tests.xml"
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rfEs", "tests/e2e/test_cuda.py",
           f"--junitxml={xml}"]
    timeout = max(10.0, run.phase_left("tests"))
    record["command"] = " ".join(cmd[1:])
    # no plugin of the machine's (pytest-cov, -timeout, -benchmark ...) between the tests and this run
    env = {**os.environ, "PYTEST_DISABLE_PLUGIN_AUTOLOAD": "1"}
    try:
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
        output, record["returncode"] = proc.stdout + proc.stderr, proc.returncode
    except subprocess.TimeoutExpired as exc:
        output, record["returncode"] = f"{exc.stdout or ''}{exc.stderr or ''}\nstopped after {timeout:.0f} s", None
    run.log_file.write(output if isinstance(output, str) else output.decode(errors="replace"))
    record["tail"] = output[-3000:] if isinstance(output, str) else ""
    if xml.is_file():
        record |= junit_summary(xml)
        record["status"] = "ok" if record["failures"] == record["errors"] == 0 else "failed"
    else:
        record["status"] = "failed"


def junit_summary(path: Path) -> dict:
    import xml.etree.ElementTree as ET

    cases = []
    for case in ET.parse(path).getroot().iter("testcase"):
        outcome = next((c.tag for c in case if c.tag in ("failure", "error", "skipped")), "passed")
        detail = next((c.get("message", "") for c in case if c.tag in ("failure", "error", "skipped")), "")
        cases.append({"name": case.get("name"), "outcome": outcome, "seconds": float(case.get("time", 0)),
                      "message": detail[:500]})
    count = {k: sum(c["outcome"] == k for c in cases) for k in ("passed", "failure", "error", "skipped")}
    return {"tests": len(cases), "passed": count["passed"], "failures": count["failure"], "errors": count["error"],
            "skipped": count["skipped"], "cases": cases}


# ------------------------------------------------------------------ phase: timings


def run_timings(run: Run, record: dict, cfg, bundle) -> None:
    from typ import distributed
    from typ.config import config_from_dict

    device, quick = run.args.device, run.args.quick
    warmup, timed = (1, 2) if quick else (3, 12)
    tiny = config_from_dict({"profile": "tiny"})
    scratch = Path(tempfile.mkdtemp(prefix="typ-gpu-timings-"))
    record["sizes"] = {"generator": "bench/gpu.yaml", "fusion, ssc, ddpm": "the tiny profile"}
    batch = TIMING_BATCH[device]
    timers = network_timers(cfg, tiny, bundle, scratch, batch)
    networks = record.setdefault("networks", {})
    for name, (kind, rate) in timers.items():
        entry = networks.setdefault(name, {"batch": batch[kind]})
        for precision in ("fp32", "bf16"):
            distributed.setup(device, precision)
            if run.phase_left("timings") < 0:
                entry[precision] = {"skipped": "the phase's time was up"}
                continue
            try:
                r = rate(warmup, timed)
                entry[precision] = {"steps_per_s": round(r, 4), "samples_per_s": round(r * batch[kind], 4)}
                run.log(f"  {name} {precision}: {r:.3f} steps/s")
            except Exception as exc:
                entry[precision] = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
                run.log(f"  {name} {precision} failed: {type(exc).__name__}: {exc}")
            run.save()
    distributed.setup(device, "fp32")
    steps = {"sampling": lambda: sampling_rates(run, cfg, bundle, device, quick),
             "voxelize": lambda: voxelize_rates(run, device, quick)}
    if device == "cuda":
        steps["determinism"] = lambda: determinism(cfg, bundle, scratch)
    for name, measure in steps.items():
        if run.phase_left("timings") < 0:
            record[name] = {"skipped": "the phase's time was up"}
            continue
        with run_step(run, record, name):
            record[name] = measure()
    distributed.setup(device, "fp32")


@contextlib.contextmanager
def run_step(run: Run, record: dict, name: str):
    """One measurement of a phase: its failure is kept, the phase goes on."""
    try:
        yield
    except Exception as exc:
        record[name] = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()}
        run.log(f"  {name} failed: {type(exc).__name__}: {exc}")
    run.save()


def sampling_rates(run: Run, cfg, bundle, device: str, quick: bool) -> dict:
    """Views/s of the whole generator (x_e' and y_r in, decoded logits out) per sampler, fp32 and bf16."""
    from typ import distributed

    pipe = generator_at_size(cfg, bundle)
    n = SAMPLING_BATCH[device]
    x_e, y_r = bundle.pairs.x_e[:n], bundle.pairs.y_r[:n]
    out = {"batch": n}
    for precision in ("fp32", "bf16"):
        distributed.setup(device, precision)
        pipe.logits(x_e, y_r, seed=0, sampler="ddim", num_inference_steps=1)   # warm-up

        def seconds(sampler, steps):
            t0 = time.perf_counter()
            pipe.logits(x_e, y_r, seed=0, sampler=sampler, num_inference_steps=steps)
            return time.perf_counter() - t0

        row = {"dpmsolver++ 10": n / seconds("dpmsolver++", 10)}
        if quick:   # DDIM's cost is fixed + per step: its 200 steps from 10 and 20
            t10, t20 = seconds("ddim", 10), seconds("ddim", 20)
            row["ddim 200"] = n / (t10 + 190 * (t20 - t10) / 10)
            row["ddim 200 extrapolated"] = True
        else:
            row["ddim 200"] = n / seconds("ddim", 200)
        out[precision] = {k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()}
        run.log(f"  sampling {precision}: " + ", ".join(f"{k} {v:.3f} views/s" for k, v in row.items()
                                                         if isinstance(v, float)))
    distributed.setup(device, "fp32")
    return out


def voxelize_rates(run: Run, device: str, quick: bool) -> dict:
    """Frames/s of typ.voxel.voxelize (numba, the CPU) and of the same bins in torch on ``device``."""
    import torch

    from typ.voxel import PAPER_GRID, voxelize
    from voxelize import synthetic_cloud

    cfg_grid = gpu_bundle.config().voxelize.grid
    grids = {"gpu.yaml 256×256×20": gpu_bundle.Grid(cfg_grid.x_range, cfg_grid.y_range, cfg_grid.z_range,
                                                     cfg_grid.shape),
             "paper 512×512×20": PAPER_GRID}
    clouds = [synthetic_cloud(100_000, seed=s) for s in range(2 if quick else 8)]
    out = {"points": 100_000, "frames": len(clouds)}
    for name, grid in grids.items():
        voxelize(clouds[0], grid)                       # compile / load numba's cache
        device_voxelize(clouds[0], grid, device)
        t0 = time.perf_counter()
        ref = [voxelize(c, grid) for c in clouds]
        typ_fps = len(clouds) / (time.perf_counter() - t0)
        sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)
        sync()
        t0 = time.perf_counter()
        got = [device_voxelize(c, grid, device) for c in clouds]
        sync()
        torch_fps = len(clouds) / (time.perf_counter() - t0)
        differ = int(sum(int((g.cpu().numpy() != r).sum()) for g, r in zip(got, ref)))
        out[name] = {"typ (CPU, numba)": round(typ_fps, 2), f"torch ({device})": round(torch_fps, 2),
                     "voxels differing": differ}
        run.log(f"  voxelize {name}: typ {typ_fps:.1f} fps, torch on {device} {torch_fps:.1f} fps, {differ} differ")
    return out


def run_training(run: Run, record: dict, cfg, bundle, pool) -> None:
    import torch

    from pipelines.typ.pipeline_typ import PointStats
    from typ import distributed

    distributed.setup(run.args.device, cfg.runtime.precision if run.args.device == "cuda" else "fp32")
    record["precision"] = distributed.current().precision
    record["config"] = gpu_bundle.as_dict(cfg)
    record["baselines"], record["tiny"] = bundle.meta["baselines"], bundle.meta.get("tiny")
    record["data"] = {"target_train_views": len(bundle.train), "target_val_views": len(bundle.val),
                      "source_train_views": len(bundle.source), "source_tuples": len(bundle.tuples),
                      "pseudo_references": len(bundle.references.x_e), "pairs": len(bundle.pairs),
                      "scenes": len(set(bundle.pairs.scenes))}
    scorer = gpu_train.Scorer(bundle.pairs, PointStats.from_dict(bundle.meta["stats"]), pool)
    work = Path(tempfile.mkdtemp(prefix="typ-gpu-train-"))
    generator = gpu_train.run_phase(cfg, bundle, scorer, work=work, deadline=run.left,
                                    reserve=min(FINAL_RESERVE[run.args.device], 10.0 * run.args.minutes),
                                    log=run.log, record=record, save=run.save)
    if generator is not None:
        save_generator(run, generator, record)
    if run.args.device == "cuda":
        record["max_memory_gib"] = round(torch.cuda.max_memory_allocated() / 2 ** 30, 2)


def save_generator(run: Run, pipe, record: dict, limit: int = 15 * 2 ** 20) -> None:
    """The trained generator's weights in bf16, one safetensors file, when it fits under ``limit``."""
    from safetensors.torch import save_file

    tensors = {f"{name}.{k}": v.detach().to("cpu").bfloat16().contiguous()
               for name in ("x_vqvae", "unet", "adapter") if getattr(pipe, name) is not None
               for k, v in getattr(pipe, name).state_dict().items() if v.is_floating_point()}
    size = sum(t.numel() * 2 for t in tensors.values())
    record["generator_bf16_bytes"] = size
    if size <= limit:
        configs = {name: getattr(pipe, name).config for name in ("x_vqvae", "box_encoder", "unet", "adapter")
                   if getattr(pipe, name) is not None}
        save_file(tensors, str(run.out / "generator.safetensors"),
                  metadata={"configs": json.dumps(configs), "thresholds": json.dumps(pipe.thresholds)})
        record["generator_file"] = "generator.safetensors"


# ------------------------------------------------------------------ pages


def write_pages(run: Run) -> None:
    """bench_gpu.md, README.md and bench_gpu.png from the results so far (partial results included)."""
    import gpu_pages

    try:
        cpu = (json.loads(Path(run.args.cpu).read_text()) if run.args.cpu and Path(run.args.cpu).is_file()
               and run.results["run"]["device_type"] == "cuda" else None)   # a CPU run is the CPU side itself
        gpu_pages.write(run.out, run.results, cpu)
    except Exception as exc:   # the pages are a view of results.json, which is already saved
        run.log(f"pages not written: {type(exc).__name__}: {exc}")
        run.results.setdefault("page_errors", []).append(traceback.format_exc())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="folder for the results (the device's $OUT)")
    ap.add_argument("--minutes", type=float, default=7.5, help="the deadline, from the start")
    ap.add_argument("--device", default="cuda", choices=["cuda", "cpu"])
    ap.add_argument("--bundle", default=str(ROOT / ".gpu"), help="bench/gpu_data.py's output")
    ap.add_argument("--phases", default=",".join(PHASES), help=f"comma-separated, of {','.join(PHASES)}")
    ap.add_argument("--quick", action="store_true", help="fewer timed steps (the CPU side of the ratios)")
    ap.add_argument("--cpu", default=str(CPU_RESULTS), help="a --device cpu run's results.json, for the ratios")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override bench/gpu.yaml over the bundle's own overrides (e.g. vqvae.batch_size=4)")
    ap.add_argument("--commit", default=None, help="the commit the working tree is (where it has no .git)")
    args = ap.parse_args(argv)
    phases = [p for p in args.phases.split(",") if p]
    unknown = sorted(set(phases) - set(PHASES))
    if unknown:
        ap.error(f"unknown phases {unknown}: choose from {list(PHASES)}")
    # the scoring workers fork before anything touches CUDA
    pool = gpu_train.scoring_pool(max(1, min(12, (os.cpu_count() or 2) - 2))) if "train" in phases else None
    run = Run(args)
    if args.device == "cuda":
        import torch

        if not torch.cuda.is_available():
            run.log("no CUDA device: nothing measured")
            return 2
    bundle = cfg = None
    try:
        bundle = gpu_bundle.read(Path(args.bundle))
        cfg = gpu_bundle.config_for(bundle, gpu_bundle.overrides_of(args.set))
    except Exception as exc:
        run.results["bundle_error"] = f"{type(exc).__name__}: {exc}"
        run.log(f"no bundle: {exc} (tests only)")
    for name in phases:
        if name != "tests" and bundle is None:
            run.results["phases"][name] = {"status": "skipped", "reason": "no bundle"}
            continue
        with run.phase(name) as record:
            if name == "tests":
                run_tests(run, record)
            elif name == "timings":
                run_timings(run, record, cfg, bundle)
            else:
                run_training(run, record, cfg, bundle, pool)
    run.log(f"done in {time.monotonic() - run.t0:.0f} s")
    run.save()
    write_pages(run)
    if pool is not None:
        pool.terminate()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
