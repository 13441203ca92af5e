"""The Prefect servers typ starts are stopped on every way out.

- ``typ serve`` stopped by SIGTERM while its server is still starting (before any deployment
  is registered) leaves no server behind, and the port is free for the next ``typ serve``.
- ``typ with-server CMD`` gives CMD (and every stage it starts) one server through
  ``PREFECT_API_URL``, stops it when CMD ends or when it is itself terminated (CMD's process
  group is terminated first), and starts none when ``PREFECT_API_URL`` is already set.
- That server refuses a request without the project's secret (``.prefect/api-auth``, mode 0600,
  made once and kept), which CMD gets as ``PREFECT_API_AUTH_STRING``; a server the user names
  gets no secret of typ's.
- ``kill -9`` of the typ process leaves no server behind, for each way typ starts one: the local
  server of ``typ serve`` / ``with-server`` / ``run all``, the local server and the Dask cluster of
  ``--runner dask``, and Prefect's temporary server: each is gone, its port closed, within seconds.
"""
from __future__ import annotations

import json
import os
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import psutil
import pytest
import yaml

from flows.server import free_port
from prefect_api import api_status
from repo_paths import REPO



def _env(tmp_path: Path, **extra) -> dict:
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / ".prefect"), "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
           "DO_NOT_TRACK": "1", "OMP_NUM_THREADS": "1"}
    for var in ("PREFECT_API_URL", "PREFECT_API_AUTH_STRING", "PREFECT_SERVER_API_AUTH_STRING"):
        env.pop(var, None)
    return {**env, **extra}


def _typ(tmp_path: Path, *argv: str, env: dict) -> subprocess.Popen:
    (tmp_path / "params.yaml").write_text(yaml.safe_dump({"profile": "tiny"}))
    return subprocess.Popen([sys.executable, "-m", "cli", "--root", str(tmp_path), *argv], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)


def _wait(what: str, check, timeout: float = 120.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        found = check()
        if found:
            return found
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout:.0f} s waiting for {what}")


def _server_children(pid: int) -> list[psutil.Process]:
    try:
        procs = psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []
    found = []
    for p in procs:
        try:
            if "server" in p.cmdline() and "start" in p.cmdline():
                found.append(p)
        except psutil.Error:
            pass
    return found


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) != 0


def _healthy(api_url: str) -> bool:
    with urllib.request.urlopen(f"{api_url}/health", timeout=5) as response:
        return response.status == 200


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def test_sigterm_while_serve_starts_its_server_leaves_no_server(tmp_path):
    port = free_port()
    serve = _typ(tmp_path, "serve", "--port", str(port), env=_env(tmp_path))
    server = None
    try:
        server = _wait("typ serve to start its Prefect server", lambda: _server_children(serve.pid))[0]
        os.kill(serve.pid, signal.SIGTERM)  # typ serve alone, as `kill PID` does, not its group
        out, _ = serve.communicate(timeout=60)
        assert serve.returncode == 128 + signal.SIGTERM, out
        assert "Prefect server http" not in out  # it was still starting: nothing was served
        psutil.wait_procs([server], timeout=30)
        assert not server.is_running(), f"the server {server.pid} survived typ serve"
        assert _port_free(port)
    finally:
        _stop(serve)
        if server is not None and server.is_running():  # the failure this test looks for: clean up
            os.killpg(server.pid, signal.SIGKILL)


#: the command typ with-server runs: reports what it sees, then waits to be stopped
CHILD = """
import json, os, sys, time
json.dump({"api": os.environ.get("PREFECT_API_URL"), "auth": os.environ.get("PREFECT_API_AUTH_STRING"),
           "pid": os.getpid()}, open(sys.argv[1] + ".tmp", "w"))
os.rename(sys.argv[1] + ".tmp", sys.argv[1])
time.sleep(float(sys.argv[2]))
sys.exit(int(sys.argv[3]))
"""


def _child_report(path: Path) -> dict:
    return _wait("the command to start", lambda: path.is_file() and json.loads(path.read_text()), timeout=300)


