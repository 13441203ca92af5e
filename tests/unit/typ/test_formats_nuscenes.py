"""typ.formats.nuscenes on the real nuScenes keyframe in shared/data, plus malformed inputs."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from typ import geometry
from typ.errors import TypError
from typ.formats.nuscenes import read_nuscenes_frame
from repo_paths import SHARED_DATA

DATA = SHARED_DATA / "nuscenes_mmdet3d_demo"
BIN = "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"
INFO = "n015-2018-07-24-11-22-45+0800_mmdet3d_info.json"


@pytest.fixture(scope="module")
def files():
    if not (DATA / BIN).is_file():
        pytest.skip("shared/data/nuscenes_mmdet3d_demo is not available")
    return DATA / BIN, DATA / INFO


def test_points_boxes_and_pose(files):
    scene = read_nuscenes_frame(*files)
    ego = scene.ego
    assert scene.dataset == "nuscenes" and ego.agent_id == "ego"
    assert ego.points.shape == (34688, 4) and ego.points.dtype == np.float32
    assert 0.0 <= ego.points[:, 3].min() and ego.points[:, 3].max() <= 1.0
    assert ego.boxes.shape == (68, 7)
    info = json.loads(files[1].read_text())["data_list"][0]
    expected_pose = np.array(info["ego2global"]) @ np.array(info["lidar_points"]["lidar2ego"])
    np.testing.assert_allclose(ego.pose, expected_pose, atol=1e-12)
    assert ego.pose.dtype == np.float64
    kept = [inst for inst in info["instances"] if inst["bbox_label_3d"] != -1]
    np.testing.assert_allclose(ego.boxes, [inst["bbox_3d"] for inst in kept])
    assert ego.box_labels.count("pedestrian") == 30 and ego.box_labels.count("barrier") == 22
    assert ego.box_labels.count("car") == 8 and len(set(ego.box_ids.tolist())) == 68


def test_point_counts_follow_num_lidar_pts(files):
    scene = read_nuscenes_frame(*files)
    counts = geometry.points_in_boxes(scene.ego.points, scene.ego.boxes).sum(axis=0)
    instances = json.loads(files[1].read_text())["data_list"][0]["instances"]
    reference = np.array([instances[k]["num_lidar_pts"] for k in scene.ego.box_ids])
    assert np.corrcoef(counts, reference)[0, 1] > 0.999


def _error(*args) -> TypError:
    with pytest.raises(TypError) as info:
        read_nuscenes_frame(*args)
    return info.value


def test_info_without_record_for_the_bin(files, tmp_path):
    other = tmp_path / "other.pcd.bin"
    shutil.copy(files[0], other)
    err = _error(other, files[1])
    assert err.where == str(files[1]) and "lidar_path" in err.field and "other.pcd.bin" in str(err)


def test_bad_label_and_box(files, tmp_path):
    doc = json.loads(files[1].read_text())
    doc["data_list"][0]["instances"][3]["bbox_label_3d"] = 42
    info = tmp_path / "info.json"
    info.write_text(json.dumps(doc))
    err = _error(files[0], info)
    assert err.where == str(info) and err.field == "instances[3].bbox_label_3d"
    doc["data_list"][0]["instances"][3]["bbox_label_3d"] = 0
    doc["data_list"][0]["instances"][3]["bbox_3d"] = [1, 2, 3]
    info.write_text(json.dumps(doc))
    assert _error(files[0], info).field == "instances[3].bbox_3d"


def test_malformed_json_and_matrix(files, tmp_path):
    info = tmp_path / "info.json"
    info.write_text("{not json")
    assert _error(files[0], info).field == "file"
    doc = json.loads(files[1].read_text())
    doc["data_list"][0]["ego2global"] = [[1, 0, 0], [0, 1, 0]]
    info.write_text(json.dumps(doc))
    err = _error(files[0], info)
    assert err.field == "ego2global" and "4x4" in str(err)


def test_bin_with_wrong_column_count(files, tmp_path):
    short = tmp_path / BIN
    short.write_bytes(files[0].read_bytes()[:-8])
    err = _error(short, files[1])
    assert err.where == str(short) and err.field == "size" and "multiple of 20" in str(err)
