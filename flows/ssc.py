"""Flow ``ssc``: collaborative semantic scene completion (V2VSSC) — train every seed's networks,
score Table I (perfect, noisy) and the robustness sweeps, write the report and the render."""
from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.common import PrefectTrainings, Timer, finish_stage
from tasks import ssc as stage
from tasks import ssc_report
from typ.config import load_config
from typ.io import write_json
from typ.tracking import stage_run

STAGE = "ssc"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def ssc_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.ssc
    out = root_path / block.out
    with stage_run(STAGE, cfg, root=root_path) as run:
        with Timer() as timer:
            with PrefectTrainings() as trainings:
                results = stage.run(block, root_path, log_fn=run.metrics, trainings=trainings)
            paths = ssc_report.write_report(results, block, root_path / block.reports, results["gallery"])
        metrics = stage.metrics_of(results, timer.seconds)
        write_json(out / "results.json", metrics)
        write_json(out / "losses.json", results["losses"])
        finish_stage(STAGE, run, metrics, root_path, artifacts=[out / "results.json", out / "losses.json", *paths])
    return metrics
