"""nuScenes LIDAR_TOP keyframes with mmdet3d (v1.x) info records written as JSON.

Points: ``.pcd.bin`` (despite the name not a PCD), float32 x5 ``[x, y, z, intensity 0..255,
ring]`` in the LIDAR_TOP frame (x right, y forward, z up). Boxes: each instance's
``bbox_3d = [x, y, z, l, w, h, yaw]`` in the same frame with z the gravity centre (which is
typ's box convention), class ``metainfo.categories`` inverted at ``bbox_label_3d``; label -1
(ignored classes) is skipped.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from typ.errors import TypError
from typ.formats.binfile import read_bin
from typ.scene import AgentView, Scene


def read_nuscenes_frame(pcd_bin_path: str | os.PathLike, info_json_path: str | os.PathLike) -> Scene:
    """One keyframe as a single-agent Scene (agent ``"ego"``).

    points: (N, 4) float32 ``[x, y, z, intensity / 255]``; pose = ``ego2global @ lidar2ego`` (float64);
    box ids are the instances' indices in the info record (ignored ones keep their index gap).
    The info record is the ``data_list`` entry whose ``lidar_points.lidar_path`` names the bin file.
    """
    bin_path, info_path = Path(pcd_bin_path), Path(info_json_path)
    info, categories = _find_record(info_path, bin_path.name)
    cloud = read_bin(bin_path, 5)
    points = np.concatenate([cloud[:, :3], cloud[:, 3:4] / np.float32(255.0)], axis=1).astype(np.float32)
    lidar = info["lidar_points"]
    pose = _matrix(info_path, "ego2global", info.get("ego2global")) @ \
        _matrix(info_path, "lidar_points.lidar2ego", lidar.get("lidar2ego"))
    names = {index: name for name, index in categories.items()}
    instances = info.get("instances", [])
    if not isinstance(instances, list):
        raise TypError(info_path, "instances", "a list of instance records", type(instances).__name__)
    boxes, labels, ids = [], [], []
    for k, inst in enumerate(instances):
        if not isinstance(inst, dict):
            raise TypError(info_path, f"instances[{k}]", "a mapping with bbox_label_3d and bbox_3d", inst)
        label = inst.get("bbox_label_3d", inst.get("bbox_label"))
        if label == -1:
            continue
        if isinstance(label, bool) or not isinstance(label, int) or label not in names:
            raise TypError(info_path, f"instances[{k}].bbox_label_3d", f"a category index in {sorted(names)} or -1",
                           label)
        box = inst.get("bbox_3d")
        if not isinstance(box, list) or len(box) != 7 or \
                not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in box):
            raise TypError(info_path, f"instances[{k}].bbox_3d", "7 numbers [x, y, z, l, w, h, yaw]", box)
        if not np.isfinite(box).all():
            raise TypError(info_path, f"instances[{k}].bbox_3d", "7 finite numbers [x, y, z, l, w, h, yaw]", box)
        boxes.append(box)
        labels.append(names[label])
        ids.append(k)
    view = AgentView(agent_id="ego", points=points, pose=pose, boxes=np.array(boxes, dtype=np.float64).reshape(-1, 7),
                     box_labels=labels, box_ids=np.array(ids, dtype=np.int64), where=str(bin_path))
    token = str(info.get("token", bin_path.name))
    return Scene(scenario=token, timestamp=str(info.get("timestamp", "")), agents={"ego": view},
                 dataset="nuscenes", split=str(info.get("split", "")))


def _find_record(info_path: Path, bin_name: str) -> tuple[dict, dict[str, int]]:
    try:
        doc = json.loads(info_path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise TypError(info_path, "file", "an existing mmdet3d info JSON", "no such file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise TypError(info_path, "file", "a readable JSON file", f"{type(exc).__name__}: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("data_list"), list):
        raise TypError(info_path, "data_list", "a list of info records (mmdet3d v1.x)", "missing")
    metainfo = doc.get("metainfo")
    categories = metainfo.get("categories") if isinstance(metainfo, dict) else None
    if not isinstance(categories, dict) or not categories:
        raise TypError(info_path, "metainfo.categories", "a mapping of class name -> label index", categories)
    for k, record in enumerate(doc["data_list"]):
        if not isinstance(record, dict) or not isinstance(record.get("lidar_points"), dict):
            raise TypError(info_path, f"data_list[{k}]", "a mapping with lidar_points {lidar_path, lidar2ego}",
                           record if not isinstance(record, dict) else record.get("lidar_points"))
        if Path(str(record["lidar_points"].get("lidar_path", ""))).name == bin_name:
            return record, categories
    raise TypError(info_path, "data_list[].lidar_points.lidar_path", f"a record for {bin_name}",
                   f"{len(doc['data_list'])} records, none for that file")


def _matrix(info_path: Path, field: str, value) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypError(info_path, field, "a 4x4 matrix of numbers", value) from None
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise TypError(info_path, field, "a finite 4x4 matrix", m.shape)
    return m
