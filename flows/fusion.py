"""Flow ``fusion``: the collaborative detection benchmark (TYP Tables 1–3, V2VSSC robustness)."""
from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.common import Timer, numeric_leaves, plain_task, write_metrics
from tasks import fusion as stage
from tasks import fusion_report
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
            plain_task(bench.train_all, "train")()
            results = plain_task(bench.score, "score")()
        results = {**results, "seconds_total": round(timer.seconds, 3),
                   "seconds_training": round(sum(bench.seconds.values()), 3)}
        write_json(out / "results.json", results)
        write_json(out / "curves.json", bench.curves())
        reports = plain_task(fusion_report.write_report, "report")(results, block, root_path / block.reports)
        metrics = {**fusion_report.metrics_of(results), "seconds_total": results["seconds_total"],
                   "seconds_training": results["seconds_training"]}
        path = write_metrics(STAGE, metrics, root_path)
        run.metrics(numeric_leaves(metrics))
        for p in [path, out / "results.json", out / "curves.json", *reports]:
            run.artifact(p)
        test = bench.test_inputs()
        for method, oracle in bench.plan.robustness.items():   # Table 1's oracle detectors, servable from MLflow
            served = ServedDetector(bench.networks[oracle][0].as_method(method)).eval()
            run.log_model(f"fusion-{method}", served, ServedDetector.example(method, test))
    return metrics
