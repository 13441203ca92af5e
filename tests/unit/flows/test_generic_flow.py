"""A stage with no flow module of its own: its task module and a registry entry make the whole stage
(flows.generic runs it, flows.dvcyaml gives its code deps, flows.pipeline its kind)."""
from __future__ import annotations

import contextlib
import json
import os
import sys
import types

import pytest

from flows import dvcyaml, generic, pipeline
from flows import stages as registry
from tasks.scene_stage import StageResult
from typ.errors import TypError


class Recorder:
    """A StageRun that keeps what it is given."""

    def __init__(self):
        self.logged, self.artifacts = {}, []

    def metrics(self, values, step=None):
        self.logged.update(values)

    def artifact(self, path, folder=None):
        self.artifacts.append(str(path))


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A project with tiny params; the MLflow run and Prefect's task wrapping replaced by recorders."""
    (tmp_path / "params.yaml").write_text("profile: tiny\n")
    run, calls = Recorder(), {"tasks": [], "published": [], "trainings": 0}

    @contextlib.contextmanager
    def stage_run(name, cfg, root):
        calls["stage_run"] = name
        yield run

    class Trainings:
        def __enter__(self):
            calls["trainings"] += 1
            return self

        def __exit__(self, *exc):
            return False

    monkeypatch.setattr(generic, "stage_run", stage_run)
    monkeypatch.setattr(generic, "PrefectTrainings", Trainings)
    monkeypatch.setattr(generic, "plain_task", lambda fn, name: calls["tasks"].append(name) or fn)
    monkeypatch.setattr(generic, "publish_markdown", lambda text, key, description: calls["published"].append(key))
    return tmp_path, run, calls


def _module(name: str, **attrs) -> types.ModuleType:
    module = types.ModuleType(f"tasks.{name}")
    module.__dict__.update(attrs)
    return module


def test_a_run_stage_writes_its_metrics_artifacts_and_summary(project):
    root, run, calls = project
    seen = {}

    def probe_run(cfg, root_, *, run):
        seen.update(profile=cfg.profile, root=root_, run=run)
        (root_ / "probe.md").write_text("# probe")
        return StageResult({"scored": 3, "nested": {"iou": 0.5}}, [root_ / "probe.md"], "# probe\n")

    metrics = generic.run_module("probe", _module("probe", run=probe_run), "params.yaml", str(root))
    assert metrics == {"scored": 3, "nested": {"iou": 0.5}}
    assert json.loads((root / "metrics" / "probe.json").read_text()) == metrics
    assert seen == {"profile": "tiny", "root": root, "run": run} and calls["stage_run"] == "probe"
    assert run.logged == {"scored": 3.0, "nested.iou": 0.5}
    assert run.artifacts == [str(root / "metrics" / "probe.json"), str(root / "probe.md")]
    # no trainings parameter: the whole run is one Prefect task named after the stage
    assert calls["tasks"] == ["probe"] and calls["trainings"] == 0 and calls["published"] == ["probe-summary"]


def test_a_stage_that_trains_gets_per_network_tasks_not_one_task(project):
    root, run, calls = project
    got = {}

    def probe_run(cfg, root_, *, run, trainings):
        got["trainings"] = trainings
        return StageResult({"trained": 2})

    assert generic.run_module("probe", _module("probe", run=probe_run), "params.yaml", str(root)) == {"trained": 2}
    assert calls["trainings"] == 1 and calls["tasks"] == [] and got["trainings"] is not None
    assert calls["published"] == []   # no summary, no markdown artifact


def test_a_scene_stage_runs_as_a_per_scene_stage(project, monkeypatch):
    root, run, calls = project
    spec = object()
    monkeypatch.setattr(generic, "per_scene_stage", lambda name, cfg, root_, s: {"stage": name, "spec": s})
    module = _module("probe", scene_stage=lambda cfg, root_: spec, run=lambda *a, **k: 1 / 0)
    assert generic.run_module("probe", module, "params.yaml", str(root)) == {"stage": "probe", "spec": spec}


def test_a_task_module_without_a_stage_shape_or_result_is_named(project):
    root, _, _ = project
    with pytest.raises(TypError, match="tasks.probe.*scene_stage / run"):
        generic.run_module("probe", _module("probe"), "params.yaml", str(root))
    with pytest.raises(TypError, match=r"tasks.probe.run.*StageResult.*dict"):
        generic.run_module("probe", _module("probe", run=lambda cfg, root, *, run: {"a": 1}), "params.yaml",
                           str(root))
    assert not (root / "metrics" / "probe.json").exists()


