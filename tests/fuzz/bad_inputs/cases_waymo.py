"""Bad-input cases: Waymo tfrecords of Frame protos (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

import struct

import numpy as np

from typ.formats.waymo import iter_tfrecord, masked_crc32c, read_waymo_frames

from bad_inputs.make_corpus import Probe, WAYMO, _waymo_file, case, tfrecord, waymo_frame


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
