"""Seeded byte-level fuzzing of typ's readers: no raw traceback, no silent change of count.

Each target is a small valid file built here: a PCD of each DATA kind (ascii, binary,
binary_compressed), a KITTI velodyne ``.bin``, an OPV2V agent ``.yaml``, a ``model.safetensors``
header and a Waymo tfrecord (its raw bytes, and its Frame payload re-framed with valid CRCs so
that the mutations reach the protobuf and range-image decoding). Every mutation is one to three
of: a flipped byte, a truncation, inserted or deleted bytes, and an edit of a header field (a
number replaced by 0, -1, 2^32, 10^20, ... ; a type letter or a word swapped). The reader must
either raise :class:`~typ.errors.TypError` or return exactly what the mutated file promises,
computed here independently of the reader: a PCD's POINTS (or WIDTH x HEIGHT), a ``.bin``'s
size / 16, the yaml's vehicles and its PCD's points, the original tensors, the range-image
pixels with a positive range. Each case is bounded to 2 s (a timer in the child); each target
runs in a forked child bounded in wall time and to 1 GiB more memory (tests/helpers/bounded.py).
"""
from __future__ import annotations

import json
import re
import signal
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest
import yaml

from bounded import run_bounded
from lzf_reference import lzf_compress
from typ.errors import TypError

SEED = 42
CASE_SECONDS = 2.0
#: replacements for a number in a header: edges of every integer type PCL and JSON use, and non-numbers
EXTREMES = ("0", "1", "-1", "2", "3", "63", "65", "255", "256", "4096", "4097", "65535", "2147483648", "4294967295",
            "4294967296", "18446744073709551616", "100000000000000000000", "1e39", "nan", "inf", "-0", "9" * 400,
            "x")
#: swaps for a word of a header: the other PCD types, sizes and kinds, safetensors dtypes, YAML oddities
WORDS = {b"F": (b"U", b"I", b"D"), b"U": (b"F", b"I"), b"4": (b"1", b"2", b"8", b"3"), b"1": (b"2", b"4", b"8"),
         b"ascii": (b"binary", b"binary_compressed"), b"binary": (b"ascii", b"binary_compressed"),
         b"binary_compressed": (b"binary", b"ascii"), b"F32": (b"F16", b"F64", b"I64", b"BOOL", b"X"),
         b"x": (b"y", b"_", b"rgb"), b"intensity": (b"rgb", b"semantic", b"x")}
NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
WORD = re.compile(rb"[A-Za-z_][A-Za-z0-9_]*|\d")


@dataclass
class Target:
    """A valid file, how many mutations of it to try, and where its header ends (header edits go there)."""

    name: str
    data: bytes
    cases: int
    read: Callable[[Path], object]              # what the reader returned (raises TypError to refuse)
    promise: Callable[[bytes], object]          # what a reader that accepts these bytes must return
    header_end: Callable[[bytes], int]
    filename: str
    reframe: bool = False                       # mutate a tfrecord's payload and frame it again with valid CRCs
    header_only: bool = False                   # mutate the header alone (a safetensors file's tensors are opaque)
    checksummed: bool = False                   # every byte is under a CRC: no mutation may be accepted


