"""typ.formats.waymo: TFRecord CRCs, the real labels-only frame, range images on a synthetic frame."""
from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from typ import geometry
from typ.errors import TypError
from typ.formats.waymo import crc32c, iter_tfrecord, masked_crc32c, read_waymo_frames, read_waymo_kitti_bin
from repo_paths import SHARED_DATA

DATA = SHARED_DATA / "waymo_mmdet3d_testdata"
dataset_pb2 = pytest.importorskip("waymo_open_dataset.dataset_pb2")


@pytest.fixture(scope="module")
def tfrecord():
    if not (DATA / "val.tfrecord").is_file():
        pytest.skip("shared/data/waymo_mmdet3d_testdata is not available")
    return DATA / "val.tfrecord"


def _bitwise_crc32c(data: bytes) -> int:
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x82F63B78 if crc & 1 else crc >> 1
    return crc ^ 0xFFFFFFFF


def test_crc32c_known_vectors():
    # RFC 3720 (iSCSI) appendix B.4 test vectors
    assert crc32c(b"123456789") == 0xE3069283
    assert crc32c(bytes(32)) == 0x8A9136AA
    assert crc32c(b"\xff" * 32) == 0x62A8AB43
    assert crc32c(bytes(range(32))) == 0x46DD794E
    assert crc32c(b"") == 0


@pytest.mark.parametrize("n", [1, 3, 4, 63, 64, 65, 257, 1000, 5003])
def test_crc32c_matches_bitwise_reference(n):
    data = np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8).tobytes()
    assert crc32c(data) == _bitwise_crc32c(data)


def _record(payload: bytes) -> bytes:
    length = struct.pack("<Q", len(payload))
    return length + struct.pack("<I", masked_crc32c(length)) + payload + struct.pack("<I", masked_crc32c(payload))


def test_real_frame(tfrecord):
    scenes = read_waymo_frames(tfrecord)
    assert len(scenes) == 1
    scene, ego = scenes[0], scenes[0].ego
    assert scene.dataset == "waymo" and scene.scenario == "1071392229495085036_1844_790_1864_790"
    assert scene.timestamp == "1507315488219118"
    assert ego.points.shape == (0, 4)  # this file has labels only, no range images
    assert len(ego.boxes) == 18
    assert ego.box_labels.count("sign") == 17 and ego.box_labels.count("vehicle") == 1
    assert len(set(ego.box_ids.tolist())) == 18
    reference = json.loads((DATA / "val_laser_labels.json").read_text())[0]
    np.testing.assert_allclose(ego.pose.ravel(), reference["vehicle_pose_4x4_row_major"], atol=1e-12)


def test_two_records(tfrecord, tmp_path):
    copy = tmp_path / "two.tfrecord"
    copy.write_bytes(tfrecord.read_bytes() * 2)
    assert [len(p) for p in iter_tfrecord(copy)] == [8140, 8140]
    assert len(read_waymo_frames(copy)) == 2


def _error(path) -> TypError:
    with pytest.raises(TypError) as info:
        list(iter_tfrecord(path))
    return info.value


def test_corrupt_payload_names_record_and_offset(tfrecord, tmp_path):
    raw = bytearray(tfrecord.read_bytes() * 2)
    second = len(raw) // 2
    raw[second + 12 + 100] ^= 0x01
    bad = tmp_path / "bad.tfrecord"
    bad.write_bytes(bytes(raw))
    err = _error(bad)
    assert err.where == str(bad)
    assert "record 1 at byte offset 8156" in str(err) and "payload crc" in str(err)
    with pytest.raises(TypError):
        read_waymo_frames(bad)


def test_corrupt_length_header(tfrecord, tmp_path):
    raw = bytearray(tfrecord.read_bytes())
    raw[2] ^= 0x40
    bad = tmp_path / "bad.tfrecord"
    bad.write_bytes(bytes(raw))
    err = _error(bad)
    assert "record 0 at byte offset 0" in str(err) and "length crc" in str(err)


@pytest.mark.parametrize("cut", [5, 100, 8150])
def test_truncated_file(tfrecord, tmp_path, cut):
    bad = tmp_path / "cut.tfrecord"
    bad.write_bytes(tfrecord.read_bytes()[:cut])
    err = _error(bad)
    assert err.where == str(bad) and "truncated" in str(err) and "offset 0" in str(err)


def test_payload_that_is_not_a_frame(tmp_path):
    path = tmp_path / "junk.tfrecord"
    path.write_bytes(_record(b"\xff\xff\xff\xff not a proto"))
    with pytest.raises(TypError) as info:
        read_waymo_frames(path)
    assert "frame 0" in info.value.where and info.value.field == "payload"


