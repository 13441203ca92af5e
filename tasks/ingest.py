"""Single-agent frames from KITTI, nuScenes or Waymo as OPV2V-layout scenarios ``generate`` reads.

Each reader gives :class:`typ.scene.Scene` objects with one agent, ``"ego"``; this module
groups them into scenarios (a Waymo tfrecord is one sequence; a KITTI or nuScenes keyframe
stands alone), moves every frame into its LiDAR's sensor frame when the dataset reports
points in a vehicle frame (Waymo: origin on the ground, so the grid's z range, which is
relative to the sensor, would miss most points), and writes them with
:func:`typ.formats.opv2v.write_scene` so that the generation path is the same as for the
simulator's target split.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from typ.errors import TypError
from typ.formats.kitti import read_kitti_frame
from typ.formats.nuscenes import read_nuscenes_frame
from typ.formats.opv2v import write_scene
from typ.formats.waymo import read_waymo_frames
from typ.io import atomic_path
from typ.scene import Scene

FORMATS = ("kitti", "nuscenes", "waymo")
#: height of the top LiDAR above the vehicle frame's origin (Waymo's is on the ground under
#: the rear axle; the top LiDAR of its Pacificas sits about 2.2 m up, as the target domain's)
SENSOR_HEIGHT = {"kitti": 0.0, "nuscenes": 0.0, "waymo": 2.2}


def read_frames(fmt: str, path: str | Path) -> list[list[Scene]]:
    """Scenarios (lists of frames in time order) of single-agent data at ``path``.

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
        scenarios = []
        for f in files:
            frames = sorted(read_waymo_frames(f), key=lambda s: int(s.timestamp))
            # OpenCOOD sorts timestamps as strings: number the frames so that order is time order
            scenarios.append([dataclasses.replace(to_sensor_frame(s, SENSOR_HEIGHT["waymo"]),
                                                  scenario=_name(f), timestamp=f"{i:06d}")
                              for i, s in enumerate(frames)])
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


def write_single_agent(scenarios: list[list[Scene]], root: Path) -> list[Path]:
    """Write every scenario as ``<root>/<scenario>/<agent>/<timestamp>.pcd|.yaml``; returns the folders."""
    folders = []
    for frames in scenarios:
        target = root / frames[0].scenario
        with atomic_path(target) as tmp:
            tmp.mkdir(parents=True)
            for scene in frames:
                write_scene(dataclasses.replace(scene, scenario=tmp.name), tmp)
        folders.append(target)
    return folders
