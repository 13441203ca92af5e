"""OPV2V / V2V4Real scenario folders: ``scenario/agent_id/timestamp.pcd`` + ``timestamp.yaml``.

The yaml of one agent at one timestamp holds (OpenCOOD's keys):

- ``lidar_pose``: ``[x, y, z, roll, yaw, pitch]``, metres and degrees, CARLA world frame.
- ``vehicles``: ``{id: {location [x, y, z], angle [roll, yaw, pitch], extent [half l, half w,
  half h], center [x, y, z]}}`` in world coordinates; ``center`` is added to ``location``
  before the box is moved (as OpenCOOD's ``project_world_objects`` does). An agent's own
  vehicle is not in its own list; the other CAVs are.
- kept if present: ``ego_speed``, ``true_ego_pos`` and, ours, ``sensor`` (domain name);
  per vehicle ``obj_type`` (car/van/truck; OPV2V, which has only cars, omits it).

Boxes in a :class:`~typ.scene.Scene` are in each agent's sensor frame; the conversion
follows OpenCOOD: object pose = (location + center, angle), ``x1_to_x2(object_pose,
lidar_pose)``, the 8 corners of ``create_bbx(extent)``, then centre = mean of corners 0, 3,
5, 6 and yaw from the length edge in the xy-plane. Sizes are ``2 * extent`` (OpenCOOD's
``corner_to_center`` measures them in the xy-plane, which is the same when the object and
the LiDAR are equally tilted, and shorter by the cosine of the relative tilt otherwise).
"""
from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Mapping

import numpy as np
import yaml

from typ import geometry
from typ.errors import TypError
from typ.formats.pcd import read_pcd, read_pcd_header, write_pcd
from typ.inputs import MiB, finite_numbers, inside, load_yaml
from typ.io import write_text
from typ.scene import AgentView, Scene

#: Extra yaml keys carried through :func:`read_meta` / ``write_scene(meta=...)``.
META_KEYS: tuple[str, ...] = ("ego_speed", "true_ego_pos", "sensor")
#: Class name of a vehicle whose yaml entry has no ``obj_type`` (OPV2V has only cars).
DEFAULT_OBJ_TYPE = "car"
#: an agent's yaml with a hundred vehicles is about 15 KB
MAX_YAML_BYTES = 1 * MiB
#: CARLA actor ids are 32-bit; the store keeps ids as int64
_ID_RANGE = range(-2**63, 2**63)


class _Loader(getattr(yaml, "CSafeLoader", yaml.SafeLoader)):
    """SafeLoader that also reads ``1e-3`` (no dot) as a float, as OpenCOOD's ``load_yaml`` does.

    The libyaml-backed loader when PyYAML has it: the resolvers are the same Python ones, and
    parsing is about 7x faster (the fusion stage reads a few hundred of these files).
    """


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?(?:[0-9][0-9_]*)(?:[eE][-+]?[0-9]+)
                  |\.[0-9_]+(?:[eE][-+][0-9]+)?
                  |[-+]?\.(?:inf|Inf|INF)
                  |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."))


def list_scenarios(root: str | os.PathLike) -> list[Path]:
    """Scenario folders under ``root``, sorted by name (hidden and temporary folders skipped; a link
    to a scenario folder is one, see :func:`agent_file`)."""
    r = Path(root)
    if not r.is_dir():
        raise TypError(r, "root", "a folder of OPV2V-layout scenarios", "not a folder")
    return [d for d in sorted(r.iterdir()) if d.is_dir() and not d.name.startswith(".")]


def list_agents(scenario_dir: str | os.PathLike) -> list[str]:
    """Agent folder names in OpenCOOD's order: sorted as strings, negative ids (RSUs) moved last.

    The first one is the ego (a link to an agent folder is one, see :func:`agent_file`).
    """
    s = Path(scenario_dir)
    if not s.is_dir():
        raise TypError(s, "scenario", "a scenario folder with one sub-folder per agent", "not a folder")
    names = [d.name for d in sorted(s.iterdir()) if d.is_dir() and not d.name.startswith(".")]
    if not names:
        raise TypError(s, "agents", "at least one agent folder", "none")
    return [a for a in names if not _is_rsu(a)] + [a for a in names if _is_rsu(a)]


def time_order(stamp: str) -> tuple:
    """Sort key of a timestamp: stamps of digits by their number (``9`` before ``10``), then any
    other as a string. OPV2V's zero-padded stamps (``000068``) sort as OpenCOOD sorts them, as strings."""
    return (int(stamp), stamp) if stamp.isascii() and stamp.isdigit() else (float("inf"), stamp)


