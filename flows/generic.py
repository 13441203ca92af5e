"""The flow of a stage that has no module of its own in ``flows/``: built from its task module.

``tasks/<name>.py`` gives the stage one of two shapes:

- ``scene_stage(cfg, root) -> SceneStage``: a per-scene stage, one Prefect task per scene,
  incremental by content hash (:func:`flows.common.per_scene_stage`);
- ``run(cfg, root, *, run) -> StageResult``: the rest, inside the stage's MLflow run (``run``,
  a :class:`typ.tracking.StageRun`). One that also takes ``trainings`` gets a
  :class:`flows.common.PrefectTrainings`, and each training it reports is its own Prefect task;
  one that does not runs as a single task named after the stage.

The result's metrics go to ``metrics/<name>.json`` and MLflow, its artifacts to the run, its
summary (if any) to a Prefect markdown artifact. dvc.yaml's code deps of such a stage are this
module's import closure and its task module's (:func:`flows.dvcyaml.code_deps`).
"""
from __future__ import annotations

import importlib
import inspect
from pathlib import Path
from typing import Callable

from prefect import flow

from flows.common import PrefectTrainings, finish_stage, per_scene_stage, plain_task, publish_markdown
from tasks.scene_stage import StageResult
from typ.config import load_config
from typ.errors import TypError
from typ.tracking import stage_run


def run_module(name: str, module, params: str, root: str) -> dict:
    """Stage ``name`` from its task ``module`` (module doc); returns its metrics."""
    root_path = Path(root)
    cfg = load_config(root_path / params)
    if hasattr(module, "scene_stage"):
        return per_scene_stage(name, cfg, root_path, module.scene_stage(cfg, root_path))
    if not callable(getattr(module, "run", None)):
        raise TypError(module.__name__, "scene_stage / run", "a stage's task module defines one of them", "neither")
    with stage_run(name, cfg, root=root_path) as run:
        if "trainings" in inspect.signature(module.run).parameters:
            with PrefectTrainings() as trainings:
                result = module.run(cfg, root_path, run=run, trainings=trainings)
        else:
            result = plain_task(module.run, name)(cfg, root_path, run=run)
        if not isinstance(result, StageResult):
            raise TypError(f"{module.__name__}.run", "return value", "a tasks.scene_stage.StageResult",
                           type(result).__name__)
        if result.summary:
            publish_markdown(result.summary, key=f"{name}-summary", description=f"typ {name} summary")
        finish_stage(name, run, result.metrics, root_path, artifacts=result.artifacts)
    return result.metrics


def flow_of(name: str) -> Callable[..., dict]:
    """Stage ``name``'s Prefect flow (named after the stage), from ``tasks/<name>.py``."""
    module = importlib.import_module(f"tasks.{name}")

    def body(params: str = "params.yaml", root: str = ".") -> dict:
        return run_module(name, module, params, root)

    body.__name__ = body.__qualname__ = f"{name}_flow"
    return flow(name=name, log_prints=False, validate_parameters=False)(body)
