"""typ.formats.kitti on the real KITTI frames in shared/data, plus malformed inputs."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from typ import geometry
from typ.errors import TypError
from typ.formats.kitti import read_calib, read_kitti_frame
from repo_paths import SHARED_DATA

DATA = SHARED_DATA
KITTI = DATA / "kitti_object_vis"
KITTI_TEST = DATA / "pointpillars_kitti_demo"


@pytest.fixture(scope="module")
def kitti():
    if not (KITTI / "training" / "velodyne" / "000000.bin").is_file():
        pytest.skip("shared/data/kitti_object_vis is not available")
    return KITTI


def _in_box_counts(scene):
    return geometry.points_in_boxes(scene.ego.points, scene.ego.boxes).sum(axis=0)


def test_frame_000000_pedestrian(kitti):
    scene = read_kitti_frame(kitti, 0)
    ego = scene.ego
    assert (scene.dataset, scene.split, scene.timestamp, ego.agent_id) == ("kitti", "training", "000000", "ego")
    assert ego.points.shape == (115384, 4) and ego.points.dtype == np.float32
    np.testing.assert_array_equal(ego.pose, np.eye(4))
    assert ego.box_labels == ("pedestrian",)
    np.testing.assert_allclose(ego.boxes[0, 3:6], [1.20, 0.48, 1.89])  # (l, w, h) from h w l = 1.89 0.48 1.20
    assert ego.boxes[0, 6] == pytest.approx(-0.01 - np.pi / 2)
    assert abs(int(_in_box_counts(scene)[0]) - 377) <= 5


def test_frame_000001_counts_and_dontcare(kitti):
    scene = read_kitti_frame(kitti, "000001")
    assert scene.ego.box_labels == ("truck", "car", "cyclist")  # 4 DontCare rows skipped
    np.testing.assert_array_equal(scene.ego.box_ids, [0, 1, 2])
    np.testing.assert_allclose(_in_box_counts(scene), [72, 9, 18], atol=2)


def test_box_centre_is_lifted_by_half_height(kitti):
    """The label's bottom-face centre, moved to the LiDAR frame, lies h/2 below the box centre."""
    calib = read_calib(kitti / "training" / "calib" / "000000.txt")
    r0 = np.eye(4)
    r0[:3, :3] = calib["R0_rect"]
    tr = np.eye(4)
    tr[:3] = calib["Tr_velo_to_cam"]
    bottom = np.linalg.inv(r0 @ tr) @ [1.84, 1.47, 8.41, 1.0]
    box = read_kitti_frame(kitti, 0).ego.boxes[0]
    assert box[2] - bottom[2] == pytest.approx(1.89 / 2, abs=0.02)  # camera y is almost -z


def test_testing_split_reduced_without_labels():
    if not (KITTI_TEST / "testing" / "velodyne_reduced" / "000002.bin").is_file():
        pytest.skip("shared/data/pointpillars_kitti_demo is not available")
    scene = read_kitti_frame(KITTI_TEST, 2, split="testing")
    assert scene.ego.points.shape == (17694, 4)
    assert scene.ego.boxes.shape == (0, 7) and scene.ego.box_labels == ()
    assert (scene.ego.points[:, 0] > 0).all()


def _copy_frame(kitti, tmp_path, frame="000000"):
    root = tmp_path / "kitti"
    for sub, ext in (("velodyne", "bin"), ("calib", "txt"), ("label_2", "txt")):
        (root / "training" / sub).mkdir(parents=True)
        shutil.copy(kitti / "training" / sub / f"{frame}.{ext}", root / "training" / sub / f"{frame}.{ext}")
    return root


def _error(fn, *args, **kwargs) -> TypError:
    with pytest.raises(TypError) as info:
        fn(*args, **kwargs)
    return info.value


def test_calib_missing_r0_rect(kitti, tmp_path):
    root = _copy_frame(kitti, tmp_path)
    calib = root / "training" / "calib" / "000000.txt"
    calib.write_text("\n".join(l for l in calib.read_text().splitlines() if not l.startswith("R0_rect")))
    err = _error(read_kitti_frame, root, 0)
    assert err.where == str(calib) and err.field == "R0_rect" and "missing" in str(err)


def test_calib_wrong_number_count(kitti, tmp_path):
    root = _copy_frame(kitti, tmp_path)
    calib = root / "training" / "calib" / "000000.txt"
    lines = [l.rsplit(" ", 1)[0] if l.startswith("Tr_velo_to_cam") else l for l in calib.read_text().splitlines()]
    calib.write_text("\n".join(lines))
    err = _error(read_calib, calib)
    assert err.field == "Tr_velo_to_cam" and "12 numbers" in str(err) and str(calib) in str(err)


def test_calib_non_numeric(kitti, tmp_path):
    root = _copy_frame(kitti, tmp_path)
    calib = root / "training" / "calib" / "000000.txt"
    calib.write_text(calib.read_text().replace("R0_rect: 9.999128000000e-01", "R0_rect: nine"))
    assert _error(read_calib, calib).field == "R0_rect"


def test_missing_calib_when_labels_exist(kitti, tmp_path):
    root = _copy_frame(kitti, tmp_path)
    (root / "training" / "calib" / "000000.txt").unlink()
    err = _error(read_kitti_frame, root, 0)
    assert "calib" in err.where and err.field == "file"


def test_malformed_label_line(kitti, tmp_path):
    root = _copy_frame(kitti, tmp_path)
    label = root / "training" / "label_2" / "000000.txt"
    label.write_text("Pedestrian 0.00 0 -0.20 712.40 143.00 810.73 307.92 1.89 0.48\n")
    err = _error(read_kitti_frame, root, 0)
    assert err.where == str(label) and err.field == "line 1"


def test_missing_velodyne(tmp_path):
    (tmp_path / "training").mkdir()
    err = _error(read_kitti_frame, tmp_path, 7)
    assert err.field == "velodyne" and "000007.bin" in str(err)


def test_truncated_velodyne(kitti, tmp_path):
    root = _copy_frame(kitti, tmp_path)
    velo = root / "training" / "velodyne" / "000000.bin"
    velo.write_bytes(velo.read_bytes()[:-6])
    err = _error(read_kitti_frame, root, 0)
    assert err.where == str(velo) and err.field == "size"
