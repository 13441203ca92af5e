"""Bad-input cases: inputs built to hang, exhaust memory or be misread (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

from pathlib import Path
import json
import struct
import zlib

import numpy as np

from typ.formats.binfile import read_bin
from typ.formats.kitti import read_kitti_frame
from typ.formats.nuscenes import read_nuscenes_frame
from typ.formats.opv2v import check_scenario
from typ.formats.pcd import read_pcd
from typ.formats.waymo import read_waymo_frames

from bad_inputs.make_corpus import (CALIB, Probe, WAYMO, _read_opv2v, _waymo_file, billion_laughs, case, cloud, fifo, kitti_frame, load_params, nuscenes_frame, nuscenes_info, opv2v_doc, opv2v_scenario, pcd_text, sparse, tfrecord, waymo_frame, write)


# Each must end in a TypError within 2 s and 1 GB (tests/fuzz/test_bad_inputs.py runs every
# reader case in a bounded child process), where typ once hung, ran out of memory, crashed the
# interpreter, let a raw OverflowError/ValueError/LinAlgError through, or returned other points.








@case("opv2v", "yaml_billion_laughs", "bomb")
def _(d):
    y = opv2v_scenario(d, billion_laughs())
    return Probe(says=(str(y), "yaml", "YAML nodes, aliases expanded"), call=_read_opv2v(y))


@case("opv2v", "check_scenario_billion_laughs", "bomb")
def _(d):
    y = opv2v_scenario(d, billion_laughs())
    return Probe(says=(str(y), "YAML nodes"), call=lambda: check_scenario(y.parent.parent))


@case("opv2v", "yaml_100k_brackets", "deep")
def _(d):
    y = opv2v_scenario(d, "lidar_pose: " + "[" * 100_000)  # crashed libyaml's composer (segfault)
    return Probe(says=(str(y), "yaml", "nested at most 32 levels deep"), call=_read_opv2v(y))


@case("opv2v", "yaml_is_a_fifo", "not a regular file")
def _(d):
    y = opv2v_scenario(d)
    y.unlink()
    fifo(y)
    return Probe(says=(str(y), "a readable UTF-8 yaml file", "FIFO"), call=_read_opv2v(y))


@case("opv2v", "lidar_pose_400_digits", "overflow")
def _(d):
    y = opv2v_scenario(d, f"lidar_pose: [{'9' * 400}, 0, 0, 0, 0, 0]\nvehicles: {{}}\n")
    return Probe(says=(str(y), "lidar_pose", "finite numbers"), call=_read_opv2v(y))


@case("opv2v", "vehicle_id_2e30", "overflow")
def _(d):
    doc = opv2v_doc()
    doc["vehicles"] = {2 * 10**30: doc["vehicles"][7]}
    y = opv2v_scenario(d, doc)
    return Probe(says=(str(y), "vehicles.2000000000000000000000000000000", "an integer vehicle id (64-bit)"),
                 call=_read_opv2v(y))


@case("params", "yaml_billion_laughs", "bomb")
def _(d):
    probe = load_params(d, billion_laughs().replace("lidar_pose:", "seed:").replace("vehicles: {}", "profile: tiny"))
    probe.says += ("yaml", "YAML nodes, aliases expanded")
    return probe


@case("params", "float_of_400_digits", "overflow")
def _(d):
    probe = load_params(d, f"vqvae:\n  lr: {'9' * 400}\n")
    probe.says += ("vqvae.lr", "a finite number")
    return probe


@case("pcd", "dev_zero", "not a regular file")
def _(d):
    return Probe(says=("/dev/zero", "a readable .pcd file", "character device"), call=lambda: read_pcd("/dev/zero"))


@case("pcd", "fifo", "not a regular file")
def _(d):
    p = fifo(d / "a.pcd")
    return Probe(says=(str(p), "a readable .pcd file", "FIFO"), call=lambda: read_pcd(p))


@case("pcd", "sparse_4_gib", "huge")
def _(d):
    p = sparse(d / "a.pcd", 4 << 30, pcd_text(data="binary", body=""))
    return Probe(says=(str(p), "a .pcd file of at most 128 MiB", str(4 << 30)), call=lambda: read_pcd(p))


def _binary_pcd(d: Path, n: int, width: int, points: int) -> Path:
    """A binary x y z intensity cloud of ``n`` rows under a header claiming WIDTH (HEIGHT 1) and POINTS."""
    header = pcd_text(points=points, data="binary", body="")
    return write(d / "a.pcd", header.replace(f"WIDTH {points}".encode(), f"WIDTH {width}".encode()) + cloud(n).tobytes())


@case("pcd", "points_fewer_than_width", "misaligned")
def _(d):
    p = _binary_pcd(d, 64, width=64, points=50)  # read as 50 points before: PCL refuses it
    return Probe(says=(str(p), "POINTS", "WIDTH x HEIGHT = 64 x 1 = 64"), call=lambda: read_pcd(p))


@case("pcd", "rows_beyond_points", "misaligned")
def _(d):
    p = _binary_pcd(d, 64, width=50, points=50)  # 14 rows more than the header: cut silently before
    return Probe(says=(str(p), "DATA", "50 points x 16 bytes = 800 bytes", "224 bytes too many"),
                 call=lambda: read_pcd(p))


@case("pcd", "nan_in_unorganised_cloud", "nan/inf")
def _(d):
    p = write(d / "a.pcd", pcd_text(body="1 2 3 0.5\nnan 5 6 0.5\n7 8 9 0.5\n"))  # the row was dropped
    return Probe(says=(str(p), "points", "NaN in 1 of 3 points"), call=lambda: read_pcd(p))


@case("pcd", "ascii_beyond_float32", "wrong dtype")
def _(d):
    p = write(d / "a.pcd", pcd_text(body="1 2 3 0.5\n1e39 5 6 0.5\n7 8 9 0.5\n"))  # became inf, then dropped
    return Probe(says=(str(p), "DATA field 'x'", "float32's range"), call=lambda: read_pcd(p))


@case("pcd", "ascii_semantic_300", "wrong dtype")
def _(d):
    p = write(d / "a.pcd", pcd_text(fields="x y z semantic", size="4 4 4 1", type_="F F F U",
                                    body="1 2 3 4\n4 5 6 300\n7 8 9 5\n"))  # read as 300 % 256 = 44
    return Probe(says=(str(p), "DATA field 'semantic'", "integers in [0, 255]"), call=lambda: read_pcd(p))


@case("pcd", "count_1e20", "huge")
def _(d):
    p = write(d / "a.pcd", pcd_text(count="1 1 1 100000000000000000000"))
    return Probe(says=(str(p), "SIZE/COUNT", "COUNT in [1, 4096]"), call=lambda: read_pcd(p))


@case("pcd", "rgb_count_2", "misaligned")
def _(d):
    p = write(d / "a.pcd", pcd_text(fields="x y z rgb", count="1 1 1 2", body="1 2 3 0 0\n4 5 6 0 0\n7 8 9 0 0\n"))
    return Probe(says=(str(p), "COUNT", "1 for field 'rgb'"), call=lambda: read_pcd(p))


def lzf_zero_runs(n_bytes: int) -> bytes:
    """LZF that inflates to ``n_bytes`` zeros: a 1-byte literal, then back references of 264 bytes at
    distance 1 (the worst case of a byte-by-byte decoder), then a literal for the rest."""
    full, rest = divmod(n_bytes - 1, 264)
    body = bytearray([0, 0]) + bytes([0xE0, 264 - 9, 0]) * full
    while rest:
        run = min(rest, 32)  # a literal run holds at most 32 bytes
        body += bytes([run - 1]) + bytes(run)
        rest -= run
    return bytes(body)


@case("pcd", "lzf_zero_runs_megabyte", "bomb")
def _(d):
    n = 1_500_000  # 24 MB of zero points from 270 KB: the pure-Python decoder took about 10 s
    packed = lzf_zero_runs(16 * n)
    p = write(d / "a.pcd", pcd_text(points=n, data="binary_compressed", body="")
              + struct.pack("<II", len(packed), 16 * n) + packed)
    read = lambda: read_pcd(p)[0].shape  # noqa: E731
    return Probe(says=(), call=read, returns=(n, 4))


@case("binfile", "fifo", "not a regular file")
def _(d):
    p = fifo(d / "000000.bin")
    return Probe(says=(str(p), "a readable point cloud file", "FIFO"), call=lambda: read_bin(p, 4))


@case("kitti", "nuscenes_x5_bin_as_velodyne", "misaligned")
def _(d):
    root = kitti_frame(d)
    x5 = cloud(64, columns=5)
    x5[:, 3] = np.arange(64) * 4.0  # intensity 0..255, nuScenes' scale; 64 x 20 B is a multiple of 16
    x5[:, 4] = np.arange(64) % 32   # ring index
    velo = write(root / "training" / "velodyne" / "000000.bin", x5.tobytes())
    return Probe(says=(str(velo), "reflectance", "values in [0, 1]"), call=lambda: read_kitti_frame(root, 0))


@case("kitti", "calib_singular", "wrong units")
def _(d):
    root = kitti_frame(d, calib=CALIB.replace("R0_rect: 9.999e-01 1.009e-02 -8.51e-03", "R0_rect: 0 0 0"))
    calib = root / "training" / "calib" / "000000.txt"
    return Probe(says=(str(calib), "R0_rect", "a rotation", "singular values"), call=lambda: read_kitti_frame(root, 0))


@case("kitti", "calib_is_a_fifo", "not a regular file")
def _(d):
    root = kitti_frame(d, calib=None)
    calib = fifo(root / "training" / "calib" / "000000.txt")
    return Probe(says=(str(calib), "a readable KITTI calib file", "FIFO"), call=lambda: read_kitti_frame(root, 0))


@case("nuscenes", "info_is_a_fifo", "not a regular file")
def _(d):
    b, i = nuscenes_frame(d)
    i.unlink()
    fifo(i)
    return Probe(says=(str(i), "a readable mmdet3d info JSON", "FIFO"), call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "category_index_a_list", "wrong dtype")
def _(d):
    info = nuscenes_info()
    info["metainfo"]["categories"]["car"] = [0]  # unhashable as a dict key: TypeError before
    b, i = nuscenes_frame(d, info)
    return Probe(says=(str(i), "metainfo.categories", "integer label index"), call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "ego2global_400_digits", "overflow")
def _(d):
    pose = np.eye(4).tolist()
    pose[0][3] = 10**400  # OverflowError before
    b, i = nuscenes_frame(d, nuscenes_info(ego2global=pose))
    return Probe(says=(str(i), "ego2global[0]", "finite numbers"), call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "bbox_of_5000_digits", "overflow")
def _(d):
    b, i = nuscenes_frame(d, json.dumps(nuscenes_info()).replace("18.4", "9" * 5000))  # json: ValueError before
    return Probe(says=(str(i), "a readable mmdet3d info JSON", "ValueError"), call=lambda: read_nuscenes_frame(b, i))


@case("nuscenes", "info_100k_brackets", "deep")
def _(d):
    b, i = nuscenes_frame(d, '{"data_list": ' + "[" * 100_000)  # json: RecursionError before
    return Probe(says=(str(i), "a readable mmdet3d info JSON", "RecursionError"),
                 call=lambda: read_nuscenes_frame(b, i))


@case("waymo", "dev_urandom", "not a regular file", needs=WAYMO)
def _(d):
    return Probe(says=("/dev/urandom", "a readable TFRecord file", "character device"),
                 call=lambda: read_waymo_frames("/dev/urandom"))


def zlib_zeros(n_chunks: int, chunk: int = 16 << 20) -> bytes:
    """A zlib stream of ``n_chunks x chunk`` zero bytes, made from one compressed chunk repeated
    (each ends in a full flush, so the blocks stand alone) and the checksum of the whole: over
    n zeros Adler-32's sums are a = 1, b = n mod 65521."""
    co = zlib.compressobj(9)
    first = co.compress(bytes(chunk)) + co.flush(zlib.Z_FULL_FLUSH)
    header, block = first[:2], first[2:]
    adler = (n_chunks * chunk % 65521) << 16 | 1
    return header + block * n_chunks + co.flush()[:-4] + struct.pack(">I", adler)


@case("waymo", "range_image_zlib_bomb", "bomb", needs=WAYMO)
def _(d):
    bomb = zlib_zeros(96)  # 1.5 MB that inflates to 1.5 GiB
    p = _waymo_file(d, tfrecord(waymo_frame(compressed=bomb).SerializeToString()))
    return Probe(says=(str(p), "ri_return1", "a range image of at most", "zlib bomb"),
                 call=lambda: read_waymo_frames(p))


@case("waymo", "range_image_shape_wraps_to_0", "overflow", needs=WAYMO)
def _(d):
    from waymo_open_dataset import dataset_pb2

    matrix = dataset_pb2.MatrixFloat()
    matrix.shape.dims.extend([2**30, 2**30, 16])  # their int64 product is 2^64 = 0: ValueError before
    p = _waymo_file(d, tfrecord(waymo_frame(compressed=zlib.compress(matrix.SerializeToString())).SerializeToString()))
    return Probe(says=(str(p), "ri_return1", "a 3-d matrix whose shape matches its data"),
                 call=lambda: read_waymo_frames(p))
