"""Flow ``fusion``: the collaborative detection benchmark (TYP Tables 1–3, V2VSSC robustness)."""
from __future__ import annotations

from pathlib import Path

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.common import Timer, numeric_leaves, write_metrics
from tasks import fusion as stage
from tasks import fusion_report
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
            table2 = task(stage.oracle_vs_generated, name="oracle-vs-generated", cache_policy=NO_CACHE)(bench)
            table3 = task(stage.pretrain_finetune, name="pretrain-finetune", cache_policy=NO_CACHE)(bench)
            curves = task(stage.robustness, name="robustness", cache_policy=NO_CACHE)(bench)
        results = {**stage.summarize(bench, table2, table3, curves), "seconds_total": round(timer.seconds, 3),
                   "seconds_training": round(sum(bench.seconds.values()), 3)}
        reports = task(fusion_report.write_report, name="report", cache_policy=NO_CACHE)(
            results, block, root_path / block.reports)
        write_json(out / "results.json", results)
        metrics = {**fusion_report.metrics_of(results), "seconds_total": results["seconds_total"],
                   "seconds_training": results["seconds_training"]}
        path = write_metrics(STAGE, metrics, root_path)
        run.metrics(numeric_leaves(metrics))
        for p in [path, out / "results.json", *reports]:
            run.artifact(p)
        for method in block.methods:  # Table 2's oracle detectors, servable from MLflow
            run.log_model(f"fusion-{method}", stage.ServedDetector(bench.oracle(method)).eval(),
                          stage.ServedDetector.example(method, bench.test))
    return metrics