def test_with_server_gives_the_command_one_server_and_stops_it(tmp_path):
    report = tmp_path / "seen.json"
    run = _typ(tmp_path, "with-server", sys.executable, "-c", CHILD, str(report), "600", "0", env=_env(tmp_path))
    try:
        seen = _child_report(report)
        assert seen["api"].startswith("http://127.0.0.1:") and _healthy(seen["api"])
        server = _server_children(run.pid)
        assert len(server) == 1
        # the API asks for the project's secret, which the command was given
        secret = tmp_path / ".prefect" / "api-auth"
        assert stat.S_IMODE(secret.stat().st_mode) == 0o600 and seen["auth"] == secret.read_text().strip()
        assert api_status(seen["api"], None) == 401 and api_status(seen["api"], seen["auth"]) == 200
        port = int(seen["api"].split(":")[2].split("/")[0])
        # SIGTERM to typ with-server while the command runs: the command's group gets it, then the server stops
        os.kill(run.pid, signal.SIGTERM)
        out, _ = run.communicate(timeout=120)
        assert run.returncode == 128 + signal.SIGTERM, out
        assert not psutil.pid_exists(seen["pid"]) or psutil.Process(seen["pid"]).status() == psutil.STATUS_ZOMBIE
        psutil.wait_procs(server, timeout=30)
        assert not any(p.is_running() for p in server) and _port_free(port)
    finally:
        if run.poll() is None:   # a check above failed: typ with-server stops its server first
            os.kill(run.pid, signal.SIGTERM)
            try:
                run.wait(60)
            except subprocess.TimeoutExpired:
                pass
        _stop(run)


def test_with_server_passes_on_the_exit_status_and_uses_a_given_api(tmp_path):
    report = tmp_path / "seen.json"
    given = "http://127.0.0.1:9/api"  # not contacted: with-server only hands it on
    run = _typ(tmp_path, "with-server", sys.executable, "-c", CHILD, str(report), "0", "3",
               env=_env(tmp_path, PREFECT_API_URL=given))
    try:
        out, _ = run.communicate(timeout=120)
        assert run.returncode == 3, out
        assert _child_report(report)["api"] == given
        assert not (tmp_path / ".prefect" / "server.log").exists()  # no server was started
        # nor a secret made or handed to a server typ did not start
        assert _child_report(report)["auth"] is None and not (tmp_path / ".prefect" / "api-auth").exists()
    finally:
        _stop(run)


@pytest.mark.parametrize("argv, says", [(["with-server"], "COMMAND: expected a command to run"),
                                        (["with-server", "no-such-program-here"], "a program on PATH")])
def test_with_server_without_a_runnable_command_is_bad_input(tmp_path, argv, says):
    run = _typ(tmp_path, *argv, env=_env(tmp_path, PREFECT_API_URL="http://127.0.0.1:9/api"))
    out, _ = run.communicate(timeout=120)
    assert run.returncode == 2 and says in out, out


def test_the_server_takes_sigterm_though_it_was_started_with_the_signals_held(tmp_path):
    """LocalServer.running holds SIGTERM/SIGINT/SIGHUP around its fork. Held by a signal mask, which
    is inherited across exec, they were blocked in the server: stop() waited out its grace and
    SIGKILLed it, and a pytest-xdist worker killed meanwhile left the server running. The server
    must have none of them blocked and stop on SIGTERM."""
    from flows.server import HELD_SIGNALS, LocalServer

    with LocalServer.running(tmp_path / "prefect", ui=False, timeout=180, env=_env(tmp_path)) as server:
        status = Path(f"/proc/{server.process.pid}/status")
        if status.exists():   # Linux: the server's blocked-signal mask has none of the held signals
            blocked = int(next(l for l in status.read_text().splitlines() if l.startswith("SigBlk:")).split()[1], 16)
            assert not any(blocked >> (int(s) - 1) & 1 for s in HELD_SIGNALS), hex(blocked)
        assert _healthy(server.api_url)
        server.stop(grace=60.0)   # before running's own stop: grace enough for SIGTERM under load
    assert server.process.returncode != -signal.SIGKILL   # it ended on SIGTERM, not on the SIGKILL after the grace
    assert _port_free(server.port)


