"""Per-scene stages on Dask write the same bytes as on Prefect's thread pool.

simulate + voxelize on a tiny params file, once with ``typ run <stage>`` and once with
``typ run <stage> --runner dask`` (simulate on typ's LocalCluster of 2 worker processes,
voxelize on a running cluster of 2 thread workers given with ``--address``), each in its own
project; every output file must be byte-identical. Both runs share one subprocess (one Python
start, one temporary Prefect server), which also checks that Dask's workers use that server
instead of starting their own. Every per-scene task logs where it ran (``flows.common.per_scene``):
in the Dask project each must have run on a Dask worker (the given cluster's workers for
voxelize), never on the flow's own threads, so a silent fallback to threads fails.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import yaml

PARAMS = {
    "profile": "tiny",
    "simulate": {"frames": 2, "azimuth_step_deg": 1.5, "agents_min": 2, "agents_max": 2, "workers": 2, "domains": {},
                 "scenarios": {"source": {"train": 1, "test": 0}, "target": {"train": 2, "val": 0, "test": 0, "pretrain": 0},
                               "real_cav": {"train": 0, "test": 0}}},
    "voxelize": {"workers": 2},
}

SCRIPT = textwrap.dedent("""
    import sys

    from distributed import LocalCluster

    from cli.main import main

    if __name__ == "__main__":
        local, dask = sys.argv[1:3]
        for stage in ("simulate", "voxelize"):
            print(f"PROJECT local {stage}", flush=True)
            assert main(["-v", "--root", local, "run", stage]) == 0
        # simulate on typ's own LocalCluster, voxelize on an existing cluster given by address
        print("PROJECT dask simulate", flush=True)
        assert main(["-v", "--root", dask, "run", "simulate", "--runner", "dask"]) == 0
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
            print("WORKERS " + " ".join(sorted(w.address for w in cluster.workers.values())), flush=True)
            print("PROJECT dask voxelize", flush=True)
            assert main(["-v", "--root", dask, "run", "voxelize", "--runner", "dask", "--address",
                         cluster.scheduler_address]) == 0
""")


def _files(root: Path) -> dict[str, bytes]:
    """Every output file's bytes; not typ's own state (.typ/: locks naming their holder, records naming inodes)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file() and ".typ" not in p.relative_to(root).parts}


def _placements(stdout: str, stderr: str) -> dict[tuple[str, str], dict[str, str]]:
    """(project, stage) -> scene -> where it ran, from the ``PROJECT`` markers (stdout) and the
    per-scene INFO lines (stderr); the two streams are ordered by the markers' stage names."""
    out: dict = {}
    lines = re.findall(r"typ: (simulate|voxelize): (\S+) ran on (\S+)", stderr)
    order = re.findall(r"^PROJECT (\w+) (\w+)$", stdout, re.M)
    for project, stage in order:
        out[(project, stage)] = {}
    for stage, scene, where in lines:
        # a stage's lines of the local project come first, then the Dask project's
        project = "local" if scene not in out[("local", stage)] else "dask"
        out[(project, stage)][scene] = where
    return out


def test_dask_runner_writes_the_same_bytes_as_threads(tmp_path):
    projects = [tmp_path / "local", tmp_path / "dask"]
    for p in projects:
        p.mkdir()
        (p / "params.yaml").write_text(yaml.safe_dump(PARAMS))
    script = tmp_path / "run_both.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PREFECT_HOME": str(tmp_path / ".prefect"),
           "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlruns.db'}", "PREFECT_LOGGING_LEVEL": "INFO",
           "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "300", "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
           "DO_NOT_TRACK": "1"}
    env.pop("PREFECT_API_URL", None)
    proc = subprocess.run([sys.executable, str(script), *map(str, projects)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-6000:]
    log = proc.stdout + proc.stderr
    assert log.count("Starting temporary server") == 1, "Dask workers started Prefect servers of their own"
    # each Dask run's server is stopped after Prefect's services delivered its events: none is left
    # retrying a closed port (7 s an event at exit, then lost), nor sends a later run's events there
    assert "Unable to connect" not in log and "failed to process item" not in log, log[-3000:]
    placed = _placements(proc.stdout, proc.stderr)
    workers = set(re.search(r"^WORKERS (.*)$", proc.stdout, re.M).group(1).split())
    assert len(workers) == 2
    for stage, scenes in (("simulate", 3), ("voxelize", 3)):   # voxelize: one task per scenario
        assert list(placed[("local", stage)].values()).count("thread") == scenes, placed[("local", stage)]
        ran_on = placed[("dask", stage)]
        assert ran_on.keys() == placed[("local", stage)].keys() and len(ran_on) == scenes
        assert "thread" not in ran_on.values(), f"{stage} fell back to threads: {ran_on}"
    assert all(w.startswith("tcp://") for w in placed[("dask", "simulate")].values())   # worker processes
    assert set(placed[("dask", "voxelize")].values()) <= workers                       # the given cluster

    local, dask = (_files(p / "data") for p in projects)
    assert sum(k.startswith("sim/") and k.endswith(".pcd") for k in local) == 3 * 2 * 2  # scenarios x agents x frames
    assert any(k.startswith("voxels/") for k in local)
    assert local.keys() == dask.keys()
    differ = [k for k in local if local[k] != dask[k]]
    assert not differ, f"differ between thread and Dask runs: {differ[:5]}"
    for stage in ("simulate", "voxelize"):
        assert (projects[1] / "metrics" / f"{stage}.json").is_file()
