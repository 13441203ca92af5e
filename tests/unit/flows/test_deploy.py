"""Prefect deployments against a real local server, and the per-scene retry policy.

The module's server is ``prefect server start`` on a free loopback port with its sqlite state in
a temporary PREFECT_HOME, started and stopped (by process group) through ``flows.server``, with
basic auth on as typ always starts it: a request without the secret of its PREFECT_HOME is refused.
``typ serve`` runs as a subprocess against it (PREFECT_API_URL set, so it starts no server of
its own); the tests trigger the on-demand deployment with ``run_deployment``, wait for the run
and check the stage's outputs, wait for the every-minute watched-folder deployment to run on its
schedule, and see a run on another project's root refused.
"""
from __future__ import annotations

import errno
import os
import shutil
import signal
import stat
import subprocess
import sys
import time

import pytest
import yaml

from flows.server import LocalServer
from prefect_api import api_status
from typ.io import atomic_path, write_manifest
from typ.errors import TypError

PARAMS = {
    "profile": "tiny",
    "simulate": {"frames": 2, "azimuth_step_deg": 1.5, "agents_min": 2, "agents_max": 2, "workers": 1, "domains": {},
                 "scenarios": {"source": {"train": 0, "test": 0}, "target": {"train": 1, "val": 0, "test": 0, "pretrain": 0},
                               "real_cav": {"train": 0, "test": 0}}},
    "serve": {"watch_cron": "* * * * *"},
}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    home = tmp_path_factory.mktemp("prefect-home")
    env = {**os.environ, "PREFECT_SERVER_SERVICES_SCHEDULER_LOOP_SECONDS": "5", "PREFECT_LOGGING_LEVEL": "WARNING"}
    with LocalServer.running(home, ui=False, env=env, timeout=180) as srv:
        yield srv
    assert srv.process.poll() is not None
    with pytest.raises(ProcessLookupError):  # nothing of its process group is left
        os.killpg(srv.process.pid, 0)


@pytest.fixture
def api(server):
    from prefect.settings import PREFECT_API_AUTH_STRING, PREFECT_API_URL, temporary_settings

    with temporary_settings(updates={PREFECT_API_URL: server.api_url, PREFECT_API_AUTH_STRING: server.auth}):
        yield server
        # send the logs and events this process still holds before the server goes, or
        # Prefect retries them against a closed port when the interpreter exits
        from prefect.events.worker import EventsWorker
        from prefect.logging.handlers import APILogWorker

        APILogWorker.drain_all(timeout=30)
        EventsWorker.drain_all(timeout=30)


def _wait_for(what: str, check, timeout: float, every: float = 1.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = check()
        if found:
            return found
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def test_the_server_asks_for_the_secret_kept_in_its_home_readable_by_its_owner_only(server):
    secret = server.home / "api-auth"
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert secret.read_text().strip() == server.auth and server.auth.startswith("typ:") and len(server.auth) > 40
    assert api_status(server.api_url, None) == 401
    assert api_status(server.api_url, "typ:not-the-secret") == 401
    assert api_status(server.api_url, server.auth) == 200


@pytest.fixture(scope="module")
def served(server, tmp_path_factory):
    """``typ serve --only typ-stage watch-generate`` on a project of :data:`PARAMS`, against the
    module's server: (project root, its log)."""
    root = tmp_path_factory.mktemp("served")
    (root / "params.yaml").write_text(yaml.safe_dump(PARAMS))
    env = {**os.environ, **server.client_env, "PREFECT_HOME": str(root / ".prefect"),
           "MLFLOW_TRACKING_URI": f"sqlite:///{root / 'mlruns.db'}", "OMP_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1", "PREFECT_LOGGING_LEVEL": "INFO"}
    log = root / "serve.log"
    with open(log, "wb") as out:
        serve = subprocess.Popen([sys.executable, "-m", "cli", "--root", str(root), "serve", "--only", "typ-stage",
                                  "watch-generate", "--poll-seconds", "1"], cwd=root, env=env, stdout=out,
                                 stderr=subprocess.STDOUT, start_new_session=True)
    try:
        yield root, log, serve
    finally:
        try:
            os.killpg(serve.pid, signal.SIGTERM)
            serve.wait(20)
        except subprocess.TimeoutExpired:
            os.killpg(serve.pid, signal.SIGKILL)
            serve.wait(20)
        except ProcessLookupError:
            pass


def _deployment(client, name: str, served):
    _, log, serve = served

    def registered():
        try:
            return client.read_deployment_by_name(name)
        except Exception:
            assert serve.poll() is None, log.read_text()[-3000:]
            return None

    return _wait_for(f"typ serve to register {name}", registered, 120)


def test_served_deployment_runs_on_demand_and_on_schedule(api, served):
    from prefect import get_client
    from prefect.client.schemas.filters import DeploymentFilter, DeploymentFilterId
    from prefect.deployments import run_deployment

    root, log, _ = served
    with get_client(sync_client=True) as client:
        _deployment(client, "typ-stage/on-demand", served)
        watch = _deployment(client, "watch-generate/scheduled", served)
        assert [s.schedule.cron for s in watch.schedules] == ["* * * * *"]
        assert watch.parameters == {"params": "params.yaml", "root": str(root.resolve())}

        run = run_deployment("typ-stage/on-demand", parameters={"stage": "simulate"}, timeout=300, poll_interval=1)
        assert run.state.is_completed(), f"{run.state}\n{log.read_text()[-4000:]}"
        pcds = sorted((root / "data" / "sim" / "target" / "train").rglob("*.pcd"))
        assert len(pcds) == 2 * 2  # agents x frames
        assert (root / "metrics" / "simulate.json").is_file()

        def scheduled_run_done():
            runs = client.read_flow_runs(deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[watch.id])))
            return [r for r in runs if r.state and r.state.is_completed()]

        done = _wait_for("a scheduled run of watch-generate", scheduled_run_done, 150, every=2)
        assert done[0].auto_scheduled


