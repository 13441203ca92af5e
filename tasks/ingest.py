"""Single-agent frames from KITTI, nuScenes or Waymo as OPV2V-layout scenarios ``generate`` reads.

Each reader gives :class:`typ.scene.Scene` objects with one agent, ``"ego"``; this module
groups them into scenarios (a Waymo tfrecord is one sequence, read and written one frame at a
time; a KITTI or nuScenes keyframe stands alone), moves every frame into its LiDAR's sensor
frame when the dataset reports points in a vehicle frame (Waymo: origin on the ground, so the
grid's z range, which is relative to the sensor, would miss most points), and writes them with
:func:`typ.formats.opv2v.write_scene` so that the generation path is the same as for the
simulator's target split.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from typ.errors import TypError
from typ.formats.kitti import read_kitti_frame
from typ.formats.nuscenes import read_nuscenes_frame
from typ.formats.opv2v import write_scene
from typ.formats.waymo import iter_waymo_frames
from typ.io import atomic_path, write_manifest
from typ.scene import Scene
from typ.sensors import resolve

FORMATS = ("kitti", "nuscenes", "waymo")
#: what the manifest of a scenario written here names as its writer (typ.io.write_manifest)
STAGE = "ingest"
#: each dataset's LiDAR height above the road in the frame the scenarios are written in (the
#: voxel grid's z is relative to it): its preset's, with the source (typ.sensors.presets)
MOUNT_HEIGHT = {fmt: resolve(fmt).mount_height for fmt in FORMATS}
#: the formats whose points come in the vehicle frame, origin on the ground under the rear axle
#: (Waymo), not the LiDAR's
_VEHICLE_FRAME = ("waymo",)
#: height of the LiDAR above the frame its points come in: 0 where that is the LiDAR's own
SENSOR_HEIGHT = {fmt: MOUNT_HEIGHT[fmt] if fmt in _VEHICLE_FRAME else 0.0 for fmt in FORMATS}


@dataclass(frozen=True)
class WaymoSegment:
    """One Waymo tfrecord as a scenario: iterating it reads its frames one at a time, in file
    order, moved to the top LiDAR's frame (a real segment is about 1 GB; no more than a frame
    is held)."""

    path: Path

    def __iter__(self) -> Iterator[Scene]:
        name = _name(self.path)
        for scene in iter_waymo_frames(self.path):
            yield dataclasses.replace(to_sensor_frame(scene, SENSOR_HEIGHT["waymo"]), scenario=name)


def read_frames(fmt: str, path: str | Path) -> list[list[Scene] | WaymoSegment]:
    """Scenarios (iterables of frames) of single-agent data at ``path``: a list of frames per
    KITTI / nuScenes keyframe, a :class:`WaymoSegment` per Waymo tfrecord.

    kitti: a KITTI object root holding ``training/`` and/or ``testing/`` (velodyne or
    velodyne_reduced, label_2, calib); every frame is its own scenario.
    nuscenes: a folder of ``*.pcd.bin`` keyframes and one mmdet3d ``*_info.json``.
    waymo: a ``.tfrecord`` file or a folder of them; each file is one scenario.
    """
    path = Path(path)
    if fmt not in FORMATS:
        raise TypError("typ generate", "--format", f"one of {list(FORMATS)}", fmt)
    if not path.exists():
        raise TypError(path, "--input", f"an existing {fmt} file or folder", "not found")
    if fmt == "kitti":
        scenarios = []
        for split in ("training", "testing"):
            names = sorted({p.stem for folder in ("velodyne", "velodyne_reduced")
                            for p in (path / split / folder).glob("*.bin")})
            for name in names:
                scene = read_kitti_frame(path, name, split)
                scenarios.append([dataclasses.replace(scene, scenario=f"kitti_{split}_{name}", timestamp="000000")])
    elif fmt == "nuscenes":
        infos = sorted(path.glob("*_info*.json")) if path.is_dir() else []
        if len(infos) != 1:
            raise TypError(path, "--input", "a folder with *.pcd.bin keyframes and exactly one mmdet3d *_info.json",
                           [p.name for p in infos])
        scenarios = [[dataclasses.replace(read_nuscenes_frame(b, infos[0]), scenario=_name(b), timestamp="000000")]
                     for b in sorted(path.glob("*.pcd.bin"))]
    else:
        files = sorted(path.glob("*.tfrecord")) if path.is_dir() else [path]
        scenarios = [WaymoSegment(f) for f in files]
    if not scenarios:
        raise TypError(path, "--input", f"{fmt} frames", "none found")
    return scenarios


def _name(path: Path) -> str:
    stem = path.name.split(".")[0]
    return "".join(c if c.isalnum() or c in "_-" else "_" for c in stem)[:80]


def to_sensor_frame(scene: Scene, height: float) -> Scene:
    """Move the ego's points, boxes and pose from a vehicle frame to a sensor ``height`` m above it."""
    if height == 0.0:
        return scene
    ego = scene.ego
    lift = np.eye(4)
    lift[2, 3] = height
    points = ego.points.copy()
    points[:, 2] -= np.float32(height)
    boxes = ego.boxes.copy()
    boxes[:, 2] -= height
    view = dataclasses.replace(ego, points=points, boxes=boxes, pose=ego.pose @ lift)
    return dataclasses.replace(scene, agents={ego.agent_id: view})


