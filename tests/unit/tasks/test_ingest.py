"""A domain read from a single-agent dataset (``simulate.sources.<domain>: {format: kitti | nuscenes |
waymo, root, splits}``): splits, sequences, the checks before anything is written, the skip of
unchanged inputs, frames streamed one at a time, and the bad inputs each named.

The KITTI, nuScenes and Waymo frames in ../shared/data are copied and broken one way at a time
(those tests skip without them); the split rules, nuScenes sequences and streaming use synthetic
datasets written here.
"""
from __future__ import annotations

import gc
import hashlib
import json
import os
import shutil
import weakref
from pathlib import Path

import numpy as np
import pytest

from tasks.ingest import (DEFAULT_FRACTIONS, DatasetScenario, assign_splits, list_dataset, name_hash,
                          write_frames)
from tasks.simulate import plan_jobs, run_job
from typ.config import config_from_dict
from typ.errors import TypError
from typ.formats.opv2v import list_timestamps, read_scene, scenario_sensor
from typ.scene import AgentView, Scene
from repo_paths import SHARED_DATA

DATA = SHARED_DATA
KITTI, KITTI_TEST = DATA / "kitti_object_vis" / "training", DATA / "pointpillars_kitti_demo" / "testing"
NUSCENES, WAYMO = DATA / "nuscenes_mmdet3d_demo", DATA / "waymo_mmdet3d_testdata"
real_data = pytest.mark.skipif(not all(p.is_dir() for p in (KITTI, KITTI_TEST, NUSCENES, WAYMO)),
                               reason="../shared/data (the real KITTI, nuScenes and Waymo frames) not present")


def kitti_copy(dst: Path, splits: dict[str, str] | None = None) -> Path:
    """A KITTI object root copied from the shared frames (training 000000, 000001; testing 000002),
    with ImageSets files ``{name: text}``."""
    shutil.copytree(KITTI, dst / "training")
    shutil.copytree(KITTI_TEST, dst / "testing")
    if splits:
        (dst / "ImageSets").mkdir()
        for name, text in splits.items():
            (dst / "ImageSets" / f"{name}.txt").write_text(text)
    return dst


def params(sources, **counts) -> dict:
    """Tiny params with only the target domain, read from ``sources``; ``counts``: target split -> scenarios."""
    return {"simulate": {"sources": {"target": sources}, "workers": 1,
                         "scenarios": {"source": {"train": 0, "test": 0}, "real_cav": {"train": 0, "test": 0},
                                       "target": {"train": 0, "val": 0, "test": 0, "pretrain": 0, **counts}}}}


def plan(tmp_path: Path, sources, **counts):
    cfg = config_from_dict(params(sources, **counts)).simulate
    return plan_jobs(cfg, root=tmp_path, out=tmp_path / "out")


def named(tmp_path: Path, sources, **counts) -> str:
    """The TypError planning ``sources`` raises (it must raise, and write nothing)."""
    with pytest.raises(TypError) as info:
        plan(tmp_path, sources, **counts)
    assert not (tmp_path / "out").exists()
    return str(info.value)


def fake(names: list[str]) -> list[DatasetScenario]:
    return [DatasetScenario("waymo", n, ()) for n in names]


# ---------------------------------------------------------------- splits


def test_a_dataset_without_splits_is_shared_out_by_the_hash_of_each_name():
    names = [f"segment-{i:04d}" for i in range(400)]
    shares = assign_splits("waymo", (fake(names), {}), {}, where="p", field="f")
    edges = np.cumsum([0.0, *DEFAULT_FRACTIONS.values()])
    for k, split in enumerate(DEFAULT_FRACTIONS):
        # independently: the first 8 bytes of sha256(name) as a fraction of 2^64
        want = [n for n in names
                if edges[k] <= int(hashlib.sha256(n.encode()).hexdigest()[:16], 16) / 2**64 < edges[k + 1]]
        assert [s.name for s in shares[split].scenarios] == want
        assert abs(len(want) / len(names) - DEFAULT_FRACTIONS[split]) < 0.06
        assert f"in [{edges[k]:.3g}, {edges[k + 1]:.3g})" in shares[split].rule
    assert sum(len(s.scenarios) for s in shares.values()) == len(names)   # every scenario, once
    assert name_hash("segment-0000") == int(hashlib.sha256(b"segment-0000").hexdigest()[:16], 16) / 2**64


