"""Stage processes for the tests that run typ's stages as a user does: one Prefect server and one
MLflow database per test session (:func:`stage_env`), projects with tiny params
(:func:`make_project`), and ``typ run <stage>`` in a child process (:func:`run_stages`). The crash,
determinism, real-data and bad-input CLI tests share them."""
from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from flows.server import LocalServer
from repo_paths import REPO

SMALL = {
    "profile": "tiny",
    "simulate": {"frames": 2, "azimuth_step_deg": 0.5, "agents_min": 2, "agents_max": 2, "workers": 1,
                 "scenarios": {"source": {"train": 0, "test": 0}, "target": {"train": 4, "val": 1, "test": 1},
                               "real_cav": {"train": 0, "test": 0}}},
    "voxelize": {"workers": 1},
    "vqvae": {"x": {"epochs": 3, "block_out_channels": [8, 16, 16, 16]},
              "y": {"epochs": 3, "block_out_channels": [8, 16, 16, 16]}, "checkpoint_every": 1},
}

_ENV = pytest.StashKey[dict]()


def stage_env(config: pytest.Config, tmp_path_factory) -> dict:
    """Environment for stage processes: one Prefect server and one MLflow database per session."""
    if _ENV not in config.stash:
        home = tmp_path_factory.mktemp("services")
        services = contextlib.ExitStack()
        server = services.enter_context(LocalServer.running(home / "prefect", ui=False, timeout=300,
                                                            env={**os.environ, "OMP_NUM_THREADS": "1"}))
        config.add_cleanup(services.close)
        config.stash[_ENV] = {
            **os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
            **server.client_env, "PREFECT_HOME": str(home / "prefect"),
            "PREFECT_LOGGING_LEVEL": "WARNING", "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1",
            "MLFLOW_TRACKING_URI": f"sqlite:///{home / 'mlruns.db'}", "DVC_NO_ANALYTICS": "1",
            # the input-hash cache is state like MLflow's store: outside the projects the tests compare
            "TYP_HASH_CACHE": str(home / "hashes.sqlite"),
            "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return config.stash[_ENV]


def make_project(root: Path, params: dict = SMALL) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    return root


#: runs ``typ run <stage>`` for each stage in turn in one process; stops at the first failure
DRIVER = """
import sys
from cli.main import main
root, stages = sys.argv[1], sys.argv[2:]
for stage in stages:
    code = main(["--root", root, "run", stage])
    if code:
        sys.exit(code)
"""


def start_stages(root: Path, env: dict, *stages: str, extra_env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", DRIVER, str(root), *stages], cwd=root,
                            env={**env, **(extra_env or {})}, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)


def run_stages(root: Path, env: dict, *stages: str, extra_env: dict | None = None) -> str:
    proc = start_stages(root, env, *stages, extra_env=extra_env)
    out, _ = proc.communicate(timeout=600)
    assert proc.returncode == 0, f"{stages} failed ({proc.returncode}):\n{out[-5000:]}"
    return out
