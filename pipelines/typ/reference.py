"""A reference sensor's inputs to the generator, made from an ego's view alone (TYP §4.1).

:func:`reference_at` puts a sensor at any pose and gives what :meth:`TYPPipeline.generate` takes:
y_r (the ego's labelled boxes, and the ego's own car, in the reference frame) and x_e' (the
ego's cloud moved there), voxelized on the reference sensor's grid. The generate stage, ``typ
generate``, the real-scan benchmark and self-training's pseudo references all build theirs here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from typ.geometry import invert, transform_boxes
from typ.resim import EGO_CAR_LWH
from typ.scene import AgentView
from typ.voxel import Grid, box_map, points_to_reference, voxelize


@dataclass(frozen=True)
class Reference:
    """A reference sensor and what the generator is given for it: y_r (the boxes it must show) and
    x_e' (the ego's cloud moved to it), both on the sensor's grid, with the cloud itself for the
    compose modes that re-simulate or cast it."""

    agent_id: str
    pose: np.ndarray        # (4, 4) float64 sensor-to-world
    boxes: np.ndarray       # (K, 7) in the reference frame
    labels: tuple[str, ...]
    ids: np.ndarray
    x_e: np.ndarray         # (C, H, W) bool, x_e'
    y_r: np.ndarray         # (1, H, W) bool
    ego_points: np.ndarray  # (N, 4) the ego's cloud in the reference frame (x_e' before voxelization)
    ego_origin: np.ndarray  # (3,) float64 the ego sensor's position in the reference frame


def reference_at(ego: AgentView, ref_pose: np.ndarray, agent_id: str, exclude_id: int | None,
                 grid: Grid) -> Reference:
    """x_e' and y_r at sensor pose ``ref_pose`` (4x4 float64, world), from the ego's view only.

    y_r holds the ego's labelled boxes (less ``exclude_id``, the vehicle carrying the
    reference sensor) plus the ego's own car, which its labels never contain.
    """
    in_ego = invert(ego.pose) @ ref_pose
    keep = ego.box_ids != exclude_id if exclude_id is not None else np.ones(len(ego.boxes), bool)
    # the ego car's centre height in its own sensor frame: that of the labelled cars, which
    # stand on the same road (a reference height when there are none)
    car_z = float(np.median(ego.boxes[:, 2])) if len(ego.boxes) else -1.0
    ego_car = np.array([[0.0, 0.0, car_z, *EGO_CAR_LWH, 0.0]])
    boxes = transform_boxes(invert(in_ego), np.concatenate([ego.boxes[keep].reshape(-1, 7), ego_car]))
    labels = tuple(np.asarray(ego.box_labels, dtype=object)[keep]) + ("car",)
    ego_numeric = int(ego.agent_id) if ego.agent_id.lstrip("-").isdigit() else -1
    ids = np.concatenate([ego.box_ids[keep], [ego_numeric]])
    moved = points_to_reference(ego.points, ego.pose, ref_pose)
    return Reference(agent_id, np.asarray(ref_pose, dtype=np.float64), boxes, labels, ids,
                     voxelize(moved, grid).transpose(2, 0, 1), box_map(boxes, grid).transpose(2, 0, 1), moved,
                     (invert(in_ego) @ np.array([0.0, 0.0, 0.0, 1.0]))[:3])