def mutate(data: bytes, rng: np.random.Generator, header_end: int) -> tuple[bytes, list[str]]:
    """One to three mutations; returns the bytes and what was done (for the failure report)."""
    out, done, wanted = bytearray(data), [], int(rng.integers(1, 4))
    while len(done) < wanted:  # a kind that finds nothing to change (no number in the header) draws again
        kind = rng.choice(["flip", "truncate", "insert", "delete", "field", "field", "word"])
        n = len(out)
        if kind == "flip" and n:
            at = int(rng.integers(0, n))
            out[at] ^= int(rng.integers(1, 256))
            done.append(f"flip@{at}")
        elif kind == "truncate" and n:
            at = int(rng.integers(0, n))
            del out[at:]
            done.append(f"truncate@{at}")
        elif kind == "insert":
            at = int(rng.integers(0, n + 1))
            out[at:at] = bytes(rng.integers(0, 256, int(rng.integers(1, 17)), dtype=np.uint8))
            done.append(f"insert@{at}")
        elif kind == "delete" and n:
            at = int(rng.integers(0, n))
            del out[at:at + int(rng.integers(1, 17))]
            done.append(f"delete@{at}")
        elif kind == "field":
            spans = [m.span() for m in NUMBER.finditer(bytes(out[:header_end]))]
            if spans:
                a, b = spans[int(rng.integers(0, len(spans)))]
                value = EXTREMES[int(rng.integers(0, len(EXTREMES)))].encode()
                out[a:b] = value
                done.append(f"field@{a}={value[:12]!r}")
        elif kind == "word":
            spans = [m.span() for m in WORD.finditer(bytes(out[:header_end])) if bytes(out[m.start():m.end()]) in WORDS]
            if spans:
                a, b = spans[int(rng.integers(0, len(spans)))]
                choices = WORDS[bytes(out[a:b])]
                value = choices[int(rng.integers(0, len(choices)))]
                out[a:b] = value
                done.append(f"word@{a}={value!r}")
    return bytes(out), done


class _CaseTimeout(Exception):
    pass


def _alarm(signum, frame):
    raise _CaseTimeout


def fuzz(target: Target, folder: Path) -> tuple[list[str], int]:
    """Every mutation of ``target``: the findings (raw exceptions, wrong counts, slow cases) and how
    many mutated files the reader accepted."""
    rng = np.random.default_rng([SEED, sum(target.name.encode())])
    findings, accepted = [], 0
    signal.signal(signal.SIGALRM, _alarm)
    path = folder / target.filename
    for case in range(target.cases):
        end = target.header_end(target.data)
        if target.reframe:
            payload = _payload(target.data)
            mutated, done = mutate(payload, rng, len(payload))
            mutated = _tfrecord(mutated)
        elif target.header_only:
            mutated, done = mutate(target.data[:end], rng, end)
            mutated += target.data[end:]
        else:
            mutated, done = mutate(target.data, rng, end)
        path.write_bytes(mutated)
        signal.setitimer(signal.ITIMER_REAL, CASE_SECONDS)
        try:
            got = target.read(path)
        except TypError:
            continue
        except _CaseTimeout:
            findings.append(f"{target.name} case {case} {done}: more than {CASE_SECONDS} s")
            continue
        except Exception as exc:  # noqa: BLE001 - the finding
            findings.append(f"{target.name} case {case} {done}: raw {type(exc).__name__}: {str(exc)[:200]}")
            continue
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        accepted += 1
        try:
            promised = target.promise(mutated)
        except Exception as exc:  # noqa: BLE001 - the file does not hold what a reader could return
            promised = f"nothing ({type(exc).__name__}: {str(exc)[:80]})"
        if got != promised:
            findings.append(f"{target.name} case {case} {done}: read {str(got)[:200]}, the file promises "
                            f"{str(promised)[:200]}")
    return findings, accepted


# ---------------------------------------------------------------- PCD (ascii, binary, binary_compressed)

FIELDS = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("semantic", "u1")]
N_POINTS = 40


def _cloud(n: int = N_POINTS, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rec = np.zeros(n, dtype=FIELDS)
    for c in "xyz":
        rec[c] = np.round(rng.uniform(-30, 30, n), 2)
    rec["intensity"] = np.round(rng.uniform(0, 1, n), 2)
    rec["semantic"] = rng.integers(0, 6, n)
    return rec


def pcd_bytes(kind: str) -> bytes:
    rec = _cloud()
    header = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity semantic\nSIZE 4 4 4 4 1\nTYPE F F F F U\n"
              f"COUNT 1 1 1 1 1\nWIDTH {N_POINTS}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {N_POINTS}\n"
              f"DATA {kind}\n").encode()
    if kind == "ascii":
        return header + "".join(f"{r['x']:.2f} {r['y']:.2f} {r['z']:.2f} {r['intensity']:.2f} {r['semantic']}\n"
                                for r in rec).encode()
    if kind == "binary":
        return header + rec.tobytes()
    raw = b"".join(np.ascontiguousarray(rec[name]).tobytes() for name, _ in FIELDS)
    packed = lzf_compress(raw)
    return header + struct.pack("<II", len(packed), len(raw)) + packed


