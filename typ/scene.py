"""The in-memory scene shared by every stage.

A :class:`Scene` is one timestamp of one scenario: a few agents (the first is the ego),
each an :class:`AgentView` with its point cloud in its own sensor frame, its float64
sensor-to-world pose, and the labelled boxes in that same sensor frame.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from typ.errors import TypError

#: Per-point semantic classes written by the simulator (uint8 codes).
SEMANTIC_CLASSES: tuple[str, ...] = ("ground", "road", "building", "vegetation", "pole", "vehicle")
SEMANTIC_CODE: dict[str, int] = {name: i for i, name in enumerate(SEMANTIC_CLASSES)}
#: Code for points whose class is not known (real data without point labels).
SEMANTIC_UNKNOWN = 255
#: Box labels of vehicles: the simulator's, KITTI's, Waymo's, nuScenes'.
VEHICLE_LABELS = frozenset({"car", "van", "truck", "vehicle", "bus", "trailer", "construction_vehicle"})


def vehicle_mask(labels) -> np.ndarray:
    """(K,) bool: which box labels are vehicles (:data:`VEHICLE_LABELS`, case-insensitive)."""
    return np.array([str(label).lower() in VEHICLE_LABELS for label in labels], dtype=bool)


@dataclass
class AgentView:
    """What one agent saw at one timestamp.

    points:    (N, 4) float32 ``[x, y, z, intensity]``, this agent's sensor frame, intensity in [0, 1].
    pose:      (4, 4) float64 sensor-to-world (see :mod:`typ.geometry`).
    boxes:     (K, 7) float64 ``[x, y, z, l, w, h, yaw]`` in this agent's sensor frame.
    box_labels: K class names (``"car"``, ``"van"``, ``"truck"``, ``"pedestrian"`` ...).
    box_ids:   (K,) int64 object ids, stable across agents and timestamps of a scenario.
    semantics: (N,) uint8 codes from :data:`SEMANTIC_CLASSES`, or None when unknown.
    """

    agent_id: str
    points: np.ndarray
    pose: np.ndarray
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    box_labels: tuple[str, ...] = ()
    box_ids: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))
    semantics: np.ndarray | None = None
    where: str = "<memory>"

    def __post_init__(self) -> None:
        w = self.where
        pts = np.asarray(self.points)
        if pts.ndim != 2 or pts.shape[1] != 4:
            raise TypError(w, "points", "array of shape (N, 4) [x, y, z, intensity]", pts.shape)
        if pts.dtype != np.float32:
            raise TypError(w, "points", "dtype float32", pts.dtype)
        if not np.isfinite(pts).all():
            raise TypError(w, "points", "finite coordinates and intensity (no NaN/Inf)",
                           f"{int((~np.isfinite(pts)).any(axis=1).sum())} non-finite rows")
        pose = np.asarray(self.pose)
        if pose.shape != (4, 4) or pose.dtype != np.float64:
            raise TypError(w, "pose", "(4, 4) float64 matrix", f"{pose.shape} {pose.dtype}")
        if not np.isfinite(pose).all() or not np.allclose(pose[3], [0, 0, 0, 1]):
            raise TypError(w, "pose", "finite rigid transform with last row [0, 0, 0, 1]", pose[3])
        boxes = np.asarray(self.boxes, dtype=np.float64).reshape(-1, 7) if np.size(self.boxes) else np.zeros((0, 7))
        if not np.isfinite(boxes).all():
            raise TypError(w, "boxes", "finite box parameters", "non-finite entries")
        if (boxes[:, 3:6] <= 0).any():
            raise TypError(w, "boxes", "positive sizes l, w, h", boxes[(boxes[:, 3:6] <= 0).any(axis=1)][:1])
        self.boxes = boxes
        self.box_labels = tuple(self.box_labels)
        self.box_ids = np.asarray(self.box_ids, dtype=np.int64).reshape(-1)
        if len(self.box_labels) != len(boxes) or len(self.box_ids) != len(boxes):
            raise TypError(w, "box_labels/box_ids", f"one label and one id per box ({len(boxes)})",
                           (len(self.box_labels), len(self.box_ids)))
        if self.semantics is not None:
            sem = np.asarray(self.semantics)
            if sem.shape != (len(pts),) or sem.dtype != np.uint8:
                raise TypError(w, "semantics", f"({len(pts)},) uint8", f"{sem.shape} {sem.dtype}")


@dataclass
class Scene:
    """One timestamp of one scenario; ``agents`` keeps insertion order and the first is the ego."""

    scenario: str
    timestamp: str
    agents: dict[str, AgentView]
    dataset: str = ""
    split: str = ""

    @property
    def ego(self) -> AgentView:
        if not self.agents:
            raise TypError(self.scenario, "agents", "at least one agent", 0)
        return next(iter(self.agents.values()))

    @property
    def ego_id(self) -> str:
        return self.ego.agent_id
