"""MLflow logging for stage runs: params (dotted names), metrics, artifacts, git commit.

The store is a sqlite database in the project (``sqlite:///mlruns.db``) unless
``MLFLOW_TRACKING_URI`` says otherwise; artifacts go beside it under ``mlartifacts/``.
A stage run started while ``TYP_PARENT_RUN_ID`` is set nests under that pipeline run.
Under ``dvc exp run`` each stage's run is tagged with the experiment's name and baseline
(``dvc.exp_name``, ``dvc.exp_baseline_rev``: DVC sets ``DVC_EXP_NAME`` / ``DVC_EXP_BASELINE_REV``
for stage commands), and a relative store resolves against the main repo (``DVC_ROOT``), so
experiments run in a temporary copy land in the project's store too. Under torchrun only
rank 0 logs; the other ranks get a handle that drops everything.
"""
from __future__ import annotations

import contextlib
import logging
import os
import re
import socket
import subprocess
import sys
import time
import warnings
from pathlib import Path
from typing import Iterator

from typ.config import Config, flatten, as_dict
from typ.io import hash_obj, hidden_below

PARENT_ENV = "TYP_PARENT_RUN_ID"
log = logging.getLogger(__name__)


#: environment DVC sets for a stage command during `dvc exp run` -> the MLflow tag it becomes
DVC_EXP_TAGS = {"DVC_EXP_NAME": "dvc.exp_name", "DVC_EXP_BASELINE_REV": "dvc.exp_baseline_rev"}


def tracking_uri(cfg: Config, root: Path) -> str:
    uri = os.environ.get("MLFLOW_TRACKING_URI") or cfg.tracking.uri
    prefix = "sqlite:///"
    if uri.startswith(prefix) and not uri[len(prefix):].startswith("/"):
        base = Path(os.environ.get("DVC_ROOT") or root)
        uri = prefix + str((base / uri[len(prefix):]).resolve())
    return uri


def git_commit(root: Path) -> str:
    """HEAD's hash, with ``-dirty`` when tracked files changed; ``unknown`` outside git."""
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, check=True).stdout.strip()
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _experiment_id(client, name: str, root: Path) -> str:
    exp = client.get_experiment_by_name(name)
    if exp is not None:
        return exp.experiment_id
    try:
        return client.create_experiment(name, artifact_location=(root / "mlartifacts").resolve().as_uri())
    except Exception:  # another process created it first
        return client.get_experiment_by_name(name).experiment_id


def is_main_process() -> bool:
    """True unless this is a torchrun rank other than 0. Asked without importing torch: a
    process that never loaded :mod:`typ.distributed` (the per-scene stages) is alone."""
    dist = sys.modules.get("typ.distributed")
    return dist is None or dist.is_main()


#: run tags that say which process a run belongs to, so a later stage can tell that it died
PID_TAG, HOST_TAG, STARTED_TAG = "typ.pid", "typ.host", "typ.pid_started"
#: run tag: seconds from entering :func:`stage_run` to the run's creation (MLflow's start-up cost)
START_TAG = "typ.mlflow_start_s"


def _process_tags() -> dict[str, str]:
    return {PID_TAG: str(os.getpid()), HOST_TAG: socket.gethostname(), STARTED_TAG: f"{_started(os.getpid())}"}


def _started(pid: int) -> float | None:
    """When process ``pid`` started (s since the epoch, as psutil gives it); None when no such process."""
    import psutil

    try:
        return round(psutil.Process(pid).create_time(), 2)
    except (psutil.NoSuchProcess, psutil.ZombieProcess):
        return None
    except psutil.Error:  # alive but not ours to inspect
        return -1.0


def process_gone(tags: dict[str, str]) -> bool:
    """Whether the process a run's tags name has ended: same host, and no process with that pid,
    or one started at another time (the pid was reused). Runs without the tags (from before
    typ recorded them) and runs of other hosts are never judged gone: nobody here can know."""
    if tags.get(HOST_TAG) != socket.gethostname() or not tags.get(PID_TAG, "").isdigit():
        return False
    started = _started(int(tags[PID_TAG]))
    if started is None:
        return True
    recorded = tags.get(STARTED_TAG, "None")
    return started != -1.0 and recorded != "None" and abs(started - float(recorded)) > 0.05


