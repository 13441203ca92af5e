"""Flow ``selftrain``: target-domain enhancement of the adapters (TYP Table 4's variants) and the
generator ``generate`` uses, per stage-1 replica."""
from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.common import PrefectTrainings, finish_stage
from tasks import selftrain as stage
from typ.config import load_config
from typ.tracking import stage_run

STAGE = "selftrain"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def selftrain_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    with stage_run(STAGE, cfg, root=root_path) as run:
        with PrefectTrainings() as trainings:
            metrics = stage.run(cfg, root_path, log_fn=run.metrics, log_model=run.log_model, trainings=trainings)
        finish_stage(STAGE, run, metrics, root_path,
                     artifacts=[stage.generator_dir(root_path / cfg.selftrain.out, cfg.stage1.seed) / "pipeline.json"])
    return metrics
