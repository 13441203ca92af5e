"""Bad-input cases: paths a dataset names that leave its root (registered with :func:`bad_inputs.make_corpus.case`).

Each case builds a dataset under ``<case>/data`` and, under ``<case>/outside``, a valid file or folder
that a path of the dataset leads to: absolute, through a ``..`` that climbs out, or through a link
in the root whose target lies outside it. Read, that file would give a frame and the call would
return: the case asks for the named error instead (:func:`typ.inputs.inside`), and
tests/unit/typ/test_inputs_inside.py checks, with an audit hook, that nothing under ``outside`` was opened.
The root itself being a link is legitimate (``kitti_root_is_a_link``).
"""
from __future__ import annotations

import json
from pathlib import Path

import yaml

from bad_inputs.make_corpus import (CALIB, NUSCENES_BIN, Probe, case, cloud, kitti_frame, nuscenes_info, opv2v_doc,
                                    opv2v_scenario, tfrecord, write)
from tasks.ingest import list_dataset, read_frames
from typ.formats.kitti import read_kitti_frame
from typ.formats.opv2v import check_root, check_scenario, read_scene, scenario_sensor

#: every case's expected text: the error says where a path must lead
INSIDE = "a path inside"


def roots(d: Path) -> tuple[Path, Path]:
    """(the dataset root, the folder outside it that its paths lead to)."""
    (d / "data").mkdir()
    (d / "outside").mkdir()
    return d / "data", d / "outside"