def mark_killed_runs(client, experiment_id: str, stage: str) -> list[str]:
    """Set the RUNNING runs of ``stage`` whose process is gone (kill -9, a power cut) to KILLED;
    returns their ids. A killed process cannot end its own run, and the UI would show it
    running forever."""
    stale = []
    runs = client.search_runs([experiment_id], filter_string=f"tags.`typ.stage` = '{stage}' "
                              "and attributes.status = 'RUNNING'", max_results=1000)
    for run in runs:
        if process_gone(run.data.tags):
            client.set_tag(run.info.run_id, "typ.killed", f"process {run.data.tags[PID_TAG]} on "
                           f"{run.data.tags[HOST_TAG]} ended without closing its run (seen {time.ctime()})")
            client.set_terminated(run.info.run_id, status="KILLED")
            log.warning("MLflow run %s of %s: its process %s is gone; marked KILLED", run.info.run_id, stage,
                        run.data.tags[PID_TAG])
            stale.append(run.info.run_id)
    return stale


@contextlib.contextmanager
def stage_run(stage: str, cfg: Config, *, root: Path | str = ".", tags: dict[str, str] | None = None
              ) -> Iterator["StageRun"]:
    """One MLflow run for one stage execution: params of the stage's block, tags (typ's, then
    ``tags``), then the body.

    Before it starts, earlier runs of the stage that a killed process left RUNNING are marked
    KILLED (:func:`mark_killed_runs`); a body ended by SIGTERM or Ctrl-C ends its run KILLED.
    """
    if not is_main_process():
        yield NullRun()
        return
    t0 = time.perf_counter()
    import mlflow
    from mlflow.tracking import MlflowClient

    root = Path(root)
    uri = tracking_uri(cfg, root)
    mlflow.set_tracking_uri(uri)
    client = MlflowClient(uri)
    exp_id = _experiment_id(client, cfg.tracking.experiment, root)
    mark_killed_runs(client, exp_id, stage)
    block = cfg.block(stage) if stage in cfg.STAGES else cfg
    params = {f"{stage}.{k}": v for k, v in flatten(block).items()} if stage in cfg.STAGES else flatten(block)
    tags = {
        "typ.stage": stage,
        "typ.profile": cfg.profile,
        "typ.params_hash": hash_obj(as_dict(block))[:16],
        "mlflow.source.git.commit": git_commit(root),
        "mlflow.runName": stage,
        "dvc.stage": stage,
        **_process_tags(),
        **{tag: os.environ[env] for env, tag in DVC_EXP_TAGS.items() if os.environ.get(env)},
        **(tags or {}),
    }
    active = mlflow.active_run()
    parent = active.info.run_id if active is not None else os.environ.get(PARENT_ENV)
    if parent:
        tags["mlflow.parentRunId"] = parent
    # what MLflow costs a stage before its work starts (import, store, the stale-run check)
    tags[START_TAG] = f"{time.perf_counter() - t0:.3f}"
    # the client, not mlflow.start_run: that one also resolves every context provider (GitPython,
    # notebooks, Databricks), a few tenths of a second per stage for tags typ sets itself
    run = client.create_run(exp_id, run_name=stage, tags=tags)
    run_id = run.info.run_id
    from mlflow.entities import Param

    client.log_batch(run_id, params=[Param(k, _short(v)) for k, v in {**params, "profile": cfg.profile}.items()],
                     synchronous=True)
    # system metrics (CPU, memory, disk, network; GPU with pynvml) every
    # MLFLOW_SYSTEM_METRICS_SAMPLING_INTERVAL seconds from a thread, offline, where
    # MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING says (the flow runner turns it on for training stages);
    # their start/stop INFO lines would be all a stage prints
    logging.getLogger("mlflow.system_metrics").setLevel(logging.WARNING)
    # active for this thread, so that mlflow's fluent calls (log_model) and nested stages see it
    with mlflow.start_run(run_id=run_id, nested=active is not None):
        try:
            yield StageRun(mlflow, run_id)
        except (KeyboardInterrupt, SystemExit):
            mlflow.end_run("KILLED")
            raise


