"""What a killed process leaves in MLflow: a stage that starts marks the RUNNING runs of its
stage whose process is gone as KILLED; a run ended by SIGTERM or Ctrl-C ends KILLED itself."""
import os
import socket
import subprocess
import sys

import pytest
from mlflow.tracking import MlflowClient

from typ.config import config_from_dict
from typ.tracking import HOST_TAG, PID_TAG, STARTED_TAG, _started, mark_killed_runs, process_gone, stage_run


@pytest.fixture
def store(tmp_path, monkeypatch):
    uri = f"sqlite:///{tmp_path / 'mlruns.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    return tmp_path, MlflowClient(uri)


def _dead_pid() -> int:
    """The pid of a process that has ended (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _left_running(client: MlflowClient, exp_id: str, stage: str, **tags) -> str:
    """A run as a killed stage process leaves it: RUNNING, with whatever process tags it had."""
    run = client.create_run(exp_id, run_name=stage, tags={"typ.stage": stage, **tags})
    return run.info.run_id


def test_a_stage_marks_runs_of_its_stage_whose_process_is_gone_killed(store):
    tmp_path, client = store
    cfg = config_from_dict({"profile": "tiny"})
    with stage_run("voxelize", cfg, root=tmp_path) as first:  # creates the experiment
        pass
    exp_id = client.get_run(first.run_id).info.experiment_id
    host, me = socket.gethostname(), os.getpid()
    me_started = str(_started(me))
    dead = _left_running(client, exp_id, "voxelize", **{PID_TAG: str(_dead_pid()), HOST_TAG: host,
                                                        STARTED_TAG: "1700000000.0"})
    reused = _left_running(client, exp_id, "voxelize", **{PID_TAG: str(me), HOST_TAG: host,  # pid now someone else's
                                                          STARTED_TAG: str(float(me_started) - 3600)})
    alive = _left_running(client, exp_id, "voxelize", **{PID_TAG: str(me), HOST_TAG: host, STARTED_TAG: me_started})
    elsewhere = _left_running(client, exp_id, "voxelize", **{PID_TAG: str(_dead_pid()), HOST_TAG: "other-host",
                                                             STARTED_TAG: "1700000000.0"})
    untagged = _left_running(client, exp_id, "voxelize")           # from before typ recorded the pid
    other_stage = _left_running(client, exp_id, "simulate", **{PID_TAG: str(_dead_pid()), HOST_TAG: host,
                                                               STARTED_TAG: "1700000000.0"})

    with stage_run("voxelize", cfg, root=tmp_path) as run:
        assert client.get_run(run.run_id).info.status == "RUNNING"
        tags = client.get_run(run.run_id).data.tags
        assert (tags[PID_TAG], tags[HOST_TAG]) == (str(me), host) and not process_gone(tags)

    status = {name: client.get_run(rid).info.status for name, rid in
              [("dead", dead), ("reused", reused), ("alive", alive), ("elsewhere", elsewhere),
               ("untagged", untagged), ("other_stage", other_stage), ("new", run.run_id)]}
    assert status == {"dead": "KILLED", "reused": "KILLED", "alive": "RUNNING", "elsewhere": "RUNNING",
                      "untagged": "RUNNING", "other_stage": "RUNNING", "new": "FINISHED"}
    assert "ended without closing its run" in client.get_run(dead).data.tags["typ.killed"]
    assert client.get_run(dead).info.end_time is not None
    # the next stage of that name finds nothing more to mark; simulate's own start marks its run
    assert mark_killed_runs(client, exp_id, "voxelize") == []
    assert mark_killed_runs(client, exp_id, "simulate") == [other_stage]


@pytest.mark.parametrize("error, status", [(KeyboardInterrupt(), "KILLED"), (SystemExit(143), "KILLED"),
                                           (ValueError("a bug"), "FAILED")])
def test_an_interrupted_stage_ends_its_run_killed_and_a_failed_one_failed(store, error, status):
    tmp_path, client = store
    with pytest.raises(type(error)):
        with stage_run("stage1", config_from_dict({"profile": "tiny"}), root=tmp_path) as run:
            raise error
    assert client.get_run(run.run_id).info.status == status


def test_a_run_killed_with_sigkill_is_marked_by_the_next_start(store, tmp_path):
    """The real thing: a process that opened a stage run dies by SIGKILL, the next start marks it."""
    _, client = store
    script = ("import os, signal, sys\n"
              "from typ.config import config_from_dict\n"
              "from typ.tracking import stage_run\n"
              "with stage_run('generate', config_from_dict({'profile': 'tiny'}), root=sys.argv[1]) as run:\n"
              "    print(run.run_id, flush=True)\n"
              "    os.kill(os.getpid(), signal.SIGKILL)\n")
    proc = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert proc.returncode == -9, proc.stderr[-2000:]
    killed = proc.stdout.split()[0]
    assert client.get_run(killed).info.status == "RUNNING"
    with stage_run("generate", config_from_dict({"profile": "tiny"}), root=tmp_path):
        pass
    assert client.get_run(killed).info.status == "KILLED"
