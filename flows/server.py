"""A local Prefect server for ``typ serve``, ``typ run all`` and ``typ with-server``: ``prefect
server start`` on loopback, sqlite in ``PREFECT_HOME``, analytics off, basic auth with the
project's secret (:func:`api_auth_string`); stopped by killing the process group it was started
in, on every way out of the code that started it.

A ``kill -9`` of typ runs no code of typ's, so each server typ starts, this one and the temporary
server Prefect starts by itself in a process without ``PREFECT_API_URL``
(:func:`bind_temporary_servers`), is started to die with the typ process that started it
(:func:`start_bound`: Linux's parent-death signal). The Dask workers of ``--runner dask`` need
nothing of typ's: distributed ends each worker process whose parent is gone.

Prefect is not imported here: it reads ``PREFECT_API_URL`` once, when first imported, so the
caller starts the server, exports its URL, and only then imports the flows.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import importlib.abc
import importlib.util
import os
import queue
import secrets
import signal
import socket
import stat
import subprocess
import sys
import threading
import time
import types
import urllib.error
import urllib.request
from pathlib import Path
from typing import Callable, Iterator, TypeVar

from typ.errors import TypError
from typ.io import TMP_PREFIX

#: signals held while a server starts or stops (see :func:`signals_held`)
HELD_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Defer :data:`HELD_SIGNALS` until the block ends, then hand each one that came meanwhile to
    the handler it would have met (first come, first handled; ``Terminated`` or KeyboardInterrupt
    is raised there, after the code inside has finished).

    A Python-level deferral, not a signal mask: ``pthread_sigmask`` blocks the calling thread only,
    and the kernel hands a process-directed SIGTERM to any thread that does not block it (a
    pytest-xdist worker runs execnet's threads, a user's process may run others). Python runs
    handlers in the main thread whichever thread took the signal, so the mask let ``Terminated``
    out between the fork and ``server = ...`` and left that server running. Ignored signals stay
    ignored; outside the main thread (where Python runs no handlers) nothing is changed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    came: list[int] = []
    previous: dict[int, object] = {}
    try:
        for s in HELD_SIGNALS:
            if signal.getsignal(s) not in (signal.SIG_IGN, None):
                previous[s] = signal.signal(s, lambda signum, frame: came.append(signum))
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        for s in dict.fromkeys(came):
            handler = previous[s]
            if callable(handler):
                handler(s, None)
            else:   # SIG_DFL: end the process as the signal would have
                signal.raise_signal(s)


#: what a bound child runs first (``python -c _BIND PARENT_PID CMD...``): it asks Linux for SIGTERM
#: when the thread that forked it ends (``PR_SET_PDEATHSIG`` = 1; the request survives exec and
#: covers ``kill -9`` of the parent), gives up if that parent is already gone, then becomes CMD
_BIND = """\
import ctypes, os, signal, sys
if ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM, 0, 0, 0) != 0:
    raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG)")
if os.getppid() != int(sys.argv[1]):
    sys.exit(1)
