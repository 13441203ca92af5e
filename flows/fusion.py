"""Flow ``fusion``: train the collaborative detection benchmark's networks (TYP Tables 1–3,
V2VSSC robustness); the evaluate stage scores them."""
from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.common import PrefectTrainings, Timer, finish_stage
from tasks import fusion as stage
from tasks.fusion_serve import ServedDetector
from typ.config import load_config
from typ.io import write_json
from typ.tracking import stage_run

STAGE = "fusion"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def fusion_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.fusion
    out = root_path / block.out
    with stage_run(STAGE, cfg, root=root_path) as run:
        with Timer() as timer:
            bench = stage.Benchmark(block, stage.Roots.from_config(block, root_path), out, log_fn=run.metrics)
            with PrefectTrainings() as trainings:
                bench.train_all(trainings)
        metrics = stage.training_summary(bench, timer.seconds)
        write_json(out / stage.TRAINING_JSON, metrics)
        write_json(out / "curves.json", bench.curves())
        loss = stage.write_loss_curve(bench, out / "loss.csv")
        finish_stage(STAGE, run, metrics, root_path, artifacts=[out / stage.TRAINING_JSON, out / "curves.json", loss])
        test = bench.test_inputs()
        for method, oracle in bench.plan.robustness.items():   # Table 1's oracle detectors, servable from MLflow
            served = ServedDetector(bench.networks[oracle][0].as_method(method)).eval()
            run.log_model(f"fusion-{method}", served, ServedDetector.example(method, test))
    return metrics