def list_timestamps(scenario_dir: str | os.PathLike) -> list[str]:
    """Timestamps (yaml stems, in :func:`time_order`) of the ego agent; OpenCOOD indexes a scenario by these."""
    ego = Path(scenario_dir) / list_agents(scenario_dir)[0]
    return sorted((f.stem for f in ego.glob("*.yaml") if "additional" not in f.name and not f.name.startswith(".")),
                  key=time_order)


def read_scene(scenario_dir: str | os.PathLike, timestamp: str, *, agents: list[str] | None = None,
               dataset: str = "", split: str = "") -> Scene:
    """One timestamp of a scenario; ``agents`` (default: :func:`list_agents`) keeps its order, first = ego."""
    s = Path(scenario_dir)
    ids = list_agents(s) if agents is None else list(agents)
    views = {}
    for agent in ids:
        yaml_path = agent_file(s, agent, f"{timestamp}.yaml")
        doc = _load_yaml(yaml_path)
        lidar_pose = finite_numbers(yaml_path, "lidar_pose", doc.get("lidar_pose"), 6)
        boxes, labels, box_ids = _vehicle_boxes(yaml_path, doc, lidar_pose)
        pcd_path = agent_file(s, agent, f"{timestamp}.pcd")
        if not pcd_path.is_file():
            raise TypError(pcd_path, "pcd", f"a point cloud beside {yaml_path.name}", "no such file")
        points, semantics = read_pcd(pcd_path)
        views[agent] = AgentView(agent_id=agent, points=points, pose=geometry.pose_to_matrix(lidar_pose),
                                 boxes=boxes, box_labels=labels, box_ids=box_ids,
                                 semantics=semantics, where=str(yaml_path))
    return Scene(scenario=s.name, timestamp=str(timestamp), agents=views, dataset=dataset, split=split)


def agent_file(scenario_dir: str | os.PathLike, agent: str, name: str) -> Path:
    """``scenario_dir/agent/name``, a file of one agent's folder, as every reader here opens it.

    ``agent`` is a folder name, never a path. Scenario and agent folders may be links: copies of
    OPV2V and V2V4Real are commonly assembled from links to the agent folders of a dataset kept
    elsewhere, and each is read as the folder it leads to (its real path is the root, as a linked
    dataset root is, :func:`typ.inputs.inside`). The file itself must lie in that folder: a
    timestamp that climbs out, or a ``.pcd``/``.yaml`` that is a link to elsewhere, is refused
    before anything is read.
    """
    s = Path(scenario_dir)
    if not _is_name(agent):
        raise TypError(s, "agent", "an agent folder name (no '/', not '.' or '..')", agent)
    return inside(name, s / agent, field="file")


def _is_name(name) -> bool:
    """Whether ``name`` is one plain folder or file name (no separator, not ``.``/``..``, no NUL)."""
    return isinstance(name, str) and name not in ("", ".", "..") and not any(c in name for c in ("/", "\\", "\0"))


def check_root(root: str | os.PathLike, splits: list[str]) -> dict[str, list[Path]]:
    """A dataset root in OPV2V layout, ``root/<split>/<scenario>/``: split -> its scenario folders.

    Each split in ``splits`` must be a folder holding at least one scenario; raises TypError
    naming the first folder that is not. The scenarios themselves: :func:`check_scenario`.
    """
    r = Path(root)
    if not r.is_dir():
        raise TypError(r, "root", "a folder with one sub-folder per split (OPV2V layout: train/, test/, ...)",
                       "not a folder")
    found = {}
    for split in splits:
        if not _is_name(split):
            raise TypError(r, "split", "a split folder name (no '/', not '.' or '..')", split)
        folder = r / split
        if not folder.is_dir():
            raise TypError(folder, "split", f"a folder of scenarios (the split {split!r} of {r})", "no such folder")
        found[split] = list_scenarios(folder)
        if not found[split]:
            raise TypError(folder, "split", "at least one scenario folder", "none")
    return found


def check_scenario(scenario_dir: str | os.PathLike) -> dict[str, int]:
    """Check one scenario as :func:`read_scene` would read it, without reading the point clouds.

    At least one agent folder; the ego's timestamps (at least one); for every agent and each of
    those timestamps, in :func:`list_agents` order, a yaml with ``lidar_pose`` (six finite numbers
    ``[x, y, z, roll, yaw, pitch]``) and ``vehicles`` (each with location, angle, extent, center),
    and a PCD beside it whose header holds x, y, z. The first bad file raises TypError naming it.
    No ``.pcd`` or ``.yaml`` of an agent folder (what a copy of the scenario takes, these frames
    or not) may be a link out of that folder (:func:`agent_file`).
    Returns counts: frames, views, points (from the PCD headers), boxes.
    """
    s = Path(scenario_dir)
    agents = list_agents(s)
    stamps = list_timestamps(s)
    if not stamps:
        raise TypError(s / agents[0], "timestamps", "at least one <timestamp>.yaml (the ego's frames)", "none")
    for agent in agents:
        for f in sorted((s / agent).iterdir()):
            if f.suffix in (".pcd", ".yaml") and not f.name.startswith("."):
                agent_file(s, agent, f.name)
    counts = {"frames": len(stamps), "views": 0, "points": 0, "boxes": 0}
    for agent in agents:
        for ts in stamps:
            yaml_path = agent_file(s, agent, f"{ts}.yaml")
            doc = _load_yaml(yaml_path)
            lidar_pose = finite_numbers(yaml_path, "lidar_pose", doc.get("lidar_pose"), 6)
            boxes, _, _ = _vehicle_boxes(yaml_path, doc, lidar_pose)
            header = read_pcd_header(agent_file(s, agent, f"{ts}.pcd"))
            counts["views"] += 1
            counts["points"] += header["points"]
            counts["boxes"] += len(boxes)
    return counts