def test_a_sigterm_held_while_the_server_forks_stops_that_server(tmp_path, monkeypatch):
    """A SIGTERM that reaches ``typ serve`` while LocalServer.running forks must stop the child it just
    started. Held by a signal mask it did not: the kernel gave the signal to another thread (here a
    stand-in for execnet's, in CI the pytest-xdist worker's own), Python raised ``Terminated`` in the
    main thread before ``server = ...`` and the child ran on. The sleep after the kill gives that
    thread time to take the signal, which CI's load gave it now and then."""
    import flows.server as server_module

    started = []
    real_popen = subprocess.Popen

    def popen_then_sigterm(cmd, **kwargs):   # a stand-in server, then a SIGTERM while the handle does not exist yet
        child = real_popen([sys.executable, "-c", "import time; time.sleep(120)"], **kwargs)
        started.append(child)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.3)
        return child

    other = threading.Event()
    threading.Thread(target=other.wait, daemon=True).start()
    monkeypatch.setattr(server_module.subprocess, "Popen", popen_then_sigterm)
    try:
        with pytest.raises(server_module.Terminated) as ended, server_module.terminate_raises():
            with server_module.LocalServer.running(tmp_path / "prefect", ui=False, timeout=60, env=_env(tmp_path)):
                pass
    finally:
        other.set()
        if started and started[0].poll() is None:
            started[0].kill()
            assert False, "the child started under the held SIGTERM still runs"
    assert ended.value.code == 128 + signal.SIGTERM
    assert len(started) == 1 and started[0].returncode == -signal.SIGTERM   # stopped by LocalServer.stop


def test_a_signal_just_after_the_server_is_healthy_stops_it(tmp_path, monkeypatch):
    """prefect_api (``typ run all``, ``typ serve``, ``typ with-server``) must stop its server whenever a
    SIGTERM lands, also in the instant after the server was healthy and before its own `try`:
    there it left the server running. The signal is stood in for by the first read of ``api_url``
    raising ``Terminated``, which is where the old code took it outside any `try`."""
    import flows.server as server_module

    started = []
    real_popen = subprocess.Popen

    def popen(cmd, **kwargs):   # a stand-in server
        started.append(real_popen([sys.executable, "-c", "import time; time.sleep(120)"], **kwargs))
        return started[-1]

    def api_url(self):
        raise server_module.Terminated(128 + signal.SIGTERM)

    monkeypatch.setattr(server_module.subprocess, "Popen", popen)
    monkeypatch.setattr(server_module.LocalServer, "wait_healthy", lambda self, timeout: None)
    monkeypatch.setattr(server_module.LocalServer, "api_url", property(api_url))
    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    try:
        with pytest.raises(server_module.Terminated):
            with server_module.prefect_api(tmp_path / "prefect"):
                pass
    finally:
        if started and started[0].poll() is None:
            started[0].kill()
            assert False, "the server started before the signal still runs"
    assert len(started) == 1 and started[0].returncode == -signal.SIGTERM
    assert "PREFECT_API_URL" not in os.environ


def test_signals_held_defers_each_signal_to_the_handler_it_would_have_met():
    """Ctrl-C inside the hold becomes KeyboardInterrupt as the block ends, after the code inside
    ran to its end; handlers are restored and an ignored signal stays ignored."""
    from flows.server import signals_held

    ran_to_end = False
    previous_hup = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    previous_int = signal.signal(signal.SIGINT, signal.default_int_handler)   # an xdist worker may ignore it
    try:
        with pytest.raises(KeyboardInterrupt):
            with signals_held():
                assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
                os.kill(os.getpid(), signal.SIGHUP)
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.2)
                ran_to_end = True
        assert ran_to_end
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
        with signals_held():   # nothing came: nothing raised
            pass
    finally:
        signal.signal(signal.SIGHUP, previous_hup)
        signal.signal(signal.SIGINT, previous_int)


