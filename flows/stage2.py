"""Flow ``stage2``: adapters on source tuples, one per stage-1 replica (plus the optional variants)."""
from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.common import PrefectTrainings, finish_stage
from tasks import stage2 as stage
from typ.config import load_config
from typ.tracking import stage_run

STAGE = "stage2"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def stage2_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    with stage_run(STAGE, cfg, root=root_path) as run:
        with PrefectTrainings() as trainings:
            metrics = stage.run(cfg, root_path, log_fn=run.metrics, log_model=run.log_model, trainings=trainings)
        finish_stage(STAGE, run, metrics, root_path)
    return metrics
