"""(x_r, y_r, x_e') tuples of TYP §3.3 from multi-agent scenarios, as dense grids.

For every timestamp and every ordered pair of agents (ego e, reference r), e ≠ r:
x_r = r's occupancy in r's frame, y_r = r's box map, x_e' = e's cloud moved into r's
frame (float64, :func:`typ.voxel.points_to_reference`) and voxelized on the same grid.
In simulated target scenarios the reference views are the hidden truth the generation is
scored against. ``grid`` is the dataset's sensor grid (``VoxelizeConfig.sensor_grid``): every
agent of a scenario carries the same sensor, so ego and reference share it.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from typ.formats.opv2v import list_agents, list_scenarios, list_timestamps, read_scene
from typ.scene import vehicle_mask
from typ.voxel import Grid, box_map, points_to_reference, voxelize


@dataclass(frozen=True)
class Pair:
    scenario: str
    timestamp: str
    ego: str
    reference: str
    x_r: np.ndarray       # (C, H, W) bool, reference frame
    y_r: np.ndarray       # (1, H, W) bool, reference frame
    x_e: np.ndarray       # (C, H, W) bool: the ego's cloud in the reference frame (x_e')
    ego_points: np.ndarray  # (N, 4) the ego's cloud in the reference frame, before voxelization
    ref_points: np.ndarray  # (M, 4) the reference's own cloud (the truth x_r came from)
    ref_boxes: np.ndarray   # (K, 7) the reference's labelled vehicles, reference frame
    ego_pose_in_ref: np.ndarray  # (4, 4) float64 the ego sensor in the reference frame


def iter_pairs(split_root: Path, grid: Grid, *, ego_only: bool = False) -> Iterator[Pair]:
    """All ordered (ego, reference) pairs under ``split_root`` (scenario folders).

    ego_only: only pairs whose ego is the scenario's ego (OpenCOOD's first agent), as in
    single-agent target data where only the ego's cloud is real.
    """
    for folder in list_scenarios(split_root):
        agents = list_agents(folder)
        for ts in list_timestamps(folder):
            scene = read_scene(folder, ts, agents=agents)
            grids = {a: voxelize(v.points, grid).transpose(2, 0, 1) for a, v in scene.agents.items()}
            boxes = {a: box_map(v.boxes, grid).transpose(2, 0, 1) for a, v in scene.agents.items()}
            egos = agents[:1] if ego_only else agents
            for e in egos:
                for r in agents:
                    if r == e:
                        continue
                    ego, ref = scene.agents[e], scene.agents[r]
                    moved = points_to_reference(ego.points, ego.pose, ref.pose)
                    yield Pair(folder.name, ts, e, r, grids[r], boxes[r], voxelize(moved, grid).transpose(2, 0, 1),
                               moved, ref.points, ref.boxes[vehicle_mask(ref.box_labels)],
                               np.linalg.solve(ref.pose, ego.pose))


def stack(pairs: list[Pair]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x_r (N, C, H, W), y_r (N, 1, H, W), x_e' (N, C, H, W)) float32."""
    return tuple(np.stack([getattr(p, k) for p in pairs]).astype(np.float32) for k in ("x_r", "y_r", "x_e"))