def test_the_api_secret_is_made_once_owner_only_and_kept(tmp_path):
    """Made with mode 0600 whatever the umask (never readable by others, not even while it is
    written), the same secret on every later use, and one that others can read is refused."""
    from flows.server import AUTH_FILE, api_auth_string
    from typ.errors import TypError

    home = tmp_path / "prefect"
    umask = os.umask(0)   # a process that would leave a new file readable and writable by everyone
    try:
        first = api_auth_string(home)
    finally:
        os.umask(umask)
    secret = home / AUTH_FILE
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600 and stat.S_IMODE(home.stat().st_mode) == 0o700
    assert first.startswith("typ:") and len(first) > 40 and secret.read_text() == first + "\n"
    assert api_auth_string(home) == first
    assert sorted(p.name for p in home.iterdir()) == [AUTH_FILE]   # no temporary left behind
    assert api_auth_string(tmp_path / "other") != first
    secret.chmod(0o644)
    with pytest.raises(TypError, match="chmod 600"):
        api_auth_string(home)
    secret.unlink()   # rotating: a new secret
    assert api_auth_string(home) != first
    secret.unlink()
    secret.symlink_to(tmp_path / "nowhere")   # not a secret, and not one to make there
    with pytest.raises(TypError, match="a readable file"):
        api_auth_string(home)
    secret.unlink()
    os.mkfifo(secret)   # must not wait for a writer
    with pytest.raises(TypError, match="a regular file"):
        api_auth_string(home)


#: runs the CLI's environment set-up for a root and prints what it left for Prefect
SETUP_ENV = """
import json, os, sys
from pathlib import Path
from flows.run import setup_env
setup_env(Path(sys.argv[1]))
print(json.dumps({k: os.environ.get(k) for k in ("PREFECT_API_AUTH_STRING", "PREFECT_SERVER_API_AUTH_STRING")}))
"""


def test_the_cli_hands_the_secret_to_the_servers_it_starts_only(tmp_path):
    """Without PREFECT_API_URL, every server of the command (a local one, Prefect's temporary one)
    asks for the project's secret and its clients send it; with one, the user's auth stands."""
    def setup_env(root: Path, **extra) -> dict:
        env = {k: v for k, v in _env(tmp_path, **extra).items() if k != "PREFECT_HOME"}
        out = subprocess.run([sys.executable, "-c", SETUP_ENV, str(root)], env=env, capture_output=True, text=True,
                             check=True, timeout=60).stdout
        return json.loads(out)

    seen = setup_env(tmp_path)
    secret = (tmp_path / ".prefect" / "api-auth").read_text().strip()
    assert seen == {"PREFECT_API_AUTH_STRING": secret, "PREFECT_SERVER_API_AUTH_STRING": secret}

    theirs = setup_env(tmp_path / "elsewhere", PREFECT_API_URL="https://prefect.example/api",
                       PREFECT_API_AUTH_STRING="theirs:secret")
    assert theirs == {"PREFECT_API_AUTH_STRING": "theirs:secret", "PREFECT_SERVER_API_AUTH_STRING": None}
    assert not (tmp_path / "elsewhere" / ".prefect").exists()


#: the CLI's environment set-up, then what MLflow and Prefect decide about usage reporting
TELEMETRY = """
import json, sys
from pathlib import Path
from flows.run import setup_env
setup_env(Path(sys.argv[1]))
from mlflow.telemetry.utils import is_telemetry_disabled
from prefect.settings import PREFECT_SERVER_ANALYTICS_ENABLED
print(json.dumps([is_telemetry_disabled(), PREFECT_SERVER_ANALYTICS_ENABLED.value()]))
"""


def test_a_typ_command_reports_no_usage_to_mlflow_or_prefect(tmp_path):
    """Outside a test or CI (which MLflow detects from PYTEST_CURRENT_TEST, CI, ...), MLflow reads
    DO_NOT_TRACK only as "true": typ's DO_NOT_TRACK=1 alone left its telemetry on, a config fetched
    from the internet and usage posted at exit of every stage process."""
    quiet = ("PYTEST_CURRENT_TEST", "CI", "GITHUB_ACTIONS", "MLFLOW_DISABLE_TELEMETRY", "DO_NOT_TRACK",
             "PREFECT_SERVER_ANALYTICS_ENABLED")
    env = {k: v for k, v in os.environ.items() if k not in quiet}
    out = subprocess.run([sys.executable, "-c", TELEMETRY, str(tmp_path)], env=env, cwd=REPO, capture_output=True,
                         text=True, check=True, timeout=120).stdout
    assert json.loads(out.strip().splitlines()[-1]) == [True, False]


# --- kill -9: no server left ----------------------------------------------------------------------

