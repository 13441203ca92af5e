"""Bad-input cases: nuScenes keyframes (.pcd.bin + mmdet3d info JSON) (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

import numpy as np

from typ.formats.nuscenes import read_nuscenes_frame

from bad_inputs.make_corpus import NUSCENES_BIN, Probe, case, cloud, nuscenes_frame, nuscenes_info


@case("nuscenes", "info_not_json", "wrong dtype")
def _(d):
    b, i = nuscenes_frame(d, '{"data_list": [')
    return Probe(says=(str(i), "file", "a readable mmdet3d info JSON", "JSONDecodeError"),
                 call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "info_without_data_list", "missing keys")
def _(d):
    b, i = nuscenes_frame(d, {"metainfo": {"categories": {"car": 0}}})
    return Probe(says=(str(i), "data_list", "a list of info records"), call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "info_without_record_for_bin", "missing keys")
def _(d):
    info = nuscenes_info()
    info["data_list"][0]["lidar_points"]["lidar_path"] = "other.pcd.bin"
    b, i = nuscenes_frame(d, info)
    return Probe(says=(str(i), "lidar_path", f"a record for {NUSCENES_BIN}"), call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "record_not_a_mapping", "wrong dtype")
def _(d):
    info = nuscenes_info()
    info["data_list"].insert(0, "n015__LIDAR_TOP")
    b, i = nuscenes_frame(d, info)
    return Probe(says=(str(i), "data_list[0]", "a mapping"), call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "instance_not_a_mapping", "wrong dtype")
def _(d):
    b, i = nuscenes_frame(d, nuscenes_info(instances=[[18.4, 5.5, 0.7, 4.1, 1.8, 1.6, 3.1]]))
    return Probe(says=(str(i), "instances[0]", "a mapping"), call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "label_is_a_list", "wrong dtype")
def _(d):
    b, i = nuscenes_frame(d, nuscenes_info(instances=[{"bbox_label_3d": [0], "bbox_3d": [1, 2, 0, 4, 2, 1.5, 0]}]))
    return Probe(says=(str(i), "instances[0].bbox_label_3d", "a category index"),
                 call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "bbox_6_numbers", "misaligned")
def _(d):
    b, i = nuscenes_frame(d, nuscenes_info(instances=[{"bbox_label_3d": 0, "bbox_3d": [1, 2, 0, 4, 2, 1.5]}]))
    return Probe(says=(str(i), "instances[0].bbox_3d", "7 numbers"), call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "bbox_nan", "nan/inf")
def _(d):
    box = [1, 2, 0, 4, float("nan"), 1.5, 0]  # json writes NaN, and Python's json reads it back
    b, i = nuscenes_frame(d, nuscenes_info(instances=[{"bbox_label_3d": 0, "bbox_3d": box}]))
    return Probe(says=(str(i), "instances[0].bbox_3d", "finite"), call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "ego2global_3x3", "misaligned")
def _(d):
    b, i = nuscenes_frame(d, nuscenes_info(ego2global=np.eye(3).tolist()))
    return Probe(says=(str(i), "ego2global", "a finite 4x4 matrix"), call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "bin_with_4_columns", "misaligned")
def _(d):
    b, i = nuscenes_frame(d, points=cloud(63, 4))  # a KITTI-style x4 cloud where x5 is expected
    return Probe(says=(str(b), "size", "a multiple of 20 bytes"), call=lambda: read_nuscenes_frame(b, i))