def scenario_sensor(scenario_dir: str | os.PathLike) -> str | None:
    """The LiDAR the ego's first yaml names (``sensor``: typ writes a real dataset's name there,
    ``kitti``, ``waymo``, ...), or None when it names none (a simulated or dropped-in scenario).

    A name that is no LiDAR of :data:`typ.sensors.SENSORS` raises TypError naming this yaml and its
    ``sensor`` field: the caller looks the name up in params' sensors, and an error raised there
    would blame ``params.yaml`` for what the scenario's file says."""
    from typ.sensors import SENSORS  # the sensors import the simulator: only a reader of ``sensor`` pays for it

    s = Path(scenario_dir)
    stamps = list_timestamps(s)
    if not stamps:
        return None
    ego = list_agents(s)[0]
    sensor = read_meta(s, ego, stamps[0]).get("sensor")
    if sensor is not None and not (isinstance(sensor, str) and sensor in SENSORS):
        raise TypError(s / ego / f"{stamps[0]}.yaml", "sensor", f"the name of a known LiDAR, one of {sorted(SENSORS)}",
                       sensor)
    return sensor


def read_meta(scenario_dir: str | os.PathLike, agent: str, timestamp: str) -> dict[str, object]:
    """The :data:`META_KEYS` present in one agent's yaml (``ego_speed``, ``true_ego_pos``, ``sensor``)."""
    doc = _load_yaml(agent_file(scenario_dir, agent, f"{timestamp}.yaml"))
    return {k: doc[k] for k in META_KEYS if k in doc}


def write_scene(scene: Scene, root_or_scenario_dir: str | os.PathLike, *,
                meta: Mapping[str, Mapping[str, object]] | None = None) -> Path:
    """Write every agent's ``.pcd`` and ``.yaml``; returns the scenario folder.

    The target is ``root_or_scenario_dir`` itself when its name is ``scene.scenario``,
    otherwise ``root_or_scenario_dir / scene.scenario``. Each file is written atomically.
    ``lidar_pose`` comes from the agent's pose; each box goes to the world as ``location`` =
    box centre, ``center`` = 0, ``extent`` = half sizes, ``angle`` = the box's world rotation
    as ``[roll, yaw, pitch]`` (that is ``[0, yaw, 0]`` for an upright LiDAR), ``obj_type`` =
    its label, so that reading the files back gives the same boxes. A box whose id is the
    agent's own id is left out, as the agent's own vehicle is in OPV2V. ``meta[agent_id]``
    adds :data:`META_KEYS` entries to that agent's yaml.
    Readers take the ego to be the first agent in :func:`list_agents` order, and OpenCOOD
    parses agent folder names as integers: name agents with numbers, the ego sorting first.
    """
    target = Path(root_or_scenario_dir)
    if target.name != scene.scenario:
        target = target / scene.scenario
    meta = meta or {}
    for agent_id, extra in meta.items():
        unknown = sorted(set(extra) - set(META_KEYS))
        if agent_id not in scene.agents or unknown:
            raise TypError("write_scene", f"meta[{agent_id!r}]", f"an agent of the scene and keys from {META_KEYS}",
                           unknown or agent_id)
    for name, value in [("timestamp", str(scene.timestamp)), *(("agent_id", a) for a in scene.agents)]:
        if not value or "/" in value or "\\" in value or value.startswith("."):
            raise TypError("write_scene", name, "a plain file or folder name", value)
    for agent_id, view in scene.agents.items():
        folder = target / agent_id
        doc = {"lidar_pose": [float(v) for v in geometry.matrix_to_pose(view.pose)],
               "vehicles": _world_vehicles(view)}
        doc.update({k: _plain(v) for k, v in meta.get(agent_id, {}).items()})
        write_pcd(folder / f"{scene.timestamp}.pcd", view.points, semantics=view.semantics)
        write_text(folder / f"{scene.timestamp}.yaml", yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))
    return target