def pcd_promise(data: bytes) -> int:
    """The points a PCD holds, derived here from its header and data: POINTS, which must equal
    WIDTH x HEIGHT, and which the data must hold exactly (binary: POINTS rows of the SIZE x COUNT
    bytes; ascii: POINTS x the COUNTs numbers; compressed: an inflated size of POINTS rows).
    Raises when the file contradicts itself: then no count is right and the reader must refuse."""
    head, _, rest = data.partition(b"\nDATA")
    kind, _, body = rest.partition(b"\n")
    entries = {}
    for line in head.split(b"\n"):
        parts = line.split()
        if parts and not parts[0].startswith(b"#"):
            entries[parts[0].upper()] = parts[1:]
    points = int(entries[b"POINTS"][0])
    if points != int(entries[b"WIDTH"][0]) * int(entries[b"HEIGHT"][0]):
        raise ValueError("POINTS is not WIDTH x HEIGHT")
    counts = [int(c) for c in entries.get(b"COUNT", [b"1"] * len(entries[b"FIELDS"]))]  # PCL: COUNT 1 if absent
    row = sum(int(size) * count for size, count in zip(entries[b"SIZE"], counts))
    kind = kind.strip()
    if kind == b"binary" and len(body) != points * row:
        raise ValueError(f"{len(body)} data bytes for {points} rows of {row}")
    if kind == b"ascii" and len(body.split()) != points * sum(counts):
        raise ValueError("not one number per field and point")
    if kind == b"binary_compressed" and struct.unpack("<I", body[4:8])[0] != points * row:
        raise ValueError("an inflated size that is not POINTS rows")
    return points


def pcd_read(path: Path) -> int:
    from typ.formats.pcd import read_pcd

    points, semantics = read_pcd(path)
    assert points.dtype == np.float32 and points.shape[1] == 4 and np.isfinite(points).all()
    assert semantics is None or semantics.shape == (len(points),)
    return len(points)


def _data_line_end(data: bytes) -> int:
    at = data.find(b"\nDATA")
    return len(data) if at < 0 else data.find(b"\n", at + 1) + 1 or len(data)


# ---------------------------------------------------------------- KITTI velodyne .bin

def kitti_bytes() -> bytes:
    rec = _cloud()
    return np.stack([rec["x"], rec["y"], rec["z"], rec["intensity"]], axis=1).astype("<f4").tobytes()


def kitti_read(path: Path) -> int:
    from typ.formats.kitti import read_velodyne

    points = read_velodyne(path)
    assert ((points[:, 3] >= 0) & (points[:, 3] <= 1)).all()
    return len(points)


def kitti_promise(data: bytes) -> int:
    if len(data) % 16:
        raise ValueError("not a whole number of x, y, z, reflectance rows")
    return len(data) // 16


# ---------------------------------------------------------------- OPV2V agent yaml (+ its PCD)

def opv2v_bytes() -> bytes:
    doc = {"lidar_pose": [10.0, 5.0, 1.9, 0.0, 30.0, 0.0], "ego_speed": 4.5,
           "vehicles": {vid: {"location": [20.0 + vid, 5.0, 0.5], "angle": [0.0, 10.0 * vid, 0.0],
                              "extent": [2.0, 1.0, 0.75], "center": [0.0, 0.0, 0.1]} for vid in (7, 8, 12)}}
    return yaml.safe_dump(doc, default_flow_style=None).encode()


def opv2v_read(path: Path) -> tuple[int, int]:
    from typ.formats.opv2v import read_scene

    view = read_scene(path.parent.parent, path.stem).ego
    return len(view.points), len(view.boxes)