def test_flow_of_names_the_flow_after_the_stage_and_runs_the_task_module(monkeypatch, tmp_path):
    module = _module("probe", run=lambda cfg, root, *, run: StageResult({}))
    monkeypatch.setitem(sys.modules, "tasks.probe", module)
    called = {}
    monkeypatch.setattr(generic, "run_module", lambda *a: called.setdefault("args", a) and {"ok": 1})
    fl = generic.flow_of("probe")
    assert fl.name == "probe" and fl.fn.__name__ == "probe_flow"
    fl.fn(params="p.yaml", root=str(tmp_path))
    assert called["args"] == ("probe", module, "p.yaml", str(tmp_path))


def test_the_runner_takes_flows_from_their_module_or_the_task_module():
    assert pipeline._flow("generate").name == "generate" and pipeline._flow("generate").fn.__module__ == "flows.generate"
    for name in ("simulate", "vqvae", "stage1", "adapt", "evaluate", "fusion", "ssc", "selftrain", "ddpm"):   # no flows/<name>.py
        assert pipeline._flow(name).name == name and pipeline._flow(name).fn.__module__ == "flows.generic"


def test_kinds_come_from_the_registry():
    by_name = registry.by_name()
    assert pipeline.PER_SCENE == tuple(n for n, s in by_name.items() if s.kind == "per-scene")
    assert pipeline.PER_SCENE == ("simulate", "voxelize", "generate")
    assert pipeline.WITHOUT_TORCH == ("simulate", "voxelize")
    assert set(pipeline.TRAINING) == set(by_name) - set(pipeline.PER_SCENE)


def test_code_deps_of_a_stage_without_a_flow_are_the_generic_flows_and_its_task_modules(tmp_path):
    for package, files in {"flows": {"generic.py": "from flows import common\n", "common.py": ""},
                           "tasks": {"probe.py": "from typ import io\n", "other.py": ""},
                           "typ": {"io.py": ""}}.items():
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text("")
        for name, text in files.items():
            (tmp_path / package / name).write_text(text)
    # flows/ and typ/ are read whole: one folder dep each; tasks/other.py is not read, so tasks/ is per file
    assert dvcyaml.code_deps("probe", tmp_path) == ["flows", "tasks/__init__.py", "tasks/probe.py", "typ"]
    (tmp_path / "flows" / "probe.py").write_text("from tasks import other\n")   # a flow of its own wins
    assert dvcyaml.code_deps("probe", tmp_path) == ["flows/__init__.py", "flows/probe.py", "tasks/__init__.py",
                                                     "tasks/other.py"]


def test_scoped_environment_restores_and_defaults_never_override_the_user(monkeypatch):
    monkeypatch.delenv("TYP_PROBE_A", raising=False)
    monkeypatch.setenv("TYP_PROBE_B", "user")
    with pipeline.scoped_environ({"TYP_PROBE_A": "true", "TYP_PROBE_B": "true"}, keep_set=True):
        assert os.environ["TYP_PROBE_A"] == "true" and os.environ["TYP_PROBE_B"] == "user"
    assert "TYP_PROBE_A" not in os.environ and os.environ["TYP_PROBE_B"] == "user"
    with pipeline.scoped_environ({"TYP_PROBE_A": "1", "TYP_PROBE_B": "2"}):   # set, then as they were
        assert (os.environ["TYP_PROBE_A"], os.environ["TYP_PROBE_B"]) == ("1", "2")
    assert "TYP_PROBE_A" not in os.environ and os.environ["TYP_PROBE_B"] == "user"


def test_a_stage_that_times_no_work_gets_its_runs_wall_time_and_one_that_does_keeps_its_own(tmp_path):
    """Every stage's row in the summary has its seconds: metrics without ``seconds_total`` or
    ``seconds_training`` (stage2, selftrain, evaluate) get the run's wall time; a stage's own
    timing, flat or per model, is left as it is."""
    import time

    from flows.common import finish_stage
    from typ.tracking import stage_seconds

    run = Recorder()
    run.started = time.perf_counter() - 2.5
    finish_stage("stage2", run, {"train_pairs": 12}, tmp_path)
    written = json.loads((tmp_path / "metrics" / "stage2.json").read_text())
    assert written["train_pairs"] == 12 and 2.5 <= written["seconds_total"] < 60 and run.logged["seconds_total"] >= 2.5
    for own in ({"seconds_total": 7.0}, {"seed_0": {"seconds_training": 3.0}, "seed_1": {"seconds_training": 4.0}}):
        finish_stage("stage1", run, own, tmp_path)
        written = json.loads((tmp_path / "metrics" / "stage1.json").read_text())
        assert written == own and stage_seconds(written) == 7.0