def test_a_datasets_own_splits_map_by_name_and_fractions_share_what_no_list_takes():
    names = [f"f{i:03d}" for i in range(100)]
    own = {"training": names[:80], "validation": names[80:]}
    default = assign_splits("waymo", (fake(names), own), {}, where="p", field="f")
    assert {k: len(v.scenarios) for k, v in default.items()} == {"train": 80, "val": 20}
    assert default["train"].rule == "waymo split training"
    mixed = assign_splits("waymo", (fake(names), own), {"test": ["validation"], "train": 0.5, "pretrain": 0.5},
                          where="p", field="f")
    assert [s.name for s in mixed["test"].scenarios] == names[80:]
    pool = [s.name for s in mixed["train"].scenarios + mixed["pretrain"].scenarios]
    assert sorted(pool) == names[:80]                                # the rest, each once
    assert all(name_hash(n) < 0.5 for n in (s.name for s in mixed["train"].scenarios))
    with pytest.raises(TypError, match=r"p: f\.splits\.val: expected split names this waymo root has: "
                                       r"\['training', 'validation'\], got 'val'"):
        assign_splits("waymo", (fake(names), own), {"val": ["val"]}, where="p", field="f")
    with pytest.raises(TypError, match=r"f\.splits: expected typ splits that share no scenario, got 'f080 in both"):
        assign_splits("waymo", (fake(names), {**own, "all": names}), {"train": ["all"], "val": ["validation"]},
                      where="p", field="f")


def test_the_source_block_is_checked_with_the_params():
    for block, field in (({"format": "lyft", "root": "x"}, "simulate.sources.target.format"),
                         ({"format": "kitti", "root": " "}, "simulate.sources.target.root"),
                         ({"format": "kitti", "root": "x", "splits": {"train": 1.5}},
                          "simulate.sources.target.splits.train"),
                         ({"format": "kitti", "root": "x", "splits": {"train": 0.7, "val": 0.4}},
                          "simulate.sources.target.splits"),
                         ({"format": "opv2v", "root": "x", "splits": {"train": 0.5}}, "simulate.sources.target.splits"),
                         ([{"format": "kitti", "root": "x"}, {"format": "kitti"}], "simulate.sources.target[1].root"),
                         ([], "simulate.sources.target")):
        with pytest.raises(TypError) as info:
            config_from_dict(params(block, train=1))
        assert str(info.value).startswith(f"params.yaml: {field}: expected "), str(info.value)
    cfg = config_from_dict(params("relative/opv2v", train=1)).simulate
    assert [(b.format, b.root) for b in cfg.source_blocks("target")] == [("opv2v", "relative/opv2v")]


# ---------------------------------------------------------------- sequences and streaming


def _nuscenes_root(root: Path, records: list[dict]) -> Path:
    """A nuScenes root: one 100-point cloud per record and an mmdet3d info JSON ``*_infos_val.json``."""
    root.mkdir()
    rng = np.random.default_rng(0)
    for r in records:
        cloud = np.c_[rng.uniform(-20, 20, (100, 3)), rng.uniform(0, 255, 100), np.zeros(100)].astype("<f4")
        cloud.tofile(root / r["lidar_points"]["lidar_path"])
    doc = {"metainfo": {"categories": {"car": 0}}, "data_list": records}
    (root / "nuscenes_infos_val.json").write_text(json.dumps(doc))
    return root


def _record(name: str, t: float, x: float, scene: str | None) -> dict:
    pose = np.eye(4)
    pose[0, 3] = x   # where the car was: the order of the frames, read back
    rec = {"token": name, "timestamp": t, "ego2global": pose.tolist(),
           "lidar_points": {"lidar_path": f"{name}.pcd.bin", "lidar2ego": np.eye(4).tolist()},
           "instances": [{"bbox_label_3d": 0, "bbox_3d": [5.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0]}]}
    return {**rec, "scene_token": scene} if scene else rec


