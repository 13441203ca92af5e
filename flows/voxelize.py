"""Flow ``voxelize``: one Prefect task per scenario, incremental by content hash."""
from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.common import per_scene_stage
from tasks import voxelize as stage
from typ.config import load_config
from typ.errors import TypError

STAGE = "voxelize"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def voxelize_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    source, out = root_path / cfg.voxelize.input, root_path / cfg.voxelize.out
    if not source.is_dir():
        raise TypError(source, "voxelize.input", "a folder of <dataset>/<split>/<scenario> (run simulate first)")
    grid = stage.to_grid(cfg.voxelize.grid)

    def plan():
        items = stage.plan_inputs(source)
        return items, stage.stale_outputs(items, out)

    return per_scene_stage(STAGE, cfg, root_path, out=out, plan=plan, work=stage.run_scene,
                           work_kwargs={"cfg": cfg.voxelize, "out": out}, label=lambda item: item.name,
                           summarize=lambda results: stage.summarize(results, grid),
                           unchanged=stage.unchanged)
