"""nuScenes LIDAR_TOP keyframes with mmdet3d (v1.x) info records written as JSON.

Points: ``.pcd.bin`` (despite the name not a PCD), float32 x5 ``[x, y, z, intensity 0..255,
ring]`` in the LIDAR_TOP frame (x right, y forward, z up). Boxes: each instance's
``bbox_3d = [x, y, z, l, w, h, yaw]`` in the same frame with z the gravity centre (which is
typ's box convention), class ``metainfo.categories`` inverted at ``bbox_label_3d``; label -1
(ignored classes) is skipped.

The info JSON is read as untrusted: at most :data:`MAX_INFO_BYTES`, nested at most
:data:`typ.inputs.MAX_DEPTH`, and every value used checked for its type and range, so a
record of the wrong shape is a TypError naming its field, never a TypeError or OverflowError.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from typ.errors import TypError
from typ.formats.binfile import read_bin
from typ.inputs import MiB, finite_matrix, finite_numbers, load_json
from typ.scene import AgentView, Scene

#: mmdet3d's info file for one split of nuScenes trainval is tens of MB; a hostile JSON within
#: this cap stays under 1 GB once parsed
MAX_INFO_BYTES = 128 * MiB


def read_nuscenes_frame(pcd_bin_path: str | os.PathLike, info_json_path: str | os.PathLike) -> Scene:
    """One keyframe as a single-agent Scene (agent ``"ego"``).

    points: (N, 4) float32 ``[x, y, z, intensity / 255]``; pose = ``ego2global @ lidar2ego`` (float64);
    box ids are the instances' indices in the info record (ignored ones keep their index gap).
    The info record is the ``data_list`` entry whose ``lidar_points.lidar_path`` names the bin file.
    """
    bin_path, info_path = Path(pcd_bin_path), Path(info_json_path)
    info, categories = _find_record(info_path, bin_path.name)
    return record_frame(info, categories, bin_path, info_path)


def record_frame(info: dict, categories: dict[str, int], bin_path: str | os.PathLike,
                 info_path: str | os.PathLike) -> Scene:
    """The keyframe of one info record (an entry of :func:`read_info`'s records) whose point cloud
    is ``bin_path``, as :func:`read_nuscenes_frame` reads it; ``info_path`` names the record in errors."""
    bin_path, info_path = Path(bin_path), Path(info_path)
    cloud = read_bin(bin_path, 5)
    points = np.concatenate([cloud[:, :3], cloud[:, 3:4] / np.float32(255.0)], axis=1).astype(np.float32)
    lidar = info["lidar_points"]
    pose = finite_matrix(info_path, "ego2global", info.get("ego2global"), 4, 4) @ \
        finite_matrix(info_path, "lidar_points.lidar2ego", lidar.get("lidar2ego"), 4, 4)
    names = {index: name for name, index in categories.items()}
    instances = info.get("instances", [])
    if not isinstance(instances, list):
        raise TypError(info_path, "instances", "a list of instance records", type(instances).__name__)
    boxes, labels, ids = [], [], []
    for k, inst in enumerate(instances):
        if not isinstance(inst, dict):
            raise TypError(info_path, f"instances[{k}]", "a mapping with bbox_label_3d and bbox_3d", inst)
        label = inst.get("bbox_label_3d", inst.get("bbox_label"))
        is_int = isinstance(label, int) and not isinstance(label, bool)
        if is_int and label == -1:
            continue
        if not is_int or label not in names:
            raise TypError(info_path, f"instances[{k}].bbox_label_3d", f"a category index in {sorted(names)} or -1",
                           label)
        boxes.append(finite_numbers(info_path, f"instances[{k}].bbox_3d", inst.get("bbox_3d"), 7))
        labels.append(names[label])
        ids.append(k)
    view = AgentView(agent_id="ego", points=points, pose=pose, boxes=np.array(boxes, dtype=np.float64).reshape(-1, 7),
                     box_labels=labels, box_ids=np.array(ids, dtype=np.int64), where=str(bin_path))
    token = _name(info_path, "token", info.get("token", bin_path.name))
    return Scene(scenario=token, timestamp=_name(info_path, "timestamp", info.get("timestamp", "")),
                 agents={"ego": view}, dataset="nuscenes", split=_name(info_path, "split", info.get("split", "")))


def _find_record(info_path: Path, bin_name: str) -> tuple[dict, dict[str, int]]:
    """(the record whose lidar_path names ``bin_name``, the categories name -> label index)."""
    records, categories = read_info(info_path)
    for record in records:
        if Path(record["lidar_points"]["lidar_path"]).name == bin_name:
            return record, categories
    raise TypError(info_path, "data_list[].lidar_points.lidar_path", f"a record for {bin_name}",
                   f"{len(records)} records, none for that file")


def read_info(info_path: str | os.PathLike) -> tuple[list[dict], dict[str, int]]:
    """An mmdet3d (v1.x) info JSON: (its ``data_list`` records, each a mapping with
    ``lidar_points.lidar_path`` a string; the categories name -> label index)."""
    info_path = Path(info_path)
    doc = load_json(info_path, "mmdet3d info JSON", max_bytes=MAX_INFO_BYTES)
    if not isinstance(doc, dict) or not isinstance(doc.get("data_list"), list):
        raise TypError(info_path, "data_list", "a list of info records (mmdet3d v1.x)", "missing")
    metainfo = doc.get("metainfo")
    categories = metainfo.get("categories") if isinstance(metainfo, dict) else None
    if not isinstance(categories, dict) or not categories or \
            not all(isinstance(v, int) and not isinstance(v, bool) for v in categories.values()):
        raise TypError(info_path, "metainfo.categories", "a mapping of class name -> integer label index", categories)
    for k, record in enumerate(doc["data_list"]):
        if not isinstance(record, dict) or not isinstance(record.get("lidar_points"), dict):
            raise TypError(info_path, f"data_list[{k}]", "a mapping with lidar_points {lidar_path, lidar2ego}",
                           record if not isinstance(record, dict) else record.get("lidar_points"))
        lidar_path = record["lidar_points"].get("lidar_path", "")
        if not isinstance(lidar_path, str) or not lidar_path:
            raise TypError(info_path, f"data_list[{k}].lidar_points.lidar_path", "a file name", lidar_path)
    return doc["data_list"], categories


def _name(info_path: Path, field: str, value) -> str:
    """A token, timestamp or split as text: a string or a number (mmdet3d's timestamps are seconds)."""
    if isinstance(value, str) or isinstance(value, float) or \
            (isinstance(value, int) and not isinstance(value, bool) and abs(value) < 2**63):
        return str(value)  # an integer of 5,000 digits would make str() raise
    raise TypError(info_path, field, "a string or a number", value)
