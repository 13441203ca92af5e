"""Flow ``voxelize``: one Prefect task per scenario, incremental by content hash."""
from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.common import per_scene_stage
from tasks import voxelize as stage
from typ.config import load_config

STAGE = "voxelize"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def voxelize_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    return per_scene_stage(STAGE, cfg, root_path, stage.scene_stage(cfg, root_path))
