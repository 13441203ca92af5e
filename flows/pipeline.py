"""The whole pipeline as one Prefect flow, and the stage registry the CLI runs from."""
from __future__ import annotations

import contextlib
import importlib
import importlib.util
import os
from pathlib import Path
from typing import Callable

from prefect import flow

from typ import registry
from flows.common import api_for_workers, runner
from flows.server import scoped_environ
from typ.config import Config, load_config
from typ.errors import TypError
from typ.io import output_lock
from typ.tracking import PARENT_ENV, is_main_process, stage_run


def _flow(stage: str) -> Callable:
    # imported lazily, one stage at a time: `typ --help` must not pay for Prefect's import of
    # every stage, and one stage's dependencies must not be needed to run another
    if importlib.util.find_spec(f"flows.{stage}") is None:  # no flow of its own: from its task module
        from flows.generic import flow_of

        return flow_of(stage)
    module = importlib.import_module(f"flows.{stage}")
    return getattr(module, f"{stage}_flow")


STAGES = Config.STAGES
_REGISTERED = registry.STAGES
#: stages that fan out per scene (a task runner: threads or Dask); the others train or score
#: (torchrun/DDP), as the stage registry says
PER_SCENE = tuple(s for s in STAGES if _REGISTERED[s].kind == "per-scene")
TRAINING = tuple(s for s in STAGES if s not in PER_SCENE)
#: stages whose code never imports torch (nor diffusers, mlflow's model code): `typ run` sets up
#: no device for them, and a run with nothing to do costs its imports of Prefect, pyarrow, MLflow
WITHOUT_TORCH = tuple(s for s in STAGES if not _REGISTERED[s].torch)
#: MLflow's switch for a run's system metrics (CPU, memory, disk, network; GPU with pynvml,
#: sampled from a thread, offline): on for the registry's training stages unless the
#: environment says otherwise, off for the others unless it says so
SYSTEM_METRICS_ENV = "MLFLOW_ENABLE_SYSTEM_METRICS_LOGGING"


#: the project root ``typ serve`` serves, in its environment and so in its flow runs' (flows.deploy)
SERVED_ROOT_ENV = "TYP_SERVED_ROOT"


def served_project_only(params: str, root: str) -> None:
    """In a run of a deployment, refuse a ``root`` other than the project ``typ serve`` serves and a
    ``params`` file outside it. A run's parameters are whatever its creator sent to the API, and a
    stage writes and deletes under the paths its params name, as the user who runs ``typ serve``.
    Called in-process (``typ run all``), the root is the CLI's own and nothing is checked."""
    from prefect.context import FlowRunContext

    ctx = FlowRunContext.get()
    if ctx is None or ctx.flow_run is None or ctx.flow_run.deployment_id is None:
        return
    where = f"flow run {ctx.flow_run.name} of {ctx.flow.name}"
    served = os.environ.get(SERVED_ROOT_ENV)
    if not served:
        raise TypError(where, "root", "a deployment served by `typ serve`, which names its project", root)
    project = Path(served)
    if not isinstance(root, str) or Path(root).resolve() != project:
        raise TypError(where, "root", f"this project's root {project}", root)
    if not isinstance(params, str) or not Path(os.path.normpath(project / params)).is_relative_to(project):
        raise TypError(where, "params", f"a params file inside {project}", params)


def run_stage(stage: str, *, params: str = "params.yaml", root: str = ".", task_runner: str = "thread",
              address: str | None = None) -> dict:
    """Run one stage's flow holding its lock on its output (:func:`typ.io.output_lock`: a second
    run is refused); per-scene stages fan out on ``task_runner`` (thread | dask)."""
    cfg = load_config(Path(root) / params)
    block = cfg.block(stage)
    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and stage not in TRAINING:  # under torchrun
        raise TypError("typ run", "stage", f"a training stage {list(TRAINING)} under torchrun "
                       "(per-scene stages scale out with --runner dask)", stage)
    fl = _flow(stage)
    if stage not in PER_SCENE:  # training stages call their tasks in turn: one thread
        task_runner, address = "thread", None
    fl = fl.with_options(task_runner=runner(getattr(block, "workers", 1), task_runner, address))
    # one run per output; under torchrun rank 0 holds the lock for the ranks, which write nothing
    system_metrics = {SYSTEM_METRICS_ENV: "true"} if _REGISTERED[stage].kind == "training" else {}
    with output_lock(stage, Path(root) / block.out) if is_main_process() else contextlib.nullcontext(), \
            api_for_workers() if task_runner == "dask" else contextlib.nullcontext(), \
            scoped_environ(system_metrics, keep_set=True):   # `typ run all`: every stage in one process
        return fl(params=params, root=root)


@flow(name="pipeline", log_prints=False, validate_parameters=False)
def pipeline_flow(params: str = "params.yaml", root: str = ".", task_runner: str = "thread",
                  address: str | None = None) -> dict:
    """Every stage in order under one parent MLflow run (stage runs nest under it)."""
    served_project_only(params, root)
    cfg = load_config(Path(root) / params)
    results = {}
    with stage_run("pipeline", cfg, root=Path(root)) as parent, scoped_environ({PARENT_ENV: parent.run_id}):
        for stage in STAGES:
            results[stage] = run_stage(stage, params=params, root=root, task_runner=task_runner, address=address)
    return results
