"""Crash safety and determinism: ``kill -9`` a stage mid-way, rerun it, and get what an
uninterrupted run gets; run the stages again in another process, and get the same bytes.

A throwaway project (tiny params, 5 target scenarios) runs the stages through the CLI
(``cli.main.main``) in subprocesses. Each stage is killed with SIGKILL (its whole process group)
as soon as its first output is complete, then rerun:

- simulate and voxelize: after the kill every file under a final name is byte-identical to the
  uninterrupted run's (nothing half-written), and after the rerun the output trees are equal
  byte for byte, with no temporary left;
- vqvae (training): after the kill every visible checkpoint loads; the rerun resumes from the
  newest one and the final models equal the uninterrupted run's (tolerance below).

Determinism: one more uninterrupted run of the same stages, with another ``PYTHONHASHSEED`` (so
iteration over sets of strings differs). Its output trees must match the first run's byte for
byte and its metrics JSON once the timing fields are dropped. Training is compared through the
saved weights: torch.save archives carry a per-save id, so their bytes differ by design. Both
kinds of test compare with the same uninterrupted run, so they live in one file (one pytest
worker computes it once).

The stage processes share one Prefect server and one MLflow database, started once per test
session (the CLI cases of tests/fuzz/test_bad_inputs.py and tests/e2e/test_real_data.py use the same
helpers), so each process pays only its imports. The training stage adds about a minute (two
more processes); it runs in `make test` (a resumed run must equal an uninterrupted one).
"""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from flows.server import LocalServer
from typ.io import hidden_below
from repo_paths import REPO
from stage_processes import SMALL, make_project, run_stages, stage_env, start_stages  # noqa: F401

TMP_PREFIX = ".tmp-"
#: what the uninterrupted run and the crashed run go through
STAGES = ("simulate", "voxelize", "vqvae")

#: final models of a resumed run against an uninterrupted one (max |Δ| over every weight):
#: batches are a function of (seed, step) and the optimizer state is in the checkpoint, so on
#: one CPU thread the two agree exactly; the tolerance only leaves room for other BLAS builds
MODEL_ATOL = 1e-6


# --- the helpers both crash and determinism tests use ----------------------------------------

_UNINTERRUPTED = pytest.StashKey[Path]()


def uninterrupted_run(config: pytest.Config, tmp_path_factory) -> Path:
    """The project after one uninterrupted run of :data:`STAGES` (PYTHONHASHSEED=1), once per session."""
    if _UNINTERRUPTED not in config.stash:
        root = make_project(tmp_path_factory.mktemp("uninterrupted"))
        run_stages(root, stage_env(config, tmp_path_factory), *STAGES, extra_env={"PYTHONHASHSEED": "1"})
        config.stash[_UNINTERRUPTED] = root
    return config.stash[_UNINTERRUPTED]


@pytest.fixture(scope="module")
def services(request, tmp_path_factory):
    return stage_env(request.config, tmp_path_factory)


@pytest.fixture(scope="module")
def reference(request, services, tmp_path_factory):
    return uninterrupted_run(request.config, tmp_path_factory)


def kill_when(proc: subprocess.Popen, done, *, timeout: float = 600) -> None:
    """SIGKILL the process group as soon as ``done()`` is true; fail if the process ends first."""
    deadline = time.monotonic() + timeout
    while not done():
        if proc.poll() is not None:
            out = proc.stdout.read()
            pytest.fail(f"the stage ended ({proc.returncode}) before it could be killed mid-way:\n{out[-3000:]}")
        if time.monotonic() > deadline:
            break
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stdout.close()


