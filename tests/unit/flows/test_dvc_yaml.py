"""dvc.yaml is generated from the stages' declarations (tasks/<stage>.py, collected by flows/stages.py):
it cannot drift from them."""
from __future__ import annotations

import subprocess
import sys

import yaml

from flows import dvcyaml, stages
from typ.config import Config

ROOT = dvcyaml.ROOT


def test_the_committed_dvc_yaml_is_what_the_registry_gives():
    assert (ROOT / "dvc.yaml").read_text() == dvcyaml.render(), "dvc.yaml drifted from the stage declarations: run `typ dvc-yaml`"


def test_each_stage_is_declared_in_its_own_task_module_which_is_its_code_dep():
    """A stage's declaration sits beside its code (``tasks/<name>.py``'s DECLARATION), so editing
    it re-runs that stage; flows/stages.py, which collects the declarations, is no stage's dep."""
    import importlib

    built = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    for s in stages.stages():
        assert importlib.import_module(f"tasks.{s.name}").DECLARATION is s
        assert f"tasks/{s.name}.py" in built[s.name]["deps"], s.name
        assert "flows/stages.py" not in built[s.name]["deps"] and "flows/dvcyaml.py" not in built[s.name]["deps"]


def test_every_config_stage_is_registered_in_order_with_its_flow_and_block():
    registered = stages.stages()
    assert tuple(s.name for s in registered) == Config.STAGES
    for s in registered:   # a flow of its own, or a task module the generic flow runs
        assert (ROOT / "flows" / f"{s.name}.py").is_file() or (ROOT / "tasks" / f"{s.name}.py").is_file(), s.name
        assert s.kind in ("per-scene", "training", "scoring") and set(s.params) <= set(Config.STAGES), s.name
        assert s.metrics == f"metrics/{s.name}.json"


def test_a_stage_added_to_the_registry_gets_its_code_params_and_outputs(monkeypatch, tmp_path):
    """One registry entry makes a whole dvc.yaml stage: the deps of its flow's imports, the profile
    keys of its blocks, its outputs; an edit to the registry shows as drift."""
    (tmp_path / "flows").mkdir()
    (tmp_path / "tasks").mkdir()
    (tmp_path / "typ").mkdir()
    (tmp_path / "flows" / "__init__.py").write_text("")
    (tmp_path / "flows" / "probe.py").write_text("from tasks import probe\n")
    (tmp_path / "tasks" / "__init__.py").write_text("")
    (tmp_path / "tasks" / "probe.py").write_text("def run():\n    from typ import io\n")
    (tmp_path / "typ" / "__init__.py").write_text("")
    (tmp_path / "typ" / "io.py").write_text("")
    (tmp_path / "typ" / "profiles.yaml").write_text("tiny:\n  probe: {}\n  fusion: {}\npaper:\n  probe: {}\n")
    probe = stages.Stage("probe", "training", data=("data/x",), params=("fusion",),
                         outs=("artifacts/probe",), reports=("reports/probe.md",), loss_curves=True)
    monkeypatch.setattr(stages, "stages", lambda: (probe,))
    built = dvcyaml.build(tmp_path)
    entry = built["stages"]["probe"]
    assert entry["cmd"] == ".venv/bin/typ run probe"
    assert entry["deps"] == ["data/x", "flows", "tasks", "typ"]   # every file of each folder is read: folders
    assert entry["params"] == ["profile", "probe", "fusion", {"typ/profiles.yaml": ["tiny.probe", "paper.probe",
                                                                                   "tiny.fusion"]}]
    assert entry["outs"] == [{"artifacts/probe": {"persist": True}}, {"reports/probe.md": {"cache": False}}]
    assert entry["metrics"] == [{"metrics/probe.json": {"cache": False}}]
    assert list(built["plots"][0]) == ["artifacts/probe/loss"]
    assert yaml.safe_load(dvcyaml.render(tmp_path)) == built


def test_typ_dvc_yaml_check_fails_on_drift_and_writes_the_file(tmp_path, capsys):
    """``typ dvc-yaml --check`` on another root: 0 on the committed file, 1 with a diff and the
    command to run on drift, and ``typ dvc-yaml`` writes what it gives (the CLI's own entry point,
    in this process: a subprocess would import every stage's task module again for nothing)."""
    import shutil

    from cli.main import main

    project = tmp_path / "p"
    for package in dvcyaml.PACKAGES:   # what code deps are computed from
        shutil.copytree(ROOT / package, project / package, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "dvc.yaml", project / "dvc.yaml")
    typ = ["--root", str(project), "dvc-yaml"]
    assert main([*typ, "--check"]) == 0, capsys.readouterr().err
    capsys.readouterr()
    (project / "dvc.yaml").write_text((project / "dvc.yaml").read_text().replace("    - tasks/realism.py\n", ""))
    assert main([*typ, "--check"]) == 1
    drift = capsys.readouterr()
    assert "-    - tasks/realism.py" not in drift.out and "+    - tasks/realism.py" in drift.out
    assert "typ dvc-yaml" in drift.err
    assert main(typ) == 0
    assert (project / "dvc.yaml").read_text() == (ROOT / "dvc.yaml").read_text()


def test_the_stage_table_of_the_docs_lists_the_registry_in_order():
    rows = [line.split("|")[1].strip() for line in (ROOT / "docs" / "stages.md").read_text().splitlines()
            if line.startswith("| ") and not line.startswith(("| stage ", "|---"))]
    assert rows == [s.name for s in stages.stages()]


def test_a_folder_is_one_dep_only_when_the_stage_reads_every_file_in_it(tmp_path):
    """Folding changes no dependency: a folder replaces its files only when every Python file in
    it (and below) is in the stage's closure; one unread file keeps the folder per file."""
    for rel in ("typ/config/__init__.py", "typ/config/a.py", "typ/config/b.py", "typ/io.py", "typ/geo.py",
                "typ/__init__.py", "typ/sim/__init__.py"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("")
    read = {"typ/__init__.py", "typ/config/__init__.py", "typ/config/a.py", "typ/config/b.py", "typ/io.py", "typ/sim"}
    assert dvcyaml.fold(read, tmp_path) == {"typ/__init__.py", "typ/config", "typ/io.py", "typ/sim"}   # geo.py unread
    assert dvcyaml.fold(read | {"typ/geo.py"}, tmp_path) == {"typ"}
    assert dvcyaml.fold(read - {"typ/config/b.py"}, tmp_path) == read - {"typ/config/b.py"}