def write_single_agent(scenarios: Iterable[Iterable[Scene]], root: Path) -> list[Path]:
    """Write every scenario as ``<root>/<scenario>/<agent>/<timestamp>.pcd|.yaml``, frame by frame as
    the scenario yields them, numbered ``000000``, ``000001``, ... in time order, with its manifest;
    returns the folders."""
    folders = []
    for scenario in scenarios:
        frames = iter(scenario)
        first = next(frames)
        target = root / first.scenario
        frames = _chain(first, frames)
        del first
        with atomic_path(target, stage=STAGE) as tmp:
            tmp.mkdir(parents=True)
            stamps = []
            for scene in frames:
                write_scene(dataclasses.replace(scene, scenario=tmp.name), tmp)
                stamps.append(scene.timestamp)
                del scene
            _number_in_time_order(tmp, stamps)
            write_manifest(tmp, STAGE, {"frames": len(stamps)})
        folders.append(target)
    return folders


def _chain(first: Scene, rest: Iterator[Scene]) -> Iterator[Scene]:
    """``first``, then ``rest``, holding ``first`` no longer than it takes to hand it on."""
    yield first
    del first
    yield from rest


def _number_in_time_order(folder: Path, stamps: list[str]) -> None:
    """Rename each frame's files from its timestamp to its rank in time: OpenCOOD sorts timestamps
    as strings, and ``000010`` after ``000009`` keeps that order the time order."""
    if len(set(stamps)) != len(stamps):
        dup = next(t for t in stamps if stamps.count(t) > 1)
        raise TypError(folder.name, "timestamp", "one frame per timestamp in a scenario", dup)
    ranked = sorted(stamps, key=lambda t: (int(t), t) if t.isdigit() else (float("inf"), t))
    renames = {old: f"{i:06d}" for i, old in enumerate(ranked) if old != f"{i:06d}"}
    agents = [d for d in folder.iterdir() if d.is_dir()]
    for stage in ("tmp", "final"):   # through temporary names: a new name may be another frame's old one
        for old, new in renames.items():
            for agent in agents:
                for suffix in (".pcd", ".yaml"):
                    src = agent / (f"{old}{suffix}" if stage == "tmp" else f".rank-{new}{suffix}")
                    dst = agent / (f".rank-{new}{suffix}" if stage == "tmp" else f"{new}{suffix}")
                    if src.exists():
                        src.rename(dst)
