"""Flow ``evaluate``: the benchmark's tables, plots and gallery from the trained models."""
from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.common import finish_stage, plain_task, publish_markdown
from tasks import evaluate as stage
from typ.config import load_config
from typ.tracking import stage_run

STAGE = "evaluate"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def evaluate_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    with stage_run(STAGE, cfg, root=root_path) as run:
        result = plain_task(stage.run, "evaluate")(cfg, root_path, run=run)
        publish_markdown(result.summary, key="evaluate-summary", description="typ benchmark summary")
        finish_stage(STAGE, run, result.metrics, root_path, artifacts=result.artifacts)
    return result.metrics