def link(path: Path, target: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.symlink_to(target)
    return path


# ---------------------------------------------------------------- nuscenes: info records' lidar_path


def nuscenes_root(d: Path, lidar_path: str) -> tuple[Path, Path, Path]:
    """(root with ``info.json`` whose one record names ``lidar_path``, its info file, a valid cloud outside)."""
    root, outside = roots(d)
    outside_bin = write(outside / NUSCENES_BIN, cloud(columns=5).tobytes())
    doc = nuscenes_info()
    doc["data_list"][0]["lidar_points"]["lidar_path"] = lidar_path.format(outside=outside)
    return root, write(root / "info.json", json.dumps(doc)), outside_bin


def lidar_path_refused(root: Path, info: Path) -> Probe:
    """What ``typ generate --format nuscenes`` lists (:func:`tasks.ingest.read_frames`) refused, naming the record."""
    return Probe(says=(str(info), "data_list[0].lidar_points.lidar_path", INSIDE),
                 call=lambda: read_frames("nuscenes", root))


@case("nuscenes", "lidar_path_absolute", "unreadable")
def _(d):
    return lidar_path_refused(*nuscenes_root(d, "{outside}/" + NUSCENES_BIN)[:2])


@case("nuscenes", "lidar_path_climbs_out", "unreadable")
def _(d):
    return lidar_path_refused(*nuscenes_root(d, "../outside/" + NUSCENES_BIN)[:2])


@case("nuscenes", "lidar_file_links_out", "unreadable")
def _(d):
    root, info, outside_bin = nuscenes_root(d, NUSCENES_BIN)
    link(root / "samples" / "LIDAR_TOP" / NUSCENES_BIN, outside_bin)   # where mmdet3d v1.x's bare name is looked up
    return lidar_path_refused(root, info)


@case("nuscenes", "info_file_links_out", "unreadable")
def _(d):
    root, outside = roots(d)
    write(root / NUSCENES_BIN, cloud(columns=5).tobytes())
    info = link(root / "mmdet3d_info.json", write(outside / "info.json", json.dumps(nuscenes_info())))
    return Probe(says=(str(info), INSIDE), call=lambda: read_frames("nuscenes", root))


# ---------------------------------------------------------------- kitti: frames found, split files, frame ids


@case("kitti", "velodyne_links_out", "unreadable")
def _(d):
    root, outside = roots(d)
    kitti_frame(root)
    scan = root / "training" / "velodyne" / "000000.bin"
    scan.unlink()
    link(scan, write(outside / "000000.bin", cloud().tobytes()))
    return Probe(says=(str(scan), INSIDE), call=lambda: list_dataset("kitti", root))


@case("kitti", "split_folder_links_out", "unreadable")
def _(d):
    root, outside = roots(d)
    kitti_frame(outside)
    training = link(root / "training", outside / "training")
    return Probe(says=(str(training / "velodyne" / "000000.bin"), INSIDE), call=lambda: list_dataset("kitti", root))


@case("kitti", "imagesets_links_out", "unreadable")
def _(d):
    root, outside = roots(d)
    kitti_frame(root)
    split = link(root / "ImageSets" / "train.txt", write(outside / "train.txt", "000000\n"))
    return Probe(says=(str(split), INSIDE), call=lambda: list_dataset("kitti", root))


@case("kitti", "calib_links_out", "unreadable")
def _(d):
    root, outside = roots(d)
    kitti_frame(root, calib=None)
    calib = link(root / "training" / "calib" / "000000.txt", write(outside / "calib.txt", CALIB))
    return Probe(says=(str(calib), INSIDE), call=lambda: read_kitti_frame(root, 0))


@case("kitti", "frame_id_climbs_out", "unreadable")
def _(d):
    root, outside = roots(d)
    kitti_frame(root)
    write(outside / "000000.bin", cloud().tobytes())
    frame = "../../../outside/000000"   # from training/velodyne/ up to the case folder
    return Probe(says=(str(root), "frame_id", "a plain name"), call=lambda: read_kitti_frame(root, frame))


@case("kitti", "root_is_a_link", "unreadable")
def _(d):
    _, outside = roots(d)
    kitti_frame(outside)
    root = link(d / "data" / "kitti", outside)   # the user's own link to a dataset kept elsewhere: read
    return Probe(says=(), call=lambda: [s.name for s in list_dataset("kitti", root)[0]],
                 returns=["kitti_training_000000"])


# ---------------------------------------------------------------- waymo: segments found


@case("waymo", "segment_links_out", "unreadable")
def _(d):
    root, outside = roots(d)
    segment = link(root / "training" / "seg.tfrecord", write(outside / "seg.tfrecord", tfrecord(b"frame")))
    return Probe(says=(str(segment), INSIDE), call=lambda: list_dataset("waymo", root))


# ---------------------------------------------------------------- opv2v: scenario and agent folders, .pcd/.yaml


def outside_agent(outside: Path) -> Path:
    """A valid agent folder ``outside/scn/1`` (000068.yaml + .pcd)."""
    return opv2v_scenario(outside).parent


@case("opv2v", "agent_folder_is_a_link", "unreadable")
def _(d):
    root, outside = roots(d)
    y = opv2v_scenario(root)
    # a scenario assembled from links to agent folders of a dataset kept elsewhere, as OPV2V and
    # V2V4Real copies often are: each agent folder is read as the folder it leads to
    link(y.parent.parent / "2", outside_agent(outside))
    return Probe(says=(), call=lambda: list(read_scene(y.parent.parent, y.stem).agents), returns=["1", "2"])


@case("opv2v", "agent_absolute", "unreadable")
def _(d):
    root, outside = roots(d)
    y = opv2v_scenario(root)
    agent = outside_agent(outside)
    return Probe(says=(str(y.parent.parent), "agent", "an agent folder name"),
                 call=lambda: read_scene(y.parent.parent, y.stem, agents=["1", str(agent)]))


@case("opv2v", "timestamp_climbs_out", "unreadable")
def _(d):
    root, outside = roots(d)
    y = opv2v_scenario(root)
    outside_agent(outside)
    stamp = "../../../outside/scn/1/000068"
    return Probe(says=(INSIDE,), call=lambda: read_scene(y.parent.parent, stamp, agents=["1"]))


@case("opv2v", "pcd_links_out", "unreadable")
def _(d):
    root, outside = roots(d)
    y = opv2v_scenario(root)
    pcd = y.with_suffix(".pcd")
    pcd.unlink()
    link(pcd, outside_agent(outside) / "000068.pcd")
    return Probe(says=(str(pcd), INSIDE), call=lambda: read_scene(y.parent.parent, y.stem))


@case("opv2v", "yaml_links_out", "unreadable")
def _(d):
    root, outside = roots(d)
    y = opv2v_scenario(root)
    y.unlink()
    link(y, outside_agent(outside) / "000068.yaml")
    return Probe(says=(str(y), INSIDE), call=lambda: check_scenario(y.parent.parent))


@case("opv2v", "extra_pcd_links_out", "unreadable")
def _(d):
    root, outside = roots(d)
    y = opv2v_scenario(root)
    # not a frame of the ego, but a file that taking the scenario into simulate's output would copy
    extra = link(y.parent / "000099.pcd", outside_agent(outside) / "000068.pcd")
    return Probe(says=(str(extra), INSIDE), call=lambda: check_scenario(y.parent.parent))


@case("opv2v", "pcd_links_out_of_a_linked_agent_folder", "unreadable")
def _(d):
    root, outside = roots(d)
    y = opv2v_scenario(root)
    kept = opv2v_scenario(root / "store").parent          # an agent folder kept elsewhere, linked in
    link(y.parent.parent / "2", kept)
    (kept / "000068.pcd").unlink()
    link(kept / "000068.pcd", outside_agent(outside) / "000068.pcd")   # its file leads out of that folder
    pcd = y.parent.parent / "2" / "000068.pcd"
    return Probe(says=(str(pcd), INSIDE), call=lambda: read_scene(y.parent.parent, y.stem))


@case("opv2v", "split_climbs_out", "unreadable")
def _(d):
    root, outside = roots(d)
    outside_agent(outside)
    return Probe(says=(str(root), "split", "a split folder name"), call=lambda: check_root(root, ["../outside"]))


@case("opv2v", "sensor_names_a_path", "unknown")
def _(d):
    y = opv2v_scenario(d, yaml.safe_dump({**opv2v_doc(), "sensor": "../../etc/passwd"}))
    return Probe(says=(str(y), "sensor", "the name of a known LiDAR"), call=lambda: scenario_sensor(y.parent.parent))