def opv2v_promise(data: bytes) -> tuple[int, int]:
    """The PCD's points and the vehicle entries of the yaml as written: its ``vehicles`` node's keys
    counted before a loader folds repeated ones into one (libyaml, as the reader: PyYAML's own
    scanner refuses some tabs that libyaml takes)."""
    root = yaml.compose(data.decode("utf-8"), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))
    (vehicles,) = [value for key, value in root.value if key.value == "vehicles"]
    if not isinstance(vehicles, yaml.MappingNode):
        raise ValueError("vehicles is not a mapping")
    return N_POINTS, len(vehicles.value)


# ---------------------------------------------------------------- safetensors header (a small module)

def safetensors_bytes() -> bytes:
    import torch
    from safetensors.torch import save

    torch.manual_seed(0)
    module = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.LayerNorm(4))
    # metadata: header bytes whose change leaves the tensors as they are (mutations a reader may accept)
    return save({k: v.contiguous() for k, v in module.state_dict().items()},
                metadata={"format": "pt", "note": "typ fuzz " * 30})


def _module(config: dict):
    import torch

    return torch.nn.Sequential(torch.nn.Linear(config["inputs"], config["width"]), torch.nn.LayerNorm(config["width"]))


def safetensors_read(path: Path) -> dict:
    from typ.artifacts import load_module

    module, _ = load_module(path.parent, _module, "fuzz")
    return {k: v.tolist() for k, v in module.state_dict().items()}


def safetensors_promise(data: bytes) -> dict:
    from safetensors.torch import load

    return {k: v.tolist() for k, v in load(safetensors_bytes()).items()}  # the header may not change a tensor


def _header_end(data: bytes) -> int:
    return 8 + int.from_bytes(data[:8], "little")


# ---------------------------------------------------------------- Waymo tfrecord

def _tfrecord(payload: bytes) -> bytes:
    from typ.formats.waymo import masked_crc32c

    length = struct.pack("<Q", len(payload))
    return length + struct.pack("<I", masked_crc32c(length)) + payload + struct.pack("<I", masked_crc32c(payload))


def _payload(record: bytes) -> bytes:
    return record[12:-4]


def waymo_bytes() -> bytes:
    from waymo_open_dataset import dataset_pb2

    frame = dataset_pb2.Frame()
    frame.context.name = "fuzz"
    frame.pose.transform.extend(np.eye(4).ravel().tolist())
    calib = frame.context.laser_calibrations.add()
    calib.name = dataset_pb2.LaserName.FRONT
    calib.beam_inclination_min, calib.beam_inclination_max = -0.2, 0.2
    calib.extrinsic.transform.extend(np.eye(4).ravel().tolist())
    image = np.zeros((4, 8, 4), np.float32)
    image[..., 0] = np.where(np.arange(32).reshape(4, 8) % 3 == 0, 0.0, 10.0 + np.arange(32).reshape(4, 8))
    image[..., 1] = 0.5
    matrix = dataset_pb2.MatrixFloat()
    matrix.data.extend(image.ravel().tolist())
    matrix.shape.dims.extend(image.shape)
    laser = frame.lasers.add()
    laser.name = dataset_pb2.LaserName.FRONT
    laser.ri_return1.range_image_compressed = zlib.compress(matrix.SerializeToString())
    return _tfrecord(frame.SerializeToString())


def waymo_read(path: Path) -> list[int]:
    from typ.formats.waymo import iter_waymo_frames

    return [len(scene.ego.points) for scene in iter_waymo_frames(path)]


