"""Real scans at other poses (issue 55): the KITTI odometry layout as a format, the novel-view
metrics against hand-computed values, the pair rule, methods that never see the scan they are
scored against, the report's JSON, and ``typ novel-view`` end to end on a shared drive.

The drives are ../shared/data's (KITTI seq 00, four scans; one nuScenes scene, eight keyframes);
tests that need them skip without them. The generator is a tiny untrained one
(tests/unit/pipelines/test_pipeline.py): the wiring, not the numbers.
"""
from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from tasks import novel_view as nvt
from typ.errors import TypError
from typ.formats.kitti_odometry import estimate_sensor, read_sequence
from typ.metrics import novel_view as nv
from repo_paths import REPO, SHARED_DATA

DATA = SHARED_DATA
KITTI, NUSCENES = DATA / "kitti_odometry_00", DATA / "nuscenes_scene_seq"
needs_data = pytest.mark.skipif(not (KITTI.is_dir() and NUSCENES.is_dir()),
                                reason="../shared/data's drives (kitti_odometry_00, nuscenes_scene_seq) not present")


def small_copy(src: Path, dst: Path, scans: int) -> Path:
    """A new dataset of the first ``scans`` scans of ``src``'s sequence 00 (copied, not linked:
    the reader refuses files outside the root), with their pose lines and calib."""
    seq, out = src / "sequences" / "00", dst / "sequences" / "00"
    (out / "velodyne").mkdir(parents=True)
    for k in range(scans):
        shutil.copyfile(seq / "velodyne" / f"{k:06d}.bin", out / "velodyne" / f"{k:06d}.bin")
    shutil.copyfile(seq / "calib.txt", out / "calib.txt")
    (out / "poses.txt").write_text("".join((seq / "poses.txt").read_text().splitlines(keepends=True)[:scans]))
    return dst


# ---------------------------------------------------------------- the format


