"""Per-scene stages on Dask write the same bytes as on Prefect's thread pool.

simulate + voxelize on a tiny params file, once with ``typ run <stage>`` and once with
``typ run <stage> --runner dask`` (simulate on typ's LocalCluster of 2 worker processes,
voxelize on a running cluster of 2 thread workers given with ``--address``), each in its own
project; every output file must be byte-identical. Both runs share one subprocess (one Python
start, one temporary Prefect server), which also checks that Dask's workers use that server
instead of starting their own.
"""
from __future__ import annotations

import os
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
            assert main(["--root", local, "run", stage]) == 0
        # simulate on typ's own LocalCluster, voxelize on an existing cluster given by address
        assert main(["--root", dask, "run", "simulate", "--runner", "dask"]) == 0
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
            assert main(["--root", dask, "run", "voxelize", "--runner", "dask", "--address",
                         cluster.scheduler_address]) == 0
""")


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


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
    assert "DaskTaskRunner" in log or "distributed" in log  # the second run really went through Dask
    assert log.count("Starting temporary server") == 1, "Dask workers started Prefect servers of their own"

    local, dask = (_files(p / "data") for p in projects)
    assert sum(k.startswith("sim/") and k.endswith(".pcd") for k in local) == 3 * 2 * 2  # scenarios x agents x frames
    assert any(k.startswith("voxels/") for k in local)
    assert local.keys() == dask.keys()
    differ = [k for k in local if local[k] != dask[k]]
    assert not differ, f"differ between thread and Dask runs: {differ[:5]}"
    for stage in ("simulate", "voxelize"):
        assert (projects[1] / "metrics" / f"{stage}.json").is_file()
