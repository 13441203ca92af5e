"""The Prefect servers typ starts are stopped on every way out.

- ``typ serve`` stopped by SIGTERM while its server is still starting (before any deployment
  is registered) leaves no server behind, and the port is free for the next ``typ serve``.
- ``typ with-server CMD`` gives CMD (and every stage it starts) one server through
  ``PREFECT_API_URL``, stops it when CMD ends or when it is itself terminated (CMD's process
  group is terminated first), and starts none when ``PREFECT_API_URL`` is already set.
"""
from __future__ import annotations

import json
import os
import signal
import socket
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

REPO = Path(__file__).resolve().parents[1]


def _env(tmp_path: Path, **extra) -> dict:
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / ".prefect"), "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
           "DO_NOT_TRACK": "1", "OMP_NUM_THREADS": "1"}
    env.pop("PREFECT_API_URL", None)
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
json.dump({"api": os.environ.get("PREFECT_API_URL"), "pid": os.getpid()}, open(sys.argv[1] + ".tmp", "w"))
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
        port = int(seen["api"].split(":")[2].split("/")[0])
        # SIGTERM to typ with-server while the command runs: the command's group gets it, then the server stops
        os.kill(run.pid, signal.SIGTERM)
        out, _ = run.communicate(timeout=120)
        assert run.returncode == 128 + signal.SIGTERM, out
        assert not psutil.pid_exists(seen["pid"]) or psutil.Process(seen["pid"]).status() == psutil.STATUS_ZOMBIE
        psutil.wait_procs(server, timeout=30)
        assert not any(p.is_running() for p in server) and _port_free(port)
    finally:
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