def stage_seconds(metrics: dict) -> float | None:
    """The seconds of work a stage reports: ``seconds_total``, else ``seconds_training``, else the
    sum of the ``seconds_training`` of its blocks (one per model or seed); None where it reports none."""
    for key in ("seconds_total", "seconds_training"):
        if isinstance(metrics.get(key), (int, float)):
            return float(metrics[key])
    nested = [stage_seconds(v) for v in metrics.values() if isinstance(v, dict)]
    nested = [s for s in nested if s is not None]
    return float(sum(nested)) if nested else None


class StageRun:
    """Thin handle so tasks never import mlflow themselves.

    Logs through the client with an explicit run id, so it works from Prefect's worker
    threads too (mlflow's active run is thread-local).
    """

    def __init__(self, mlflow, run_id: str):
        from mlflow.tracking import MlflowClient

        self._mlflow = mlflow
        self._client = MlflowClient()
        self.run_id = run_id
        #: when the stage's run began (perf_counter): the wall time of a stage that times no work itself
        self.started = time.perf_counter()

    def metrics(self, values: dict[str, float], step: int | None = None) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        clean = [Metric(metric_name(k), float(v), now, step or 0) for k, v in values.items()
                 if isinstance(v, (int, float)) and not isinstance(v, bool)]
        if clean:
            self._client.log_batch(self.run_id, metrics=clean, synchronous=True)

    def artifact(self, path: str | Path, subdir: str | None = None) -> None:
        path = Path(path)
        if path.is_dir():
            self._client.log_artifacts(self.run_id, str(path), artifact_path=subdir)
        elif path.exists():
            self._client.log_artifact(self.run_id, str(path), artifact_path=subdir)


    def log_image(self, image, artifact_file: str) -> None:
        """An image (H, W, 3|4) uint8 or float in [0, 1], or a PIL image, as ``artifact_file`` (.png)."""
        self._client.log_image(self.run_id, _image(image), artifact_file=artifact_file)

    def log_figure(self, fig, artifact_file: str) -> None:
        """A matplotlib Figure (e.g. from :mod:`typ.viz`) as ``artifact_file`` (.png), at its own dpi."""
        self._client.log_figure(self.run_id, fig, artifact_file, save_kwargs={"dpi": fig.dpi})

    def log_table(self, rows, artifact_file: str) -> None:
        """Per-sample scores as an MLflow table (``artifact_file`` .json), which the UI can sort and
        filter: ``rows`` a list of {column: value} dicts (columns in order of first appearance) or
        {column: values}."""
        self._client.log_table(self.run_id, table_frame(rows), artifact_file)

    def log_input(self, path: str | Path, *, context: str, root: str | Path = ".", name: str | None = None,
                  digest: str | None = None) -> None:
        """Record a folder or file the stage read as an MLflow dataset input (the run's Datasets).

        context: its role, e.g. ``train`` / ``eval``; name: default ``path`` relative to ``root``;
        digest: default :func:`listing_digest` (file names and sizes: cheap, not a content hash;
        pass e.g. the md5 from dvc.lock for one). The profile holds the file and byte counts.
        """
        from mlflow.entities import DatasetInput, InputTag

        self._client.log_inputs(self.run_id, [DatasetInput(dataset_entity(path, root=root, name=name, digest=digest),
                                                           [InputTag("mlflow.data.context", context)])])

    def log_model(self, name: str, module, inputs, *, output: str | None = None) -> str:
        """Log a trained torch module as an MLflow model with a signature; returns its URI.

        ``inputs``: an example batch, one tensor or ``{argument name: tensor}`` for a module
        called with keywords; ``output``: the attribute of the module's output that holds the
        result tensor (e.g. ``"logits"``), when the output is not a tensor itself. The module is
        run once on ``inputs`` to infer the signature. Load it back with
        ``mlflow.pyfunc.load_model(uri).predict({name: array, ...})``; the module itself is
        ``.unwrap_python_model().module``.
        """
        import mlflow
        from mlflow.models import infer_signature

        from typ.mlflow_model import TorchModule, pip_requirements

        wrapper = TorchModule(module, output=output)
        named = inputs if isinstance(inputs, dict) else {"input": inputs}
        example = {k: v.detach().cpu().numpy() for k, v in named.items()}
        signature = infer_signature(example, wrapper.predict(None, example))
        active = self._mlflow.active_run()
        resume = active is None or active.info.run_id != self.run_id
        with (self._mlflow.start_run(run_id=self.run_id, nested=active is not None) if resume
              else contextlib.nullcontext()), warnings.catch_warnings():
            # no input example on purpose (a paper-scale x is 20 MB); the signature has the shapes
            warnings.filterwarnings("ignore", message=".*(input example|type hints).*", category=UserWarning)
            info = mlflow.pyfunc.log_model(name=name, python_model=wrapper, signature=signature,
                                           pip_requirements=pip_requirements())
        return info.model_uri


