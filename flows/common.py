"""What every stage flow shares: config + MLflow run, per-scene fan-out with a progress bar,
metrics written for DVC.

Prefect is imported where it is used, not here: :func:`settle_unchanged` runs before it is."""
from __future__ import annotations

import contextlib
import functools
import importlib
import os
import logging
import re
import sys
import time
from pathlib import Path
from typing import Callable, Iterator, Sequence

from tasks.scene_stage import SceneStage
from typ.config import Config, load_config
from typ.errors import TypError
from typ.io import output_lock, remove_stale_temporaries, remove_written, temporaries, write_json, written_by
from typ.tracking import is_main_process, stage_run, stage_seconds

log = logging.getLogger("typ")


#: retries of a per-scene task after a transient I/O error (backoff 1 s, then 4 s)
IO_RETRIES = 2


class StageFailed(RuntimeError):
    """A per-scene task failed; the message names the stage and the scene."""


def per_scene(fn: Callable, items: Sequence, *, label: Callable[[object], str], stage: str,
              retries: int = 0, **kwargs) -> list:
    """Run ``fn(item, **kwargs)`` for every item as Prefect tasks, with a rich progress bar.

    Results come back in ``items`` order. A failing item stops the stage with its name in
    the error; bad input (TypError) is deterministic, so it is never retried. Where each item
    ran (a Dask worker's address, or ``thread``) is logged at INFO.
    """
    from prefect import task
    from prefect.cache_policies import NO_CACHE
    from prefect.futures import as_completed
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    @functools.wraps(fn)
    def placed(item, **kw):
        return fn(item, **kw), worker_address()

    wrapped = task(placed, name=f"{stage}-scene", retries=retries, retry_delay_seconds=[1, 4, 16][:retries],
                   retry_condition_fn=_retry_unless_bad_input, cache_policy=NO_CACHE, log_prints=False)
    futures = {wrapped.with_options(task_run_name=f"{stage}-{label(item)}").submit(item, **kwargs): i
               for i, item in enumerate(items)}
    results: list = [None] * len(items)
    with Progress(TextColumn(f"[bold]{stage}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TextColumn("{task.description}"), transient=False) as bar:
        job = bar.add_task("", total=len(items))
        for fut in as_completed(list(futures)):
            i = futures[fut]
            try:
                results[i], where = fut.result()
                log.info("%s: %s ran on %s", stage, label(items[i]), where)
            except TypError:
                raise
            except Exception as exc:
                raise StageFailed(f"{stage}: scene {label(items[i])} failed: {type(exc).__name__}: {exc}") from exc
            bar.update(job, advance=1, description=label(items[i]))
    return results


def worker_address() -> str:
    """The address of the Dask worker running the calling task, or ``thread`` outside Dask."""
    if "distributed" not in sys.modules:  # a Dask worker has it loaded; importing it costs 0.3 s
        return "thread"
    try:
        from distributed import get_worker
        return str(get_worker().address)
    except (ImportError, ValueError):
        return "thread"


#: OSErrors that say the input is wrong, not that the disk, network or worker hiccuped
DETERMINISTIC_OS_ERRORS = (FileNotFoundError, FileExistsError, IsADirectoryError, NotADirectoryError,
                           PermissionError)


def _retry_unless_bad_input(task, task_run, state) -> bool:
    """Retry transient I/O failures only: an OSError (EIO, a stale NFS handle, a dropped
    connection, a timeout) that is not one of :data:`DETERMINISTIC_OS_ERRORS`. Bad input
    (TypError) and bugs (any other exception) fail the same way every time."""
    try:
        state.result()
    except TypError:
        return False
    except DETERMINISTIC_OS_ERRORS:
        return False
    except OSError:
        return True
    except Exception:
        return False
    return False


RUNNERS = ("thread", "dask")


def runner(workers: int, kind: str = "thread", address: str | None = None):
    """The task runner for per-scene fan-out.

    ``thread``: Prefect's thread pool in this process. ``dask``: prefect-dask's DaskTaskRunner on
    the cluster at ``address`` (``tcp://host:8786``), or on a LocalCluster of ``workers``
    single-threaded processes when no address is given.
    """
    if kind == "thread":
        from prefect.task_runners import ThreadPoolTaskRunner

        if address:
            raise TypError("typ run", "--address", "no address with --runner thread (only with --runner dask)", address)
        return ThreadPoolTaskRunner(max_workers=workers)
    if kind != "dask":
        raise TypError("typ run", "--runner", f"one of {list(RUNNERS)}", kind)
    from prefect_dask import DaskTaskRunner

    if address:
        return DaskTaskRunner(address=address)
    return DaskTaskRunner(cluster_class="distributed.LocalCluster",
                          cluster_kwargs={"n_workers": workers, "threads_per_worker": 1, "processes": True,
                                          "dashboard_address": None})


@contextlib.contextmanager
def api_for_workers() -> Iterator[None]:
    """One Prefect API for this process and its Dask workers.

    Without ``PREFECT_API_URL`` Prefect starts a temporary server per process, so each Dask
    worker process would start its own (seconds each, one sqlite file). Start typ's local server
    (:func:`flows.server.prefect_api`, the one ``typ run all`` and ``typ serve`` start, in
    ``PREFECT_HOME``) here instead; its URL and auth reach the workers through the environment
    they are spawned with and the settings they receive. A cluster on other machines needs a
    server they can reach: set ``PREFECT_API_URL``.
    """
    from prefect.settings import PREFECT_API_AUTH_STRING, PREFECT_API_URL, PREFECT_HOME, temporary_settings

    from flows.server import prefect_api

    if PREFECT_API_URL.value():
        yield
        return
    with prefect_api(Path(PREFECT_HOME.value())) as (url, server), \
            temporary_settings(updates={PREFECT_API_URL: url, PREFECT_API_AUTH_STRING: server.auth}):
        yield


def publish_markdown(markdown: str, *, key: str, description: str | None = None) -> str | None:
    """Publish ``markdown`` (a stage's summary) as a Prefect markdown artifact of the current run.

    The artifact shows in the Prefect UI under the flow run and, by ``key`` (lower-case letters,
    digits and dashes; other characters become dashes), in the Artifacts page, where each run adds
    a version. Outside a flow or task run (a task's plain function called directly, a test) there
    is nothing to attach it to: it returns None and talks to no server.
    """
    from prefect.artifacts import create_markdown_artifact
    from prefect.context import FlowRunContext, TaskRunContext

    if FlowRunContext.get() is None and TaskRunContext.get() is None:
        return None
    return str(create_markdown_artifact(markdown=markdown, key=artifact_key(key), description=description))


def artifact_key(name: str) -> str:
    """A Prefect artifact key from a name: lower case, runs of other characters -> ``-``."""
    key = re.sub(r"[^a-z0-9-]+", "-", name.lower()).strip("-")
    if not key:
        raise TypError("publish_markdown", "key", "a name with letters or digits", name)
    return key


def plain_task(fn: Callable, name: str):
    """``fn`` as a Prefect task without result caching: training and sampling must really run."""
    from prefect import task
    from prefect.cache_policies import NO_CACHE

    return task(fn, name=name, cache_policy=NO_CACHE)


class PrefectTrainings:
    """:class:`tasks.training.Trainings` with each training a stage reports as one Prefect task
    run named after it: trained here, the task runs it; trained by a process pool, the task starts
    with it and ends with it, in its state. Use it as a context manager: on the way out it waits
    until each of those has its final state.

    A pool's trainings run at once, so their task runs get a thread pool of their own: the training
    flows' own task runner has one thread (they call their tasks in turn), on which each task run
    would wait for the one before it and start late."""

    def __init__(self) -> None:
        self.pending: list = []
        self._runner = None

    def __enter__(self) -> "PrefectTrainings":
        from prefect.task_runners import ThreadPoolTaskRunner

        self._runner = ThreadPoolTaskRunner().__enter__()   # threads on demand, one per running training
        return self

    def __exit__(self, *exc) -> None:
        from prefect.futures import wait

        try:
            wait(self.pending)
        finally:
            self._runner.__exit__(*exc)

    def run(self, name: str, fn: Callable[[], object]) -> object:
        return training_task(name, fn)

    def step(self, name: str, fn: Callable[[], object]) -> object:
        return plain_task(fn, name)()

    def started(self, name: str, future) -> None:
        if self._runner is None:
            raise RuntimeError("PrefectTrainings.started outside its `with` block")
        self.pending.append(self._runner.submit(_training_task(future.result, name), parameters={}))


def _training_task(fn: Callable, name: str):
    return plain_task(fn, name).with_options(task_run_name=name)   # the run is called as the training


def training_task(name: str, fn: Callable[[], object]) -> object:
    """One training, run here as a Prefect task run named ``name`` (``train-<network>-seed<k>``):
    what a flow that trains one network at a time calls, :meth:`PrefectTrainings.run` as well."""
    return _training_task(fn, name)()


def write_metrics(stage: str, metrics: dict, root: Path = Path(".")) -> Path:
    """``metrics/<stage>.json`` for DVC; under torchrun only rank 0 writes it."""
    path = root / "metrics" / f"{stage}.json"
    if is_main_process():
        write_json(path, metrics)
    return path


def finish_stage(stage: str, run, metrics: dict, root: Path, *, artifacts=()) -> Path:
    """The end every stage flow shares: ``metrics/<stage>.json`` for DVC, the numbers to the
    MLflow run, and the metrics file plus ``artifacts`` (paths, or (path, folder) pairs) as
    the run's artifacts. A stage whose metrics time no work of their own (no ``seconds_total`` or
    ``seconds_training``, :func:`typ.tracking.stage_seconds`) gets its run's wall time as
    ``seconds_total``, so that every stage's row in the summary has its seconds."""
    started = getattr(run, "started", None)
    if started is not None and stage_seconds(metrics) is None:
        metrics = {**metrics, "seconds_total": round(time.perf_counter() - started, 3)}
    path = write_metrics(stage, metrics, root)
    run.metrics(numeric_leaves(metrics))
    for item in (path, *artifacts):
        run.artifact(*item) if isinstance(item, tuple) else run.artifact(item)
    return path


def numeric_leaves(metrics: dict, prefix: str = "") -> dict[str, float]:
    """Flatten nested metrics to ``a.b`` names, numbers only (for MLflow)."""
    out = {}
    for k, v in metrics.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(numeric_leaves(v, name + "."))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[name] = v
    return out


class Timer:
    def __enter__(self):
        self.t0 = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self.t0


def per_scene_stage(stage: str, cfg: Config, root: Path, spec: SceneStage) -> dict:
    """The shape every per-scene stage shares, inside one MLflow run.

    Remove temporaries a killed run left under ``spec.out``; ``spec.plan()`` gives the items to
    do and the stale outputs, of which those the stage wrote are deleted and the others kept
    (:func:`remove_stale`); each item runs ``spec.work`` as a Prefect task, except
    those ``spec.unchanged`` settles here (a task costs ~20 ms of orchestration, which was most
    of a no-op stage on a hundred scenes); ``spec.summarize(results)`` gives the stage metrics,
    written to ``metrics/<stage>.json`` for DVC and logged to MLflow. The caller holds the
    stage's lock on ``spec.out`` (:func:`typ.io.output_lock`): temporaries here are a killed run's.
    """
    with stage_run(stage, cfg, root=root) as run:
        with Timer() as timer:
            cleaned = remove_stale_temporaries(spec.out) if spec.out.exists() else 0
            items, stale = spec.plan()
            removed = remove_stale(stage, spec.out, stale)
            settled = {i: r for i, item in enumerate(items)
                       if spec.unchanged is not None and (r := spec.unchanged(item, **spec.work_kwargs)) is not None}
            todo = [item for i, item in enumerate(items) if i not in settled]
            ran = iter(per_scene(spec.work, todo, label=spec.label, stage=stage, retries=IO_RETRIES,
                                 **spec.work_kwargs) if todo else [])
            results = [settled[i] if i in settled else next(ran) for i in range(len(items))]
        return _finish_scenes(stage, run, spec, results, root, removed_stale=removed, removed_temporaries=cleaned,
                              kept_not_written_by_typ=len(stale) - removed, seconds_total=round(timer.seconds, 3))


def remove_stale(stage: str, out: Path, stale: list[Path]) -> int:
    """Delete what of ``stale`` the stage wrote (:func:`typ.io.remove_written`: its record matches it)
    and the folders that leaves empty; the rest is typ's to leave alone: a warning names it (a
    user's files where the stage's outputs go). Returns how many were deleted."""
    kept = []
    for path in stale:
        if remove_written(path, stage):
            log.info("%s: removed %s: its input is gone", stage, path)
            _remove_empty_parents(path, out)
        else:
            kept.append(path)
    if kept:
        log.warning("%s: left alone %d path(s) under %s that the stage did not write: %s%s", stage, len(kept),
                    out, ", ".join(str(p) for p in kept[:5]), " ..." if len(kept) > 5 else "")
    return len(stale) - len(kept)


def _remove_empty_parents(path: Path, top: Path) -> None:
    """Remove the folders between ``path`` and ``top`` that deleting ``path`` left empty."""
    for parent in path.parents:
        if parent == top or top not in parent.parents:
            return
        try:
            parent.rmdir()
        except OSError:  # not empty: it holds something else
            return


def settle_unchanged(stage: str, cfg: Config, root: Path, spec: SceneStage) -> dict | None:
    """A per-scene stage with nothing to do, settled without Prefect: its metrics, or None.

    When ``spec.out`` holds no temporaries, no output the stage wrote is stale and
    ``spec.unchanged`` settles every item, the stage's MLflow run is logged as
    :func:`per_scene_stage` would log it (the same metrics, ``metrics/<stage>.json``, the skip
    reasons at INFO), tagged ``typ.prefect`` =
    ``not started: every scene unchanged``, and the metrics are returned. Otherwise nothing is
    touched and None is returned, at the first item with work: the caller runs the stage's flow,
    which checks again. This is what lets ``typ run <stage>`` with nothing to do skip importing
    Prefect and starting a flow run (about half of a no-op stage's seconds).
    """
    if spec.unchanged is None:
        return None
    with Timer() as timer:
        if spec.out.exists() and next(temporaries(spec.out), None) is not None:
            return None
        items, stale = spec.plan()
        if any(written_by(path, stage) for path in stale):
            return None
        results = []
        for item in items:
            if (r := spec.unchanged(item, **spec.work_kwargs)) is None:
                return None
            results.append(r)
    with stage_run(stage, cfg, root=root, tags={"typ.prefect": "not started: every scene unchanged"}) as run:
        return _finish_scenes(stage, run, spec, results, root, removed_stale=0, removed_temporaries=0,
                              kept_not_written_by_typ=len(stale), seconds_total=round(timer.seconds, 3))


def settle_stage(stage: str, *, params: str = "params.yaml", root: Path = Path(".")) -> dict | None:
    """:func:`settle_unchanged` for the per-scene ``stage`` (one the registry says needs no
    torch: the CLI asks) when this process is not one rank of several (under torchrun such a
    stage is refused by ``flows.pipeline.run_stage``); None otherwise, or when it has work."""
    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        return None
    cfg = load_config(root / params)
    spec = importlib.import_module(f"tasks.{stage}").scene_stage(cfg, root)
    with output_lock(stage, spec.out):
        metrics = settle_unchanged(stage, cfg, root, spec)
    if metrics is not None:
        log.info("%s: every scene unchanged (%s); settled without a Prefect flow run", stage,
                 metrics.get("skipped_unchanged"))
    return metrics


def _finish_scenes(stage: str, run, spec: SceneStage, results: list[dict], root: Path, **counts) -> dict:
    metrics = spec.summarize(results)
    metrics.update(counts)
    for r in results:
        if r["skipped"]:
            log.info("%s: skipped %s (%s)", stage, r["scenario"], r["skipped"])
    finish_stage(stage, run, metrics, root)
    return metrics