def _matrix(array: np.ndarray) -> bytes:
    m = dataset_pb2.MatrixFloat()
    m.data.extend(array.astype(np.float32).ravel().tolist())
    m.shape.dims.extend(array.shape)
    return zlib.compress(m.SerializeToString())


FRAME_POSE = geometry.pose_to_matrix([100.0, 200.0, 3.0, 0.0, 30.0, 0.0])


def _synthetic_frame(top_pixel_offset=(0.0, 0.0, 0.0)):
    """FRONT: 2x4 image, min/max inclinations, laser turned 90 deg left; TOP: 3x2, listed inclinations."""
    frame = dataset_pb2.Frame()
    frame.context.name = "synthetic"
    frame.timestamp_micros = 42
    frame.pose.transform.extend(FRAME_POSE.ravel().tolist())

    front = frame.context.laser_calibrations.add()
    front.name = dataset_pb2.LaserName.FRONT
    front.beam_inclination_min, front.beam_inclination_max = -0.2, 0.2
    extrinsic = geometry.pose_to_matrix([4.0, 0.0, 1.0, 0.0, 90.0, 0.0])
    front.extrinsic.transform.extend(extrinsic.ravel().tolist())
    image = np.zeros((2, 4, 4))
    image[0, 1, :2] = [10.0, 0.5]
    image[1, 2, :2] = [20.0, 2.0]
    laser = frame.lasers.add()
    laser.name = dataset_pb2.LaserName.FRONT
    laser.ri_return1.range_image_compressed = _matrix(image)

    top = frame.context.laser_calibrations.add()
    top.name = dataset_pb2.LaserName.TOP
    top.beam_inclinations.extend([-0.3, 0.0, 0.05])
    top.extrinsic.transform.extend(np.eye(4).ravel().tolist())
    first, second = np.zeros((3, 2, 4)), np.zeros((3, 2, 4))
    first[2, 0, :2] = [5.0, 0.1]
    second[0, 1, :2] = [7.0, 0.2]
    pixel_pose = np.zeros((3, 2, 6))
    pixel_pose[..., 2] = np.radians(30.0)  # [roll, pitch, yaw, x, y, z]: the frame pose ...
    pixel_pose[..., 3:] = np.array([100.0, 200.0, 3.0]) + top_pixel_offset  # ... moved in the world
    laser = frame.lasers.add()
    laser.name = dataset_pb2.LaserName.TOP
    laser.ri_return1.range_image_compressed = _matrix(first)
    laser.ri_return1.range_image_pose_compressed = _matrix(pixel_pose)
    laser.ri_return2.range_image_compressed = _matrix(second)
    return frame


def _read(tmp_path, frame):
    path = tmp_path / "synthetic.tfrecord"
    path.write_bytes(_record(frame.SerializeToString()))
    return read_waymo_frames(path)[0].ego


def test_range_images_to_points(tmp_path):
    points = _read(tmp_path, _synthetic_frame()).points
    c1, s1 = np.cos(0.1), np.sin(0.1)
    q = np.sqrt(0.5)
    expected = np.array([
        # TOP (laser name 1) first; rows are listed inclinations reversed: row 2 -> -0.3.
        # Column 0 of 2 looks along azimuth +90 deg; the pixel pose equals the frame pose.
        [0.0, 5 * np.cos(0.3), -5 * np.sin(0.3), np.tanh(0.1)],
        # second return, row 0 -> 0.05, column 1 of 2 -> azimuth -90 deg
        [0.0, -7 * np.cos(0.05), 7 * np.sin(0.05), np.tanh(0.2)],
        # FRONT: rows 0, 1 -> inclinations +0.1, -0.1 (uniform over [-0.2, 0.2]); the laser is
        # turned +90 deg, so column 1 (laser azimuth -45 deg) looks along vehicle azimuth +45 deg
        [4 + 10 * c1 * q, 10 * c1 * q, 1 + 10 * s1, np.tanh(0.5)],
        [4 + 20 * c1 * q, -20 * c1 * q, 1 - 20 * s1, np.tanh(2.0)],
    ])
    assert points.dtype == np.float32
    np.testing.assert_allclose(points, expected, atol=1e-5)


def test_top_pixel_pose_moves_points(tmp_path):
    still = _read(tmp_path, _synthetic_frame()).points
    moved = _read(tmp_path, _synthetic_frame(top_pixel_offset=(1.0, 0.0, 0.0))).points
    # a pixel captured 1 m further along world x lands R_frame^T (1, 0, 0) away in the vehicle frame
    shift = FRAME_POSE[:3, :3].T @ [1.0, 0.0, 0.0]
    np.testing.assert_allclose(moved[:2, :3] - still[:2, :3], [shift, shift], atol=1e-5)
    np.testing.assert_allclose(moved[2:], still[2:])


