"""Waymo Open Dataset frames from TFRecord files, without TensorFlow.

TFRecord: each record is ``<u64 length><u32 masked crc32c(length bytes)><payload><u32 masked
crc32c(payload)>``, little-endian; TensorFlow masks a CRC as ``((crc >> 15) | (crc << 17)) +
0xa282ead8`` (mod 2^32). Both CRCs are checked. CRC-32C (Castagnoli, reflected polynomial
0x82F63B78) is computed with numpy over many lanes at once, then the lanes are combined.

Frames: each payload is a ``waymo.open_dataset.Frame`` (``dataset_pb2`` from the
``waymo-open-dataset-tf-2-12-0`` wheel, installed without TensorFlow). Points and boxes are
in the **vehicle frame** (x forward, y left, z up), which plays the sensor frame of the single
agent ``"ego"``; its pose is ``frame.pose.transform`` (vehicle -> world). Intensity is
``tanh(raw intensity)`` (OpenPCDet's and mmdet3d's ``norm_intensity`` convention), since raw
Waymo intensities are unbounded.

Sizes are bounded before anything is allocated: a record at most :data:`MAX_RECORD_BYTES`
(a frame with its camera images is about 5 MB), a range image at most
:data:`MAX_RANGE_IMAGE_PIXELS` pixels of at most :data:`MAX_RANGE_IMAGE_CHANNELS` channels,
and its zlib stream is inflated no further than such an image can take, so a 2 MB record
cannot inflate to gigabytes.
"""
from __future__ import annotations

import hashlib
import math
import os
import struct
import zlib
from pathlib import Path
from typing import Iterator

import numpy as np

from typ.errors import TypError
from typ.formats.binfile import read_bin
from typ.inputs import MiB, open_regular
from typ.scene import AgentView, Scene

_POLY = 0x82F63B78
_MASK_DELTA = 0xA282EAD8
_U32 = 0xFFFFFFFF
#: a segment is about 1 GB; a file far beyond that is no segment
MAX_TFRECORD_BYTES = 64 * 1024 * MiB
#: one Frame, camera images included, is about 5 MB
MAX_RECORD_BYTES = 64 * MiB
#: pixels of one range image: the TOP laser's is 64 x 2650 = 169,600; a 128 x 4096 sensor fits
MAX_RANGE_IMAGE_PIXELS = 1 << 19
#: channels of a range image (range, intensity, elongation, no-label-zone) or a pixel pose (6)
MAX_RANGE_IMAGE_CHANNELS = 8
#: the serialized MatrixFloat of the largest range image: its float32 values plus the shape
_MAX_MATRIX_BYTES = 4 * MAX_RANGE_IMAGE_PIXELS * MAX_RANGE_IMAGE_CHANNELS + 1024


def _byte_table() -> np.ndarray:
    crc = np.arange(256, dtype=np.uint32)
    for _ in range(8):
        crc = np.where(crc & 1, (crc >> 1) ^ np.uint32(_POLY), crc >> 1).astype(np.uint32)
    return crc


_TABLE = _byte_table()
_TABLE_LIST = _TABLE.tolist()


def _raw_crc(lanes: np.ndarray) -> np.ndarray:
    """CRC register after feeding each row of ``lanes`` (L, m) uint8, starting from 0, no final xor."""
    crc = np.zeros(len(lanes), dtype=np.uint32)
    for col in lanes.T:
        crc = _TABLE[(crc ^ col) & 0xFF] ^ (crc >> 8)
    return crc


def _zero_shift_tables(m: int) -> list[list[int]]:
    """Byte tables of the linear map "advance the register over m zero bytes"."""
    basis = _raw_crc_from(np.uint32(1) << np.arange(32, dtype=np.uint32), m)
    tables = []
    for k in range(4):
        table = np.zeros(256, dtype=np.uint32)
        for bit in range(8):
            table[(np.arange(256) >> bit) & 1 == 1] ^= basis[8 * k + bit]
        tables.append(table.tolist())
    return tables


def _raw_crc_from(states: np.ndarray, m: int) -> np.ndarray:
    crc = states.astype(np.uint32)
    for _ in range(m):
        crc = _TABLE[crc & 0xFF] ^ (crc >> 8)
    return crc


