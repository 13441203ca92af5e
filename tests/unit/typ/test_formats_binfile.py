"""typ.formats.binfile: every malformed .bin gives a TypError naming the file and the field."""
from __future__ import annotations

import numpy as np
import pytest

from typ.errors import TypError
from typ.formats.binfile import read_bin


def _cloud(n=10, columns=4):
    rng = np.random.default_rng(0)
    return rng.uniform(-50, 50, (n, columns)).astype(np.float32)


def _raises(path, field, *fragments):
    with pytest.raises(TypError) as info:
        read_bin(path, 4)
    msg = str(info.value)
    assert str(path) in msg and info.value.field == field, msg
    for fragment in fragments:
        assert fragment in msg, msg
    return msg


def test_reads_float32_cloud(tmp_path):
    cloud = _cloud()
    (tmp_path / "a.bin").write_bytes(cloud.tobytes())
    got = read_bin(tmp_path / "a.bin", 4)
    assert got.dtype == np.float32 and got.shape == (10, 4)
    np.testing.assert_array_equal(got, cloud)
    got[0, 0] = 1.0  # the result is a writable copy


def test_missing_file(tmp_path):
    _raises(tmp_path / "nope.bin", "file", "no such file")


def test_directory_is_unreadable(tmp_path):
    _raises(tmp_path, "file", "readable")


def test_empty_file(tmp_path):
    (tmp_path / "e.bin").write_bytes(b"")
    _raises(tmp_path / "e.bin", "points", "empty", "0 bytes")


def test_truncated_file(tmp_path):
    (tmp_path / "t.bin").write_bytes(_cloud().tobytes()[:-3])
    _raises(tmp_path / "t.bin", "size", "157 bytes", "multiple of 16")


def test_misaligned_column_count(tmp_path):
    (tmp_path / "m.bin").write_bytes(_cloud(3, 5).tobytes())  # 60 bytes read as 4 columns
    _raises(tmp_path / "m.bin", "size", "60 bytes", "multiple of 16")


def test_nan_points_are_counted(tmp_path):
    cloud = _cloud()
    cloud[2, 0] = np.nan
    cloud[7, 3] = np.inf
    (tmp_path / "n.bin").write_bytes(cloud.tobytes())
    _raises(tmp_path / "n.bin", "points", "2 of 10 points", "NaN/Inf", "[0, 3]")


def test_float64_file_is_reported_as_wrong_dtype(tmp_path):
    cloud = _cloud(16).astype(np.float64) + np.random.default_rng(1).uniform(0, 1, (16, 4))
    (tmp_path / "d.bin").write_bytes(cloud.tobytes())
    _raises(tmp_path / "d.bin", "dtype", "float32 little-endian", "float64")


def test_big_endian_file_is_reported_as_wrong_dtype(tmp_path):
    (tmp_path / "b.bin").write_bytes(_cloud().astype(">f4").tobytes())
    _raises(tmp_path / "b.bin", "dtype", "float32 little-endian")


def test_large_extra_columns_are_not_coordinates(tmp_path):
    cloud = _cloud(4, 6)
    cloud[:, 5] = 1.55e15  # Waymo timestamps in microseconds
    (tmp_path / "w.bin").write_bytes(cloud.tobytes())
    assert read_bin(tmp_path / "w.bin", 6).shape == (4, 6)


def test_column_count_must_cover_xyz(tmp_path):
    (tmp_path / "a.bin").write_bytes(_cloud().tobytes())
    with pytest.raises(TypError, match="columns"):
        read_bin(tmp_path / "a.bin", 2)
