"""Stage ``voxelize`` (TYP §3.2): every agent view -> BEV occupancy x and box map y, per scene.

Input: OPV2V-layout scenarios under ``<input>/<dataset>/<split>/<scenario>/`` (the simulator's
output, or real OPV2V / V2V4Real dropped in the same way). Output: one Parquet file per
scenario in :mod:`typ.store` (``<out>/dataset=<d>/split=<s>/<scenario>.parquet``) holding each
(agent, timestamp)'s sparse occupancy and box-map indices. A scenario whose content hash
(all its files + the grid) matches the stored one is skipped; a view with no point inside
the grid is recorded (empty occupancy) and counted as ``empty_views``.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tasks.scene_stage import SceneStage
from typ.config import Config, GridConfig, VoxelizeConfig
from typ.errors import TypError
from typ.formats.opv2v import list_agents, list_timestamps, read_scene, scenario_sensor
import typ.formats.opv2v
import typ.store
import typ.voxel
from typ.io import code_digest, hash_files, hidden_below
from typ.sensors import mount_height
from typ.store import list_scenes, scene_path, stored_input_hash, write_scene_voxels
from typ.voxel import Grid, box_map, voxelize
from typ.registry import declare

log = logging.getLogger(__name__)

STAGE = "voxelize"
#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare("voxelize", data=("data/sim",), outs=("data/voxels",))
#: the reader's, voxelizer's and store's source: a change to any redoes every scene
_CODE = code_digest(typ.formats.opv2v, typ.voxel, typ.store)


@dataclass(frozen=True)
class ScenarioInput:
    dataset: str
    split: str
    folder: Path

    @property
    def name(self) -> str:
        return self.folder.name


def to_grid(cfg: GridConfig) -> Grid:
    return Grid(cfg.x_range, cfg.y_range, cfg.z_range, cfg.shape)


def plan_inputs(root: Path) -> list[ScenarioInput]:
    """Scenario folders ``root/<dataset>/<split>/<scenario>`` (hidden names excluded at every level:
    temporaries, and typ's records of what simulate wrote, ``<dataset>/.typ/``)."""
    return [ScenarioInput(p.parent.parent.name, p.parent.name, p) for p in sorted(root.glob("*/*/*"))
            if p.is_dir() and not hidden_below(p, root)]


def input_hash(item: ScenarioInput, grid: Grid) -> str:
    files = sorted(p for p in item.folder.rglob("*") if p.is_file() and not p.name.startswith("."))
    names = [str(p.relative_to(item.folder)) for p in files]
    return hash_files(files, extra=f"{names}|{grid.digest()}|{_CODE}")


def stale_outputs(items: list[ScenarioInput], out: Path) -> list[Path]:
    wanted = {scene_path(out, i.dataset, i.split, i.name) for i in items}
    return [s.path for s in list_scenes(out) if s.path not in wanted]


def _scene_state(item: ScenarioInput, cfg: VoxelizeConfig, out: Path) -> tuple[Path, Grid, str, dict]:
    """(output path, grid, input hash, result fields) of one scenario."""
    height = mount_height(scenario_sensor(item.folder) or item.dataset, cfg.mount_height, where=str(item.folder))
    grid = to_grid(cfg.grid).for_sensor(height)
    base = {"scenario": item.name, "dataset": item.dataset, "split": item.split}
    return scene_path(out, item.dataset, item.split, item.name), grid, input_hash(item, grid), base


def unchanged(item: ScenarioInput, *, cfg: VoxelizeConfig, out: Path) -> dict | None:
    """The skipped result of a scenario whose stored voxels have its input hash, else None. A
    scenario with no stored voxels is not hashed here (a fresh run would read every input twice,
    the first time serially in the flow's process)."""
    stored = stored_input_hash(scene_path(out, item.dataset, item.split, item.name))
    if stored is None:
        return None
    _, _, digest, base = _scene_state(item, cfg, out)
    return {**base, "skipped": "unchanged"} if stored == digest else None


def run_scene(item: ScenarioInput, *, cfg: VoxelizeConfig, out: Path) -> dict:
    """Voxelize every (agent, timestamp) of one scenario on its dataset's sensor grid (the grid at
    the height of the LiDAR its yaml names, a real dataset's, else of its domain:
    :func:`typ.sensors.mount_height`); skip it when its inputs are unchanged."""
    path, grid, digest, base = _scene_state(item, cfg, out)
    if stored_input_hash(path) == digest:  # as unchanged(): the flow settles most such scenes itself
        return {**base, "skipped": "unchanged"}
    t0 = time.perf_counter()
    stats = {"views": 0, "empty_views": 0, "points": 0, "points_in_grid": 0, "occupied": 0, "box_cells": 0}

    def records():
        agents = list_agents(item.folder)
        for ts in list_timestamps(item.folder):
            scene = read_scene(item.folder, ts, agents=agents, dataset=item.dataset, split=item.split)
            for agent_id, view in scene.agents.items():
                occupancy = voxelize(view.points, grid)
                boxes = box_map(view.boxes, grid)
                n_occ = int(occupancy.sum())
                stats["views"] += 1
                stats["points"] += len(view.points)
                stats["points_in_grid"] += _count_in_grid(view.points, grid)
                stats["occupied"] += n_occ
                stats["box_cells"] += int(boxes.sum())
                if n_occ == 0:
                    stats["empty_views"] += 1
                    log.warning("voxelize: %s/%s agent %s at %s has no point inside the grid",
                                item.dataset, item.name, agent_id, ts)
                yield (agent_id, ts), (occupancy, boxes)

    write_scene_voxels(path, records(), grid=grid, input_hash=digest, stage=STAGE, inside=out)
    return {**base, "skipped": None, "seconds": time.perf_counter() - t0, **stats}


def _count_in_grid(points: np.ndarray, grid: Grid) -> int:
    p = points[:, :3].astype(np.float64)
    return int(((p >= grid.lower) & (p < grid.upper)).all(axis=1).sum())


def summarize(results: list[dict], grid: Grid) -> dict:
    done = [r for r in results if r["skipped"] is None]
    cells = int(np.prod(grid.shape))
    views = sum(r["views"] for r in done)
    metrics = {"scenarios": len(results), "voxelized": len(done),
               "skipped_unchanged": sum(r["skipped"] == "unchanged" for r in results),
               "views": views, "empty_views": sum(r["empty_views"] for r in done),
               "seconds_voxelizing": round(sum(r["seconds"] for r in done), 3)}
    if views:
        points = sum(r["points"] for r in done)
        metrics["occupancy_density"] = round(sum(r["occupied"] for r in done) / (views * cells), 6)
        metrics["box_cells_per_view"] = round(sum(r["box_cells"] for r in done) / views, 2)
        metrics["points_in_grid_fraction"] = round(sum(r["points_in_grid"] for r in done) / max(points, 1), 4)
        metrics["views_per_second"] = round(views / max(metrics["seconds_voxelizing"], 1e-9), 2)
    return metrics


def scene_stage(cfg: Config, root: Path) -> SceneStage:
    """The stage's pieces for ``flows.common``: every scenario under ``voxelize.input``."""
    source, out = root / cfg.voxelize.input, root / cfg.voxelize.out
    if not source.is_dir():
        raise TypError(source, "voxelize.input", "a folder of <dataset>/<split>/<scenario> (run simulate first)")
    grid = to_grid(cfg.voxelize.grid)

    def plan():
        items = plan_inputs(source)
        return items, stale_outputs(items, out)

    return SceneStage(out=out, plan=plan, work=run_scene,
                      work_kwargs={"cfg": cfg.voxelize, "out": out},
                      label=lambda item: item.name, summarize=lambda results: summarize(results, grid),
                      unchanged=unchanged)
