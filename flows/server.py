"""A local Prefect server for ``typ serve``, ``typ run all`` and ``typ with-server``: ``prefect
server start`` on loopback, sqlite in ``PREFECT_HOME``, analytics off; stopped by killing the
process group it was started in, on every way out of the code that started it.

Prefect is not imported here: it reads ``PREFECT_API_URL`` once, when first imported, so the
caller starts the server, exports its URL, and only then imports the flows.
"""
from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Iterator

from typ.errors import TypError

#: signals held while a server starts or stops (see :meth:`LocalServer.start`)
HELD_SIGNALS = {signal.SIGTERM, signal.SIGINT, signal.SIGHUP}
#: ``python -c`` program: unblock :data:`HELD_SIGNALS`, then exec ``python <its arguments>`` (same pid)
UNBLOCK_AND_EXEC = ("import os, signal, sys; signal.pthread_sigmask(signal.SIG_UNBLOCK, {%s}); "
                    "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])"
                    % ", ".join(f"signal.{s.name}" for s in sorted(HELD_SIGNALS)))


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class LocalServer:
    """One ``prefect server start`` child process in its own session (process group)."""

    def __init__(self, process: subprocess.Popen, host: str, port: int, log: Path):
        self.process, self.host, self.port, self.log = process, host, port, log

    @property
    def api_url(self) -> str:
        return f"http://{self.host}:{self.port}/api"

    @property
    def ui_url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @classmethod
    def start(cls, home: Path, *, host: str = "127.0.0.1", port: int | None = None, ui: bool = True,
              timeout: float = 120.0, env: dict | None = None) -> "LocalServer":
        """Start the server with its state (sqlite ``prefect.db``, logs) in ``home``; wait until healthy."""
        home = Path(home).resolve()
        home.mkdir(parents=True, exist_ok=True)
        port = port or free_port(host)
        with socket.socket() as s:
            if s.connect_ex((host, port)) == 0:
                raise TypError("typ serve", "--port", f"a free port on {host} (set PREFECT_API_URL to use the "
                               "server already there)", port)
        child_env = {**(env if env is not None else os.environ), "PREFECT_HOME": str(home),
                     "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1"}
        child_env.pop("PREFECT_API_URL", None)
        log = home / "server.log"
        # The child inherits the signal mask held below across fork and exec: unblock the held
        # signals before exec'ing prefect (a shim, not preexec_fn, which is unsafe beside threads).
        # Blocked, the server ignored SIGTERM and Ctrl-C: every stop waited out its grace for
        # SIGKILL, and pytest-xdist killed a worker stopping one in its cleanup, leaving it running.
        cmd = [sys.executable, "-c", UNBLOCK_AND_EXEC, "-m", "prefect", "server", "start", "--host", host,
               "--port", str(port), "--analytics-off", "--ui" if ui else "--no-ui"]
        # A signal that arrives between the fork and `server = ...` would leave a server nobody
        # knows about: hold SIGTERM/SIGINT until the handle exists, then stop it on any way out.
        # A signal held meanwhile is raised as the mask is restored, so the restore lies inside
        # the `try` that stops the server (restored in a `finally` before it, a SIGTERM sent while
        # the child started left that child running).
        held = signal.pthread_sigmask(signal.SIG_BLOCK, HELD_SIGNALS)
        try:
            with open(log, "ab") as out:
                proc = subprocess.Popen(cmd, env=child_env, stdout=out, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL, start_new_session=True)
        except BaseException:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
            raise
        server = cls(proc, host, port, log)
        try:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)
            server.wait_healthy(timeout)
        except BaseException:  # SIGTERM (as SystemExit), Ctrl-C, a failed start: no server left behind
            server.stop()
            raise
        return server

    def wait_healthy(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"prefect server exited with {self.process.returncode}; see {self.log}:\n"
                                   + self.log.read_text()[-2000:])
            try:
                with urllib.request.urlopen(f"{self.api_url}/health", timeout=2) as r:
                    if r.status == 200:
                        return
            except (urllib.error.URLError, OSError):
                pass
            time.sleep(0.5)
        self.stop()
        raise RuntimeError(f"prefect server not healthy after {timeout:.0f} s; see {self.log}")

    def stop(self, grace: float = 10.0) -> None:
        """SIGTERM the server's process group (uvicorn and its services), then SIGKILL what is left.
        A second SIGTERM or Ctrl-C meanwhile waits until the server is gone."""
        held = signal.pthread_sigmask(signal.SIG_BLOCK, HELD_SIGNALS)
        try:
            try:
                if self.process.poll() is None:
                    os.killpg(self.process.pid, signal.SIGTERM)
                    try:
                        self.process.wait(grace)
                    except subprocess.TimeoutExpired:
                        pass
                os.killpg(self.process.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.process.wait(grace)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, held)


@contextlib.contextmanager
def prefect_api(home: Path, *, host: str = "127.0.0.1", port: int | None = None, ui: bool = False,
                timeout: float = 300.0) -> Iterator[tuple[str, LocalServer | None]]:
    """``(PREFECT_API_URL, server)`` for everything started inside: the API the environment
    names (a server of the user's, Prefect Cloud: ``server`` is None), else a local server
    started here and stopped on the way out. ``PREFECT_API_URL`` is set while open."""
    given = os.environ.get("PREFECT_API_URL")
    if given:
        yield given, None
        return
    server = LocalServer.start(home, host=host, port=port, ui=ui, timeout=timeout)
    os.environ["PREFECT_API_URL"] = server.api_url
    try:
        yield server.api_url, server
    finally:
        os.environ.pop("PREFECT_API_URL", None)
        server.stop()


class Terminated(SystemExit):
    """SIGTERM or SIGHUP, raised in the main thread so that every ``finally`` runs."""


@contextlib.contextmanager
def terminate_raises() -> Iterator[None]:
    """While open, SIGTERM and SIGHUP raise :class:`Terminated` (exit status 128 + signal) instead
    of ending the process at once: servers and child processes started inside are stopped by
    the code that started them. Ctrl-C already raises KeyboardInterrupt."""
    def handler(signum, frame):
        raise Terminated(128 + signum)

    previous = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