def test_a_nuscenes_scene_is_one_scenario_in_time_order_and_a_lone_keyframe_its_own(tmp_path):
    root = _nuscenes_root(tmp_path / "nuscenes", [
        _record("b", 1532402928.1, 2.0, "s1"), _record("lone", 1532402930.0, 9.0, None),
        _record("a", 1532402927.6, 1.0, "s1"), _record("c", 1532402928.6, 3.0, "s1")])
    scenarios, splits = list_dataset("nuscenes", root)
    assert [s.name for s in scenarios] == ["lone", "nuscenes_s1"] and splits == {"val": ["lone", "nuscenes_s1"]}
    scene = scenarios[1]
    assert [p.name for p in scene.files] == ["a.pcd.bin", "b.pcd.bin", "c.pcd.bin"]
    (tmp_path / "out").mkdir()
    counts = write_frames(scene, tmp_path / "out", sensor="nuscenes")
    assert counts == {"frames": 3, "views": 3, "points": 300, "boxes": 3}
    assert list_timestamps(tmp_path / "out") == ["000000", "000001", "000002"]
    xs = [read_scene(tmp_path / "out", ts).ego.pose[0, 3] for ts in list_timestamps(tmp_path / "out")]
    assert xs == [1.0, 2.0, 3.0] and scenario_sensor(tmp_path / "out") == "nuscenes"


def test_frames_are_written_one_at_a_time(tmp_path):
    made: list[weakref.ref] = []
    most = []

    def frames():
        for k in range(12):
            gc.collect()
            most.append(sum(r() is not None for r in made))   # frames still held when the next is read
            view = AgentView("ego", np.full((50_000, 4), 0.5, np.float32), np.eye(4))
            made.append(weakref.ref(view))
            yield Scene("s", f"{100 + k}", {"ego": view})
            del view

    (tmp_path / "s").mkdir()
    assert write_frames(frames(), tmp_path / "s", sensor="waymo")["frames"] == 12
    assert max(most) <= 2      # the frame being written and the one handed on: never the sequence
    assert list_timestamps(tmp_path / "s") == [f"{k:06d}" for k in range(12)]


# ---------------------------------------------------------------- real frames


@real_data
def test_kitti_imagesets_are_the_splits_and_unchanged_frames_are_skipped_by_content(tmp_path):
    root = kitti_copy(tmp_path / "kitti", {"train": "000001\n", "val": "000000\n"})
    sources = {"format": "kitti", "root": "kitti"}
    jobs = plan(tmp_path, sources, train=1, val=1, test=1)
    assert [(j.split, j.name) for j in jobs] == [("test", "kitti_testing_000002"), ("train", "kitti_training_000001"),
                                                ("val", "kitti_training_000000")]
    assert jobs[1].counts == {"frames": 1, "views": 1, "points": 120268, "boxes": 3}   # checked when planned
    assert [run_job(j, tmp_path / "out")["skipped"] for j in jobs] == [None] * 3
    bin_file = root / "training" / "velodyne" / "000000.bin"
    os.utime(bin_file, ns=(1, 1))                              # the same bytes, another stat
    again = plan(tmp_path, sources, train=1, val=1, test=1)
    assert not any(j.counts for j in again)                    # unchanged: not checked again
    assert [run_job(j, tmp_path / "out")["skipped"] for j in again] == ["unchanged"] * 3
    cloud = np.fromfile(bin_file, "<f4").reshape(-1, 4)
    cloud[0, 0] += 1.0
    cloud.tofile(bin_file)                                     # a changed frame: checked and taken again
    changed = plan(tmp_path, sources, train=1, val=1, test=1)
    assert [bool(j.counts) for j in changed] == [False, False, True]
    assert [run_job(j, tmp_path / "out")["skipped"] for j in changed] == ["unchanged", "unchanged", None]
    stored = read_scene(tmp_path / "out" / "target" / "val" / "kitti_training_000000", "000000").ego.points
    assert np.array_equal(stored[:, :3], cloud[:, :3])


def _truncate(path: Path, by: int = 3) -> None:
    path.write_bytes(path.read_bytes()[:-by])


@real_data
@pytest.mark.parametrize("case", ["missing calib", "truncated bin", "nuScenes cloud as KITTI's", "empty root",
                                  "no such root", "split file naming a missing frame", "split the dataset lacks",
                                  "more scenarios than the split has", "one dataset twice",
                                  "nuScenes record without its cloud", "truncated nuScenes cloud",
                                  "truncated Waymo segment", "corrupt Waymo record"])