def test_a_deployment_run_on_another_root_is_refused(api, served, tmp_path):
    """Whoever may create flow runs chooses their parameters: a run pointed at another project, or
    at a params file outside this one, would write and delete there as the user of ``typ serve``.
    Such a run fails naming the parameter, and nothing is written where it pointed."""
    from prefect import get_client
    from prefect.deployments import run_deployment

    root, log, _ = served
    other = tmp_path / "someone-else"
    other.mkdir()
    # a params file that points the stage's output there too
    foreign = {**PARAMS, "simulate": {**PARAMS["simulate"], "out": str(other / "sim")}}
    (other / "params.yaml").write_text(yaml.safe_dump(foreign))
    with get_client(sync_client=True) as client:
        for name in ("typ-stage/on-demand", "watch-generate/scheduled"):
            _deployment(client, name, served)
    stage = {"stage": "simulate"}
    for name, parameters, field in (("typ-stage/on-demand", {**stage, "root": str(other)}, "root"),
                                    ("typ-stage/on-demand", {**stage, "params": os.path.relpath(other / "params.yaml",
                                                                                                root)}, "params"),
                                    ("typ-stage/on-demand", {**stage, "params": str(other / "params.yaml")}, "params"),
                                    ("watch-generate/scheduled", {"root": str(other)}, "root")):
        run = run_deployment(name, parameters=parameters, timeout=300, poll_interval=1)
        assert run.state.is_failed(), f"{name} {parameters}: {run.state}\n{log.read_text()[-4000:]}"
        assert f"{field}: expected " in run.state.message and "TypError" in run.state.message, run.state.message
    assert sorted(p.name for p in other.iterdir()) == ["params.yaml"]


CALLS: dict[str, int] = {}


def _flaky(scene: str) -> str:
    CALLS[scene] = CALLS.get(scene, 0) + 1
    if scene == "eio" and CALLS[scene] == 1:
        raise OSError(errno.EIO, "Input/output error (a flaky disk)")
    if scene == "bug":
        raise ValueError("a deterministic bug")
    if scene == "bad":
        raise TypError("data/sim/bad", "scenario", "an OPV2V scenario folder")
    if scene == "gone":
        raise FileNotFoundError(errno.ENOENT, "No such file", scene)
    return scene


def test_retries_only_transient_io_errors_and_failures_name_the_scene(api):
    from prefect import flow

    from flows.common import IO_RETRIES, StageFailed, per_scene

    @flow(name="retry-policy")
    def run(items):
        return per_scene(_flaky, items, label=str, stage="probe", retries=IO_RETRIES)

    CALLS.clear()
    assert run(["ok", "eio"]) == ["ok", "eio"]
    assert CALLS == {"ok": 1, "eio": 2}  # EIO retried once (after the 1 s backoff), then fine
    for scene, error in (("bug", StageFailed), ("gone", StageFailed), ("bad", TypError)):
        CALLS.clear()
        with pytest.raises(error) as info:
            run([scene])
        assert CALLS == {scene: 1}, f"{scene} was retried"
        if error is StageFailed:
            assert f"probe: scene {scene} failed" in str(info.value)
        else:
            assert "data/sim/bad" in str(info.value)


def _scene_work(scene: str, *, out) -> dict:
    CALLS[scene] = CALLS.get(scene, 0) + 1
    return {"scenario": scene, "skipped": None}


def _scene_unchanged(scene: str, *, out) -> dict | None:
    return {"scenario": scene, "skipped": "unchanged"} if scene.startswith("old") else None


def _probe_stage(items, tmp_path):
    from tasks.scene_stage import SceneStage

    return SceneStage(out=tmp_path / "out", plan=lambda: (items, []), work=_scene_work,
                      work_kwargs={"out": tmp_path},
                      label=str, summarize=lambda rs: {"order": [r["scenario"] for r in rs],
                                                       "ran": sum(r["skipped"] is None for r in rs)},
                      unchanged=_scene_unchanged)


