"""Collaborative samples from OPV2V-layout folders, with OpenCOOD's conventions (code ours).

One sample per (scenario, timestamp of the ego), scenarios sorted by name, timestamps sorted
(OpenCOOD ``basedataset.BaseDataset``). The conventions kept, each with its OpenCOOD source
(DerrickXuNu/OpenCOOD ``opencood/data_utils/datasets/basedataset.py`` and
``intermediate_fusion_dataset.py``):

- Ego: the first agent of :func:`typ.formats.opv2v.list_agents` (sorted, RSUs last).
- Cooperating agents: every other agent whose x/y distance from the ego is at most
  ``comm_range`` (70 m, ``COM_RANGE``), measured with the agent's pose at the frame it sends
  (the delayed one) against the ego's current pose, before any pose noise.
- Transforms are float64 ``x1_to_x2(agent_pose, ego_pose)`` = ``inv(ego_to_world) @
  agent_to_world`` (:func:`typ.geometry.relative_transform`); the ego's is the identity.
- Ground truth: the labelled vehicles of the ego and of every cooperating agent at the
  *current* frame (``reform_param`` keeps current ``vehicles`` under delay), moved into the
  ego frame with true current poses, kept when all 8 corners lie inside ``lidar_range``
  (``mask_boxes_outside_range_numpy``), deduplicated by object id, first occurrence (ego
  first) kept. As there, the ego's own car is in the ground truth whenever a cooperating
  agent labels it.
- Delay (``time_delay_calculation``, ``async_mode: sim``): cooperating agents send the data
  of ``delay_frames`` frames earlier (10 Hz: 100 ms a frame); the transform maps the agent's
  delayed pose to the ego's current pose (``cur_ego_pose_flag``). The ego is never delayed.
  OpenCOOD clamps the delay at the first frame of a sequence, so on short sequences the delay
  applied is less than the one asked for; here only frames ``t >= delay_frames`` are samples
  (and none before ``first_frame``, so that several delays can be scored on the same frames),
  every message is exactly ``delay_frames`` old (``FusionSample.time_delay`` says so).
- Pose noise (``add_loc_noise``): Gaussian noise on the cooperating agents' x and y
  (``position_std`` m) and yaw (``heading_std_deg``) before the transform is formed; the
  ego's pose, the ground truth and the communication range stay noise-free. OpenCOOD
  re-seeds one global generator with the same seed on every call, so every agent of every
  sample gets the same draw; here each (sample, agent) has its own stream of ``seed``.
- Points within the 3.9 m x 2.2 m footprint around each sensor are dropped (``mask_ego_points``).
- Visibility (``min_points``, not OpenCOOD's: OPV2V labels every vehicle in range, seen or not):
  a vehicle is ground truth only when at least ``min_points`` points of the agents' *true*
  current clouds (the ego's and the cooperating agents' in range, own cars masked) fall in its
  box, as V2V4Real labels what its fused LiDAR saw and Waymo's LEVEL_2 drops boxes without a
  point; an agent's own labels need that many points of its own true cloud. True clouds even
  with ``cav_root``, so that generated cooperators train on the same labels as true ones.

``cav_root`` replaces the cooperating agents' clouds by the ones at the same
``<scenario>/<agent>/<timestamp>.pcd`` under another root (TYP's generated reference views),
while the ego's cloud, all poses and all labels come from ``root``; the generated agent's
yaml must carry the same ``lidar_pose``. A generated cloud covers only the generator's grid
around its agent (±51.2 m in x and y), so with ``cav_extent`` (the half side of that square,
for ``cav_root`` clouds or a generated split whose cooperating agents are all generated) a
cooperating agent's labels are kept only where all four BEV corners lie inside the square, in
its own labels and in what it adds to the fused ground truth; the ego's labels, from its true
cloud, are kept whole.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.warp import communication_mask
from typ import geometry
from typ.errors import TypError
from typ.formats.opv2v import list_agents, list_scenarios, list_timestamps, read_scene
from typ.formats.pcd import read_pcd
from typ.geometry import points_in_boxes
from typ.scene import AgentView

#: OpenCOOD's ``mask_ego_points``: the sensor's own car, [-1.95, 1.95] x [-1.1, 1.1] m
EGO_FOOTPRINT = (1.95, 1.1)
#: metres of pose disagreement tolerated between ``root`` and ``cav_root`` for one agent
POSE_TOLERANCE = 1e-3


def unavailable(folder: Path) -> str | None:
    """Why ``folder`` holds no scenarios to use (None: it does)."""
    if not folder.is_dir():
        return f"{folder} does not exist (the generate stage writes it)"
    if not list_scenarios(folder):
        return f"{folder} holds no scenario"
    return None


@dataclass(frozen=True)
class FusionSample:
    """What the ego has at one timestamp: its view, the messages in range, the ground truth.

    agent_ids:       L agents, the ego first, then the cooperating agents in range (list_agents order).
    clouds:          L (n_i, 4) float32 ``[x, y, z, intensity]``, each in its own sensor frame
                     at the frame it was sent (``timestamp`` minus ``time_delay``).
    transforms:      (L, 4, 4) float64 agent->ego as the ego uses it: the agent's (delayed, noisy)
                     pose to the ego's current pose; ``[0]`` is the identity.
    true_transforms: (L, 4, 4) float64 agent->ego from both current, noise-free poses.
    time_delay:      (L,) int64 frames (100 ms at 10 Hz) each message is old; 0 for the ego.
    gt_boxes:        (M, 7) float64 ``[x, y, z, l, w, h, yaw]``, ego frame, current frame, in range.
    gt_ids:          (M,) int64 object ids of ``gt_boxes``.
    agent_boxes:     L (K_i, 7) float64: each agent's own labels in its own frame at the frame of
                     its cloud, in range (single-agent training targets: no and late fusion).
    """

    scenario: str
    timestamp: str
    agent_ids: tuple[str, ...]
    clouds: tuple[np.ndarray, ...]
    transforms: np.ndarray
    true_transforms: np.ndarray
    time_delay: np.ndarray
    gt_boxes: np.ndarray
    gt_ids: np.ndarray
    agent_boxes: tuple[np.ndarray, ...]

    @property
    def num_agents(self) -> int:
        return len(self.agent_ids)


def boxes_in_range(boxes: np.ndarray, lidar_range: Sequence[float], *, xy_only: bool = False) -> np.ndarray:
    """(K,) bool: all 8 corners of each box inside ``[x_min, y_min, z_min, x_max, y_max, z_max]``
    (OpenCOOD ``mask_boxes_outside_range_numpy`` with ``min_num_corners=8``; bounds inclusive).
    ``xy_only``: the x/y bounds only, as OpenCOOD filters predictions
    (``get_mask_for_boxes_within_range_torch``)."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    if len(b) == 0:
        return np.zeros(0, dtype=bool)
    r = np.asarray(lidar_range, dtype=np.float64)
    axes = 2 if xy_only else 3
    corners = geometry.box_corners(b)[..., :axes]
    return ((corners >= r[:axes]) & (corners <= r[3:3 + axes])).all(axis=(1, 2))