def test_each_bad_input_is_named_before_anything_is_written(tmp_path, case):
    kitti = {"format": "kitti", "root": "kitti"}
    splits = {"train": "000001\n", "val": "000000\n"}
    if case in ("nuScenes record without its cloud", "truncated nuScenes cloud"):
        shutil.copytree(NUSCENES, tmp_path / "nuscenes")
        cloud = next((tmp_path / "nuscenes").glob("*.pcd.bin"))
        cloud.unlink() if case.startswith("nuScenes record") else _truncate(cloud, 4)
        message = named(tmp_path, {"format": "nuscenes", "root": "nuscenes", "splits": {"train": 1.0}}, train=1)
        want = ("_mmdet3d_info.json: data_list[0].lidar_points.lidar_path: expected a point cloud file"
                if case.startswith("nuScenes record") else f"{cloud}: size: expected a multiple of 20 bytes")
    elif case in ("truncated Waymo segment", "corrupt Waymo record"):
        (tmp_path / "waymo" / "validation").mkdir(parents=True)
        segment = tmp_path / "waymo" / "validation" / "segment-1.tfrecord"
        raw = bytearray((WAYMO / "val.tfrecord").read_bytes())
        if case.startswith("truncated"):
            raw = raw[:-100]
        else:
            raw[500] ^= 0xFF
        segment.write_bytes(bytes(raw))
        message = named(tmp_path, {"format": "waymo", "root": "waymo"}, val=1)
        want = (f"{segment}: record 0 at byte offset 0: expected" if case.startswith("truncated")
                else f"{segment}: record 0 at byte offset 0: payload crc: expected masked crc32c")
    elif case in ("empty root", "no such root"):
        if case == "empty root":
            (tmp_path / "kitti").mkdir()
        message = named(tmp_path, kitti, train=1)
        want = (f"{tmp_path / 'kitti'}: root: expected kitti frames (training/ or testing/ with velodyne/*.bin), "
                "got 'none found'" if case == "empty root"
                else f"{tmp_path / 'kitti'}: root: expected a kitti dataset folder, got 'not a folder'")
    else:
        if case == "split file naming a missing frame":
            splits["val"] = "000000\n000007\n"
        root = kitti_copy(tmp_path / "kitti", splits)
        sources, counts = kitti, {"train": 1, "val": 1}
        if case == "missing calib":
            (root / "training" / "calib" / "000001.txt").unlink()
            want = f"{root / 'training' / 'calib' / '000001.txt'}: file: expected an existing KITTI calib file"
        elif case == "truncated bin":
            _truncate(root / "training" / "velodyne" / "000000.bin")
            want = f"{root / 'training' / 'velodyne' / '000000.bin'}: size: expected a multiple of 16 bytes"
        elif case == "nuScenes cloud as KITTI's":
            shutil.copy(next(NUSCENES.glob("*.pcd.bin")), root / "training" / "velodyne" / "000001.bin")
            want = f"{root / 'training' / 'velodyne' / '000001.bin'}: reflectance: expected values in [0, 1]"
        elif case == "split file naming a missing frame":
            want = f"{root / 'ImageSets' / 'val.txt'}: line 2: expected a frame id of training/velodyne"
        elif case == "split the dataset lacks":
            sources = {**kitti, "splits": {"train": ["train"], "val": ["validation"]}}
            want = ("params.yaml: simulate.sources.target.splits.val: expected split names this kitti root has: "
                    "['testing', 'train', 'training', 'val'], got 'validation'")
        elif case == "more scenarios than the split has":
            counts = {"train": 2}
            want = "params.yaml: simulate.scenarios.target.train: expected at most 1"
        else:
            sources = [kitti, {**kitti, "splits": {"val": ["train"]}}]   # 000001 in train and, again, in val
            want = ("params.yaml: simulate.sources.target: expected sources whose scenarios have distinct names, "
                    "got 'kitti_training_000001 twice'")
        message = named(tmp_path, sources, **counts)
    assert message.startswith(want) or (case == "nuScenes record without its cloud" and want in message), message


@real_data
def test_a_bad_frame_in_any_scenario_stops_the_stage_before_it_writes(tmp_path):
    """The stage plans (and checks) every scenario before its first one is written."""
    from tasks.simulate import scene_stage

    root = kitti_copy(tmp_path / "kitti", {"train": "000000\n000001\n"})
    _truncate(root / "training" / "velodyne" / "000001.bin")       # the last scenario the plan takes
    (tmp_path / "params.yaml").write_text(json.dumps(params({"format": "kitti", "root": "kitti"}, train=2)))
    from typ.config import load_config

    with pytest.raises(TypError, match="000001.bin: size"):
        scene_stage(load_config(tmp_path / "params.yaml"), tmp_path)
    assert not (tmp_path / "data").exists()


# ---------------------------------------------------------------- the stages after, on a real target