def crc32c(data: bytes) -> int:
    """CRC-32C of ``data`` (initial value and final xor 0xFFFFFFFF); crc32c(b"123456789") == 0xE3069283."""
    n = len(data)
    if n < 64:
        crc = _U32
        for byte in data:
            crc = _TABLE_LIST[(crc ^ byte) & 0xFF] ^ (crc >> 8)
        return crc ^ _U32
    buf = np.frombuffer(data, dtype=np.uint8).copy()
    # For a reflected CRC, starting from 0xFFFFFFFF equals starting from 0 with the first
    # 4 bytes inverted; starting from 0, leading zero bytes change nothing, so the data can
    # be zero-padded at the front and cut into equal lanes.
    buf[:4] ^= 0xFF
    lanes_n = max(1, min(4096, n // 256))
    m = -(-n // lanes_n)
    padded = np.zeros(lanes_n * m, dtype=np.uint8)
    padded[lanes_n * m - n:] = buf
    lane_crcs = _raw_crc(padded.reshape(lanes_n, m)).tolist()
    t0, t1, t2, t3 = _zero_shift_tables(m)
    crc = 0
    for lane in lane_crcs:  # CRC(A || B) = shift_|B|(CRC(A)) ^ CRC(B) when starting from 0
        crc = t0[crc & 0xFF] ^ t1[(crc >> 8) & 0xFF] ^ t2[(crc >> 16) & 0xFF] ^ t3[crc >> 24] ^ lane
    return crc ^ _U32


def masked_crc32c(data: bytes) -> int:
    """TensorFlow's masked CRC-32C, as stored in TFRecord files."""
    crc = crc32c(data)
    return ((((crc >> 15) | (crc << 17)) & _U32) + _MASK_DELTA) & _U32


def iter_tfrecord(path: str | os.PathLike) -> Iterator[bytes]:
    """Yield each record's payload, reading the file one record at a time (a real segment is about
    1 GB: only the current record is in memory); TypError (file, record index, byte offset) on a
    bad CRC or truncation."""
    p = Path(path)
    with open_regular(p, "TFRecord file", max_bytes=MAX_TFRECORD_BYTES) as (f, size):
        offset, index = 0, 0
        while offset < size:
            where = f"record {index} at byte offset {offset}"
            head = _read_exactly(f, p, 12)
            if len(head) < 12:
                raise TypError(p, where, "a 12-byte record header (length, length crc)",
                               f"{len(head)} bytes left (truncated file)")
            length_bytes = head[:8]
            (length,), (length_crc,) = struct.unpack("<Q", length_bytes), struct.unpack("<I", head[8:12])
            if masked_crc32c(length_bytes) != length_crc:
                raise TypError(p, f"{where}: length crc", f"masked crc32c {masked_crc32c(length_bytes):#010x}",
                               f"{length_crc:#010x} (corrupt header)")
            start = offset + 12
            # checked before reading: a corrupt or hostile length is never allocated
            if length > MAX_RECORD_BYTES:
                raise TypError(p, where, f"a record of at most {MAX_RECORD_BYTES // MiB} MiB (a Waymo Frame)",
                               f"{length} bytes")
            if size - start < length + 4:
                raise TypError(p, where, f"{length} payload bytes + 4 crc bytes",
                               f"{size - start} bytes left (truncated file)")
            payload = _read_exactly(f, p, length)
            tail = _read_exactly(f, p, 4)
            if len(payload) < length or len(tail) < 4:  # the file shrank while being read
                raise TypError(p, where, f"{length} payload bytes + 4 crc bytes",
                               f"{len(payload) + len(tail)} bytes (truncated file)")
            (payload_crc,) = struct.unpack("<I", tail)
            expected = masked_crc32c(payload)
            if expected != payload_crc:
                raise TypError(p, f"{where}: payload crc", f"masked crc32c {expected:#010x}",
                               f"{payload_crc:#010x} (corrupt payload of {length} bytes at offset {start})")
            yield payload
            del payload
            offset, index = start + length + 4, index + 1


def _read_exactly(f, p: Path, n: int) -> bytes:
    try:
        return f.read(n)
    except OSError as exc:
        raise TypError(p, "file", "a readable TFRecord file", f"{type(exc).__name__}: {exc.strerror}") from None


def read_waymo_frames(path: str | os.PathLike) -> list[Scene]:
    """Every Frame of a Waymo tfrecord (all in memory: for a whole segment, iterate
    :func:`iter_waymo_frames` instead)."""
    return list(iter_waymo_frames(path))


def iter_waymo_frames(path: str | os.PathLike) -> Iterator[Scene]:
    """Each Frame of a Waymo tfrecord as a single-agent Scene (agent ``"ego"``, vehicle frame), in
    file order, one at a time: memory stays at about one frame whatever the file's size.

    points: (N, 4) float32 ``[x, y, z, tanh(intensity)]`` from the range images of every laser,
    first and second returns, pixels with range > 0. A frame without range images (labels-only
    files such as mmdet3d's test frame) gets a (0, 4) cloud.
    boxes: ``laser_labels`` (K, 7) ``[center_x, center_y, center_z, length, width, height, heading]``;
    labels are the type names lower-cased without ``TYPE_`` (vehicle, pedestrian, sign, cyclist);
    box ids are a stable 63-bit hash of the label's string id.
    A file with no record, and NaN/Inf range or intensity pixels, raise TypError (the frames
    before a bad one have been yielded by then).
    """
    from waymo_open_dataset import dataset_pb2, label_pb2

    count = 0
    for index, payload in enumerate(iter_tfrecord(path)):
        where = f"{path} (frame {index})"
        try:
            frame = dataset_pb2.Frame.FromString(payload)
        except Exception as exc:  # protobuf's DecodeError has no stable import path across versions
            raise TypError(where, "payload", "a serialized waymo.open_dataset.Frame", type(exc).__name__) from None
        del payload
        pose = _transform(where, "pose.transform", frame.pose.transform)
        boxes = np.array([[lb.box.center_x, lb.box.center_y, lb.box.center_z,
                           lb.box.length, lb.box.width, lb.box.height, lb.box.heading]
                          for lb in frame.laser_labels], dtype=np.float64).reshape(-1, 7)
        labels = tuple(_enum_name(where, f"laser_labels[{k}].type", label_pb2.Label.Type, lb.type)
                       .removeprefix("TYPE_").lower() for k, lb in enumerate(frame.laser_labels))
        ids = np.array([_stable_id(lb.id) for lb in frame.laser_labels], dtype=np.int64)
        view = AgentView(agent_id="ego", points=_frame_points(where, frame, pose, dataset_pb2), pose=pose,
                         boxes=boxes, box_labels=labels, box_ids=ids, where=where)
        scene = Scene(scenario=frame.context.name, timestamp=str(frame.timestamp_micros), agents={"ego": view},
                      dataset="waymo")
        del frame, view
        count += 1
        yield scene
        del scene  # while the caller asks for the next frame, hold none
    if not count:
        raise TypError(path, "records", "at least one Frame record", "an empty file")


def read_waymo_kitti_bin(path: str | os.PathLike) -> np.ndarray:
    """mmdet3d's Waymo-to-KITTI ``.bin`` (float32 x6: x, y, z, intensity, elongation, timestamp µs).

    Returns (N, 4) float32 ``[x, y, z, tanh(intensity)]`` in the vehicle frame.
    """
    cloud = read_bin(path, 6)
    return np.concatenate([cloud[:, :3], np.tanh(cloud[:, 3:4])], axis=1).astype(np.float32)


def _enum_name(where: str, field: str, enum, value: int) -> str:
    """The name of a proto enum value; a value the enum does not define (proto3 keeps it) is refused."""
    if value not in enum.values():
        raise TypError(where, field, f"one of {sorted(enum.keys())}", value)
    return enum.Name(value)


def _stable_id(text: str) -> int:
    return int.from_bytes(hashlib.blake2b(text.encode("utf-8"), digest_size=8).digest(), "little") & (2**63 - 1)


def _transform(where: str, field: str, values) -> np.ndarray:
    m = np.array(values, dtype=np.float64)
    if m.shape != (16,) or not np.isfinite(m).all():
        raise TypError(where, field, "16 finite numbers (4x4 row-major)", m.shape)
    return m.reshape(4, 4)


def _matrix_float(where: str, field: str, compressed: bytes, dataset_pb2, dims: int) -> np.ndarray:
    """zlib-compressed MatrixFloat -> float32 array of its shape (``dims`` axes), inflated no
    further than the largest range image can take."""
    inflate = zlib.decompressobj()
    try:
        raw = inflate.decompress(compressed, _MAX_MATRIX_BYTES)
    except zlib.error as exc:
        raise TypError(where, field, "a zlib-compressed MatrixFloat", f"zlib.error: {exc}") from None
    if inflate.unconsumed_tail:
        raise TypError(where, field, f"a range image of at most {MAX_RANGE_IMAGE_PIXELS} pixels x "
                       f"{MAX_RANGE_IMAGE_CHANNELS} channels ({_MAX_MATRIX_BYTES} bytes inflated)",
                       f"more than {_MAX_MATRIX_BYTES} bytes from {len(compressed)} compressed (a zlib bomb?)")
    if not inflate.eof:
        raise TypError(where, field, "a complete zlib stream", f"{len(compressed)} bytes, cut short")
    try:
        mat = dataset_pb2.MatrixFloat.FromString(raw)
    except Exception as exc:  # protobuf's DecodeError has no stable import path across versions
        raise TypError(where, field, "a zlib-compressed MatrixFloat", type(exc).__name__) from None
    return _shaped(where, field, tuple(mat.shape.dims), mat.data, dims)


def _shaped(where: str, field: str, shape: tuple[int, ...], data, dims: int) -> np.ndarray:
    """A range image's values as float32 of ``shape``: ``dims`` axes, each >= 1, within the size caps,
    their product (in Python integers: numpy's int64 product of large dims wraps, even to 0) equal
    to the number of values."""
    if len(shape) != dims or min(shape, default=0) < 1 or math.prod(shape) != len(data):
        raise TypError(where, field, f"a {dims}-d matrix whose shape matches its data",
                       f"shape {shape}, {len(data)} values")
    if shape[0] * shape[1] > MAX_RANGE_IMAGE_PIXELS or math.prod(shape[2:]) > MAX_RANGE_IMAGE_CHANNELS:
        raise TypError(where, field, f"at most {MAX_RANGE_IMAGE_PIXELS} pixels x {MAX_RANGE_IMAGE_CHANNELS} channels",
                       f"shape {shape}")
    return np.array(data, dtype=np.float32).reshape(shape)


def _frame_points(where: str, frame, frame_pose: np.ndarray, dataset_pb2) -> np.ndarray:
    """All lasers' returns in the vehicle frame, in Waymo's order (calibrations sorted by laser name)."""
    lasers = {laser.name: laser for laser in frame.lasers}
    clouds = [np.zeros((0, 4), dtype=np.float32)]
    top = dataset_pb2.LaserName.TOP
    calibrations = sorted(frame.context.laser_calibrations, key=lambda c: c.name)
    names = [_enum_name(where, "context.laser_calibrations[].name", dataset_pb2.LaserName.Name, c.name)
             for c in calibrations]
    if len(set(names)) != len(names):  # one calibration per laser: more would decode its images again
        raise TypError(where, "context.laser_calibrations", "one calibration per laser", names)
    for calib, name in zip(calibrations, names):
        laser = lasers.get(calib.name)
        if laser is None:
            continue
        pixel_pose = None
        if calib.name == top and laser.ri_return1.range_image_pose_compressed:
            field = f"lasers[{name}].ri_return1.range_image_pose_compressed"
            raw_pose = _matrix_float(where, field, laser.ri_return1.range_image_pose_compressed, dataset_pb2, 3)
            if raw_pose.shape[2] != 6:
                raise TypError(where, field, "6 channels [roll, pitch, yaw, x, y, z] per pixel", raw_pose.shape)
            pixel_pose = _pixel_poses(raw_pose)
        extrinsic = _transform(where, f"laser_calibrations[{name}].extrinsic", calib.extrinsic.transform)
        for ret_name in ("ri_return1", "ri_return2"):
            ret = getattr(laser, ret_name)
            field = f"lasers[{name}].{ret_name}"
            if ret.range_image_compressed:
                image = _matrix_float(where, field, ret.range_image_compressed, dataset_pb2, 3)
            elif len(ret.range_image.data):  # the deprecated uncompressed field
                image = _shaped(where, f"{field}.range_image", tuple(ret.range_image.shape.dims),
                                ret.range_image.data, 3)
            else:
                continue
            if image.shape[2] < 2:
                raise TypError(where, field, "range image channels [range, intensity, ...]", image.shape)
            bad = ~np.isfinite(image[..., :2]).all(axis=-1)
            if bad.any():
                raise TypError(where, field, "finite range and intensity in every pixel",
                               f"NaN/Inf in {int(bad.sum())} of {bad.size} pixels")
            height = image.shape[0]
            if len(calib.beam_inclinations):
                inclinations = np.array(calib.beam_inclinations, dtype=np.float64)
                if len(inclinations) != height:
                    raise TypError(where, f"laser_calibrations[{name}].beam_inclinations",
                                   f"{height} values, one per range image row", len(inclinations))
            else:
                inclinations = uniform_inclinations(calib.beam_inclination_min, calib.beam_inclination_max, height)
            if pixel_pose is not None and pixel_pose.shape[:2] != image.shape[:2]:
                raise TypError(where, f"lasers[{name}].ri_return1.range_image_pose_compressed",
                               f"shape {image.shape[:2]} + (6,)", pixel_pose.shape[:2] + (6,))
            clouds.append(range_image_to_points(image, inclinations=inclinations, extrinsic=extrinsic,
                                                pixel_pose=pixel_pose, frame_pose=frame_pose))
    return np.concatenate(clouds, axis=0)


def uniform_inclinations(low: float, high: float, height: int) -> np.ndarray:
    """(height,) beam inclinations (radians, ascending) for a laser calibrated by min/max only.

    Pixel centres: ``low + (i + 0.5) / height * (high - low)``, as Waymo's ``compute_inclination``.
    """
    return low + (np.arange(height) + 0.5) / height * (high - low)


def range_image_to_points(image: np.ndarray, *, inclinations: np.ndarray, extrinsic: np.ndarray,
                          pixel_pose: np.ndarray | None = None, frame_pose: np.ndarray | None = None) -> np.ndarray:
    """One return's range image -> (M, 4) float32 ``[x, y, z, tanh(intensity)]`` in the vehicle frame.

    image: (H, W, C) float32, channel 0 range (m), channel 1 intensity; pixels with range <= 0
    are dropped. inclinations: (H,) ascending, as in the calibration; row 0 of the image is the
    highest beam. extrinsic: (4, 4) laser -> vehicle. Column c looks along azimuth
    ``(2 (W - c - 0.5) / W - 1) pi`` in the laser frame, corrected by the extrinsic's yaw so
    that the middle of the image faces the vehicle's x axis.
    pixel_pose: (H, W, 4, 4) vehicle -> world at each pixel's capture time (TOP laser; rolling
    shutter), with frame_pose (4, 4) vehicle -> world at the frame time.
    """
    height, width = image.shape[:2]
    rng = image[..., 0].astype(np.float64)
    incl = np.asarray(inclinations, dtype=np.float64)[::-1][:, None]
    az_correction = np.arctan2(extrinsic[1, 0], extrinsic[0, 0])
    azimuth = ((np.arange(width, 0, -1) - 0.5) / width * 2.0 - 1.0) * np.pi - az_correction
    local = np.stack([np.cos(azimuth)[None, :] * np.cos(incl) * rng,
                      np.sin(azimuth)[None, :] * np.cos(incl) * rng,
                      np.sin(incl) * rng], axis=-1)
    points = local @ extrinsic[:3, :3].T + extrinsic[:3, 3]
    if pixel_pose is not None:
        if frame_pose is None:
            raise TypError(None, "frame_pose", "the frame's vehicle pose when pixel poses are given", None)
        points = np.einsum("hwij,hwj->hwi", pixel_pose[..., :3, :3], points) + pixel_pose[..., :3, 3]
        world_to_vehicle = np.linalg.inv(frame_pose)
        points = points @ world_to_vehicle[:3, :3].T + world_to_vehicle[:3, 3]
    keep = rng > 0
    return np.concatenate([points[keep], np.tanh(image[..., 1][keep].astype(np.float64))[:, None]],
                          axis=1).astype(np.float32)


def _pixel_poses(raw: np.ndarray) -> np.ndarray:
    """(H, W, 6) ``[roll, pitch, yaw, x, y, z]`` -> (H, W, 4, 4), rotation ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    roll, pitch, yaw = (raw[..., k].astype(np.float64) for k in range(3))
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    m = np.zeros(raw.shape[:2] + (4, 4))
    m[..., 0, 0], m[..., 0, 1], m[..., 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    m[..., 1, 0], m[..., 1, 1], m[..., 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    m[..., 2, 0], m[..., 2, 1], m[..., 2, 2] = -sp, cp * sr, cp * cr
    m[..., :3, 3] = raw[..., 3:6]
    m[..., 3, 3] = 1.0
    return m