def test_inclination_count_must_match_rows(tmp_path):
    frame = _synthetic_frame()
    top = next(c for c in frame.context.laser_calibrations if c.name == dataset_pb2.LaserName.TOP)
    top.beam_inclinations.append(0.1)
    with pytest.raises(TypError) as info:
        _read(tmp_path, frame)
    assert "beam_inclinations" in info.value.field and "frame 0" in info.value.where


def test_corrupt_range_image(tmp_path):
    frame = _synthetic_frame()
    frame.lasers[0].ri_return1.range_image_compressed = b"not zlib"
    with pytest.raises(TypError) as info:
        _read(tmp_path, frame)
    assert info.value.field == "lasers[FRONT].ri_return1"


def test_kitti_format_bins():
    bins = sorted((DATA / "kitti_format" / "velodyne").glob("*.bin"))
    if len(bins) != 2:
        pytest.skip("shared/data/waymo_mmdet3d_testdata/kitti_format is not available")
    for path in bins:
        points = read_waymo_kitti_bin(path)
        assert points.shape == (800, 4) and points.dtype == np.float32
        assert 0.0 <= points[:, 3].min() and points[:, 3].max() <= 1.0
        raw = np.fromfile(path, dtype=np.float32).reshape(-1, 6)
        np.testing.assert_array_equal(points[:, :3], raw[:, :3])


def test_kitti_format_bin_wrong_dtype(tmp_path):
    path = tmp_path / "f64.bin"
    rng = np.random.default_rng(3)
    path.write_bytes(rng.uniform(-40, 40, (50, 6)).astype(np.float64).tobytes())
    with pytest.raises(TypError) as info:
        read_waymo_kitti_bin(path)
    assert info.value.where == str(path) and info.value.field == "dtype"
    assert "float32 little-endian" in str(info.value)


# --- streaming: a segment is read one record at a time -------------------------------------------

SEGMENT_FRAMES, SEGMENT_WIDTH = 32, 2650     # a real TOP range image is 64 x 2650


def _segment(path: Path) -> dict:
    """A large synthetic segment: SEGMENT_FRAMES frames, each a full 64 x 2650 TOP range image of
    random returns (about 2.7 MB compressed, 170k points), frame i at x = i m, timestamps in
    reverse file order. Returns sizes in MB."""
    rng = np.random.default_rng(0)
    image = np.zeros((64, SEGMENT_WIDTH, 4), dtype=np.float32)
    image[..., 0] = rng.uniform(2.0, 70.0, image.shape[:2])
    image[..., 1] = rng.uniform(0.0, 1.5, image.shape[:2])
    frame = dataset_pb2.Frame()
    frame.context.name = "segment-synthetic_0000"
    top = frame.context.laser_calibrations.add()
    top.name = dataset_pb2.LaserName.TOP
    top.beam_inclination_min, top.beam_inclination_max = -0.3, 0.05
    top.extrinsic.transform.extend(np.eye(4).ravel().tolist())
    laser = frame.lasers.add()
    laser.name = dataset_pb2.LaserName.TOP
    laser.ri_return1.range_image_compressed = _matrix(image)
    with open(path, "wb") as f:
        for i in range(SEGMENT_FRAMES):
            frame.timestamp_micros = 1_507_315_488_000_000 + 100_000 * (SEGMENT_FRAMES - i)
            del frame.pose.transform[:]
            frame.pose.transform.extend(geometry.pose_to_matrix([float(i), 0.0, 0.0, 0.0, 0.0, 0.0]).ravel().tolist())
            f.write(_record(frame.SerializeToString()))
    points_mb = 64 * SEGMENT_WIDTH * 4 * 4 / 2**20
    return {"file_mb": path.stat().st_size / 2**20, "frame_mb": path.stat().st_size / 2**20 / SEGMENT_FRAMES,
            "points_mb": points_mb}


#: in a fresh process: peak RSS (ru_maxrss, kB) after a one-frame warm-up, and after the whole file
PEAK = """
import json, resource, sys
from pathlib import Path
mode, path, out = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
peak = lambda: resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
if mode == "read":
    from typ.formats.waymo import iter_waymo_frames
    frames = iter_waymo_frames(path)
    next(frames)                                   # one frame's buffers exist now
    warm = peak()
    count = 1 + sum(1 for _ in frames)
else:
    from tasks.ingest import read_frames, write_single_agent
    write_single_agent(read_frames("waymo", path.with_name("one.tfrecord")), out / "warm")
    warm = peak()
    count = len(write_single_agent(read_frames("waymo", path), out / "all"))
print(json.dumps({"warm_mb": warm, "peak_mb": peak(), "count": count}))
"""