os.execvp(sys.argv[2], sys.argv[2:])
"""

T = TypeVar("T")


class _Spawner:
    """Runs each ``start()`` in one daemon thread that lives as long as this process does.

    Linux sends the parent-death signal when the *thread* that forked the child ends, not the
    process: a server forked by a thread that ends before the process (a task runner's, Prefect's
    events worker, which may be the first to start Prefect's temporary server) would be stopped
    with that thread. A daemon thread ends only with the process."""

    def __init__(self):
        self._lock = threading.Lock()
        self._owner: int | None = None   # the process whose thread serves ``_jobs``: a fork has none
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        os.register_at_fork(after_in_child=self._forked)

    def __call__(self, start: Callable[[], T]) -> T:
        with self._lock:
            if self._owner != os.getpid():
                self._jobs = queue.SimpleQueue()
                threading.Thread(target=self._serve, args=(self._jobs,), name="typ-server-spawner",
                                 daemon=True).start()
                self._owner = os.getpid()
        done: concurrent.futures.Future = concurrent.futures.Future()
        self._jobs.put((start, done))
        return done.result()

    def _forked(self) -> None:
        self._lock = threading.Lock()   # a fork while another thread held it would keep it held

    @staticmethod
    def _serve(jobs: queue.SimpleQueue) -> None:
        while True:
            start, done = jobs.get()
            try:
                done.set_result(start())
            except BaseException as exc:  # handed to the caller, whatever it is
                done.set_exception(exc)


_spawn = _Spawner()


def bound_command(cmd: list[str]) -> list[str]:
    """``cmd`` run so that it gets SIGTERM when this process ends, by ``kill -9`` too (:data:`_BIND`);
    ``cmd`` itself where Linux's ``prctl`` is missing."""
    if not sys.platform.startswith("linux"):
        return list(cmd)
    return [sys.executable, "-I", "-S", "-c", _BIND, str(os.getpid()), *cmd]


def start_bound(args: list[str], **popen_kwargs) -> subprocess.Popen:
    """``subprocess.Popen(args, **popen_kwargs)`` (its signature: Prefect passes ``args=``) of a child
    that gets SIGTERM when this process ends, ``kill -9`` included (:func:`bound_command`), forked by a
    thread that lasts as long as the process (:class:`_Spawner`). The Popen is what it would be for
    ``args``: same pid once the child runs ``args``, same exit status, same signals."""
    return _spawn(lambda: subprocess.Popen(bound_command(args), **popen_kwargs))


class _BoundSubprocess(types.ModuleType):
    """The ``subprocess`` module as Prefect's server module sees it once bound: its ``Popen`` starts
    the child with :func:`start_bound`; everything else is the real module's."""

    def __init__(self):
        super().__init__("subprocess")
        self.Popen = start_bound

    def __getattr__(self, name: str):
        return getattr(subprocess, name)


#: Prefect's module whose ``SubprocessASGIServer`` starts the temporary server (uvicorn, a child
#: process) when a client finds no ``PREFECT_API_URL``; it starts it with its module's ``subprocess.Popen``
TEMPORARY_SERVER_MODULE = "prefect.server.api.server"


def bind_temporary_servers() -> None:
    """Make the temporary server Prefect starts by itself in this process die with this process.

    Prefect's ``SubprocessASGIServer`` starts uvicorn as a plain child and stops it at exit; a
    ``kill -9`` left it serving. Its module's ``subprocess`` is replaced by :class:`_BoundSubprocess`,
    so the command, environment and handling stay Prefect's own. Prefect must not be imported
    before ``PREFECT_API_URL`` is settled (it reads its settings once), so, when the module is not
    imported yet, this happens as it is imported (:class:`_AfterImport`)."""
    module = sys.modules.get(TEMPORARY_SERVER_MODULE)
    if module is not None:
        _bind_module(module)
    elif not any(isinstance(f, _AfterImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _AfterImport(TEMPORARY_SERVER_MODULE, _bind_module))


def _bind_module(module: types.ModuleType) -> None:
    if not isinstance(module.subprocess, _BoundSubprocess):
        module.subprocess = _BoundSubprocess()


class _AfterImport(importlib.abc.MetaPathFinder):
    """Calls ``then(module)`` once module ``name`` has been executed by its first import, before the
    importer gets it; then leaves ``sys.meta_path``."""

    def __init__(self, name: str, then: Callable[[types.ModuleType], None]):
        self.name, self.then = name, then

    def find_spec(self, fullname, path, target=None):
        if fullname != self.name:
            return None
        sys.meta_path.remove(self)   # once, and not met again by the search below
        spec = importlib.util.find_spec(fullname)
        if spec is not None and spec.loader is not None:
            execute, then = spec.loader.exec_module, self.then

            def exec_module(module):
                execute(module)
                then(module)

            spec.loader.exec_module = exec_module
        return spec


#: the file in ``PREFECT_HOME`` that holds the API secret of the servers typ starts
AUTH_FILE = "api-auth"
#: the user name in that secret: the UI and ``curl -u`` take ``user:password``
AUTH_USER = "typ"


def api_auth_string(home: Path) -> str:
    """The basic-auth string ``typ:<secret>`` that the Prefect servers typ starts with their state in
    ``home`` ask for (``PREFECT_SERVER_API_AUTH_STRING``) and their clients send
    (``PREFECT_API_AUTH_STRING``): without it any local user could start a stage, with parameters of
    their choosing, that runs as the owner of ``typ serve``.

    Kept in ``home/api-auth`` and the same on every run; made on first use under a temporary name
    opened with mode 0600 (never readable by others, not even while written) and linked into place,
    so that two first uses at once agree on one secret. Delete the file to rotate the secret."""
    path = Path(home) / AUTH_FILE
    if not path.exists():
        _new_secret(path)
    return _read_secret(path)


def _new_secret(path: Path) -> None:
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    tmp = path.with_name(f"{TMP_PREFIX}{path.name}.{os.getpid()}.{secrets.token_hex(4)}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "w") as out:
            out.write(f"{AUTH_USER}:{secrets.token_urlsafe(32)}\n")
            out.flush()
            os.fsync(out.fileno())
        with contextlib.suppress(FileExistsError):   # another typ made it first: its secret stands
            os.link(tmp, path)
    finally:
        tmp.unlink()


def _read_secret(path: Path) -> str:
    try:   # non-blocking: a FIFO in its place must not hang the start; a regular file reads as usual
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except OSError as exc:   # a dangling link, a folder without read permission
        raise TypError(path, "file", "a readable file holding the Prefect API secret", exc.strerror) from None
    with os.fdopen(fd) as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise TypError(path, "file", "a regular file holding the Prefect API secret", stat.filemode(st.st_mode))
        if st.st_uid != os.geteuid() or st.st_mode & 0o077:
            raise TypError(path, "mode", f"a file of yours only you can read: `chmod 600 {path}` (or delete it to "
                           "make a new secret)", f"{stat.filemode(st.st_mode)}, owner uid {st.st_uid}")
        secret = f.read(4096).strip()
    if not secret:
        raise TypError(path, "secret", "the Prefect API secret (delete the empty file to make a new one)", "")
    return secret


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class LocalServer:
    """One ``prefect server start`` child process in its own session (process group), asking every
    request but its health check for ``auth`` (basic auth)."""

    def __init__(self, process: subprocess.Popen, host: str, port: int, home: Path, auth: str):
        self.process, self.host, self.port, self.home, self.auth = process, host, port, home, auth

    @property
    def log(self) -> Path:
        return self.home / "server.log"

    @property
    def auth_file(self) -> Path:
        return self.home / AUTH_FILE

    @property
    def api_url(self) -> str:
        return f"http://{self.host}:{self.port}/api"

    @property
    def client_env(self) -> dict[str, str]:
        """What a Prefect client needs in its environment to use this server."""
        return {"PREFECT_API_URL": self.api_url, "PREFECT_API_AUTH_STRING": self.auth}

    @property
    def ui_url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @classmethod
    @contextlib.contextmanager
    def running(cls, home: Path, *, host: str = "127.0.0.1", port: int | None = None, ui: bool = True,
                timeout: float = 120.0, env: dict | None = None) -> Iterator["LocalServer"]:
        """A server with its state (sqlite ``prefect.db``, logs) in ``home``, healthy while open and
        stopped on every way out, a SIGTERM at any moment included: the handle is assigned inside
        the `try` that stops it (a ``start`` that returned the server left a gap before the
        caller's own `try`)."""
        server = None
        try:
            with signals_held():
                server = cls._launch(home, host=host, port=port, ui=ui, env=env)
            server.wait_healthy(timeout)
            yield server
        finally:
            if server is not None:
                drain_prefect_services()
                server.stop()

    @classmethod
    def _launch(cls, home: Path, *, host: str, port: int | None, ui: bool, env: dict | None) -> "LocalServer":
        """Fork ``prefect server start`` in its own session; not yet healthy. The caller holds the
        signals (:func:`signals_held`) until it holds the handle this returns: a signal between the
        fork and ``server = ...`` would leave a server nobody knows about."""
        home = Path(home).resolve()
        home.mkdir(mode=0o700, parents=True, exist_ok=True)
        auth = api_auth_string(home)
        port = port or free_port(host)
        with socket.socket() as s:
            if s.connect_ex((host, port)) == 0:
                raise TypError("typ serve", "--port", f"a free port on {host} (set PREFECT_API_URL to use the "
                               "server already there)", port)
        child_env = {**(env if env is not None else os.environ), "PREFECT_HOME": str(home),
                     "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DO_NOT_TRACK": "1",
                     "MLFLOW_DISABLE_TELEMETRY": "true",
                     # the server asks for it; its own services are clients of its API
                     "PREFECT_SERVER_API_AUTH_STRING": auth, "PREFECT_API_AUTH_STRING": auth}
        child_env.pop("PREFECT_API_URL", None)
        cmd = [sys.executable, "-m", "prefect", "server", "start", "--host", host, "--port", str(port),
               "--analytics-off", "--ui" if ui else "--no-ui"]
        with open(home / "server.log", "ab") as out:
            # its own session: stop() ends its group; bound: a kill -9 of this process ends it too
            process = start_bound(cmd, env=child_env, stdout=out, stderr=subprocess.STDOUT,
                                  stdin=subprocess.DEVNULL, start_new_session=True)
        return cls(process, host, port, home, auth)

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
        with signals_held():
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


@contextlib.contextmanager
def prefect_api(home: Path, *, host: str = "127.0.0.1", port: int | None = None, ui: bool = False,
                timeout: float = 300.0) -> Iterator[tuple[str, LocalServer | None]]:
    """``(PREFECT_API_URL, server)`` for everything started inside: the API the environment
    names (a server of the user's, Prefect Cloud: ``server`` is None, and its auth is the user's
    business), else a local server started here and stopped on the way out. While open,
    ``PREFECT_API_URL`` and that server's ``PREFECT_API_AUTH_STRING`` are set."""
    given = os.environ.get("PREFECT_API_URL")
    if given:
        yield given, None
        return
    with LocalServer.running(home, host=host, port=port, ui=ui, timeout=timeout) as server, \
            scoped_environ(server.client_env):
        yield server.api_url, server


@contextlib.contextmanager
def scoped_environ(values: dict[str, str], *, keep_set: bool = False) -> Iterator[None]:
    """``values`` in ``os.environ`` for the block's duration, then each variable as it was (unset
    or its previous value). ``keep_set``: a variable the environment already sets keeps its value
    (``values`` are defaults)."""
    if keep_set:
        values = {k: v for k, v in values.items() if k not in os.environ}
    previous = {k: os.environ.get(k) for k in values}
    try:
        os.environ.update(values)
        yield
    finally:
        for k, v in previous.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def drain_prefect_services(timeout: float = 10.0) -> None:
    """Deliver what Prefect's background services of this process still queue (events, API logs)
    while their server is up, and stop them; the next flow starts fresh ones against the API of
    its time. A server stopped first leaves them retrying its closed port at exit (7 s an event,
    each then lost), and a later flow's events go to the dead port too: the services keep the URL
    they started with. Nothing to do where Prefect was never imported."""
    for module, service in (("prefect.events.worker", "EventsWorker"), ("prefect.logging.handlers", "APILogWorker")):
        if module in sys.modules:
            getattr(sys.modules[module], service).drain_all(timeout=timeout, at_exit=False)


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