def waymo_promise(data: bytes) -> list[int]:
    """Per record, the pixels with a positive range in the range images of calibrated lasers,
    decoded here with protobuf and zlib directly."""
    from waymo_open_dataset import dataset_pb2

    counts, offset = [], 0
    while offset < len(data):
        (length,) = struct.unpack("<Q", data[offset:offset + 8])
        frame = dataset_pb2.Frame.FromString(data[offset + 12:offset + 12 + length])
        calibrated = {c.name for c in frame.context.laser_calibrations}
        n = 0
        for laser in frame.lasers:
            for ret in (laser.ri_return1, laser.ri_return2):
                if laser.name in calibrated and ret.range_image_compressed:
                    m = dataset_pb2.MatrixFloat.FromString(zlib.decompress(ret.range_image_compressed))
                    image = np.array(m.data, np.float32).reshape(tuple(m.shape.dims))
                    n += int((image[..., 0] > 0).sum())
        counts.append(n)
        offset += 12 + length + 4
    return counts


# ---------------------------------------------------------------- the test

TARGETS = {
    "pcd_ascii": lambda: Target("pcd_ascii", pcd_bytes("ascii"), 600, pcd_read, pcd_promise, _data_line_end,
                                "fuzzed.pcd"),
    "pcd_binary": lambda: Target("pcd_binary", pcd_bytes("binary"), 600, pcd_read, pcd_promise, _data_line_end,
                                 "fuzzed.pcd"),
    "pcd_binary_compressed": lambda: Target("pcd_binary_compressed", pcd_bytes("binary_compressed"), 600, pcd_read,
                                            pcd_promise, _data_line_end, "fuzzed.pcd"),
    "kitti_bin": lambda: Target("kitti_bin", kitti_bytes(), 300, kitti_read, kitti_promise, lambda d: 0, "000000.bin"),
    "opv2v_yaml": lambda: Target("opv2v_yaml", opv2v_bytes(), 300, opv2v_read, opv2v_promise, len, "fuzzed.yaml"),
    "safetensors_header": lambda: Target("safetensors_header", safetensors_bytes(), 200, safetensors_read,
                                         safetensors_promise, _header_end, "model.safetensors", header_only=True),
    "tfrecord": lambda: Target("tfrecord", waymo_bytes(), 200, waymo_read, waymo_promise, lambda d: 12,
                               "segment.tfrecord", checksummed=True),
    "tfrecord_payload": lambda: Target("tfrecord_payload", waymo_bytes(), 300, waymo_read, waymo_promise, len,
                                       "segment.tfrecord", reframe=True),
}


def _setup(name: str, folder: Path) -> Path:
    """The folder a target's file is read in: an OPV2V scenario with a valid PCD beside the yaml; a
    module folder with its config.json; otherwise the folder itself."""
    if name == "opv2v_yaml":
        from typ.formats.pcd import write_pcd

        rec = _cloud()
        folder = folder / "scn" / "1"
        folder.mkdir(parents=True)
        write_pcd(folder / "fuzzed.pcd", np.stack([rec["x"], rec["y"], rec["z"], rec["intensity"]], 1))
    if name == "safetensors_header":
        (folder / "config.json").write_text(json.dumps({"config": {"inputs": 3, "width": 4}}))
    return folder


@pytest.mark.parametrize("name", sorted(TARGETS))
def test_mutated_files_are_refused_or_read_as_they_promise(name, tmp_path):
    if name.startswith("tfrecord"):
        pytest.importorskip("waymo_open_dataset")
    if name.startswith("pcd"):
        from typ.formats.pcd import lzf_decompress

        lzf_decompress(bytes([0, 7]), 1)  # compiled here, once: the child inherits it
    target = TARGETS[name]()
    folder = _setup(name, tmp_path)
    (folder / target.filename).write_bytes(target.data)
    assert target.read(folder / target.filename) == target.promise(target.data)  # the valid file reads as promised

    outcome = run_bounded(lambda: fuzz(target, folder), seconds=120, keep=lambda result: result)
    assert outcome.kind == "returned", str(outcome)
    findings, accepted = outcome.value
    assert findings == [], f"{len(findings)} findings:\n" + "\n".join(findings[:20])
    # the promise is exercised: some mutations leave a readable file (a flipped coordinate, an
    # edited comment), except where a CRC covers every byte
    assert accepted == 0 if target.checksummed else accepted > 0, accepted
