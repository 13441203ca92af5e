"""The bad-input corpus: every reader, params.yaml, the voxel store and the CLI, fed broken input.

Nothing here is committed as a blob: each case writes a valid input into a folder and then
breaks it (truncated, misaligned, wrong dtype, NaN/Inf, empty, huge header counts, missing
keys, wrong units, corrupt CRC, unreadable, unknown stage or profile). ``case.build(folder)``
returns a :class:`Probe`: how to feed the input to typ, and the texts the error must contain
(the file or field it names and what was expected). tests/test_bad_inputs.py runs them all.

    python tests/bad_inputs/make_corpus.py OUT   # write every case under OUT/<reader>/<name>/, list them
"""
from __future__ import annotations

import json
import os
import struct
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

if __package__ in (None, ""):  # run as a script: make the repository importable
    sys.path[:0] = [str(Path(__file__).resolve().parents[2]), str(Path(__file__).resolve().parents[1])]

from typ import geometry
from typ.formats.binfile import read_bin
from typ.formats.kitti import read_calib, read_kitti_frame, read_labels
from typ.formats.nuscenes import read_nuscenes_frame
from typ.formats.opv2v import check_scenario, list_agents, list_scenarios, read_scene, write_scene
from typ.formats.pcd import read_pcd, write_pcd
from typ.formats.waymo import iter_tfrecord, masked_crc32c, read_waymo_frames, read_waymo_kitti_bin
from typ.scene import AgentView, Scene
from typ.store import read_scene_voxels, scene_path, stored_grid, stored_input_hash, write_scene_voxels
from typ.voxel import Grid, box_map, voxelize

KINDS = ("truncated", "misaligned", "wrong dtype", "nan/inf", "empty", "huge", "missing keys", "wrong units",
         "corrupt crc", "unreadable", "unknown", "bomb", "not a regular file", "deep", "overflow",
         "link", "forged")

#: the grid of every store case: small enough to write in a millisecond
GRID = Grid((-8.0, 8.0), (-8.0, 8.0), (-2.0, 2.0), (16, 16, 4))


@dataclass
class Probe:
    """How to feed one bad input to typ, and what the error must say.

    Exactly one of ``call`` (must raise :class:`typ.errors.TypError`, or return ``returns`` when
    that is set: an input that must be read correctly, and fast), ``argv`` (``cli.main.main``
    in this process: exit code 2) or ``process`` (``python -m cli`` in a subprocess: exit code 2;
    for cases that start a stage's flow) is set. ``says``: substrings of the message (for the CLI,
    of stderr). ``watch``: the folder whose files and bytes must be the same before and after
    (the case's whole folder by default): previous outputs untouched, no partial or temporary file.
    """

    says: tuple[str, ...]
    call: Callable[[], object] | None = None
    argv: list[str] | None = None
    process: list[str] | None = None
    cwd: Path | None = None
    watch: Path | None = None
    returns: object = None


@dataclass(frozen=True)
class Case:
    reader: str        # binfile, pcd, opv2v, kitti, nuscenes, waymo, store, voxel, params, cli, artifact, show, io
    name: str
    kind: str          # one of KINDS
    build: Callable[[Path], Probe] = field(repr=False, compare=False)
    needs_non_root: bool = False  # permission cases: root reads anything
    needs: str = ""               # an optional module the case imports

    @property
    def id(self) -> str:
        return f"{self.reader}/{self.name}"


CASES: list[Case] = []


def case(reader: str, name: str, kind: str, *, needs_non_root: bool = False, needs: str = ""):
    assert kind in KINDS, kind

    def register(build: Callable[[Path], Probe]) -> Callable[[Path], Probe]:
        CASES.append(Case(reader, name, kind, build, needs_non_root, needs))
        return build

    return register


# ---------------------------------------------------------------- valid inputs to break


def cloud(n: int = 64, columns: int = 4, seed: int = 0) -> np.ndarray:
    """(n, columns) float32: x, y in [-40, 40] m, z in [-2, 1] m, the rest in [0, 1]."""
    rng = np.random.default_rng(seed)
    out = rng.uniform(0.0, 1.0, (n, columns)).astype(np.float32)
    out[:, :2] = rng.uniform(-40.0, 40.0, (n, 2))
    out[:, 2] = rng.uniform(-2.0, 1.0, n)
    return out


