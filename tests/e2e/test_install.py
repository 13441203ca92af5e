"""`pip install .` gives a typ that runs: pyproject.toml declares what typ imports, within
bounds that hold the versions requirements.lock pins (the set CI tests), and the layers import
one way (CLI -> flows -> tasks -> models, typ).

The clean-venv install is slow (a few minutes: every wheel from the local index into a new
venv): it runs with TYP_SLOW=1, e.g.
``TYP_SLOW=1 .venv/bin/python -m pytest -q tests/e2e/test_install.py``.
"""
from __future__ import annotations

import ast
import importlib.metadata as metadata
import os
import re
import shutil
import subprocess
import sys
import tomllib
import venv
from pathlib import Path

import pytest
import yaml
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from repo_paths import REPO

ROOT = REPO
PACKAGES = ("typ", "cli", "flows", "tasks", "models", "pipelines")
#: imported by typ, deliberately not a declared dependency (the reason)
OPTIONAL = {"waymo_open_dataset": "installed with --no-deps: its declared dependencies pull TensorFlow"}
SLOW = bool(os.environ.get("TYP_SLOW"))


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _lock() -> dict[str, str]:
    """requirements.lock's pins, and torch's from the Makefile (installed first, alone)."""
    pins = {"torch": re.search(r"^TORCH := torch==(\S+)$", (ROOT / "Makefile").read_text(), re.M).group(1)}
    for line in (ROOT / "requirements.lock").read_text().splitlines():
        line = line.split("#")[0].strip()
        if "==" in line:
            name, version = line.split("==", 1)
            pins[canonicalize_name(name.split("[")[0])] = version.strip()
    return pins


def _imports(package: str) -> set[str]:
    """Top-level names every module of ``package`` imports (absolute imports, anywhere in the file)."""
    found = set()
    for path in (ROOT / package).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                found |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module.split(".")[0])
    return found


def test_every_declared_dependency_is_pinned_in_the_lock_within_its_bounds():
    lock = _lock()
    declared = [Requirement(r) for r in _pyproject()["project"]["dependencies"]]
    declared += [Requirement(r) for rs in _pyproject()["project"]["optional-dependencies"].values() for r in rs]
    for req in declared:
        name = canonicalize_name(req.name)
        assert name in lock, f"{req.name} is declared but requirements.lock does not pin it"
        assert req.specifier.contains(lock[name], prereleases=True), f"{req} excludes the tested {lock[name]}"
        assert req.specifier, f"{req.name}: no bounds"
    torch = next(r for r in declared if r.name == "torch")
    assert not torch.specifier.contains("2.14.0") and torch.specifier.contains("2.13.0+cpu")


def test_every_third_party_import_is_declared():
    distributions = metadata.packages_distributions()
    declared = {canonicalize_name(Requirement(r).name) for r in _pyproject()["project"]["dependencies"]}
    stdlib = set(sys.stdlib_module_names)
    missing = {}
    for package in PACKAGES:
        for name in _imports(package) - stdlib - set(PACKAGES) - set(OPTIONAL):
            owners = {canonicalize_name(d) for d in distributions.get(name, [])}
            assert owners, f"{package} imports {name}, which no installed distribution provides"
            if not owners & declared:
                missing[name] = sorted(owners)
    assert not missing, f"imported but not in pyproject.toml's dependencies: {missing}"


def test_layers_import_one_way():
    """typ and models never import pipelines, flows, tasks or the CLI; pipelines never import
    tasks, flows or the CLI; tasks never import flows or the CLI; flows never import the CLI."""
    above = {"typ": {"pipelines", "flows", "tasks", "cli"}, "models": {"pipelines", "flows", "tasks", "cli"},
             "pipelines": {"flows", "tasks", "cli"}, "tasks": {"flows", "cli"}, "flows": {"cli"}}
    for package, forbidden in above.items():
        assert not _imports(package) & forbidden, f"{package} imports {_imports(package) & forbidden}"
    entry = _pyproject()["project"]["scripts"]["typ"]
    assert entry == "cli.main:main"


def _run(cmd, **kwargs) -> subprocess.CompletedProcess:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, **kwargs)
    assert proc.returncode == 0, f"{cmd} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
    return proc


@pytest.mark.slow
@pytest.mark.skipif(not SLOW, reason="slow (a clean venv and every wheel): runs with TYP_SLOW=1")
def test_pip_install_into_a_clean_venv_gives_a_working_typ(tmp_path):
    """torch first (as the Makefile does), then `pip install -c requirements.lock .` from a copy of
    the tracked files; the installed `typ` checks params and simulates, outside the checkout."""
    src = tmp_path / "src"
    files = _run(["git", "ls-files", "-co", "--exclude-standard"], cwd=ROOT).stdout.splitlines()
    for rel in files:
        if (ROOT / rel).is_file():
            (src / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / rel, src / rel)
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    py = env_dir / "bin" / "python"
    torch_version = metadata.version("torch").split("+")[0]
    _run([str(py), "-m", "pip", "install", "-q", f"torch=={torch_version}"])
    _run([str(py), "-m", "pip", "install", "-q", "-c", str(ROOT / "requirements.lock"), str(src)])
    freeze = _run([str(py), "-m", "pip", "freeze"]).stdout
    installed = {canonicalize_name(n): v for n, v in re.findall(r"^([A-Za-z0-9_.\-]+)==(\S+)$", freeze, re.M)}
    assert installed["torch"].split("+")[0] == torch_version
    lock = _lock()
    off_lock = {n: v for n, v in installed.items() if n != "typ" and lock.get(n, v) != v.split("+")[0]}
    assert not off_lock, f"installed versions that differ from requirements.lock: {off_lock}"

    project = tmp_path / "project"   # no checkout here: the installed package and its profiles only
    project.mkdir()
    params = {"profile": "tiny", "simulate": {"frames": 1, "azimuth_step_deg": 2.0, "agents_min": 2,
                                              "agents_max": 2, "workers": 1, "domains": {},
                                              "scenarios": {"source": {"train": 1}, "target": {"train": 0},
                                                            "real_cav": {"train": 0}}}}
    (project / "params.yaml").write_text(yaml.safe_dump(params))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PREFECT_API_URL", "VIRTUAL_ENV")}
    env.update(MLFLOW_TRACKING_URI=f"sqlite:///{project / 'mlruns.db'}", OMP_NUM_THREADS="1",
               PATH=f"{env_dir / 'bin'}:{env['PATH']}")
    typ = str(env_dir / "bin" / "typ")
    where = _run([str(py), "-c", "import cli, typ; print(cli.__file__, typ.__file__)"], cwd=project, env=env).stdout
    assert str(ROOT) not in where and str(env_dir) in where
    check = _run([typ, "check"], cwd=project, env=env)
    assert yaml.safe_load(check.stdout)["simulate"]["frames"] == 1
    _run([typ, "run", "simulate"], cwd=project, env=env)
    pcds = sorted((project / "data" / "sim" / "source" / "train").rglob("*.pcd"))
    assert len(pcds) == 2  # 2 agents x 1 frame
    assert (project / "metrics" / "simulate.json").is_file()
