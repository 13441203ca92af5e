"""Flow ``voxelize``: one Prefect task per scenario, incremental by content hash."""
from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.common import Timer, log, numeric_leaves, per_scene, write_metrics
from tasks import voxelize as stage
from typ.config import load_config
from typ.errors import TypError
from typ.io import remove_stale_temporaries
from typ.tracking import stage_run

STAGE = "voxelize"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def voxelize_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.voxelize
    source, out = root_path / block.input, root_path / block.out
    if not source.is_dir():
        raise TypError(source, "voxelize.input", "a folder of <dataset>/<split>/<scenario> (run simulate first)")
    grid = stage.to_grid(block.grid)
    with stage_run(STAGE, cfg, root=root_path) as run:
        with Timer() as timer:
            cleaned = remove_stale_temporaries(out) if out.exists() else 0
            items = stage.plan_inputs(source)
            stale = stage.stale_outputs(items, out)
            for p in stale:
                log.info("voxelize: removing %s: its scenario is gone", p)
                p.unlink()
            results = per_scene(stage.run_scene, items, label=lambda i: i.name, stage=STAGE, grid=grid, out=out)
        metrics = stage.summarize(results, grid)
        metrics.update(removed_stale=len(stale), removed_temporaries=cleaned, seconds_total=round(timer.seconds, 3))
        for r in results:
            if r["skipped"]:
                log.info("voxelize: skipped %s (%s)", r["scenario"], r["skipped"])
        path = write_metrics(STAGE, metrics, root_path)
        run.metrics(numeric_leaves(metrics))
        run.artifact(path)
    return metrics
