"""Flow ``simulate``: each domain's scenarios (simulated, or taken from a real dataset), one Prefect
task per scenario."""
from __future__ import annotations

from pathlib import Path

from prefect import flow

from flows.common import per_scene_stage
from tasks import simulate as stage
from typ.config import load_config

STAGE = "simulate"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def simulate_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    return per_scene_stage(STAGE, cfg, root_path, stage.scene_stage(cfg, root_path))