def test_settle_unchanged_logs_a_no_op_stage_only_when_nothing_has_work(tmp_path, monkeypatch):
    """Before Prefect starts: every scene unchanged, no stale output, no temporary -> the stage's
    MLflow run and metrics as its flow would write them; any work at all -> None, nothing logged."""
    import contextlib

    from flows import common
    from tasks.scene_stage import SceneStage

    runs, finished = [], {}
    monkeypatch.setattr(common, "stage_run", lambda stage, cfg, root, tags: runs.append(tags) or
                        contextlib.nullcontext(None))
    monkeypatch.setattr(common, "finish_stage", lambda stage, run, metrics, root: finished.update(metrics))
    CALLS.clear()
    metrics = common.settle_unchanged("probe", None, tmp_path, _probe_stage(["old_a", "old_b"], tmp_path))
    assert metrics["order"] == ["old_a", "old_b"] and metrics["ran"] == 0 and finished == metrics
    assert (metrics["removed_stale"], metrics["removed_temporaries"]) == (0, 0) and metrics["seconds_total"] >= 0
    assert runs == [{"typ.prefect": "not started: every scene unchanged"}] and CALLS == {}
    runs.clear()
    assert common.settle_unchanged("probe", None, tmp_path, _probe_stage(["old_a", "new_b"], tmp_path)) is None
    stale = _probe_stage(["old_a"], tmp_path)
    stale = SceneStage(**{**stale.__dict__, "plan": lambda: (["old_a"], [tmp_path / "out" / "gone"])})
    # a stale path that is not the stage's (nothing there, or a folder typ did not write) is no work ...
    assert common.settle_unchanged("probe", None, tmp_path, stale)["kept_not_written_by_typ"] == 1
    runs.clear()
    (tmp_path / "out" / "gone").mkdir(parents=True)
    assert common.settle_unchanged("probe", None, tmp_path, stale)["kept_not_written_by_typ"] == 1
    runs.clear()
    shutil.rmtree(tmp_path / "out" / "gone")
    with atomic_path(tmp_path / "out" / "gone", stage="probe") as tmp:   # ... one the stage wrote is
        tmp.mkdir()
        write_manifest(tmp, "probe", {})
    assert common.settle_unchanged("probe", None, tmp_path, stale) is None
    shutil.rmtree(tmp_path / "out" / "gone")
    (tmp_path / "out" / "scene").mkdir(parents=True)
    (tmp_path / "out" / "scene" / ".tmp-x.parquet.1").write_bytes(b"partial")   # a killed run's temporary
    assert common.settle_unchanged("probe", None, tmp_path, _probe_stage(["old_a"], tmp_path)) is None
    assert runs == [] and CALLS == {} and (tmp_path / "out" / "scene" / ".tmp-x.parquet.1").exists()


def test_per_scene_stage_settles_unchanged_scenes_without_a_prefect_task(api, tmp_path, monkeypatch):
    """A no-op stage must not pay a Prefect task per unchanged scene; results keep the plan's order."""
    import contextlib

    from prefect import flow

    from flows import common

    finished = {}
    monkeypatch.setattr(common, "stage_run", lambda stage, cfg, root: contextlib.nullcontext(None))
    monkeypatch.setattr(common, "finish_stage", lambda stage, run, metrics, root: finished.update(metrics))
    submitted = []
    real = common.per_scene
    monkeypatch.setattr(common, "per_scene", lambda fn, items, **kw: submitted.extend(items) or real(fn, items, **kw))

    @flow(name="settle")
    def run(items):
        return common.per_scene_stage("probe", None, tmp_path, _probe_stage(items, tmp_path))

    CALLS.clear()
    run(["old_a", "new_b", "old_c", "new_d"])
    assert submitted == ["new_b", "new_d"] and CALLS == {"new_b": 1, "new_d": 1}
    assert finished["order"] == ["old_a", "new_b", "old_c", "new_d"] and finished["ran"] == 2
    submitted.clear()
    run(["old_a", "old_c"])  # all unchanged: no task at all
    assert submitted == [] and finished["order"] == ["old_a", "old_c"] and finished["ran"] == 0


def test_watched_folder_finds_new_scenarios_and_points_generate_at_them(tmp_path):
    from flows.deploy import DERIVED_PARAMS, new_scenarios, watch_params
    from typ.config import load_config

    watch, out = tmp_path / "incoming", tmp_path / "generated-incoming"
    for name in ("scene_a", "scene_b"):
        (watch / "target" / "test" / name / "0").mkdir(parents=True)
    (watch / "target" / ".tmp-partial").mkdir()
    (out / "target" / "test" / "scene_a").mkdir(parents=True)  # generated by an earlier run
    fresh = new_scenarios(watch, out)
    assert {k: [p.name for p in v] for k, v in fresh.items()} == {("target", "test"): ["scene_b"]}
    assert new_scenarios(tmp_path / "missing", out) == {}

    (tmp_path / "params.yaml").write_text(yaml.safe_dump(PARAMS))
    derived = watch_params(tmp_path / "params.yaml", watch, out, [("target", "test")])
    assert derived == str(out / DERIVED_PARAMS)
    cfg = load_config(derived)  # what generate will load: valid against the current schema
    assert cfg.generate.input == str(watch) and cfg.generate.out == str(out)
    assert [(s.dataset, s.split) for s in cfg.generate.sets] == [("target", "test")]
    assert cfg.simulate.frames == PARAMS["simulate"]["frames"]  # the rest of the project's params kept