def _peak(mode: str, path: Path, out: Path) -> dict:
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-c", PEAK, mode, str(path), str(out)], capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_a_large_segment_is_read_and_ingested_in_memory_of_a_few_frames(tmp_path):
    from typ.formats.opv2v import list_timestamps, read_meta  # noqa: F401  (reader of the ingested frames)

    path = tmp_path / "segment.tfrecord"
    sizes = _segment(path)
    one = next(iter_tfrecord(path))
    (tmp_path / "one.tfrecord").write_bytes(_record(one))
    per_frame = sizes["frame_mb"] + sizes["points_mb"]          # a payload and its cloud
    assert sizes["file_mb"] > 20 * per_frame / 2                  # the file is many frames
    read = _peak("read", path, tmp_path)
    assert read["count"] == SEGMENT_FRAMES
    # the old reader held the whole file and every frame's cloud: file_mb + 32 clouds (~170 MB)
    assert read["peak_mb"] - read["warm_mb"] < 3 * per_frame, (read, sizes)
    ingest = _peak("ingest", path, tmp_path / "out")
    assert ingest["peak_mb"] - ingest["warm_mb"] < 3 * per_frame, (ingest, sizes)

    # written frame by frame, and numbered in time order (the file holds them newest first)
    folder = tmp_path / "out" / "all" / "segment"
    stamps = list_timestamps(folder)
    assert stamps == [f"{i:06d}" for i in range(SEGMENT_FRAMES)]
    import yaml

    xs = [yaml.safe_load((folder / "ego" / f"{t}.yaml").read_text())["lidar_pose"][0] for t in stamps]
    assert xs == pytest.approx([float(SEGMENT_FRAMES - 1 - i) for i in range(SEGMENT_FRAMES)])
    assert not list(folder.rglob(".rank-*"))


def _pitched_frame(offset=(0.0, 0.0, 0.0), pixel_poses=True):
    """The synthetic frame on a ramp: the frame pose and every TOP pixel pose (unless not
    ``pixel_poses``) are roll 5 deg, pitch -8 deg, yaw 30 deg, the pixels moved ``offset`` in the
    world. The frame pose is written out here as Waymo's ``Rz(yaw) Ry(pitch) Rx(roll)``, the pixel
    poses as the six numbers Waymo stores. TOP's image is 3 x 4, one return in every pixel, so
    that its points look along azimuths +-45 and +-135 deg (x and y both non-zero)."""
    roll, pitch, yaw = np.radians([5.0, -8.0, 30.0])
    rx = np.array([[1, 0, 0], [0, np.cos(roll), -np.sin(roll)], [0, np.sin(roll), np.cos(roll)]])
    ry = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rz @ ry @ rx, [100.0, 200.0, 3.0]
    frame = _synthetic_frame()
    del frame.pose.transform[:]
    frame.pose.transform.extend(pose.ravel().tolist())
    top = next(laser for laser in frame.lasers if laser.name == dataset_pb2.LaserName.TOP)
    image = np.zeros((3, 4, 4))
    image[..., 0], image[..., 1] = 5.0 + np.arange(12).reshape(3, 4), 0.1
    top.ri_return1.range_image_compressed = _matrix(image)
    top.ri_return2.range_image_compressed = _matrix(np.zeros((3, 4, 4)))
    top.ri_return1.range_image_pose_compressed = b""
    if pixel_poses:
        pixel_pose = np.zeros((3, 4, 6))
        pixel_pose[...] = [roll, pitch, yaw, *(pose[:3, 3] + offset)]
        top.ri_return1.range_image_pose_compressed = _matrix(pixel_pose)
    return frame, pose


def test_top_pixel_poses_with_pitch_and_roll_are_the_frame_pose_they_name(tmp_path):
    """Pixel poses equal to a pitched and rolled frame pose leave the TOP points where the frame
    alone puts them (a pixel pose built in another rotation order, or with pitch's or roll's sign
    flipped, moves them); pixels captured 1 m further along world x land R_frame^T (1, 0, 0) away."""
    still = _read(tmp_path, _pitched_frame(pixel_poses=False)[0]).points
    frame, pose = _pitched_frame()
    pitched = _read(tmp_path, frame).points
    assert len(pitched) == 12 + 2 and np.abs(pitched[:12, :2]).min() > 2.0     # TOP first, then FRONT
    np.testing.assert_allclose(pitched, still, atol=1e-5)
    moved = _read(tmp_path, _pitched_frame(offset=(1.0, 0.0, 0.0))[0]).points
    shift = pose[:3, :3].T @ [1.0, 0.0, 0.0]
    assert abs(shift[2]) > 0.05                      # the pitch shows in the shift
    np.testing.assert_allclose(moved[:12, :3] - pitched[:12, :3], np.tile(shift, (12, 1)), atol=1e-5)
    np.testing.assert_allclose(moved[12:], pitched[12:])