def tree(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes)."""
    # not typ's records of what it wrote (.typ/): they hold inodes and times, which no two runs share
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and ".typ" not in p.relative_to(folder).parts}


def final_names(folder: Path) -> dict[str, bytes]:
    """Files under ``folder`` whose path has no hidden (temporary) part."""
    return {rel: data for rel, data in tree(folder).items()
            if not any(part.startswith(".") for part in Path(rel).parts)}


# --- the tests --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def crashed(services, reference, tmp_path_factory):
    """The same stages, each killed once mid-way and then rerun; the state seen right after each kill."""
    root = make_project(tmp_path_factory.mktemp("crashed"))
    seen = {}
    sim, vox = root / "data" / "sim", root / "data" / "voxels"
    # a scenario in place, not a temporary nor typ's records (<domain>/.typ/written, which a kill between
    # a record and its rename leaves with no scenario: the kill came too early and the test saw nothing)
    scenarios = lambda: [p for p in sim.glob("*/*/*") if p.is_dir() and not hidden_below(p, sim)]  # noqa: E731
    scenes = lambda: [p for p in vox.glob("*/*/*.parquet") if not p.name.startswith(".")]  # noqa: E731
    checkpoints = lambda: list((root / "artifacts" / "vqvae" / "x" / "checkpoints").glob("*/step_*.pt"))  # noqa: E731

    kill_when(start_stages(root, services, "simulate"), lambda: scenarios())
    seen["simulate"] = final_names(sim)
    # the rerun of simulate completes; voxelize is killed after its first scene
    kill_when(start_stages(root, services, "simulate", "voxelize"), lambda: scenes())
    seen["voxelize"] = final_names(vox)
    kill_when(start_stages(root, services, "voxelize", "vqvae"), lambda: checkpoints())
    seen["vqvae"] = {str(p.relative_to(root)): _loads(p) for p in sorted((root / "artifacts").rglob("*.pt"))
                     if not any(part.startswith(".") for part in p.relative_to(root).parts)}
    run_stages(root, services, "vqvae")
    return root, seen


def _loads(path: Path) -> str:
    """'ok' if torch can load the file, else the error."""
    import torch

    try:
        torch.load(path, map_location="cpu", weights_only=False)
        return "ok"
    except Exception as exc:  # noqa: BLE001 - a half-written file fails in many ways
        return f"{type(exc).__name__}: {exc}"


@pytest.mark.parametrize("stage, folder", [("simulate", "data/sim"), ("voxelize", "data/voxels")])
def test_killed_stage_shows_only_whole_files(reference, crashed, stage, folder):
    root, seen = crashed
    expected = final_names(reference / folder)
    partial = seen[stage]
    assert partial, f"{stage}: nothing finished before the kill"
    assert len(partial) < len(expected), f"{stage} was not killed mid-way"
    for rel, data in partial.items():
        assert rel in expected and data == expected[rel], f"{stage}: {rel} differs from the uninterrupted run"


@pytest.mark.parametrize("folder", ["data/sim", "data/voxels"])
def test_rerun_after_kill_equals_uninterrupted_byte_for_byte(reference, crashed, folder):
    root, _ = crashed
    got, expected = tree(root / folder), tree(reference / folder)
    assert not [rel for rel in got if TMP_PREFIX in rel], "temporaries left after the rerun"
    assert sorted(got) == sorted(expected)
    assert [rel for rel in got if got[rel] != expected[rel]] == []


def test_killed_training_resumes_to_the_uninterrupted_model(reference, crashed):
    from typ.artifacts import read_weights
    from tasks.training import checkpoints

    root, seen = crashed
    after_kill = seen["vqvae"]
    assert any("/checkpoints/" in rel for rel in after_kill)
    assert "artifacts/vqvae/x/model.safetensors" not in after_kill, "x finished training before the kill"
    assert {rel: state for rel, state in after_kill.items() if state != "ok"} == {}  # every visible file is whole
    run_dirs = [p for p in (root / "artifacts" / "vqvae" / "x" / "checkpoints").iterdir() if p.name != ".typ"]
    assert len(run_dirs) == 1 and checkpoints(run_dirs[0])   # the rerun resumed the killed run's folder
    for kind in ("x", "y"):   # y is pooled (no weights) in the tiny profile; x is the trained network
        got = read_weights(root / "artifacts" / "vqvae" / kind, "vqvae")
        want = read_weights(reference / "artifacts" / "vqvae" / kind, "vqvae")
        assert got.keys() == want.keys() and (got or kind == "y")
        worst = max(((got[k].double() - want[k].double()).abs().max().item() for k in got if got[k].numel()),
                    default=0.0)
        assert worst <= MODEL_ATOL, (kind, worst)
    assert not [p for p in (root / "artifacts").rglob(f"{TMP_PREFIX}*")], "temporaries left after the rerun"


# --- determinism: a second uninterrupted run -------------------------------------------------

TIMING = re.compile(r"seconds|per_second")


def without_timing(metrics):
    if isinstance(metrics, dict):
        return {k: without_timing(v) for k, v in metrics.items() if not TIMING.search(k)}
    return metrics


@pytest.fixture(scope="module")
def two_runs(services, reference, tmp_path_factory):
    again = make_project(tmp_path_factory.mktemp("again"))
    run_stages(again, services, *STAGES, extra_env={"PYTHONHASHSEED": "2"})
    return reference, again


@pytest.mark.parametrize("folder", ["data/sim", "data/voxels"])
def test_outputs_are_byte_identical(two_runs, folder):
    a, b = (tree(root / folder) for root in two_runs)
    assert a, f"{folder} is empty"
    assert sorted(a) == sorted(b)
    assert [rel for rel in a if a[rel] != b[rel]] == []


@pytest.mark.parametrize("stage", ["simulate", "voxelize", "vqvae"])
def test_metrics_are_identical_but_for_timings(two_runs, stage):
    a, b = (json.loads((root / "metrics" / f"{stage}.json").read_text()) for root in two_runs)
    assert without_timing(a) == without_timing(b)
    assert without_timing(a) != {}


def test_trained_weights_are_identical(two_runs):
    import torch

    from typ.artifacts import read_config, read_weights

    for kind in ("x", "y"):
        a, b = (root / "artifacts" / "vqvae" / kind for root in two_runs)
        assert read_config(a, "vqvae") == read_config(b, "vqvae")
        wa, wb = read_weights(a, "vqvae"), read_weights(b, "vqvae")
        assert wa.keys() == wb.keys() and (wa or kind == "y")   # y is pooled (no weights) in the tiny profile
        assert all(torch.equal(wa[k], wb[k]) for k in wa), kind