class NullRun:
    """What a torchrun rank other than 0 logs to: nothing."""

    run_id = ""

    def metrics(self, values: dict[str, float], step: int | None = None) -> None:
        pass

    def artifact(self, path: str | Path, subdir: str | None = None) -> None:
        pass

    def log_model(self, name: str, module, inputs, *, output: str | None = None) -> str:
        return ""

    def log_image(self, image, artifact_file: str) -> None:
        pass

    def log_figure(self, fig, artifact_file: str) -> None:
        pass

    def log_table(self, rows, artifact_file: str) -> None:
        pass

    def log_input(self, path, *, context: str, root=".", name=None, digest=None) -> None:
        pass


def metric_name(name: str) -> str:
    """``name`` with what MLflow refuses in metric names (``dpmsolver++``'s ``+``) replaced by ``_``."""
    return _NOT_IN_METRIC_NAMES.sub("_", name)


_NOT_IN_METRIC_NAMES = re.compile(r"[^\w\-. :/]")


def _short(value) -> str:
    text = str(value)
    return text if len(text) <= 500 else text[:497] + "..."


def _image(image):
    """An ndarray for MLflow: uint8 as it is, floats clipped to [0, 1] (MLflow refuses others)."""
    import numpy as np

    if not isinstance(image, np.ndarray):
        return image
    if image.dtype.kind == "f":
        return np.clip(np.nan_to_num(image), 0.0, 1.0)
    return image


def table_frame(rows):
    """A pandas DataFrame from rows ({column: value} dicts, columns in order of first appearance)
    or from {column: values}."""
    import pandas as pd

    if isinstance(rows, dict):
        return pd.DataFrame(rows)
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns]
    return pd.DataFrame([[row.get(k) for k in columns] for row in rows], columns=columns)


def listing_digest(path: str | Path) -> tuple[str, dict]:
    """(16-hex digest of the sorted (relative name, size) of every file under ``path``, profile).

    Reads no file content, so it costs one directory walk; a file edited in place to the same
    size keeps the digest. Hidden files and typ's temporaries are skipped.
    """
    path = Path(path)
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file()
                                                 and not hidden_below(p, path))
    listing = [(p.name if p == path else str(p.relative_to(path)), p.stat().st_size) for p in files]
    return hash_obj(listing)[:16], {"files": len(listing), "bytes": sum(size for _, size in listing)}


def dataset_entity(path: str | Path, *, root: str | Path = ".", name: str | None = None, digest: str | None = None):
    """The :class:`mlflow.entities.Dataset` :meth:`StageRun.log_input` records for ``path``."""
    import json

    from mlflow.entities import Dataset

    path, root = Path(path), Path(root)
    if not path.exists():
        from typ.errors import TypError

        raise TypError(path, "dataset", "a file or folder the stage read", "missing")
    listed, profile = listing_digest(path)
    try:
        default_name = str(path.resolve().relative_to(root.resolve()))
    except ValueError:
        default_name = str(path)
    return Dataset(name=name or default_name, digest=digest or listed, source_type="local",
                   source=json.dumps({"uri": path.resolve().as_uri()}), profile=json.dumps(profile))