#: how long a server may outlive a typ process killed by SIGKILL (it gets SIGTERM at once, then shuts down)
AFTER_KILL = 30.0

#: the two other ways a ``typ run`` starts servers, in one process (one Python start, one kill): a
#: ``typ run STAGE`` without PREFECT_API_URL gets Prefect's own temporary server at its first client;
#: ``typ run STAGE --runner dask`` starts typ's local Prefect server for its workers
#: (flows.common.api_for_workers) and the LocalCluster of its task runner. It reports every process
#: it started and both APIs, then waits to be killed
SERVERS = """
import json, os, sys, time
from pathlib import Path

import psutil

if __name__ == "__main__":
    from flows.run import setup_env

    setup_env(Path(sys.argv[1]))
    from prefect.client.orchestration import get_client

    with get_client(sync_client=True) as client:
        client.hello()
    from prefect.server.api.server import SubprocessASGIServer

    temporary = SubprocessASGIServer._instances[None]
    from flows.common import api_for_workers, runner

    with api_for_workers():
        from prefect.settings import PREFECT_API_URL

        with runner(2, "dask") as task_runner:
            task_runner.client.run(os.getpid)   # the cluster starts with its first use
            pids = [p.pid for p in psutil.Process().children(recursive=True)]
            assert temporary.server_process.pid in pids
            json.dump({"apis": [temporary.api_url, PREFECT_API_URL.value()], "pids": pids},
                      open(sys.argv[2] + ".tmp", "w"))
            os.rename(sys.argv[2] + ".tmp", sys.argv[2])
            time.sleep(600)
"""


def _port_of(api_url: str) -> int:
    return int(api_url.split(":")[2].split("/")[0])


def _gone(pids: list[int]) -> bool:
    return not [p for p in pids if psutil.pid_exists(p) and psutil.Process(p).status() != psutil.STATUS_ZOMBIE]


def _kill_left(pids: list[int]) -> None:
    """The failure these tests look for: clean up what outlived its typ process, by pid."""
    for pid in pids:
        try:
            psutil.Process(pid).kill()
        except psutil.Error:
            pass


def test_kill_9_of_a_run_leaves_neither_server_nor_dask_worker_behind(tmp_path):
    """SIGKILL runs no code of typ's: Prefect's temporary server, typ's local server for Dask
    workers and the workers themselves must each end because their parent did."""
    report = tmp_path / "started.json"
    proc = subprocess.Popen([sys.executable, "-c", SERVERS, str(tmp_path), str(report)], cwd=REPO, env=_env(tmp_path),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    started = {"pids": []}
    try:
        started = _wait("the servers to start", lambda: (report.is_file() and json.loads(report.read_text()))
                        or (proc.poll() is not None and pytest.fail(proc.stdout.read()[-3000:])), timeout=300)
        ports = {_port_of(api) for api in started["apis"]}
        assert len(ports) == 2 and len(started["pids"]) >= 4   # two servers, two Dask workers (and their nanny)
        assert not any(_port_free(port) for port in ports)
        os.kill(proc.pid, signal.SIGKILL)   # the typ process alone, as `kill -9 PID` does
        proc.wait(30)
        _wait("the servers and workers to end after their parent", lambda: _gone(started["pids"]), timeout=AFTER_KILL)
        assert all(_port_free(port) for port in ports)
    finally:
        _stop(proc)
        _kill_left(started["pids"])


def test_kill_9_of_typ_serve_leaves_no_server_behind(tmp_path):
    """``typ serve``'s local server (the one ``typ with-server`` and ``typ run all`` start too) ends with it."""
    port = free_port()
    serve = _typ(tmp_path, "serve", "--port", str(port), env=_env(tmp_path))
    servers: list[psutil.Process] = []
    try:
        servers = _wait("typ serve to start its Prefect server", lambda: _server_children(serve.pid), timeout=300)
        _wait("the server to listen", lambda: not _port_free(port), timeout=300)
        os.kill(serve.pid, signal.SIGKILL)
        serve.wait(30)
        _wait("the server to end after typ serve", lambda: _gone([p.pid for p in servers]), timeout=AFTER_KILL)
        assert _port_free(port)
    finally:
        _stop(serve)
        _kill_left([p.pid for p in servers])