def _one_agent(folder: Path, sensor: str | None, ground_z: float) -> Scene:
    """A one-agent scenario: a flat road ``ground_z`` below the LiDAR and a car, written to ``folder``
    (its yaml naming ``sensor`` when given)."""
    rng = np.random.default_rng(1)
    road = np.c_[rng.uniform(-40, 40, (4000, 2)), np.full(4000, ground_z), np.full(4000, 0.3)].astype(np.float32)
    view = AgentView("ego", road, np.eye(4), np.array([[12.0, 3.0, ground_z + 0.75, 4.0, 1.8, 1.5, 0.2]]),
                     ("car",), np.array([7]))
    scene = Scene(folder.name, "000000", {"ego": view})
    folder.mkdir(parents=True)
    if sensor is None:
        from typ.formats.opv2v import write_scene

        write_scene(scene, folder)
    else:
        write_frames([scene], folder, sensor=sensor)
    return scene


def test_a_real_frames_grid_sits_at_its_own_lidars_height_in_voxelize_and_generate(tmp_path):
    from tasks.generate import Generator, _scenario_state
    from tasks.voxelize import ScenarioInput, _scene_state
    from typ.config import GenerateSet
    from typ.voxel import Grid

    cfg = config_from_dict({})
    for sensor, height in (("kitti", 1.76), ("waymo", 2.184), (None, 2.2)):   # None: the domain's (simulated)
        folder = tmp_path / "sim" / "target" / "pretrain" / f"s_{sensor}"
        _one_agent(folder, sensor, -height)
        _, grid, _, _ = _scene_state(ScenarioInput("target", "pretrain", folder), cfg.voxelize, tmp_path / "vox")
        assert grid.z_range == pytest.approx((-0.75 - height, 3.25 - height))

        class Pipe:
            grid = Grid((-51.2, 51.2), (-51.2, 51.2), (-0.75, 3.25), (128, 128, 8))

        generator = Generator(Pipe(), dict(cfg.voxelize.mount_height), digest="")
        gset = GenerateSet(dataset="target", split="pretrain", references="vehicles")
        _, grid, _, _, _ = _scenario_state((gset, folder), cfg.generate, generator, tmp_path / "gen")
        assert grid.z_range == pytest.approx((-0.75 - height, 3.25 - height))


def test_selftrain_sees_a_real_frame_from_the_domains_height(tmp_path):
    from tasks.selftrain import target_frames

    kitti = _one_agent(tmp_path / "train" / "kitti_0", "kitti", -1.76).ego
    simulated = _one_agent(tmp_path / "train" / "sim_0", None, -2.2).ego
    lifted, same = target_frames(tmp_path / "train", {"target": 2.2}, "target")
    assert np.allclose(lifted.points[:, 2], -2.2) and np.allclose(same.points[:, 2], -2.2)   # one ground channel
    assert np.allclose(lifted.boxes[:, 2], kitti.boxes[:, 2] - 0.44) and np.allclose(same.boxes, simulated.boxes)
    world = lambda v: v.points[:, :3].astype(np.float64) @ v.pose[:3, :3].T + v.pose[:3, 3]   # noqa: E731
    assert np.allclose(world(lifted), world(kitti), atol=1e-4)                           # the same road
    assert [f.points[:, 2].mean() for f in target_frames(tmp_path / "train")] == pytest.approx([-1.76, -2.2])


def test_evaluate_says_why_it_cannot_score_single_agent_scenes(tmp_path):
    from tasks.evaluate import missing_truth
    from typ.formats.opv2v import write_scene

    scene = _one_agent(tmp_path / "target" / "test" / "kitti_0", "kitti", -1.76)
    reason = missing_truth(tmp_path / "target" / "test")
    assert "no scenario of target/test has a second agent" in reason and "no true reference view" in reason
    other = AgentView("1", scene.ego.points, np.eye(4))
    write_scene(Scene("pair", "000000", {"0": scene.ego, "1": other}), tmp_path / "target" / "test")
    assert missing_truth(tmp_path / "target" / "test") is None


def test_ddpm_says_why_it_cannot_train_on_scans_without_point_classes(tmp_path):
    from PIL import Image

    from tasks.ddpm import Scan, unlabelled
    from tasks.ddpm_report import write_skipped

    labelled = Scan(("s", "0", "000000"), np.zeros((3, 4), np.float32), np.zeros(3, np.uint8))
    real = Scan(("kitti_0", "ego", "000000"), np.zeros((3, 4), np.float32), None)
    assert unlabelled([labelled], "target/train") is None
    reason = unlabelled([labelled, real], "target/train")
    assert "target/train carry no per-point classes" in reason
    md, *pngs = write_skipped(tmp_path, reason)
    assert md.read_text() == f"# LiDAR DDPM\n\nNot run: {reason}.\n"
    assert [p.name for p in pngs] == ["ddpm_pareto.png", "ddpm_samples.png"]
    assert all(Image.open(p).size == (700, 160) for p in pngs)