def write(path: Path, data: bytes | str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


def unreadable(path: Path) -> Path:
    path.chmod(0)
    return path


def pcd_text(fields="x y z intensity", size="4 4 4 4", type_="F F F F", count="1 1 1 1",
             points: int | str = 3, data="ascii", body="1 2 3 0.5\n4 5 6 0.5\n7 8 9 0.5\n") -> bytes:
    return (f"# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {type_}\nCOUNT {count}\n"
            f"WIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {data}\n{body}").encode()


def opv2v_doc(**changes) -> dict:
    doc = {"lidar_pose": [10.0, 5.0, 1.9, 0.0, 30.0, 0.0],
           "vehicles": {7: {"location": [20.0, 5.0, 0.5], "angle": [0.0, 10.0, 0.0],
                            "extent": [2.0, 1.0, 0.75], "center": [0.0, 0.0, 0.0]}}}
    doc.update(changes)
    return doc


def opv2v_scenario(folder: Path, doc: dict | str | None = None, *, ts: str = "000068") -> Path:
    """``folder/scn/1/<ts>.yaml + .pcd`` (one agent); ``doc`` replaces the yaml (text as is)."""
    yaml_path = folder / "scn" / "1" / f"{ts}.yaml"
    write_pcd(yaml_path.with_suffix(".pcd"), cloud())
    doc = opv2v_doc() if doc is None else doc
    write(yaml_path, doc if isinstance(doc, str) else yaml.safe_dump(doc))
    return yaml_path


CALIB = ("P2: 7.07e+02 0 6.04e+02 4.57e+01 0 7.07e+02 1.80e+02 -3.45e-01 0 0 1 4.98e-03\n"
         "R0_rect: 9.999e-01 1.009e-02 -8.51e-03 -1.012e-02 9.999e-01 -4.03e-03 8.47e-03 4.12e-03 9.999e-01\n"
         "Tr_velo_to_cam: 6.93e-03 -9.999e-01 -2.76e-03 -2.46e-02 -1.16e-03 2.75e-03 -9.999e-01 -6.13e-02 "
         "9.999e-01 6.93e-03 -1.14e-03 -3.32e-01\n")
LABEL = ("Car 0.00 0 1.85 387.63 181.54 423.81 203.12 1.67 1.87 3.69 -16.53 2.39 58.49 1.57\n"
         "DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10\n")


def kitti_frame(root: Path, *, label: str | None = LABEL, calib: str | None = CALIB) -> Path:
    """A KITTI object frame ``root/training/{velodyne,calib,label_2}/000000.*``; returns root."""
    base = root / "training"
    write(base / "velodyne" / "000000.bin", cloud().tobytes())
    if calib is not None:
        write(base / "calib" / "000000.txt", calib)
    if label is not None:
        write(base / "label_2" / "000000.txt", label)
    return root


NUSCENES_BIN = "n015__LIDAR_TOP__1532402927647951.pcd.bin"


def nuscenes_info(**record_changes) -> dict:
    pose = np.eye(4).tolist()
    record = {"token": "tok", "timestamp": 1532402927647951, "ego2global": pose,
              "lidar_points": {"num_pts_feats": 5, "lidar_path": NUSCENES_BIN, "lidar2ego": pose},
              "instances": [{"bbox_label_3d": 0, "bbox_3d": [18.4, 5.5, 0.7, 4.1, 1.8, 1.6, 3.1]}]}
    record.update(record_changes)
    return {"metainfo": {"categories": {"car": 0, "pedestrian": 1}}, "data_list": [record]}


def nuscenes_frame(folder: Path, info: dict | str | None = None, points: np.ndarray | None = None) -> tuple[Path, Path]:
    bin_path = write(folder / NUSCENES_BIN, (cloud(columns=5) if points is None else points).tobytes())
    info = nuscenes_info() if info is None else info
    info_path = write(folder / "info.json", info if isinstance(info, str) else json.dumps(info))
    return bin_path, info_path


def tfrecord(*payloads: bytes) -> bytes:
    """TFRecord framing with valid masked CRC-32C: ``<Q len><I crc(len)><payload><I crc(payload)>``."""
    out = b""
    for payload in payloads:
        length = struct.pack("<Q", len(payload))
        out += length + struct.pack("<I", masked_crc32c(length)) + payload + struct.pack("<I", masked_crc32c(payload))
    return out


def waymo_frame(*, pose: np.ndarray | None = None, range_image: np.ndarray | None = None,
                compressed: bytes | None = None):
    """A ``dataset_pb2.Frame`` with one FRONT laser (2x4 range image) and one label."""
    from waymo_open_dataset import dataset_pb2, label_pb2

    frame = dataset_pb2.Frame()
    frame.context.name = "synthetic"
    frame.timestamp_micros = 42
    frame.pose.transform.extend((np.eye(4) if pose is None else pose).ravel().tolist())
    calib = frame.context.laser_calibrations.add()
    calib.name = dataset_pb2.LaserName.FRONT
    calib.beam_inclination_min, calib.beam_inclination_max = -0.2, 0.2
    calib.extrinsic.transform.extend(np.eye(4).ravel().tolist())
    if range_image is None:
        range_image = np.zeros((2, 4, 4), dtype=np.float32)
        range_image[0, 1, :2] = [10.0, 0.5]
    if compressed is None:
        matrix = dataset_pb2.MatrixFloat()
        matrix.data.extend(range_image.astype(np.float32).ravel().tolist())
        matrix.shape.dims.extend(range_image.shape)
        compressed = zlib.compress(matrix.SerializeToString())
    laser = frame.lasers.add()
    laser.name = dataset_pb2.LaserName.FRONT
    laser.ri_return1.range_image_compressed = compressed
    label = frame.laser_labels.add()
    label.id = "a"
    label.type = label_pb2.Label.TYPE_VEHICLE
    label.box.center_x, label.box.length, label.box.width, label.box.height = 8.0, 4.0, 2.0, 1.5
    return frame


def store_records(n: int = 2, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    return {(str(a), "000000"): (rng.random(GRID.shape) < 0.2, rng.random((*GRID.shape[:2], 1)) < 0.1)
            for a in range(n)}


def store_file(path: Path) -> Path:
    return write_scene_voxels(path, store_records(), grid=GRID, input_hash="h")


def forged_store(path: Path, meta_changes: dict | None = None, *, drop_meta: bool = False, occ_ix: int = 1) -> Path:
    import pyarrow as pa
    import pyarrow.parquet as pq

    from typ import store

    meta = {"format": store.FORMAT, "version": store.FORMAT_VERSION, "grid": GRID.to_dict(), "input_hash": "h"}
    meta.update(meta_changes or {})
    schema = store._SCHEMA
    if not drop_meta:
        schema = schema.with_metadata({store.METADATA_KEY: json.dumps(meta).encode()})
    rows = {"scene": ["s"], "agent_id": ["1"], "timestamp": ["0"], "occ_ix": [[occ_ix]], "occ_iy": [[0]],
            "occ_iz": [[0]], "box_ix": [[]], "box_iy": [[]]}
    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pydict(rows, schema=schema), path)
    return path


def params(folder: Path, raw: dict | str) -> Path:
    return write(folder / "params.yaml", raw if isinstance(raw, str) else yaml.safe_dump(raw, sort_keys=False))


def load_params(folder: Path, raw: dict | str) -> Probe:
    from typ.config import load_config

    path = params(folder, raw)
    return Probe(says=(str(path),), call=lambda: load_config(path))


# ---------------------------------------------------------------- binfile (KITTI .bin, headerless float32)


@case("binfile", "empty", "empty")
def _(d):
    p = write(d / "a.bin", b"")
    return Probe(says=(str(p), "points", "at least one point"), call=lambda: read_bin(p, 4))


@case("binfile", "truncated", "truncated")
def _(d):
    p = write(d / "a.bin", cloud().tobytes()[:-3])
    return Probe(says=(str(p), "size", "a multiple of 16 bytes"), call=lambda: read_bin(p, 4))


@case("binfile", "kitti_x4_read_as_waymo_x6", "misaligned")
def _(d):
    p = write(d / "0000000.bin", cloud(65).tobytes())  # 65 x 16 B is no multiple of 24 B
    return Probe(says=(str(p), "size", "a multiple of 24 bytes"), call=lambda: read_waymo_kitti_bin(p))


@case("binfile", "float64", "wrong dtype")
def _(d):
    p = write(d / "a.bin", (cloud().astype(np.float64) + 0.123).tobytes())
    return Probe(says=(str(p), "dtype", "float32 little-endian"), call=lambda: read_bin(p, 4))


@case("binfile", "big_endian", "wrong dtype")
def _(d):
    p = write(d / "a.bin", cloud().astype(">f4").tobytes())
    return Probe(says=(str(p), "dtype", "float32 little-endian"), call=lambda: read_bin(p, 4))


@case("binfile", "nan_x", "nan/inf")
def _(d):
    c = cloud()
    c[5, 0] = np.nan
    p = write(d / "a.bin", c.tobytes())
    return Probe(says=(str(p), "points", "finite values", "1 of 64 points"), call=lambda: read_bin(p, 4))


@case("binfile", "inf_intensity", "nan/inf")
def _(d):
    c = cloud()
    c[3, 3] = np.inf
    p = write(d / "a.bin", c.tobytes())
    return Probe(says=(str(p), "points", "finite values", "columns [3]"), call=lambda: read_bin(p, 4))


@case("binfile", "millimetres", "wrong units")
def _(d):
    c = cloud()
    c[:, :3] *= 1000.0  # a scan stored in mm: returns at 40,000 "m"
    p = write(d / "a.bin", c.tobytes())
    return Probe(says=(str(p), "dtype", "<= 10000 m", "millimetres"), call=lambda: read_bin(p, 4))


@case("binfile", "missing", "missing keys")
def _(d):
    p = d / "absent.bin"
    return Probe(says=(str(p), "file", "an existing point cloud file"), call=lambda: read_bin(p, 4))


@case("binfile", "directory", "unreadable")
def _(d):
    p = d / "a.bin"
    p.mkdir()
    return Probe(says=(str(p), "file", "a readable point cloud file"), call=lambda: read_bin(p, 4))


@case("binfile", "no_permission", "unreadable", needs_non_root=True)
def _(d):
    p = unreadable(write(d / "a.bin", cloud().tobytes()))
    return Probe(says=(str(p), "file", "a readable point cloud file", "PermissionError"), call=lambda: read_bin(p, 4))


# ---------------------------------------------------------------- pcd (OPV2V / V2V4Real clouds)


@case("pcd", "empty", "empty")
def _(d):
    p = write(d / "a.pcd", b"")
    return Probe(says=(str(p), "header", "DATA"), call=lambda: read_pcd(p))


@case("pcd", "header_cut_before_data", "truncated")
def _(d):
    p = write(d / "a.pcd", pcd_text().split(b"POINTS")[0])
    return Probe(says=(str(p), "header", "DATA"), call=lambda: read_pcd(p))


@case("pcd", "binary_body_truncated", "truncated")
def _(d):
    good = d / "good.pcd"
    write_pcd(good, cloud())
    p = write(d / "a.pcd", good.read_bytes()[:-10])
    good.unlink()
    return Probe(says=(str(p), "DATA", "64 points", "truncated"), call=lambda: read_pcd(p))


@case("pcd", "huge_points_count", "huge")
def _(d):
    good = d / "good.pcd"
    write_pcd(good, cloud())
    p = write(d / "a.pcd", good.read_bytes().replace(b"WIDTH 64", b"WIDTH 4294967295")
              .replace(b"POINTS 64", b"POINTS 4294967295"))
    good.unlink()
    return Probe(says=(str(p), "DATA", "4294967295 points", "truncated"), call=lambda: read_pcd(p))


@case("pcd", "negative_points_count", "huge")
def _(d):
    p = write(d / "a.pcd", pcd_text(points="-3"))
    return Probe(says=(str(p), "POINTS", "one integer in [0, 4294967295]"), call=lambda: read_pcd(p))


@case("pcd", "ascii_count_mismatch", "misaligned")
def _(d):
    p = write(d / "a.pcd", pcd_text(body="1 2 3 0.5\n4 5 6\n7 8 9 0.5\n"))
    return Probe(says=(str(p), "DATA", "3 points x 4 values = 12 numbers"), call=lambda: read_pcd(p))


@case("pcd", "ascii_not_numbers", "wrong dtype")
def _(d):
    p = write(d / "a.pcd", pcd_text(body="1 2 3 0.5\n4 five 6 0.5\n7 8 9 0.5\n"))
    return Probe(says=(str(p), "DATA", "whitespace-separated numbers"), call=lambda: read_pcd(p))


@case("pcd", "float16_type", "wrong dtype")
def _(d):
    p = write(d / "a.pcd", pcd_text(size="4 4 2 4"))
    return Probe(says=(str(p), "TYPE/SIZE", "one of"), call=lambda: read_pcd(p))


@case("pcd", "size_entries_missing", "missing keys")
def _(d):
    p = write(d / "a.pcd", pcd_text(size="4 4 4"))
    return Probe(says=(str(p), "SIZE", "4 entries, one per field"), call=lambda: read_pcd(p))


@case("pcd", "no_z_field", "missing keys")
def _(d):
    p = write(d / "a.pcd", pcd_text(fields="x y w intensity"))
    return Probe(says=(str(p), "FIELDS", "fields x, y and z"), call=lambda: read_pcd(p))


@case("pcd", "unknown_data_kind", "unknown")
def _(d):
    p = write(d / "a.pcd", pcd_text(data="binary_lz4"))
    return Probe(says=(str(p), "DATA", "one of ('ascii', 'binary', 'binary_compressed')"), call=lambda: read_pcd(p))


@case("pcd", "lzf_stream_corrupt", "corrupt crc")
def _(d):
    # sizes (6 compressed, 48 raw), then a back reference to before the first byte
    payload = struct.pack("<II", 6, 3 * 4 * 4) + bytes([0xE0, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF])
    p = write(d / "a.pcd", pcd_text(data="binary_compressed", body="") + payload)
    return Probe(says=(str(p), "DATA", "valid LZF-compressed data"), call=lambda: read_pcd(p))


@case("pcd", "nan_intensity", "nan/inf")
def _(d):
    p = write(d / "a.pcd", pcd_text(body="1 2 3 0.5\n4 5 6 nan\n7 8 9 0.5\n"))
    return Probe(says=(str(p), "intensity", "finite values"), call=lambda: read_pcd(p))


@case("pcd", "semantic_as_float", "wrong dtype")
def _(d):
    p = write(d / "a.pcd", pcd_text(fields="x y z semantic", body="1 2 3 0.5\n4 5 6 1.5\n7 8 9 2\n"))
    return Probe(says=(str(p), "semantic", "unsigned integer codes"), call=lambda: read_pcd(p))


@case("pcd", "millimetres", "wrong units")
def _(d):
    c = cloud()
    c[:, :3] *= 1000.0
    p = d / "a.pcd"
    write_pcd(p, c)
    return Probe(says=(str(p), "points", "<= 10000 m", "millimetres"), call=lambda: read_pcd(p))


@case("pcd", "directory", "unreadable")
def _(d):
    p = d / "a.pcd"
    p.mkdir()
    return Probe(says=(str(p), "file", "a readable .pcd file"), call=lambda: read_pcd(p))


# ---------------------------------------------------------------- opv2v (scenario/agent/timestamp.yaml + .pcd)


def _read_opv2v(yaml_path: Path):
    return lambda: read_scene(yaml_path.parent.parent, yaml_path.stem)


@case("opv2v", "yaml_not_yaml", "wrong dtype")
def _(d):
    y = opv2v_scenario(d, "lidar_pose: [1, 2\nvehicles: {}\n")
    return Probe(says=(str(y), "yaml", "well-formed YAML", "line"), call=_read_opv2v(y))


@case("opv2v", "yaml_empty", "empty")
def _(d):
    y = opv2v_scenario(d, "")
    return Probe(says=(str(y), "yaml", "a mapping with lidar_pose and vehicles"), call=_read_opv2v(y))


@case("opv2v", "yaml_truncated", "truncated")
def _(d):
    text = yaml.safe_dump(opv2v_doc())
    y = opv2v_scenario(d, text[: text.index("vehicles")])  # cut before the vehicles block
    return Probe(says=(str(y), "vehicles", "a mapping of vehicle id"), call=_read_opv2v(y))


@case("opv2v", "yaml_binary", "wrong dtype")
def _(d):
    y = opv2v_scenario(d, "")
    y.write_bytes(b"\xff\xfe\x00lidar_pose\x80\x81")
    return Probe(says=(str(y), "yaml", "a readable UTF-8 yaml file"), call=_read_opv2v(y))


@case("opv2v", "lidar_pose_missing", "missing keys")
def _(d):
    doc = opv2v_doc()
    del doc["lidar_pose"]
    y = opv2v_scenario(d, doc)
    return Probe(says=(str(y), "lidar_pose", "a list of 6 numbers", "missing"), call=_read_opv2v(y))


@case("opv2v", "lidar_pose_5_numbers", "misaligned")
def _(d):
    y = opv2v_scenario(d, opv2v_doc(lidar_pose=[10.0, 5.0, 1.9, 0.0, 30.0]))
    return Probe(says=(str(y), "lidar_pose", "a list of 6 numbers"), call=_read_opv2v(y))


@case("opv2v", "lidar_pose_nan", "nan/inf")
def _(d):
    y = opv2v_scenario(d, yaml.safe_dump(opv2v_doc()).replace("- 30.0", "- .nan", 1))
    return Probe(says=(str(y), "lidar_pose", "finite numbers"), call=_read_opv2v(y))


@case("opv2v", "vehicle_location_strings", "wrong dtype")
def _(d):
    doc = opv2v_doc()
    doc["vehicles"][7]["location"] = ["20", "5", "0.5"]
    y = opv2v_scenario(d, doc)
    return Probe(says=(str(y), "vehicles.7.location", "3 numbers"), call=_read_opv2v(y))


@case("opv2v", "vehicle_extent_missing", "missing keys")
def _(d):
    doc = opv2v_doc()
    del doc["vehicles"][7]["extent"]
    y = opv2v_scenario(d, doc)
    return Probe(says=(str(y), "vehicles.7.extent", "a list of 3 numbers", "missing"), call=_read_opv2v(y))


@case("opv2v", "vehicle_extent_zero", "wrong units")
def _(d):
    doc = opv2v_doc()
    doc["vehicles"][7]["extent"] = [2.0, 0.0, 0.75]
    y = opv2v_scenario(d, doc)
    return Probe(says=(str(y), "vehicles.7.extent", "positive half sizes"), call=_read_opv2v(y))


@case("opv2v", "vehicle_id_not_integer", "wrong dtype")
def _(d):
    doc = opv2v_doc()
    doc["vehicles"] = {"car-7": doc["vehicles"][7]}
    y = opv2v_scenario(d, doc)
    return Probe(says=(str(y), "vehicles.car-7", "an integer vehicle id"), call=_read_opv2v(y))


@case("opv2v", "pcd_missing_beside_yaml", "missing keys")
def _(d):
    y = opv2v_scenario(d)
    y.with_suffix(".pcd").unlink()
    return Probe(says=(str(y.with_suffix(".pcd")), "pcd", "a point cloud beside"), call=_read_opv2v(y))


@case("opv2v", "pcd_truncated", "truncated")
def _(d):
    y = opv2v_scenario(d)
    pcd = y.with_suffix(".pcd")
    pcd.write_bytes(pcd.read_bytes()[:-7])
    return Probe(says=(str(pcd), "DATA", "truncated"), call=_read_opv2v(y))


@case("opv2v", "scenario_without_agents", "empty")
def _(d):
    s = d / "scn"
    s.mkdir()
    return Probe(says=(str(s), "agents", "at least one agent folder"), call=lambda: list_agents(s))


@case("opv2v", "root_is_a_file", "unreadable")
def _(d):
    r = write(d / "train", "not a folder")
    return Probe(says=(str(r), "root", "a folder of OPV2V-layout scenarios"), call=lambda: list_scenarios(r))


@case("opv2v", "yaml_no_permission", "unreadable", needs_non_root=True)
def _(d):
    y = unreadable(opv2v_scenario(d))
    return Probe(says=(str(y), "yaml", "a readable UTF-8 yaml file", "PermissionError"), call=_read_opv2v(y))


# ---------------------------------------------------------------- kitti (velodyne/calib/label_2)


@case("kitti", "calib_r0_rect_missing", "missing keys")
def _(d):
    p = write(d / "calib.txt", "\n".join(l for l in CALIB.splitlines() if not l.startswith("R0_rect")))
    return Probe(says=(str(p), "R0_rect", "with 9 numbers", "missing"), call=lambda: read_calib(p))


@case("kitti", "calib_11_numbers", "misaligned")
def _(d):
    p = write(d / "calib.txt", CALIB.replace(" -3.32e-01", ""))
    return Probe(says=(str(p), "Tr_velo_to_cam", "12 numbers"), call=lambda: read_calib(p))


@case("kitti", "calib_nan", "nan/inf")
def _(d):
    p = write(d / "calib.txt", CALIB.replace("9.999e-01 1.009e-02", "nan 1.009e-02"))
    return Probe(says=(str(p), "R0_rect", "finite numbers"), call=lambda: read_calib(p))


@case("kitti", "calib_no_colon", "wrong dtype")
def _(d):
    p = write(d / "calib.txt", CALIB.replace("R0_rect:", "R0_rect"))
    return Probe(says=(str(p), "line 2", "'NAME: v1 v2 ...'"), call=lambda: read_calib(p))


def _labels(d: Path, text: str) -> Probe:
    p = write(d / "label.txt", text)
    calib = read_calib(write(d / "calib.txt", CALIB))
    return Probe(says=(str(p), "line 1"), call=lambda: read_labels(p, calib))


@case("kitti", "label_14_fields", "truncated")
def _(d):
    probe = _labels(d, LABEL.replace(" 1.57\n", "\n", 1))
    probe.says += ("15 fields",)
    return probe


@case("kitti", "label_non_numeric", "wrong dtype")
def _(d):
    probe = _labels(d, LABEL.replace("1.67 1.87 3.69", "1.67 wide 3.69"))
    probe.says += ("numbers in fields 9-15",)
    return probe


@case("kitti", "label_zero_height", "wrong units")
def _(d):
    probe = _labels(d, LABEL.replace("1.67 1.87 3.69", "0 1.87 3.69"))
    probe.says += ("positive h, w, l",)
    return probe


@case("kitti", "label_centimetres", "wrong units")
def _(d):
    probe = _labels(d, LABEL.replace("1.67 1.87 3.69", "167 187 369"))
    probe.says += ("h, w, l <= 100 m",)
    return probe


@case("kitti", "label_nan_location", "nan/inf")
def _(d):
    probe = _labels(d, LABEL.replace("-16.53 2.39 58.49", "nan 2.39 58.49"))
    probe.says += ("finite",)
    return probe


@case("kitti", "frame_without_velodyne", "missing keys")
def _(d):
    root = kitti_frame(d)
    (root / "training" / "velodyne" / "000000.bin").unlink()
    return Probe(says=(str(root / "training"), "velodyne", "000000.bin"), call=lambda: read_kitti_frame(root, 0))


@case("kitti", "labels_without_calib", "missing keys")
def _(d):
    root = kitti_frame(d, calib=None)
    calib = root / "training" / "calib" / "000000.txt"
    return Probe(says=(str(calib), "file", "an existing KITTI calib file"), call=lambda: read_kitti_frame(root, 0))


@case("kitti", "velodyne_truncated", "truncated")
def _(d):
    root = kitti_frame(d)
    velo = root / "training" / "velodyne" / "000000.bin"
    velo.write_bytes(velo.read_bytes()[:-5])
    return Probe(says=(str(velo), "size", "a multiple of 16 bytes"), call=lambda: read_kitti_frame(root, 0))


# ---------------------------------------------------------------- nuscenes (.pcd.bin + mmdet3d info JSON)


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


# ---------------------------------------------------------------- waymo (tfrecord of Frame protos)

WAYMO = "waymo_open_dataset"


def _waymo_file(d: Path, data: bytes) -> Path:
    return write(d / "segment.tfrecord", data)


@case("waymo", "empty_file", "empty", needs=WAYMO)
def _(d):
    p = _waymo_file(d, b"")
    return Probe(says=(str(p), "records", "at least one Frame record"), call=lambda: read_waymo_frames(p))


@case("waymo", "truncated_payload", "truncated", needs=WAYMO)
def _(d):
    p = _waymo_file(d, tfrecord(waymo_frame().SerializeToString())[:-20])
    return Probe(says=(str(p), "record 0 at byte offset 0", "truncated file"), call=lambda: read_waymo_frames(p))


@case("waymo", "truncated_header", "truncated", needs=WAYMO)
def _(d):
    payload = waymo_frame().SerializeToString()
    p = _waymo_file(d, tfrecord(payload) + tfrecord(payload)[:7])
    return Probe(says=(str(p), "record 1", "a 12-byte record header"), call=lambda: read_waymo_frames(p))


@case("waymo", "payload_crc_flipped", "corrupt crc", needs=WAYMO)
def _(d):
    data = bytearray(tfrecord(waymo_frame().SerializeToString()))
    data[40] ^= 0x10
    p = _waymo_file(d, bytes(data))
    return Probe(says=(str(p), "payload crc", "masked crc32c"), call=lambda: read_waymo_frames(p))


@case("waymo", "length_crc_flipped", "corrupt crc", needs=WAYMO)
def _(d):
    data = bytearray(tfrecord(waymo_frame().SerializeToString()))
    data[9] ^= 0x01
    p = _waymo_file(d, bytes(data))
    return Probe(says=(str(p), "length crc", "corrupt header"), call=lambda: list(iter_tfrecord(p)))


@case("waymo", "huge_length_with_valid_crc", "huge", needs=WAYMO)
def _(d):
    length = struct.pack("<Q", 2**62)
    p = _waymo_file(d, length + struct.pack("<I", masked_crc32c(length)) + b"\0" * 64)
    return Probe(says=(str(p), "a record of at most 64 MiB", str(2**62)), call=lambda: read_waymo_frames(p))


@case("waymo", "payload_not_a_frame", "wrong dtype", needs=WAYMO)
def _(d):
    p = _waymo_file(d, tfrecord(b"\xff\xff\xff\xff not a Frame proto"))
    return Probe(says=(str(p), "frame 0", "payload", "a serialized waymo.open_dataset.Frame"),
                 call=lambda: read_waymo_frames(p))


@case("waymo", "pose_nan", "nan/inf", needs=WAYMO)
def _(d):
    pose = np.eye(4)
    pose[0, 3] = np.nan
    p = _waymo_file(d, tfrecord(waymo_frame(pose=pose).SerializeToString()))
    return Probe(says=(str(p), "pose.transform", "16 finite numbers"), call=lambda: read_waymo_frames(p))


@case("waymo", "range_image_inf", "nan/inf", needs=WAYMO)
def _(d):
    image = np.zeros((2, 4, 4), dtype=np.float32)
    image[0, 1, :2] = [np.inf, 0.5]
    image[1, 2, :2] = [12.0, np.nan]
    p = _waymo_file(d, tfrecord(waymo_frame(range_image=image).SerializeToString()))
    return Probe(says=(str(p), "lasers[FRONT].ri_return1", "finite range and intensity", "2 of 8 pixels"),
                 call=lambda: read_waymo_frames(p))


@case("waymo", "range_image_zlib_corrupt", "corrupt crc", needs=WAYMO)
def _(d):
    good = waymo_frame()
    broken = bytearray(good.lasers[0].ri_return1.range_image_compressed)
    broken[-3] ^= 0xFF  # zlib's adler32 trailer
    p = _waymo_file(d, tfrecord(waymo_frame(compressed=bytes(broken)).SerializeToString()))
    return Probe(says=(str(p), "lasers[FRONT].ri_return1", "a zlib-compressed MatrixFloat"),
                 call=lambda: read_waymo_frames(p))


@case("waymo", "tfrecord_is_a_directory", "unreadable", needs=WAYMO)
def _(d):
    p = d / "segment.tfrecord"
    p.mkdir()
    return Probe(says=(str(p), "file", "a readable TFRecord file"), call=lambda: read_waymo_frames(p))


# ---------------------------------------------------------------- store (per-scene Parquet voxels)


@case("store", "not_parquet", "wrong dtype")
def _(d):
    p = write(d / "s.parquet", "scene,agent\ns,1\n")
    return Probe(says=(str(p), "file", "a Parquet file written by typ.store"), call=lambda: read_scene_voxels(p))


@case("store", "empty_file", "empty")
def _(d):
    p = write(d / "s.parquet", b"")
    return Probe(says=(str(p), "file", "a Parquet file written by typ.store"), call=lambda: stored_input_hash(p))


@case("store", "footer_cut", "truncated")
def _(d):
    p = store_file(d / "s.parquet")
    p.write_bytes(p.read_bytes()[:-9])
    return Probe(says=(str(p), "file", "a Parquet file written by typ.store"), call=lambda: read_scene_voxels(p))


@case("store", "huge_footer_length", "huge")
def _(d):
    p = store_file(d / "s.parquet")
    raw = p.read_bytes()
    p.write_bytes(raw[:-8] + struct.pack("<I", 2**31 - 1) + raw[-4:])
    return Probe(says=(str(p), "file", "a Parquet file written by typ.store"), call=lambda: read_scene_voxels(p))


@case("store", "data_page_byte_flipped", "corrupt crc")
def _(d):
    import pyarrow.parquet as pq

    p = store_file(d / "s.parquet")
    raw, good = p.read_bytes(), pq.read_table(p)
    chunk = pq.ParquetFile(p).metadata.row_group(0).column(3)  # occ_ix's values
    # the first flip that Parquet alone reads back without complaint, as other voxel indices:
    # only the page CRC can tell
    for pos in range(chunk.data_page_offset, chunk.data_page_offset + chunk.total_compressed_size):
        flipped = bytearray(raw)
        flipped[pos] ^= 0x04
        p.write_bytes(bytes(flipped))
        try:
            if not pq.read_table(p).equals(good):
                break
        except Exception:  # noqa: BLE001 - this flip is caught by Parquet itself; look further
            continue
    return Probe(says=(str(p), "file", "a readable Parquet file written by typ.store"),
                 call=lambda: read_scene_voxels(p))


@case("store", "foreign_parquet", "missing keys")
def _(d):
    p = forged_store(d / "s.parquet", drop_meta=True)
    return Probe(says=(str(p), "schema metadata", "typ.voxel_store", "missing"), call=lambda: stored_input_hash(p))


@case("store", "future_version", "unknown")
def _(d):
    p = forged_store(d / "s.parquet", {"version": 99})
    return Probe(says=(str(p), "schema metadata", "version 1"), call=lambda: stored_input_hash(p))


@case("store", "grid_without_shape", "missing keys")
def _(d):
    grid = GRID.to_dict()
    del grid["shape"]
    p = forged_store(d / "s.parquet", {"grid": grid})
    return Probe(says=(str(p), "grid", "exactly the keys"), call=lambda: stored_grid(p))


@case("store", "index_outside_grid", "huge")
def _(d):
    p = forged_store(d / "s.parquet", occ_ix=40)
    return Probe(says=(str(p), "occ_ix", "indices < 16"), call=lambda: read_scene_voxels(p))


@case("store", "missing_file", "missing keys")
def _(d):
    p = d / "s.parquet"
    return Probe(says=(str(p), "file", "an existing voxel store file", "missing"), call=lambda: read_scene_voxels(p))


@case("store", "rewrite_with_float_occupancy_keeps_old_file", "wrong dtype")
def _(d):
    p = store_file(d / "s.parquet")
    records = {k: (v[0].astype(np.float32), v[1]) for k, v in store_records().items()}
    return Probe(says=(str(p), "occupancy", "(16, 16, 4) bool", "float32"),
                 call=lambda: write_scene_voxels(p, records, grid=GRID, input_hash="new"))


@case("store", "rewrite_with_wrong_grid_shape_keeps_old_file", "misaligned")
def _(d):
    p = store_file(d / "s.parquet")
    records = {("1", "0"): (np.zeros((16, 16, 5), bool), np.zeros((16, 16, 1), bool))}
    return Probe(says=(str(p), "occupancy", "(16, 16, 4) bool"),
                 call=lambda: write_scene_voxels(p, records, grid=GRID, input_hash="new"))


@case("store", "scene_name_escapes_root", "unknown")
def _(d):
    return Probe(says=(str(d), "scene", "a non-empty name of letters"),
                 call=lambda: scene_path(d, "target", "train", "../x"))


# ---------------------------------------------------------------- voxel grid and voxelize


@case("voxel", "nan_and_inf_points", "nan/inf")
def _(d):
    pts = cloud()
    pts[1, 0], pts[2, 2] = np.nan, -np.inf
    return Probe(says=("points", "finite x, y, z", "2 rows with NaN/Inf"), call=lambda: voxelize(pts, GRID))


@case("voxel", "integer_points", "wrong dtype")
def _(d):
    pts = (cloud() * 100).astype(np.int32)
    return Probe(says=("points", "dtype float32 or float64", "int32"), call=lambda: voxelize(pts, GRID))


@case("voxel", "points_with_2_columns", "misaligned")
def _(d):
    pts = cloud()[:, :2]
    return Probe(says=("points", "(N, >=3)", "(64, 2)"), call=lambda: voxelize(pts, GRID))


@case("voxel", "grid_range_reversed", "wrong units")
def _(d):
    return Probe(says=("x_range", "min < max"), call=lambda: Grid((51.2, -51.2), (-51.2, 51.2), (-3.0, 1.0), (8, 8, 2)))


@case("voxel", "box_with_nan_yaw", "nan/inf")
def _(d):
    return Probe(says=("boxes", "finite box parameters"), call=lambda: box_map([[0, 0, 0, 4, 2, 1.5, np.nan]], GRID))


# ---------------------------------------------------------------- params.yaml (typ.config.load_config)


@case("params", "missing_file", "missing keys")
def _(d):
    from typ.config import load_config

    p = d / "params.yaml"
    return Probe(says=(str(p), "file", "a params.yaml"), call=lambda: load_config(p))


@case("params", "invalid_yaml", "wrong dtype")
def _(d):
    probe = load_params(d, "profile: tiny\nsimulate: {frames: 2\n")
    probe.says += ("yaml", "well-formed YAML")
    return probe


@case("params", "top_level_list", "wrong dtype")
def _(d):
    probe = load_params(d, "- profile\n- tiny\n")
    probe.says += ("<top level>", "a mapping of stage blocks")
    return probe


@case("params", "not_utf8", "wrong dtype")
def _(d):
    probe = load_params(d, "")
    Path(probe.says[0]).write_bytes(b"profile: tiny\nsimulate: {seed: \xff\xfe}\n")
    probe.says += ("file", "a readable UTF-8 params.yaml")
    return probe


@case("params", "is_a_directory", "unreadable")
def _(d):
    from typ.config import load_config

    p = d / "params.yaml"
    p.mkdir()
    return Probe(says=(str(p), "file", "a readable UTF-8 params.yaml"), call=lambda: load_config(p))


@case("params", "no_permission", "unreadable", needs_non_root=True)
def _(d):
    probe = load_params(d, {"profile": "tiny"})
    unreadable(Path(probe.says[0]))
    probe.says += ("file", "PermissionError")
    return probe


@case("params", "unknown_profile", "unknown")
def _(d):
    probe = load_params(d, {"profile": "huge"})
    probe.says += ("profile", "one of ['tiny', 'small', 'paper']", "'huge'")
    return probe


@case("params", "unknown_stage_block", "unknown")
def _(d):
    probe = load_params(d, {"profile": "tiny", "voxelise": {"workers": 2}})
    probe.says += ("voxelise", "one of the known keys")
    return probe


@case("params", "unknown_key_in_block", "unknown")
def _(d):
    probe = load_params(d, {"voxelize": {"grid": {"shape": [128, 128, 8], "voxel_size": 0.8}}})
    probe.says += ("voxelize.grid.voxel_size", "one of the known keys")
    return probe


@case("params", "string_for_integer", "wrong dtype")
def _(d):
    probe = load_params(d, {"simulate": {"frames": "two"}})
    probe.says += ("simulate.frames", "an integer", "'two'")
    return probe


@case("params", "float_for_integer", "wrong dtype")
def _(d):
    probe = load_params(d, {"vqvae": {"batch_size": 4.5}})
    probe.says += ("vqvae.batch_size", "an integer")
    return probe


@case("params", "grid_shape_two_numbers", "misaligned")
def _(d):
    probe = load_params(d, {"voxelize": {"grid": {"shape": [128, 128]}}})
    probe.says += ("voxelize.grid.shape", "a list of 3")
    return probe


@case("params", "nan_learning_rate", "nan/inf")
def _(d):
    probe = load_params(d, "vqvae:\n  lr: .nan\n")
    probe.says += ("vqvae.lr", "a finite number")
    return probe


@case("params", "inf_distance", "nan/inf")
def _(d):
    probe = load_params(d, "generate:\n  max_distance: .inf\n")
    probe.says += ("generate.max_distance", "a finite number")
    return probe


@case("params", "grid_range_reversed", "wrong units")
def _(d):
    probe = load_params(d, {"voxelize": {"grid": {"x_range": [51.2, -51.2]}}})
    probe.says += ("voxelize.grid.x_range", "min < max")
    return probe


@case("params", "threshold_in_percent", "wrong units")
def _(d):
    probe = load_params(d, {"vqvae": {"threshold": 50}})
    probe.says += ("vqvae.threshold", "a probability in (0, 1)")
    return probe


@case("params", "postprocess_candidates_in_percent", "wrong units")
def _(d):
    probe = load_params(d, {"stage1": {"postprocess": {"candidates": [10, 20, 30]}}})
    probe.says += ("stage1.postprocess.candidates[0]", "a probability in (0, 1)")
    return probe


@case("params", "negative_scenario_count", "wrong units")
def _(d):
    probe = load_params(d, {"simulate": {"scenarios": {"target": {"train": -1}}}})
    probe.says += ("simulate.scenarios.target.train", "an integer in [0, 100000]")
    return probe


@case("params", "huge_sample_steps", "huge")
def _(d):
    probe = load_params(d, {"stage1": {"sample_steps": 10**9}})
    probe.says += ("stage1.sample_steps", "an integer in [1, 10000]")
    return probe


@case("params", "block_is_a_number", "wrong dtype")
def _(d):
    probe = load_params(d, {"simulate": 3})
    probe.says += ("simulate", "a mapping for SimulateConfig")
    return probe


@case("params", "unknown_schedule", "unknown")
def _(d):
    probe = load_params(d, {"stage1": {"schedule": "cosine2"}})
    probe.says += ("stage1.schedule", "one of [")
    return probe


# ---------------------------------------------------------------- CLI (typ ...): exit code 2, message on stderr

PRIOR = {"data/sim/target/train/old/1/000000.yaml": "lidar_pose: [0, 0, 0, 0, 0, 0]\nvehicles: {}\n",
         "metrics/voxelize.json": '{"voxelized": 1}\n'}


def project(d: Path, raw: dict | str | None = None) -> Path:
    """A project folder: params.yaml and outputs of an earlier run, which no failing command may touch."""
    root = d / "proj"
    params(root, {"profile": "tiny"} if raw is None else raw)
    for rel, text in PRIOR.items():
        write(root / rel, text)
    return root


def _cli(root: Path, *argv: str, says: tuple[str, ...]) -> Probe:
    return Probe(says=says, argv=["--root", str(root), *argv], watch=root)


@case("cli", "run_unknown_stage", "unknown")
def _(d):
    root = project(d)
    return _cli(root, "run", "voxelise", says=("typ run", "stage", "one of ['all', 'simulate'", "'voxelise'"))


@case("cli", "unknown_command", "unknown")
def _(d):
    root = project(d)
    return _cli(root, "frobnicate", says=("invalid choice", "frobnicate"))


@case("cli", "run_without_stage", "missing keys")
def _(d):
    root = project(d)
    return _cli(root, "run", says=("the following arguments are required: stage",))


@case("cli", "params_missing", "missing keys")
def _(d):
    root = project(d)
    return _cli(root, "--params", "nope.yaml", "run", "simulate", says=(str(root / "nope.yaml"), "file"))


@case("cli", "params_is_a_directory", "unreadable")
def _(d):
    root = project(d)
    (root / "conf").mkdir()
    return _cli(root, "--params", "conf", "run", "simulate",
                says=(str(root / "conf"), "file", "a readable UTF-8 params.yaml"))


@case("cli", "params_no_permission", "unreadable", needs_non_root=True)
def _(d):
    root = project(d)
    unreadable(root / "params.yaml")
    return _cli(root, "run", "simulate", says=(str(root / "params.yaml"), "PermissionError"))


@case("cli", "params_unknown_profile", "unknown")
def _(d):
    root = project(d, {"profile": "huge"})
    return _cli(root, "run", "voxelize", says=("params.yaml: profile", "one of ['tiny', 'small', 'paper']"))


@case("cli", "params_wrong_type", "wrong dtype")
def _(d):
    root = project(d, {"profile": "tiny", "simulate": {"frames": "two"}})
    return _cli(root, "run", "simulate", says=("params.yaml: simulate.frames: expected an integer, got 'two'",))


@case("cli", "check_params_nan", "nan/inf")
def _(d):
    root = project(d, "profile: tiny\nvoxelize:\n  grid: {z_range: [-3.0, .inf]}\n")
    return _cli(root, "check", says=("voxelize.grid.z_range[1]", "a finite number"))


def _stage_process(root: Path, stage: str, says: tuple[str, ...]) -> Probe:
    return Probe(says=says, process=["--root", str(root), "run", stage], cwd=root, watch=root)


@case("cli", "voxelize_nan_intensity_in_a_scan", "nan/inf")
def _(d):
    """Through the whole stage: the scene's earlier voxels and the other outputs stay as they were."""
    root = d / "proj"
    params(root, {"profile": "tiny", "voxelize": {"workers": 1}})
    scene = root / "data" / "sim" / "target" / "train" / "target_train_0000"
    pts = cloud()
    good = Scene("target_train_0000", "000000", {"1": AgentView("1", pts, geometry.pose_to_matrix([0] * 6))})
    write_scene(good, scene.parent)
    write_scene_voxels(scene_path(root / "data" / "voxels", "target", "train", scene.name),
                       store_records(), grid=GRID, input_hash="an earlier run")
    write(root / "metrics" / "voxelize.json", '{"voxelized": 1}\n')
    bad = scene / "1" / "000000.pcd"
    bad.write_bytes(pcd_text(body="1 2 3 0.5\n4 5 6 nan\n7 8 9 0.5\n"))
    return _stage_process(root, "voxelize", says=(str(bad), "intensity", "finite values"))


# ---------------------------------------------------------------- trained artifacts (safetensors + JSON)
# One small model of each kind is saved as its stage saves it, then damaged; loading it as the
# next stage does must name the file and the stage that makes it. torch is imported inside.


def _tiny_vqvae():
    import torch

    from models.vqvae import BEVVQVAE

    torch.manual_seed(0)
    return BEVVQVAE(in_channels=4, latent_channels=3, block_out_channels=(8, 8), num_codes=8, norm_num_groups=4)


def _tiny_unet():
    from models.ldm import LatentDiffusion

    return LatentDiffusion(latent_channels=3, cond_channels=1, sample_size=8, block_out_channels=(8, 8),
                           layers_per_block=1, cross_attention_dim=8, attention_head_dim=4, norm_num_groups=4)


@case("artifact", "vqvae_truncated_weights", "truncated", needs="torch")
def _(d):
    from tasks.vqvae import load_model, save_model

    save_model(_tiny_vqvae(), d / "x")
    w = d / "x" / "model.safetensors"
    w.write_bytes(w.read_bytes()[:-100])
    return Probe(says=(str(w), "safetensors", "vqvae stage"), call=lambda: load_model(d / "x"))


@case("artifact", "stage1_missing_config", "missing keys", needs="torch")
def _(d):
    from tasks import stage1
    from typ.config import config_from_dict

    cfg = config_from_dict({}).stage1
    stage1.save_model(_tiny_unet(), cfg, {"low": 0.5, "high": 0.5, "noise_std": 0.0}, d / "seed_0")
    (d / "seed_0" / "config.json").unlink()
    return Probe(says=(str(d / "seed_0" / "config.json"), "missing", "stage1 stage"),
                 call=lambda: stage1.load_model(d / "seed_0"))


@case("artifact", "adapter_wrong_shape", "misaligned", needs="torch")
def _(d):
    from safetensors.torch import load, save

    from tasks import stage2

    unet = _tiny_unet()
    stage2.save_adapter(stage2.build_adapter(unet, res_blocks=1, seed=0), d / "adapter")
    w = d / "adapter" / "model.safetensors"
    state = load(w.read_bytes())
    name = sorted(state)[0]
    state[name] = state[name].reshape(-1)[:1].clone()  # one tensor of another shape
    w.write_bytes(save(state))
    return Probe(says=(str(w), f"weights.{name}", "shape", "stage2 stage"), call=lambda: stage2.load_adapter(d / "adapter"))


@case("artifact", "detector_corrupt_config", "unknown", needs="torch")
def _(d):
    from typ.artifacts import load_module

    (d / "early").mkdir()
    (d / "early" / "config.json").write_text('{"config": {"method": "early", ')  # cut off mid-write
    return Probe(says=(str(d / "early" / "config.json"), "JSON", "fusion stage"),
                 call=lambda: load_module(d / "early", lambda c: None, "fusion"))


@case("artifact", "checkpoint_truncated", "truncated", needs="torch")
def _(d):
    from tasks.training import load_latest, save_checkpoint

    path = save_checkpoint(d / "run", 4, {"model": _tiny_vqvae().state_dict()})
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    return Probe(says=(str(path), "complete training checkpoint"), call=lambda: load_latest(d / "run"))


@case("artifact", "checkpoint_with_code", "unknown", needs="torch")
def _(d):
    import io
    import pickle

    from tasks.training import load_latest

    (d / "run").mkdir()
    path = d / "run" / "step_00000004.pt"
    buf = io.BytesIO()
    pickle.dump({"step": 4, "hook": print}, buf)  # a pickle that would call code when loaded
    path.write_bytes(buf.getvalue())
    return Probe(says=(str(path), "tensors and numbers only"), call=lambda: load_latest(d / "run"))


@case("artifact", "generator_missing_thresholds", "missing keys", needs="torch")
def _(d):
    import json as json_

    from models.vqvae import PooledBoxMap
    from pipelines.typ.pipeline_typ import TYPPipeline

    grid = Grid((-6.4, 6.4), (-6.4, 6.4), (-0.75, 3.25), (16, 16, 4))
    pipe = TYPPipeline(_tiny_vqvae(), PooledBoxMap(downsample=2), _tiny_unet(), None, grid, "linear", 1000, "ddim",
                       2, {"low": 0.5, "high": 0.5, "noise_std": 0.0})
    pipe.save_pretrained(d / "generator")
    meta = d / "generator" / "pipeline.json"
    doc = json_.loads(meta.read_text())
    del doc["thresholds"]
    meta.write_text(json_.dumps(doc))
    return Probe(says=(str(meta), "selftrain stage", "thresholds"), call=lambda: TYPPipeline.from_pretrained(d / "generator"))


# ---------------------------------------------------------------- built to hang, exhaust memory or be misread
# Each must end in a TypError within 2 s and 1 GB (tests/test_bad_inputs.py runs every
# reader case in a bounded child process), where typ once hung, ran out of memory, crashed the
# interpreter, let a raw OverflowError/ValueError/LinAlgError through, or returned other points.


def fifo(path: Path) -> Path:
    """A named pipe nobody writes to: opening it for reading blocks, reading it never ends."""
    path.parent.mkdir(parents=True, exist_ok=True)
    os.mkfifo(path)
    return path


def sparse(path: Path, size: int, head: bytes = b"") -> Path:
    """A file of ``size`` bytes that takes no disk: ``head``, then a hole of zeros."""
    write(path, head)
    with open(path, "r+b") as f:
        f.truncate(size)
    return path


def billion_laughs(levels: int = 9) -> str:
    """A ~540-byte YAML ``lidar_pose`` that expands to 9^levels scalars through aliases."""
    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for k in range(1, levels):
        lines.append(f"a{k}: &a{k} [" + ", ".join([f"*a{k - 1}"] * 9) + "]")
    return "\n".join(lines) + f"\nlidar_pose: [*a{levels - 1}, *a{levels - 1}, 0, 0, 0, 0]\nvehicles: {{}}\n"


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


# -------- typ show: the manifests (_typ.json) of simulated and generated scenarios


def _show(folder: Path, out: Path):
    from tasks.show import ShowOptions, show
    from typ import viz
    from typ.voxel import TINY_GRID

    return lambda: show(folder, out, ShowOptions(grid=TINY_GRID, window=viz.Window(resolution=0.4), resim=False))


@case("show", "sim_job_azimuth_step_1e-5", "huge")
def _(d):
    from tasks.simulate import MANIFEST, ScenarioJob

    y = opv2v_scenario(d)
    job = ScenarioJob("target", "train", 0, 7, 1, 4, 1e-5, 70.0, 0.1)  # its key matches: anyone can compute one
    manifest = write(y.parent.parent / MANIFEST, json.dumps({"job": job.describe(), "key": job.key()}))
    return Probe(says=(str(manifest), "job.azimuth_step_deg", "a step in [0.05, 10] deg"),
                 call=_show(y.parent.parent, d / "out"), watch=y.parent.parent)


@case("show", "yaml_billion_laughs", "bomb")
def _(d):
    y = opv2v_scenario(d, billion_laughs())
    return Probe(says=(str(y), "YAML nodes, aliases expanded"), call=_show(y.parent.parent, d / "out"),
                 watch=y.parent.parent)


@case("show", "generated_agents_not_a_list", "wrong dtype")
def _(d):
    from tasks.generate import MANIFEST

    y = opv2v_scenario(d)
    manifest = write(y.parent.parent / MANIFEST, json.dumps({"generated_agents": 5}))  # TypeError before
    return Probe(says=(str(manifest), "generated_agents", "a list of agent folder names"),
                 call=_show(y.parent.parent, d / "out"))


@case("show", "manifest_is_a_fifo", "not a regular file")
def _(d):
    from tasks.generate import MANIFEST

    y = opv2v_scenario(d)
    manifest = fifo(y.parent.parent / MANIFEST)
    return Probe(says=(str(manifest), "a readable JSON file", "FIFO"), call=_show(y.parent.parent, d / "out"),
                 watch=y.parent.parent)


# -------- trained artifacts: config.json, model.safetensors and pipeline.json are not trusted


@case("artifact", "vqvae_config_huge_sizes", "huge", needs="torch")
def _(d):
    from tasks.vqvae import load_model, save_model

    save_model(_tiny_vqvae(), d / "x")
    path = d / "x" / "config.json"
    doc = json.loads(path.read_text())
    doc["config"]["block_out_channels"] = [100_000, 100_000]  # 360 GB of convolution weights before
    path.write_text(json.dumps(doc))
    return Probe(says=(str(path), "config.block_out_channels", "vqvae stage"), call=lambda: load_model(d / "x"))


@case("artifact", "vqvae_config_zero_groups", "wrong units", needs="torch")
def _(d):
    from tasks.vqvae import load_model, save_model

    save_model(_tiny_vqvae(), d / "x")
    path = d / "x" / "config.json"
    doc = json.loads(path.read_text())
    doc["config"]["norm_num_groups"] = 0  # ZeroDivisionError before
    path.write_text(json.dumps(doc))
    return Probe(says=(str(path), "config", "ZeroDivisionError"), call=lambda: load_model(d / "x"))


@case("artifact", "weights_sparse_4_gib", "huge", needs="torch")
def _(d):
    from tasks.vqvae import load_model, save_model

    save_model(_tiny_vqvae(), d / "x")
    w = d / "x" / "model.safetensors"
    sparse(w, 4 << 30, w.read_bytes())  # read whole before any check: MemoryError
    return Probe(says=(str(w), "of at most 1024 MiB", str(4 << 30)), call=lambda: load_model(d / "x"))


@case("artifact", "weights_header_offsets_past_the_end", "truncated", needs="torch")
def _(d):
    from tasks.vqvae import load_model, save_model

    save_model(_tiny_vqvae(), d / "x")
    w = d / "x" / "model.safetensors"
    raw = w.read_bytes()
    n = int.from_bytes(raw[:8], "little")
    header = json.loads(raw[8:8 + n])
    name = sorted(k for k in header if k != "__metadata__")[0]
    header[name]["data_offsets"][1] += 4 << 30  # a tensor claimed to span 4 GiB more
    text = json.dumps(header).encode()
    w.write_bytes(len(text).to_bytes(8, "little") + text + raw[8 + n:])
    return Probe(says=(str(w), f"header.{name}", "data_offsets"), call=lambda: load_model(d / "x"))


def _generator(d: Path, **changes) -> Probe:
    import json as json_

    from models.vqvae import PooledBoxMap
    from pipelines.typ.pipeline_typ import TYPPipeline

    grid = Grid((-6.4, 6.4), (-6.4, 6.4), (-0.75, 3.25), (16, 16, 4))
    pipe = TYPPipeline(_tiny_vqvae(), PooledBoxMap(downsample=2), _tiny_unet(), None, grid, "linear", 1000, "ddim",
                       2, {"low": 0.5, "high": 0.5, "noise_std": 0.0})
    pipe.save_pretrained(d / "generator")
    meta = d / "generator" / "pipeline.json"
    doc = json_.loads(meta.read_text())
    doc.update(changes)
    meta.write_text(json_.dumps(doc))
    return Probe(says=(str(meta),), call=lambda: TYPPipeline.from_pretrained(d / "generator"))


@case("artifact", "generator_grid_of_a_trillion_voxels", "huge", needs="torch")
def _(d):
    probe = _generator(d, grid={"x_range": [-6.4, 6.4], "y_range": [-6.4, 6.4], "z_range": [-0.75, 3.25],
                                "shape": [100_000, 100_000, 100]})
    probe.says += ("shape", "at most 67108864 voxels")
    return probe


@case("artifact", "generator_thresholds_reversed", "wrong units", needs="torch")
def _(d):
    probe = _generator(d, thresholds={"low": 0.9, "high": 0.1, "noise_std": 0.0})
    probe.says += ("thresholds", "0 <= low <= high <= 1")
    return probe


# ---------------------------------------------------------------- the cases kept in modules of their own

# each module registers its cases with :func:`case` when imported (after every helper above exists)
from bad_inputs import cases_bounds, cases_ownership, cases_paths, cases_sequences  # noqa: E402,F401


# ---------------------------------------------------------------- as a script


def main(argv: list[str]) -> int:
    from bad_inputs.make_corpus import CASES  # as a script this module is __main__: the cases register there

    if len(argv) != 1:
        print(__doc__.strip().splitlines()[-1].strip(), file=sys.stderr)
        return 2
    out = Path(argv[0])
    for c in CASES:
        folder = out / c.reader / c.name
        folder.mkdir(parents=True, exist_ok=True)
        try:
            probe = c.build(folder)
        except ImportError as exc:
            print(f"{c.id:60s} skipped: {exc}")
            continue
        how = "typ " + " ".join(probe.argv or probe.process or []) if probe.call is None else "reader"
        print(f"{c.id:60s} {c.kind:13s} {how}")
    print(f"{len(CASES)} cases under {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
