"""The whole pipeline as one Prefect flow, and the stage registry the CLI runs from."""
from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

from prefect import flow

from flows.common import runner
from typ.config import Config, load_config
from typ.tracking import PARENT_ENV, stage_run


def _flows() -> dict[str, Callable]:
    # imported lazily: `typ --help` must not pay for Prefect's import of every stage
    from flows.simulate import simulate_flow
    from flows.voxelize import voxelize_flow
    from flows.adapt import adapt_flow
    from flows.generate import generate_flow
    from flows.stage1 import stage1_flow
    from flows.stage2 import stage2_flow
    from flows.vqvae import vqvae_flow

    return {"simulate": simulate_flow, "voxelize": voxelize_flow, "vqvae": vqvae_flow, "stage1": stage1_flow,
            "adapt": adapt_flow, "stage2": stage2_flow, "generate": generate_flow}


STAGES = Config.STAGES


def run_stage(stage: str, *, params: str = "params.yaml", root: str = ".") -> dict:
    """Run one stage's flow with the task runner its params ask for."""
    cfg = load_config(Path(root) / params)
    block = cfg.block(stage)
    fl = _flows()[stage]
    return fl.with_options(task_runner=runner(getattr(block, "workers", 1)))(params=params, root=root)


@flow(name="pipeline", log_prints=False, validate_parameters=False)
def pipeline_flow(params: str = "params.yaml", root: str = ".") -> dict:
    """Every stage in order under one parent MLflow run (stage runs nest under it)."""
    cfg = load_config(Path(root) / params)
    results = {}
    with stage_run("pipeline", cfg, root=Path(root)) as parent:
        previous = os.environ.get(PARENT_ENV)
        os.environ[PARENT_ENV] = parent.run_id
        try:
            for stage in STAGES:
                results[stage] = run_stage(stage, params=params, root=root)
        finally:
            if previous is None:
                os.environ.pop(PARENT_ENV, None)
            else:
                os.environ[PARENT_ENV] = previous
    return results
