"""The bad-input corpus: every reader, params.yaml, the voxel store and the CLI, fed broken input.

Nothing here is committed as a blob: each case writes a valid input into a folder and then
breaks it (truncated, misaligned, wrong dtype, NaN/Inf, empty, huge header counts, missing
keys, wrong units, corrupt CRC, unreadable, unknown stage or profile). ``case.build(folder)``
returns a :class:`Probe`: how to feed the input to typ, and the texts the error must contain
(the file or field it names and what was expected). tests/fuzz/test_bad_inputs.py runs them all.

This module holds the case type, :func:`case` and the valid inputs the cases break; the cases sit
in one module per format or input (``cases_binfile.py``, ``cases_pcd.py``, ``cases_opv2v.py``,
``cases_kitti.py``, ``cases_nuscenes.py``, ``cases_waymo.py``, ``cases_store.py``,
``cases_voxel.py``, ``cases_params.py``, ``cases_cli.py``, ``cases_artifacts.py``,
``cases_hostile.py``, ``cases_show.py``) or per concern (``cases_bounds.py``,
``cases_ownership.py``, ``cases_paths.py``, ``cases_sequences.py``), each imported at the end.

    python tests/fuzz/bad_inputs/make_corpus.py OUT   # write every case under OUT/<reader>/<name>/, list them
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
    sys.path[:0] = [str(Path(__file__).resolve().parents[3]), str(Path(__file__).resolve().parents[1])]

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


# ---------------------------------------------------------------- helpers the case modules share

def _read_opv2v(yaml_path: Path):
    return lambda: read_scene(yaml_path.parent.parent, yaml_path.stem)


WAYMO = "waymo_open_dataset"


def _waymo_file(d: Path, data: bytes) -> Path:
    return write(d / "segment.tfrecord", data)


PRIOR = {"data/sim/target/train/old/1/000000.yaml": "lidar_pose: [0, 0, 0, 0, 0, 0]\nvehicles: {}\n",
         "metrics/voxelize.json": '{"voxelized": 1}\n'}


def _cli(root: Path, *argv: str, says: tuple[str, ...]) -> Probe:
    return Probe(says=says, argv=["--root", str(root), *argv], watch=root)


def _tiny_unet():
    from models.ldm import LatentDiffusion

    return LatentDiffusion(latent_channels=3, cond_channels=1, sample_size=8, block_out_channels=(8, 8),
                           layers_per_block=1, cross_attention_dim=8, attention_head_dim=4, norm_num_groups=4)


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


# ---------------------------------------------------------------- the cases kept in modules of their own

# each module registers its cases with :func:`case` when imported (after every helper above exists)
from bad_inputs import (cases_binfile, cases_pcd, cases_opv2v, cases_kitti, cases_nuscenes, cases_waymo,  # noqa: E402,F401
                        cases_store, cases_voxel, cases_params, cases_cli, cases_artifacts, cases_hostile, cases_show,
                        cases_bounds, cases_ownership, cases_paths, cases_sequences)


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