def test_every_registered_reader_is_offered_and_resolves_its_functions_and_a_sensor():
    """``simulate.sources.<domain>.format`` and ``typ generate --format`` take the reader registry's
    names (typ.registry.READERS); each entry's functions exist, and its LiDAR is a preset: the one
    of its name, or the one it names (kitti-odometry: KITTI's HDL-64E, when a drive's scans are not
    estimated or named another)."""
    from tasks.ingest import READERS
    from typ.config import SOURCE_FORMATS, config_from_dict
    from typ.registry import READERS as SPECS
    from typ.sensors import resolve

    assert tuple(READERS) == tuple(SPECS) and SOURCE_FORMATS[-1] == "opv2v"
    for name, reader in READERS.items():
        spec = SPECS[name]
        assert reader.spec is spec and reader.name == name and callable(reader.find) and callable(reader.frames)
        assert (reader.estimate is not None) == bool(spec.estimate)
        assert resolve(reader.preset).mount_height > 0   # every reader resolves a sensor
        source = {"format": name, "root": "data/x"}
        assert config_from_dict({"simulate": {"sources": {"target": source}}}).simulate.sources["target"].format == name
    assert READERS["kitti-odometry"].preset == "kitti" and READERS["nuscenes"].preset == "nuscenes"


def test_a_reader_whose_lidar_is_named_per_source_needs_no_preset_of_its_name(monkeypatch):
    """A new vehicle-frame format whose LiDAR typ has no preset of the format's name: the module
    imports and lists it (heights are looked up when a scenario is read); a scenario that names a
    preset is lifted by that preset's height, one that names none is a named error."""
    from tasks.ingest import READERS, Reader
    from typ.registry import ReaderSpec
    from typ.sensors import SENSORS

    ego = AgentView("ego", np.array([[1.0, 2.0, 0.5, 0.1]], np.float32), np.eye(4),
                    boxes=np.array([[5.0, 0.0, 0.8, 4.0, 2.0, 1.6, 0.0]]), box_labels=("car",),
                    box_ids=np.array([0]))
    frames = lambda scenario: iter([Scene(scenario.name, "7", {"ego": ego})])   # noqa: E731
    spec = ReaderSpec("fleet:find", "fleet:frames", "logs/*.bin", vehicle_frame=True)
    monkeypatch.setitem(READERS, "fleet-logs", Reader("fleet-logs", spec, lambda root: ([], {}), frames))
    named = list(DatasetScenario("fleet-logs", "drive_a", (), sensor="nuscenes"))
    lift = SENSORS["nuscenes"].mount_height
    assert [s.timestamp for s in named] == ["000000"]
    view = named[0].ego
    np.testing.assert_allclose(view.points[:, 2], [0.5 - lift], rtol=1e-6)
    np.testing.assert_allclose(view.boxes[:, 2], [0.8 - lift])
    np.testing.assert_allclose(view.pose[:3, 3], [0.0, 0.0, lift])
    with pytest.raises(TypError, match=r"fleet-logs reader.*sensor.*fleet-logs"):
        list(DatasetScenario("fleet-logs", "drive_b", ()))


def test_frames_are_numbered_in_time_order_when_their_stamps_differ_in_length(tmp_path):
    """Stamps "10", "9", "100", "8" (a dataset's own, unpadded): time order is 8, 9, 10, 100, and
    the written frames 000000..000003 keep it; as strings "10" < "100" < "8" < "9"."""
    def frames():
        for stamp in ("10", "9", "100", "8"):
            pose = np.eye(4)
            pose[0, 3] = float(stamp)                   # the frame's time, to tell them apart
            yield Scene("s", stamp, {"ego": AgentView("ego", np.zeros((1, 4), np.float32), pose)})

    (tmp_path / "s").mkdir()
    assert write_frames(frames(), tmp_path / "s", sensor="waymo")["frames"] == 4
    stamps = list_timestamps(tmp_path / "s")
    assert stamps == ["000000", "000001", "000002", "000003"]
    assert [read_scene(tmp_path / "s", t).ego.pose[0, 3] for t in stamps] == [8.0, 9.0, 10.0, 100.0]
    assert not list((tmp_path / "s").rglob(".rank-*"))