def _is_rsu(agent: str) -> bool:
    try:
        return int(agent) < 0
    except ValueError:
        return False


def _load_yaml(path: Path) -> dict:
    doc = load_yaml(path, "UTF-8 yaml file", max_bytes=MAX_YAML_BYTES, loader=_Loader, field="yaml",
                    missing="an existing agent yaml")
    if not isinstance(doc, dict):
        raise TypError(path, "yaml", "a mapping with lidar_pose and vehicles", type(doc).__name__)
    return doc


def _vehicle_boxes(path: Path, doc: dict, lidar_pose: np.ndarray):
    """(K, 7) boxes in this LiDAR's frame, K labels, (K,) ids from the yaml's ``vehicles``."""
    vehicles = doc.get("vehicles")
    if vehicles is None:
        raise TypError(path, "vehicles", "a mapping of vehicle id -> {location, angle, extent, center}", "missing")
    if not isinstance(vehicles, dict):
        raise TypError(path, "vehicles", "a mapping of vehicle id -> {location, angle, extent, center}",
                       type(vehicles).__name__)
    world_to_lidar = geometry.invert(geometry.pose_to_matrix(lidar_pose))
    boxes, labels, ids = [], [], []
    for vid, v in vehicles.items():
        field = f"vehicles.{vid}"
        if isinstance(vid, bool) or not isinstance(vid, int) or vid not in _ID_RANGE:
            raise TypError(path, field, "an integer vehicle id (64-bit)", vid)
        if not isinstance(v, dict):
            raise TypError(path, field, "a mapping with location, angle, extent, center", type(v).__name__)
        location = finite_numbers(path, f"{field}.location", v.get("location"), 3)
        angle = finite_numbers(path, f"{field}.angle", v.get("angle"), 3)
        extent = finite_numbers(path, f"{field}.extent", v.get("extent"), 3)
        center = finite_numbers(path, f"{field}.center", v.get("center", [0.0, 0.0, 0.0]), 3)
        if (extent <= 0).any():
            raise TypError(path, f"{field}.extent", "positive half sizes", extent.tolist())
        obj_type = v.get("obj_type", DEFAULT_OBJ_TYPE)
        if not isinstance(obj_type, str) or not obj_type:
            raise TypError(path, f"{field}.obj_type", "a class name such as car, van, truck", obj_type)
        object_to_lidar = world_to_lidar @ geometry.pose_to_matrix(np.concatenate([location + center, angle]))
        boxes.append(_corners_to_box(object_to_lidar, extent))
        labels.append(obj_type.lower())
        ids.append(vid)
    return np.array(boxes).reshape(-1, 7), tuple(labels), np.array(ids, dtype=np.int64)


def _corners_to_box(object_to_lidar: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """OpenCOOD's create_bbx corners moved by ``object_to_lidar`` -> ``[x, y, z, l, w, h, yaw]``."""
    local = geometry.box_corners(np.array([0, 0, 0, *(2 * extent), 0.0]))[0]
    corners = local @ object_to_lidar[:3, :3].T + object_to_lidar[:3, 3]
    centre = corners[[0, 3, 5, 6]].mean(axis=0)
    # OpenCOOD averages the angles of these four parallel edges; summing the vectors first
    # gives the same yaw without its averaging across the +-pi seam.
    edge = (corners[1] - corners[2]) + (corners[0] - corners[3]) + (corners[5] - corners[6]) + (corners[4] - corners[7])
    return np.array([*centre, *(2 * extent), np.arctan2(edge[1], edge[0])])


def _world_vehicles(view: AgentView) -> dict[int, dict]:
    """The agent's boxes as OPV2V ``vehicles`` entries in world coordinates."""
    own = int(view.agent_id) if re.fullmatch(r"-?\d+", view.agent_id) else None
    out = {}
    for box, label, vid in zip(view.boxes, view.box_labels, view.box_ids):
        if own is not None and int(vid) == own:
            continue
        if int(vid) in out:
            raise TypError(view.where, "box_ids", "unique object ids (one yaml entry per vehicle)", int(vid))
        c, s = np.cos(box[6]), np.sin(box[6])
        box_to_sensor = np.array([[c, -s, 0, box[0]], [s, c, 0, box[1]], [0, 0, 1, box[2]], [0, 0, 0, 1]])
        x, y, z, roll, yaw, pitch = geometry.matrix_to_pose(view.pose @ box_to_sensor)
        out[int(vid)] = {"location": [float(x), float(y), float(z)],
                         "angle": [float(roll), float(yaw), float(pitch)],
                         "extent": [float(v) / 2 for v in box[3:6]],
                         "center": [0.0, 0.0, 0.0],
                         "obj_type": str(label)}
    return out


def _plain(value):
    """numpy scalars/arrays -> plain Python, so yaml.safe_dump can write them."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