@needs_data
def test_both_shared_drives_read_with_lidar_poses():
    kitti, nus = read_sequence(KITTI, "00"), read_sequence(NUSCENES, "00")
    assert (len(kitti), len(nus)) == (4, 8) and kitti.times is None
    for drive in (kitti, nus):
        assert drive.poses.dtype == np.float64 and drive.poses.shape == (len(drive), 4, 4)
        np.testing.assert_allclose(drive.poses[0], np.eye(4), atol=1e-12)   # the first scan's frame is the world
        rot = drive.poses[:, :3, :3]
        assert np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max() < 1e-5
    # LiDAR pose = camera pose @ Tr: KITTI's camera moves along its z (forward); the LiDAR along its x
    steps = np.linalg.norm(np.diff(kitti.poses[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, [7.49, 8.58, 9.29], atol=0.01)
    assert kitti.poses[1, 0, 3] == pytest.approx(7.49, abs=0.02) and abs(kitti.poses[1, 2, 3]) < 0.2
    assert kitti.points(0).shape == (124668, 4) and kitti.points(0).dtype == np.float32
    # nuScenes' LIDAR_TOP frame: x right, y forward; Tr is the identity, the poses the LiDAR's
    assert nus.poses[7, 1, 3] == pytest.approx(50.33, abs=0.01)
    assert estimate_sensor(kitti.points(0))[0] == "kitti" and estimate_sensor(nus.points(0))[0] == "nuscenes"


@needs_data
def test_a_copy_reads_the_same_and_ingests_as_one_sequence(tmp_path, monkeypatch):
    from tasks.ingest import list_dataset, write_single_agent
    from typ.formats.opv2v import list_timestamps, read_scene, scenario_sensor

    copy = small_copy(NUSCENES, tmp_path / "copy", 3)
    a, b = read_sequence(NUSCENES, "00"), read_sequence(copy, "00")
    monkeypatch.chdir(tmp_path)                                   # a root relative to the working folder
    np.testing.assert_array_equal(read_sequence(Path("copy"), "00").poses, b.poses)
    np.testing.assert_array_equal(b.poses, a.poses[:3])
    np.testing.assert_array_equal(b.points(2), a.points(2))
    scenarios, splits = list_dataset("kitti-odometry", copy)
    assert [s.name for s in scenarios] == ["copy_00"] and splits == {} and scenarios[0].lidar == "nuscenes"
    (folder,) = write_single_agent(scenarios, tmp_path / "out")
    assert list_timestamps(folder) == ["000000", "000001", "000002"] and scenario_sensor(folder) == "nuscenes"
    last = read_scene(folder, "000002")
    np.testing.assert_allclose(last.ego.pose, a.poses[2], atol=1e-5)       # the pose kept, through the yaml
    assert len(last.ego.points) == len(a.points(2)) and len(last.ego.boxes) == 0
    # named sensor and frame ranges (a drive split for TYP §3.4)
    from tasks.ingest import frame_range_splits

    shares = frame_range_splits(list_dataset("kitti-odometry", copy, sensor="kitti")[0], {"train": (0, 2),
                                                                                          "test": (2, 3)},
                                where="params.yaml", field="simulate.sources.target")
    assert [s.name for s in shares["train"].scenarios] == ["copy_00_f0-2"]
    assert [len(list(s)) for s in shares["test"].scenarios] == [1] and shares["test"].scenarios[0].lidar == "kitti"
    assert "scans [2, 3)" in shares["test"].rule
    with pytest.raises(TypError, match="frame_ranges.test"):
        frame_range_splits(scenarios, {"test": (2, 9)}, where="params.yaml", field="simulate.sources.target")


def test_frame_ranges_are_checked_in_params():
    from typ.config import SourceConfig

    ok = SourceConfig(format="kitti-odometry", root="d", frame_ranges={"train": (0, 5), "test": (5, 8)})
    ok.check("params.yaml", "s")
    for bad, field in (({"train": (0, 5), "test": (4, 8)}, "frame_ranges"), ({"train": (3, 3)}, "frame_ranges.train")):
        with pytest.raises(TypError) as err:
            dataclasses.replace(ok, frame_ranges=bad).check("params.yaml", "s")
        assert err.value.field == f"s.{field}"
    with pytest.raises(TypError, match="kitti-odometry"):
        SourceConfig(format="kitti", root="d", frame_ranges={"train": (0, 5)}).check("params.yaml", "s")


# ---------------------------------------------------------------- the metrics, by hand


def test_chamfer_and_fscore_follow_lidar4d():
    pred = np.array([[0.0, 0, 0], [1.0, 0, 0], [5.0, 0, 0]])
    true = np.array([[0.0, 0, 0.1], [1.0, 0, 0.3]])
    to_true, to_pred = nv.nearest_squared(pred, true), nv.nearest_squared(true, pred)
    np.testing.assert_allclose(to_true, [0.01, 0.09, 16.09])
    np.testing.assert_allclose(to_pred, [0.01, 0.09])
    # squared distances, the two means added: (0.01 + 0.09 + 16.09) / 3 + (0.01 + 0.09) / 2
    assert nv.chamfer(to_true, to_pred) == pytest.approx(16.19 / 3 + 0.05)
    # threshold 0.05 m² on squared distances: 0.01 passes, 0.09 (0.3 m) does not
    f, p, r = nv.fscore(to_true, to_pred)
    assert (p, r) == (pytest.approx(1 / 3), 0.5) and f == pytest.approx(2 * (1 / 3) * 0.5 / (1 / 3 + 0.5))
    assert nv.fscore([1.0], [1.0]) == (0.0, 0.0, 0.0)                       # P + R = 0: F = 0, not NaN
    assert np.isnan(nv.chamfer([], [0.1]))
    assert nv.fscore(nv.nearest_squared(pred, np.zeros((0, 3))), [])[0] == 0.0
    # within 80 m: |p| < 80
    assert len(nv.within_range(np.array([[79.9, 0, 0], [80.0, 0, 0], [0, 60, 60]], np.float32))) == 1
    precision, recall = nv.masked_precision_recall(to_true, to_pred, np.array([True, False, True]),
                                                   np.array([False, False]))
    assert precision == 0.5 and np.isnan(recall)


def test_range_image_depth_raydrop_and_rows():
    elevations = (-10.0, 0.0, 10.0)
    pts = np.array([[10.0, 0, 0], [5.0, 0, 0],                 # beam 1, azimuth 0: the nearer one is kept
                    [0, 10.0, np.tan(np.radians(10.0)) * 10],   # beam 2, azimuth 90 deg
                    [-3.0, 0, -np.tan(np.radians(10.0)) * 3],   # beam 0, azimuth 180 deg (the last column)
                    [90.0, 0, 0]])                              # beyond 80 m
    rows, residual = nv.beams(pts, elevations)
    np.testing.assert_array_equal(rows, [1, 1, 2, 0, 1])
    np.testing.assert_allclose(residual, 0, atol=1e-9)
    image = nv.sensor_range_image(pts, rows, n_beams=3, azimuth_bins=4)
    expected = np.zeros((3, 4))
    expected[1, 2], expected[2, 3], expected[0, 3] = 5.0, np.linalg.norm(pts[2]), np.linalg.norm(pts[3])
    np.testing.assert_allclose(image, expected)
    other = expected.copy()
    other[1, 2], other[2, 3], other[0, 3] = 7.0, 0.0, expected[0, 3] + 1.0
    other[0, 0] = 4.0
    # both have a return on 2 pixels, errors 2 and 1
    assert nv.depth_errors(other, expected) == (pytest.approx(np.sqrt(2.5)), pytest.approx(1.5))
    assert nv.raydrop_accuracy(other, expected) == pytest.approx(10 / 12)   # (2, 3) and (0, 0) disagree
    np.testing.assert_allclose(nv.row_occupancy(expected), [0.25, 0.25, 0.25])
    assert nv.row_l1(other, expected) == pytest.approx((0.25 + 0 + 0.25) / 3)
    assert nv.on_beam(pts, residual + [0, 0.04, 0.06, 0, 0]) == (4, 5)
    assert nv.on_beam(pts, residual, min_range=6.0) == (3, 3)
    assert np.isnan(nv.depth_errors(np.zeros((3, 4)), expected)[0])


# ---------------------------------------------------------------- the pair rule


def test_every_pair_two_to_forty_metres_apart_both_ways():
    poses = np.tile(np.eye(4), (6, 1, 1))
    poses[:, 0, 3] = [0.0, 1.5, 5.0, 15.0, 30.0, 41.5]
    pairs = nvt.build_pairs(poses)
    got = {(p.ego, p.reference): p.band for p in pairs}
    # 0-1 (1.5 m) too close; 0-5 (41.5 m) too far; 1-5 exactly 40 m: in, the last band closed
    assert set(got) == {(i, j) for i in range(6) for j in range(6) if i != j} - {(0, 1), (1, 0), (0, 5), (5, 0)}
    assert got[(1, 5)] == got[(5, 1)] == "20-40" and got[(0, 2)] == "0-10" and got[(2, 3)] == "10-20"
    assert got[(3, 2)] == "10-20" and got[(1, 2)] == "0-10"
    assert [(p.ego, p.reference) for p in pairs] == sorted(got)
    assert nvt.picture_pairs(pairs) == [pairs[0], next(p for p in pairs if p.band == "10-20"),
                                        next(p for p in pairs if p.band == "20-40")]


def test_intervals_resample_ego_frames_and_differences_are_paired():
    pairs = [nvt.Pair(0, 1, 5.0), nvt.Pair(1, 0, 5.0), nvt.Pair(2, 0, 15.0), nvt.Pair(0, 2, 15.0)]
    results = []
    for n, pair in enumerate(pairs):
        base = {k: 0.5 for k in nvt.METRICS}
        results.append(nvt.PairResult(pair, scores={"copy": {**base, "fscore": 0.2 + 0.1 * n},
                                                    "resim": {**base, "fscore": 0.3 + 0.1 * n}}))
    s = nvt.summarize(results, ["copy", "resim"], n_boot=200)
    assert s["methods"]["copy"]["all"]["fscore"].value == pytest.approx(0.35)
    d = s["differences"]["vs_copy"]["resim"]["all"]["fscore"]
    assert (d.value, d.low, d.high) == pytest.approx((0.1, 0.1, 0.1))     # paired: the same 0.1 every pair
    assert nvt.beats(d, "fscore") and not nvt.beats(d, "chamfer")
    assert s["methods"]["copy"]["0-10"]["fscore"].low < s["methods"]["copy"]["0-10"]["fscore"].high
    # 10-20: two pairs, two ego frames; a band of one ego frame has no interval
    one = nvt.summarize(results[:1], ["copy", "resim"], n_boot=50)
    assert np.isnan(one["methods"]["copy"]["0-10"]["fscore"].low)
    assert not nvt.beats(one["differences"]["vs_copy"]["resim"]["0-10"]["fscore"], "fscore")
    assert "resim" not in s["differences"]["vs_resim"] and "ratios_to_map_oracle" in s


# ---------------------------------------------------------------- methods never see scan j


@pytest.fixture(scope="module")
def tiny_generator():
    from tasks.generate import Generator
    from tiny_pipeline import tiny_pipeline as _pipeline

    return Generator(_pipeline(), {}, "test", 0.4)


@needs_data
def test_no_method_sees_the_scan_it_is_scored_against(tmp_path, tiny_generator):
    from typ.sensors import resolve

    copy = small_copy(NUSCENES, tmp_path / "copy", 3)
    drive, spec = read_sequence(copy, "00"), resolve("nuscenes")
    grid = tiny_generator.grid("nuscenes")
    pair = nvt.Pair(0, 2, 17.5)
    junk = np.random.default_rng(0).uniform(-30, 30, (5000, 4)).astype(np.float32)
    clean = nvt.DriveScans(drive)
    poisoned = nvt.DriveScans(drive, read=lambda k: junk if k == pair.reference else drive.points(k))
    for name, method in nvt.METHODS.items():
        a = method.view(nvt.pair_input(clean, pair, spec, grid, generator=tiny_generator))
        b = method.view(nvt.pair_input(poisoned, pair, spec, grid, generator=tiny_generator))
        np.testing.assert_array_equal(a, b, err_msg=name)
        assert len(a) > 100, name
    # the oracle's map is the other scans': poisoning scan 1 changes it
    other = nvt.DriveScans(drive, read=lambda k: junk if k == 1 else drive.points(k))
    oracle = nvt.METHODS["map_oracle"].view
    assert len(oracle(nvt.pair_input(clean, pair, spec, grid))) != len(oracle(nvt.pair_input(other, pair, spec, grid)))


# ---------------------------------------------------------------- the report and the command


def assert_json_shape(doc: dict, methods: list[str], bands: set[str]) -> None:
    assert isinstance(doc["pairs"], int) and doc["pairs"] == len(doc["per_pair"])
    assert set(doc["methods"]) == set(methods)
    for method, by_band in doc["methods"].items():
        assert set(by_band) == bands
        for figures in by_band.values():
            assert set(figures) >= {"chamfer", "fscore", "precision", "recall", "depth_rmse", "depth_medae",
                                    "raydrop_acc", "on_beam", "row_l1"}
            assert all(set(v) == {"value", "low", "high"} for v in figures.values())
    assert set(doc["differences"]) == {f"vs_{b}" for b in nvt.BASELINES if b in methods}
    assert set(doc["differences"]["vs_copy"]) == set(methods) - {"copy"}


@needs_data
def test_typ_novel_view_end_to_end(tmp_path, tiny_generator):
    from cli.main import main
    from pipelines.typ.pipeline_typ import generator_dir

    root = tmp_path / "project"
    root.mkdir()
    shutil.copyfile(REPO / "params.yaml", root / "params.yaml")
    tiny_generator.pipe.save_pretrained(generator_dir(root / "artifacts" / "selftrain", 0))
    out, drive = tmp_path / "report", small_copy(NUSCENES, tmp_path / "drive", 3)   # the map: scans 0-2
    assert main(["--root", str(root), "novel-view", "--format", "kitti-odometry", "--input", str(drive),
                 "--out", str(out), "--max-pairs", "2", "--methods", "copy,resim,cast,cast_no_typ,map_oracle"]) == 0
    doc = json.loads((out / "novel_view.json").read_text())
    methods = ["copy", "resim", "cast", "cast_no_typ", "map_oracle"]
    assert_json_shape(doc, methods, {"0-10", "10-20", "all"})
    assert doc["sequence"]["sensor"] == "nuscenes" and doc["pairs"] == 2
    assert [(p["ego"], p["reference"]) for p in doc["per_pair"]] == [(0, 1), (0, 2)]
    assert "artifacts/selftrain/generator/seed_0" in doc["models"]["cast"] and doc["models"]["copy"].startswith("none")
    assert doc["methods"]["cast"]["all"]["on_beam"]["value"] > 0.99           # a scan of the drive's LiDAR
    per = doc["per_pair"][0]["methods"]
    assert per["map_oracle"]["fscore"] > per["copy"]["fscore"]
    assert sorted(p.name for p in out.glob("*.png")) == ["pair_0000_0001.png", "pair_0000_0002.png"]
    text = (out / "novel_view.md").read_text()
    assert "LiDAR4D" in text and "## 0-10 m" in text and "pair_0000_0002.png" in text
    for bad in (["--frames", "3:2"], ["--max-pairs", "-1"], ["--methods", "copy,oracle"]):
        assert main(["--root", str(root), "novel-view", "--format", "kitti-odometry", "--input", str(drive),
                     "--out", str(tmp_path / "bad"), "--no-pictures", *bad]) == 2
    assert not (tmp_path / "bad").exists()


@needs_data
def test_pairs_made_two_at_a_time_score_the_same(tmp_path):
    from typ.sensors import resolve
    from typ.voxel import TINY_GRID

    drive = read_sequence(small_copy(NUSCENES, tmp_path / "copy", 3), "00")
    spec = resolve("nuscenes")
    grid = TINY_GRID.for_sensor(spec.mount_height)
    pairs = nvt.build_pairs(drive.poses)[:3]     # (0, 1), (0, 2), (1, 0)
    runs = [nvt.run_pairs(nvt.DriveScans(drive), pairs, spec, grid, ["copy", "map_oracle"], workers=w)
            for w in (1, 2)]
    assert [r.pair for r in runs[0]] == [r.pair for r in runs[1]] == pairs
    assert [r.scores for r in runs[0]] == [r.scores for r in runs[1]]


@needs_data
def test_evaluate_scores_the_drives_params_name(tmp_path, tiny_generator):
    from tasks.evaluate import NOVEL_VIEW, novel_view_section
    from pipelines.typ.pipeline_typ import generator_dir
    from typ.config import config_from_dict, read_params

    raw = read_params(REPO / "params.yaml")
    assert novel_view_section(config_from_dict(raw), tmp_path) == ({}, [], [])     # make run: no drive, nothing
    copy = small_copy(NUSCENES, tmp_path / "drive", 3)
    tiny_generator.pipe.save_pretrained(generator_dir(tmp_path / "artifacts" / "selftrain", 0))
    raw["evaluate"] = {**raw["evaluate"], "n_boot": 20, "novel_view": {
        "sequences": [{"root": str(copy), "sensor": "nuscenes", "frames": [1, 3]}], "max_pairs": 1, "pictures": False}}
    metrics, paths, lines = novel_view_section(config_from_dict(raw), tmp_path)
    (name, figures), = metrics.items()
    assert name == "drive_00" and figures["pairs"] == 1 and "scans [1, 3)" in figures["pair_rule"]
    assert "selftrain/generator/seed_0" in figures["models"]["cast"]
    assert set(figures["methods"]) == set(nvt.METHODS) and figures["methods"]["cast"]["all"]["fscore"]["value"] > 0
    assert sorted(p.name for p in paths) == ["novel_view.json", "novel_view.md"]
    assert all(p.parent == tmp_path / NOVEL_VIEW / name for p in paths) and "drive_00" in lines[-1]
