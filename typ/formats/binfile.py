"""Validated reading of raw float32 point clouds (KITTI ``.bin``, nuScenes ``.pcd.bin``, mmdet3d Waymo bins).

These files carry no header: a wrong column count, a truncated copy or a float64 dump
reads as plausible-looking garbage with ``np.fromfile``. :func:`read_bin` checks what
can be checked and raises :class:`~typ.errors.TypError` naming the file and the field.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from typ.errors import TypError
from typ.inputs import MiB, read_regular

#: Coordinates beyond this (metres) are not LiDAR returns in the sensor's own frame (the
#: longest-range automotive sensors see ~1 km): the bytes are not float32 LE, or not metres.
MAX_ABS_COORDINATE = 1e4
#: A point cloud file: ten times the largest single scan (128 beams, two returns, ~1 M points
#: of 32 bytes); within it a hostile file stays well under 1 GB of memory to check.
MAX_CLOUD_BYTES = 128 * MiB


def read_bin(path: str | os.PathLike, columns: int) -> np.ndarray:
    """Read a headerless little-endian float32 cloud -> ``(N, columns)`` float32, N >= 1.

    The first three columns are x, y, z in metres (the file's own sensor frame); the
    rest are passed through unchanged. Raises TypError for a missing or unreadable
    file, a size that is not a whole number of points, an empty cloud, coordinates
    beyond ``MAX_ABS_COORDINATE`` (wrong dtype, byte order or units) and NaN/Inf values.
    """
    p = Path(path)
    if columns < 3:
        raise TypError(p, "columns", "at least 3 (x, y, z)", columns)
    record = 4 * columns
    raw = read_regular(p, "point cloud file", max_bytes=MAX_CLOUD_BYTES)
    if len(raw) == 0:
        raise TypError(p, "points", f"at least one point ({record} bytes)", "empty file (0 bytes)")
    if len(raw) % record:
        raise TypError(p, "size", f"a multiple of {record} bytes ({columns} float32 per point); "
                       "the file is truncated or has a different column count",
                       f"{len(raw)} bytes ({len(raw) % record} bytes left over)")
    cloud = np.frombuffer(raw, dtype="<f4").reshape(-1, columns).astype(np.float32)
    xyz = cloud[:, :3]
    with np.errstate(invalid="ignore"):
        absurd = np.isfinite(xyz) & (np.abs(xyz) > MAX_ABS_COORDINATE)
    if absurd.any():
        raise TypError(p, "dtype", f"float32 little-endian with |x|, |y|, |z| <= {MAX_ABS_COORDINATE:g} m",
                       f"{int(absurd.any(axis=1).sum())} of {len(cloud)} points beyond that "
                       f"(max {float(np.abs(xyz[absurd]).max()):.3g}); the file may be float64, big-endian "
                       "or in millimetres")
    bad_rows = ~np.isfinite(cloud).all(axis=1)
    if bad_rows.any():
        bad_cols = np.flatnonzero(~np.isfinite(cloud).all(axis=0)).tolist()
        raise TypError(p, "points", "finite values (no NaN/Inf)",
                       f"{int(bad_rows.sum())} of {len(cloud)} points with NaN/Inf in columns {bad_cols}")
    return cloud
