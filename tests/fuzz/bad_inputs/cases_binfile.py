"""Bad-input cases: headerless float32 .bin clouds (KITTI, Waymo's mmdet3d bins) (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

import numpy as np

from typ.formats.binfile import read_bin
from typ.formats.waymo import read_waymo_kitti_bin

from bad_inputs.make_corpus import Probe, case, cloud, unreadable, write


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