def mask_ego_points(points: np.ndarray) -> np.ndarray:
    """Drop the points on the sensor's own car (OpenCOOD ``mask_ego_points``)."""
    hx, hy = EGO_FOOTPRINT
    inside = (np.abs(points[:, 0]) <= hx) & (np.abs(points[:, 1]) <= hy)
    return points[~inside]


def noisy_pose(pose: np.ndarray, rng: np.random.Generator, position_std: float,
               heading_std_deg: float) -> np.ndarray:
    """(4, 4) sensor-to-world with N(0, position_std²) added to x and y and N(0, heading_std_deg²)
    degrees to the yaw (rotation about the world z axis, kept through the sensor origin)."""
    dx, dy = rng.normal(0.0, position_std, 2) if position_std > 0 else (0.0, 0.0)
    dyaw = np.radians(rng.normal(0.0, heading_std_deg)) if heading_std_deg > 0 else 0.0
    c, s = np.cos(dyaw), np.sin(dyaw)
    out = pose.copy()
    out[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ pose[:3, :3]
    out[0, 3] += dx
    out[1, 3] += dy
    return out


class FusionDataset(Sequence):
    """OPV2V-layout scenarios under ``root`` as a sequence of :class:`FusionSample`."""

    def __init__(self, root: str | os.PathLike, *, lidar_range: Sequence[float], comm_range: float = 70.0,
                 cav_root: str | os.PathLike | None = None, delay_frames: int = 0, position_std: float = 0.0,
                 heading_std_deg: float = 0.0, seed: int = 0, max_scenarios: int | None = None,
                 max_agents: int | None = None, first_frame: int = 0, cav_extent: float | None = None,
                 min_points: int = 0, cache: bool = True):
        """root: a split folder (``<domain>/<split>``) of scenarios; lidar_range: [x_min, y_min, z_min,
        x_max, y_max, z_max] m of the detector (ground truth is kept inside it); comm_range: m;
        cav_root: another split folder the cooperating agents' clouds come from; delay_frames:
        age of the cooperating agents' data in frames; position_std (m) / heading_std_deg (deg):
        pose noise of the cooperating agents; seed: of that noise; max_scenarios: the first N
        scenarios only (None: all); max_agents: at most this many agents per sample, the ego
        included (OpenCOOD's ``max_cav``; None: all); first_frame: frames before it are not samples
        (frames before ``delay_frames`` never are); cav_extent: half side (m) of the square a
        cooperating agent's (generated) cloud covers around it (None: unlimited); min_points: a label
        counts when at least this many true points fall in its box (0: every label); cache: keep
        read agent views in memory."""
        self.root = Path(root)
        where = str(self.root)
        r = [float(v) for v in lidar_range]
        if len(r) != 6 or not (r[0] < r[3] and r[1] < r[4] and r[2] < r[5]):
            raise TypError(where, "lidar_range", "[x_min, y_min, z_min, x_max, y_max, z_max] with min < max", r)
        if not comm_range > 0:
            raise TypError(where, "comm_range", "a distance > 0 (m)", comm_range)
        if isinstance(delay_frames, bool) or not isinstance(delay_frames, (int, np.integer)) or delay_frames < 0:
            raise TypError(where, "delay_frames", "an integer >= 0 (frames of 100 ms)", delay_frames)
        for name, value in (("position_std", position_std), ("heading_std_deg", heading_std_deg)):
            if not (np.isfinite(value) and value >= 0):
                raise TypError(where, name, "a standard deviation >= 0", value)
        if max_scenarios is not None and max_scenarios < 1:
            raise TypError(where, "max_scenarios", "None or a count >= 1", max_scenarios)
        if max_agents is not None and max_agents < 1:
            raise TypError(where, "max_agents", "None or a count >= 1", max_agents)
        if isinstance(first_frame, bool) or not isinstance(first_frame, (int, np.integer)) or first_frame < 0:
            raise TypError(where, "first_frame", "an integer >= 0 (a frame index)", first_frame)
        if cav_extent is not None and not (np.isfinite(cav_extent) and cav_extent > 0):
            raise TypError(where, "cav_extent", "None or a half side > 0 (m)", cav_extent)
        if isinstance(min_points, bool) or not isinstance(min_points, (int, np.integer)) or min_points < 0:
            raise TypError(where, "min_points", "an integer >= 0 (points in a box)", min_points)
        self.lidar_range, self.comm_range = tuple(r), float(comm_range)
        self.cav_root = None if cav_root is None else Path(cav_root)
        if self.cav_root is not None and not self.cav_root.is_dir():
            raise TypError(self.cav_root, "cav_root", "a folder of OPV2V-layout scenarios", "not a folder")
        self.delay_frames, self.position_std, self.heading_std_deg = int(delay_frames), float(position_std), \
            float(heading_std_deg)
        self.seed, self.max_agents, self.cache = int(seed), max_agents, cache
        self.first_frame = int(first_frame)
        self.cav_extent = None if cav_extent is None else float(cav_extent)
        self.min_points = int(min_points)
        scenarios = list_scenarios(self.root)[:max_scenarios]
        if not scenarios:
            raise TypError(where, "scenarios", "at least one scenario folder", "none")
        self.scenarios: list[tuple[Path, list[str], list[str]]] = []
        self.index: list[tuple[int, int]] = []
        for s, folder in enumerate(scenarios):
            agents, timestamps = list_agents(folder), list_timestamps(folder)
            if not timestamps:
                raise TypError(folder / agents[0], "timestamps", "at least one <timestamp>.yaml of the ego", "none")
            self.scenarios.append((folder, agents, timestamps))
            self.index += [(s, t) for t in range(max(self.first_frame, self.delay_frames), len(timestamps))]
        if not self.index:
            raise TypError(where, "delay_frames", f"sequences longer than the first frame scored "
                           f"(max(first_frame, delay_frames) = {max(self.first_frame, self.delay_frames)})",
                           f"at most {max(len(t) for _, _, t in self.scenarios)} frames")
        self._views: dict[tuple[str, str, str], AgentView] = {}
        self._cav_clouds: dict[tuple[str, str, str], np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.index)

    def with_options(self, **changes) -> "FusionDataset":
        """The same data with other perturbations (delay, noise, seed), sharing the read cache."""
        kw = dict(lidar_range=self.lidar_range, comm_range=self.comm_range, cav_root=self.cav_root,
                  delay_frames=self.delay_frames, position_std=self.position_std,
                  heading_std_deg=self.heading_std_deg, seed=self.seed, max_scenarios=len(self.scenarios),
                  max_agents=self.max_agents, first_frame=self.first_frame, cav_extent=self.cav_extent,
                  min_points=self.min_points, cache=self.cache)
        other = FusionDataset(self.root, **{**kw, **changes})
        other._views = self._views
        if other.cav_root == self.cav_root:
            other._cav_clouds = self._cav_clouds
        return other

    def _view(self, folder: Path, agent: str, timestamp: str) -> AgentView:
        key = (folder.name, agent, timestamp)
        view = self._views.get(key)
        if view is None:
            view = read_scene(folder, timestamp, agents=[agent]).ego
            if self.cache:
                self._views[key] = view
        return view

    def _cav_points(self, scenario: str, agent: str, timestamp: str, pose: np.ndarray) -> np.ndarray:
        """The cloud of ``agent`` under ``cav_root``, checked to be taken at ``pose``."""
        key = (scenario, agent, timestamp)
        points = self._cav_clouds.get(key)
        if points is None:
            folder = self.cav_root / scenario
            if not (folder / agent / f"{timestamp}.pcd").is_file():
                raise TypError(folder / agent / f"{timestamp}.pcd", "cav_root",
                               "a generated cloud for every cooperating agent of the real scenario", "no such file")
            view = read_scene(folder, timestamp, agents=[agent]).ego
            if np.abs(view.pose[:3, 3] - pose[:3, 3]).max() > POSE_TOLERANCE or \
                    np.abs(view.pose[:3, :3] - pose[:3, :3]).max() > POSE_TOLERANCE:
                raise TypError(view.where, "lidar_pose", "the pose of the same agent in the real scenario",
                               geometry.matrix_to_pose(view.pose).round(3).tolist())
            points = view.points
            if self.cache:
                self._cav_clouds[key] = points
        return points

    def __getitem__(self, i: int) -> FusionSample:
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        s, t = self.index[i]
        folder, agents, timestamps = self.scenarios[s]
        now = timestamps[t]
        sent = timestamps[t - self.delay_frames]
        ego = self._view(folder, agents[0], now)
        others = agents[1:]
        sent_views = [self._view(folder, a, sent) for a in others]
        in_range = communication_mask(np.stack([v.pose for v in sent_views]), ego.pose, self.comm_range).numpy() \
            if others else np.zeros(0, dtype=bool)
        chosen = [j for j in range(len(others)) if in_range[j]]
        if self.max_agents is not None:
            chosen = chosen[:self.max_agents - 1]

        ids, clouds, transforms, true_transforms, delays, agent_boxes = \
            [ego.agent_id], [mask_ego_points(ego.points)], [np.eye(4)], [np.eye(4)], [0], [self._own(ego)]
        gt_boxes, gt_ids, seen = [ego.boxes], [ego.box_ids], [clouds[0]]
        for j in chosen:
            view_sent, agent = sent_views[j], others[j]
            view_now = self._view(folder, agent, now)
            rng = np.random.default_rng([self.seed, i, agents.index(agent)])
            pose = noisy_pose(view_sent.pose, rng, self.position_std, self.heading_std_deg)
            points = view_sent.points if self.cav_root is None else \
                self._cav_points(folder.name, agent, sent, view_sent.pose)
            ids.append(agent)
            clouds.append(mask_ego_points(points))
            transforms.append(geometry.relative_transform(pose, ego.pose))
            now_to_ego = geometry.relative_transform(view_now.pose, ego.pose)
            true_transforms.append(now_to_ego)
            delays.append(self.delay_frames)
            own, now_boxes, now_ids = self._own(view_sent), view_now.boxes, view_now.box_ids
            if self.cav_extent is not None:
                own = own[self._covered(own)]
                covered = self._covered(now_boxes)
                now_boxes, now_ids = now_boxes[covered], now_ids[covered]
            agent_boxes.append(own)
            gt_boxes.append(geometry.transform_boxes(now_to_ego, now_boxes))
            gt_ids.append(now_ids)
            if self.min_points:
                seen.append(geometry.transform_points(now_to_ego, mask_ego_points(view_now.points)))
        boxes, box_ids = np.concatenate(gt_boxes).reshape(-1, 7), np.concatenate(gt_ids).astype(np.int64)
        keep = boxes_in_range(boxes, self.lidar_range)
        boxes, box_ids = boxes[keep], box_ids[keep]
        _, first = np.unique(box_ids, return_index=True)
        first = np.sort(first)
        if self.min_points:
            first = first[self._visible(np.concatenate(seen), boxes[first])]
        return FusionSample(scenario=folder.name, timestamp=now, agent_ids=tuple(ids), clouds=tuple(clouds),
                            transforms=np.stack(transforms), true_transforms=np.stack(true_transforms),
                            time_delay=np.asarray(delays, dtype=np.int64), gt_boxes=boxes[first],
                            gt_ids=box_ids[first], agent_boxes=tuple(agent_boxes))

    def _own(self, view: AgentView) -> np.ndarray:
        """The view's labels in range (and, with ``min_points``, seen by its own true cloud)."""
        boxes = view.boxes[boxes_in_range(view.boxes, self.lidar_range)]
        return boxes[self._visible(mask_ego_points(view.points), boxes)] if self.min_points else boxes

    def _visible(self, points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
        """(K,) bool: at least ``min_points`` of ``points`` (same frame) inside each box."""
        if len(boxes) == 0:
            return np.zeros(0, dtype=bool)
        near = np.hypot(points[:, 0], points[:, 1]) <= np.hypot(boxes[:, 0], boxes[:, 1]).max() + 5.0
        return points_in_boxes(points[near], boxes).sum(0) >= self.min_points

    def _covered(self, boxes: np.ndarray) -> np.ndarray:
        """(K,) bool: boxes (agent frame) inside the square a generated cloud covers."""
        e = self.cav_extent
        return boxes_in_range(boxes, (-e, -e, -np.inf, e, e, np.inf), xy_only=True)
