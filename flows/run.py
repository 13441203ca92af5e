"""How a typ command runs its flows: the environment (:func:`setup_env`), ``typ run``
(:func:`run_command`: the Prefect API, settling an unchanged per-scene stage before Prefect is
imported, the device), ``typ with-server`` (:func:`with_server`, :func:`run_child`) and the
quiet tracebacks of bad input. The CLI parses the arguments and calls these; nothing here
imports Prefect, MLflow or torch before a command needs them.
"""
from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
from pathlib import Path

from typ.config import Config
from typ.errors import TypError
from typ.hashcache import ENV as HASH_CACHE_ENV

STAGES = Config.STAGES

#: loggers of typ's own code (typ.*, tasks.*), included in Prefect's logging by :func:`setup_env`
STAGE_LOGGERS = ("typ", "tasks")


def setup_env(root: Path) -> None:
    """The environment every typ command runs its flows in: Prefect's home and settings inside the
    project, MLflow and DVC offline, the input-hash cache, typ's loggers in Prefect's, and the
    project's API secret for every Prefect server the process tree starts."""
    # Prefect keeps its state inside the project and runs without a server by default.
    os.environ.setdefault("PREFECT_HOME", str((root / ".prefect").resolve()))
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    # MLflow takes DO_NOT_TRACK only as "true": without this, every stage process fetches a
    # telemetry config from the internet and posts usage records at exit (a second, offline)
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    # the ephemeral API server's 20 s default start-up limit is missed on a loaded 2-core machine
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")
    os.environ.setdefault("DVC_NO_ANALYTICS", "1")
    # input hashes of unchanged files, keyed by their stat (typ.hashcache): a no-op stage reads nothing
    os.environ.setdefault(HASH_CACHE_ENV, str((root / ".typ" / "hashes.sqlite").resolve()))
    # the stage code's loggers go to the Prefect API with the flow run's (its UI shows them);
    # outside a run they stay local without Prefect's "no flow run" warning
    extra = [n for n in os.environ.get("PREFECT_LOGGING_EXTRA_LOGGERS", "").split(",") if n.strip()]
    os.environ["PREFECT_LOGGING_EXTRA_LOGGERS"] = ",".join(extra + [n for n in STAGE_LOGGERS if n not in extra])
    os.environ.setdefault("PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW", "ignore")
    if not os.environ.get("PREFECT_API_URL") and "prefect" not in sys.modules:
        # every Prefect server this process tree starts (a local one, Prefect's temporary one)
        # asks for the project's secret and every client sends it; a server that PREFECT_API_URL
        # names is the user's, with the user's auth. Prefect reads its settings once, when
        # imported: after that (typ called in-process) its client would not send what its
        # temporary server, started later with this environment, asks for
        from flows.server import api_auth_string, bind_temporary_servers

        auth = api_auth_string(Path(os.environ["PREFECT_HOME"]))
        os.environ["PREFECT_SERVER_API_AUTH_STRING"] = os.environ["PREFECT_API_AUTH_STRING"] = auth
        bind_temporary_servers()   # and a kill -9 of this process ends its temporary server too
    rank = int(os.environ.get("RANK", "0"))
    if rank > 0:  # torchrun: each rank's temporary Prefect server keeps its own sqlite file
        os.environ["PREFECT_HOME"] = str(Path(os.environ["PREFECT_HOME"]) / f"rank-{rank}")


class _BadInputWithoutTraceback(logging.Filter):
    """Prefect's engine logs a failed flow or task with its traceback. For bad input (TypError)
    the message is the whole story, and the CLI prints it as its last line: drop the traceback."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.exc_info and isinstance(record.exc_info[1], TypError):
            record.exc_info, record.exc_text = None, None
        return True


def quiet_bad_input_tracebacks() -> None:
    """Install :class:`_BadInputWithoutTraceback` on Prefect's run loggers (once)."""
    for name in ("prefect.flow_runs", "prefect.task_runs"):
        logger = logging.getLogger(name)
        if not any(isinstance(f, _BadInputWithoutTraceback) for f in logger.filters):
            logger.addFilter(_BadInputWithoutTraceback())


