"""Flow ``simulate``: the embedded simulator's scenarios, one Prefect task per scenario."""
from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.common import Timer, log, numeric_leaves, per_scene, write_metrics
from tasks import simulate as stage
from typ.config import load_config
from typ.io import remove_stale_temporaries
from typ.tracking import stage_run

STAGE = "simulate"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def simulate_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.simulate
    out = root_path / block.out
    with stage_run(STAGE, cfg, root=root_path) as run:
        with Timer() as timer:
            cleaned = remove_stale_temporaries(out) if out.exists() else 0
            jobs = stage.plan_jobs(block)
            stale = stage.stale_scenarios(jobs, out)
            stage.remove_stale(stale)
            results = per_scene(stage.run_job, jobs, label=lambda j: j.name, stage=STAGE, out=out)
        metrics = stage.summarize(results)
        metrics.update(removed_stale=len(stale), removed_temporaries=cleaned, seconds_total=round(timer.seconds, 3))
        for r in results:
            if r["skipped"]:
                log.info("simulate: skipped %s (%s)", r["scenario"], r["skipped"])
        path = write_metrics(STAGE, metrics, root_path)
        run.metrics(numeric_leaves(metrics))
        run.artifact(path)
    return metrics
