"""Prefect deployments of typ, served by ``typ serve``.

- ``pipeline/scheduled``: every stage in order (``pipeline_flow``) on ``serve.pipeline_cron``.
- ``watch-generate/scheduled``: on ``serve.watch_cron``, look in ``serve.watch`` for new
  single-agent scenarios (``<watch>/<dataset>/<split>/<scenario>``, OPV2V layout) and run
  ``generate`` on them with the trained models; results go to ``serve.watch_out``.
- ``typ-stage/on-demand``: one stage by name, no schedule (run it from the UI or with
  ``prefect deployment run typ-stage/on-demand -p stage=voxelize``).

Deployment parameters are the params file and the project root: each run reads the params
in effect when it starts, as ``typ run`` does, and a run on another root or with a params file
outside the project is refused (``served_project_only``). Flows are referenced by module path,
so the runner's flow-run processes import them from the installed project.
"""
from __future__ import annotations

from pathlib import Path

import yaml
from prefect import flow
from prefect.types.entrypoint import EntrypointType

from flows.pipeline import SERVED_ROOT_ENV, pipeline_flow, run_stage, served_project_only
from flows.server import scoped_environ
from typ.config import load_config, read_params
from typ.formats.opv2v import list_scenarios
from typ.io import write_text

DERIVED_PARAMS = ".params.yaml"


@flow(name="typ-stage", log_prints=False, validate_parameters=False)
def stage_flow(stage: str = "simulate", params: str = "params.yaml", root: str = ".",
               task_runner: str = "thread") -> dict:
    """One stage, as ``typ run <stage>`` runs it."""
    served_project_only(params, root)
    return run_stage(stage, params=params, root=root, task_runner=task_runner)


def watched_scenarios(watch: Path) -> dict[tuple[str, str], list[Path]]:
    """(dataset, split) -> scenario folders under ``watch/<dataset>/<split>/``."""
    if not watch.is_dir():
        return {}
    return {(d.parent.name, d.name): list_scenarios(d) for d in sorted(watch.glob("*/*"))
            if d.is_dir() and not d.name.startswith(".") and not d.parent.name.startswith(".")}


def new_scenarios(watch: Path, out: Path) -> dict[tuple[str, str], list[Path]]:
    """The watched scenarios that have no output under ``out/<dataset>/<split>/`` yet."""
    fresh = {(d, s): [f for f in folders if not (out / d / s / f.name).is_dir()]
             for (d, s), folders in watched_scenarios(watch).items()}
    return {k: v for k, v in fresh.items() if v}


def watch_params(params_file: Path, watch: Path, out: Path, sets: list[tuple[str, str]]) -> str:
    """The project's params with ``generate`` pointed at the watched folder, written beside the
    outputs (``<out>/.params.yaml``) so that what a run did can be read back."""
    raw = read_params(params_file)
    raw["generate"] = {**(raw.get("generate") or {}), "input": str(watch), "out": str(out),
                       "sets": [{"dataset": d, "split": s, "references": "vehicles"} for d, s in sets]}
    path = out / DERIVED_PARAMS
    write_text(path, yaml.safe_dump(raw, sort_keys=False))
    return str(path)


@flow(name="watch-generate", log_prints=False, validate_parameters=False)
def watch_flow(params: str = "params.yaml", root: str = ".") -> dict:
    """Generate collaborative views for scenarios dropped into ``serve.watch`` since the last run.

    Nothing new: returns at once, without loading any model. Otherwise ``generate`` runs over
    every (dataset, split) folder of the watched tree (it skips scenarios already done).
    """
    served_project_only(params, root)
    root_path = Path(root)
    cfg = load_config(root_path / params)
    watch, out = (root_path / cfg.serve.watch).resolve(), (root_path / cfg.serve.watch_out).resolve()
    fresh = new_scenarios(watch, out)
    result = {"new": {f"{d}/{s}": [p.name for p in folders] for (d, s), folders in fresh.items()}}
    if not fresh:
        return result
    derived = watch_params(root_path / params, watch, out, sorted(watched_scenarios(watch)))
    result["generate"] = run_stage("generate", params=derived, root=str(root_path))
    return result


def deployments(root: Path, params: str = "params.yaml") -> dict:
    """name -> RunnerDeployment, schedules and parameters from the params file."""
    root = Path(root).resolve()
    cfg = load_config(root / params)
    base = {"params": params, "root": str(root)}
    module = EntrypointType.MODULE_PATH
    return {
        "pipeline": pipeline_flow.to_deployment("scheduled", cron=cfg.serve.pipeline_cron, parameters=base,
                                                entrypoint_type=module, tags=["typ"]),
        "watch-generate": watch_flow.to_deployment("scheduled", cron=cfg.serve.watch_cron, parameters=base,
                                                   entrypoint_type=module, tags=["typ"]),
        "typ-stage": stage_flow.to_deployment("on-demand", parameters={**base, "stage": "simulate"},
                                              entrypoint_type=module, tags=["typ"]),
    }


def serve(root: Path, params: str = "params.yaml", only: list[str] | None = None,
          poll_seconds: float | None = None) -> None:
    """Register the deployments with the API in ``PREFECT_API_URL`` and run their flow runs
    here until interrupted (schedules are paused on shutdown)."""
    from prefect import serve as prefect_serve

    from typ.errors import TypError

    available = deployments(root, params)
    unknown = sorted(set(only or []) - set(available))
    if unknown:
        raise TypError("typ serve", "--only", f"deployment names from {sorted(available)}", unknown)
    chosen = [d for name, d in available.items() if not only or name in only]
    kwargs = {"query_seconds": poll_seconds} if poll_seconds else {}
    with scoped_environ({SERVED_ROOT_ENV: str(Path(root).resolve())}):   # the flow runs' processes inherit it
        prefect_serve(*chosen, **kwargs)