def settled_before_prefect(stage: str) -> bool:
    """Whether ``typ run <stage>`` first tries to settle it without Prefect: a per-scene stage that
    needs no torch (the stage registry says), whose every scene may be unchanged."""
    from typ.registry import STAGES as REGISTERED

    spec = REGISTERED[stage]
    return spec.kind == "per-scene" and not spec.torch


def run_command(stage: str, *, params: str, root: Path, runner: str = "thread", address: str | None = None) -> int:
    """``typ run <stage>`` (or ``all``): the params checked before Prefect starts, the Prefect API,
    a per-scene stage settled without Prefect when every scene is unchanged, the device for the
    stages that use torch, then the stage's flow (or the pipeline's). Returns the exit status."""
    root = Path(root)
    if stage != "all" and stage not in STAGES:
        raise TypError("typ run", "stage", f"one of {['all', *STAGES]}", stage)
    from typ.config import load_config

    cfg = load_config(root / params)  # fail on bad params before Prefect starts
    setup_env(root)
    from flows.server import prefect_api, terminate_raises

    # `all`: one Prefect API for every stage (a local server unless PREFECT_API_URL names one);
    # one stage: the API the environment names, else Prefect's temporary server for this process
    with terminate_raises(), (prefect_api(Path(os.environ["PREFECT_HOME"])) if stage == "all"
                              else contextlib.nullcontext()):
        if stage != "all" and runner == "thread" and not address and settled_before_prefect(stage):
            from flows.common import settle_stage

            # every scene unchanged: logged to MLflow, done before Prefect is even imported
            if settle_stage(stage, params=params, root=root) is not None:
                return 0
        from flows.pipeline import WITHOUT_TORCH, pipeline_flow, run_stage

        uses_torch = stage not in WITHOUT_TORCH
        if uses_torch:  # a per-scene stage that never touches torch does not pay for importing it
            from typ import distributed

            distributed.setup(cfg.runtime.device, cfg.runtime.precision, where=cfg.source)
        quiet_bad_input_tracebacks()
        try:
            if stage == "all":
                pipeline_flow(params=params, root=str(root), task_runner=runner, address=address)
            else:
                run_stage(stage, params=params, root=str(root), task_runner=runner,
                          address=address)
        finally:
            if uses_torch:
                distributed.teardown()
    return 0


def with_server(cmd: list[str], *, root: Path) -> int:
    """``typ with-server COMMAND``: one Prefect API (a local server unless PREFECT_API_URL names
    one) for ``cmd`` and every typ process it starts; ``cmd``'s exit status."""
    if not cmd:
        raise TypError("typ with-server", "COMMAND", "a command to run, e.g. `typ with-server dvc repro`", "nothing")
    root = Path(root).resolve()
    setup_env(root)
    from flows.server import prefect_api, terminate_raises

    with terminate_raises(), prefect_api(Path(os.environ["PREFECT_HOME"])) as (url, server):
        if server is not None:
            print(f"typ: Prefect server {url} for `{' '.join(cmd)}` (log {server.log}, API secret in "
                  f"{server.auth_file})", file=sys.stderr, flush=True)
        return run_child(cmd)


def run_child(cmd: list[str], *, grace: float = 60.0) -> int:
    """Run ``cmd`` in its own process group and return its exit status (128 + signal when a
    signal ended it). When this process is interrupted (Ctrl-C, SIGTERM), the whole group gets
    the signal (dvc and the stage it runs), then SIGKILL after ``grace`` seconds."""
    try:
        proc = subprocess.Popen(cmd, start_new_session=True)
    except OSError as exc:
        raise TypError("typ with-server", "COMMAND", "a program on PATH", f"{cmd[0]}: {exc.strerror}") from None
    try:
        rc = proc.wait()
    except BaseException as exc:
        sig = signal.SIGINT if isinstance(exc, KeyboardInterrupt) else signal.SIGTERM
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        raise
    return 128 - rc if rc < 0 else rc
