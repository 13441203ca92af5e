"""typ.formats.pcd: round trips, Open3D compatibility both ways, ascii/compressed data, bad files."""
from __future__ import annotations

import numpy as np
import pytest

from typ.errors import TypError
from typ.formats.pcd import lzf_decompress, read_pcd, write_pcd


def _cloud(n=500, seed=0):
    rng = np.random.default_rng(seed)
    pts = np.concatenate([rng.uniform(-80, 80, (n, 3)), rng.uniform(0, 1, (n, 1))], axis=1).astype(np.float32)
    return pts, rng.integers(0, 6, n).astype(np.uint8)


def _open3d():
    try:
        import open3d
    except ImportError as exc:  # the wheel also needs system libraries (libusb)
        pytest.skip(f"open3d not importable: {exc}")
    return open3d


@pytest.mark.parametrize("with_semantics", [False, True])
def test_round_trip(tmp_path, with_semantics):
    pts, sem = _cloud()
    path = tmp_path / "000068.pcd"
    write_pcd(path, pts, semantics=sem if with_semantics else None)
    got, got_sem = read_pcd(path)
    assert got.dtype == np.float32 and got.shape == pts.shape
    np.testing.assert_array_equal(got[:, :3], pts[:, :3])
    assert np.abs(got[:, 3] - pts[:, 3]).max() <= 0.5 / 255 + 1e-7
    if with_semantics:
        np.testing.assert_array_equal(got_sem, sem)
    else:
        assert got_sem is None
    assert [p.name for p in tmp_path.iterdir()] == ["000068.pcd"]  # no temporaries left


@pytest.mark.parametrize("with_semantics", [False, True])
def test_open3d_reads_our_files(tmp_path, with_semantics):
    o3d = _open3d()
    pts, sem = _cloud()
    path = tmp_path / "a.pcd"
    write_pcd(path, pts, semantics=sem if with_semantics else None)
    cloud = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(np.asarray(cloud.points), pts[:, :3].astype(np.float64))
    # OpenCOOD's pcd_to_np takes the intensity from colors[:, 0]
    assert np.abs(np.asarray(cloud.colors)[:, 0] - pts[:, 3]).max() <= 0.5 / 255 + 1e-7


@pytest.mark.parametrize("mode", [dict(write_ascii=False), dict(write_ascii=True), dict(compressed=True)])
def test_we_read_open3d_files(tmp_path, mode):
    o3d = _open3d()
    pts, _ = _cloud(2000, seed=1)
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(pts[:, :3].astype(np.float64))
    cloud.colors = o3d.utility.Vector3dVector(np.repeat(pts[:, 3:4].astype(np.float64), 3, axis=1))
    path = tmp_path / "o3d.pcd"
    assert o3d.io.write_point_cloud(str(path), cloud, **mode)
    got, sem = read_pcd(path)
    assert sem is None and got.shape == (2000, 4)
    atol = 1e-4 if mode.get("write_ascii") else 0  # ascii prints a limited number of digits
    np.testing.assert_allclose(got[:, :3], pts[:, :3], atol=atol, rtol=0)
    assert np.abs(got[:, 3] - pts[:, 3]).max() <= 0.5 / 255 + 1e-7


HEADER = ("# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {size}\nTYPE {type}\nCOUNT {count}\n"
          "WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n")


def test_ascii_intensity_field_and_padding(tmp_path):
    path = tmp_path / "i.pcd"
    body = "1 2 3 0 0 0.25 7\n4 5 6 0 0 0.5 9\n"
    path.write_text(HEADER.format(fields="x y z _ intensity semantic", size="4 4 4 4 4 1", type="F F F U F U",
                                  count="1 1 1 2 1 1", n=2, data="ascii") + body)
    got, sem = read_pcd(path)
    np.testing.assert_allclose(got, [[1, 2, 3, 0.25], [4, 5, 6, 0.5]])
    np.testing.assert_array_equal(sem, [7, 9])


def test_packed_float_rgb_binary_and_nan_rows(tmp_path):
    rgb = np.array([(51 << 16) | (1 << 8) | 2, 255 << 16, 0], dtype=np.uint32).view(np.float32)
    rec = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")])
    rec["x"], rec["y"], rec["z"], rec["rgb"] = [1, 2, np.nan], [0, 0, 0], [0, 0, 0], rgb
    header = HEADER.format(fields="x y z rgb", size="4 4 4 4", type="F F F F", count="1 1 1 1", n=3, data="binary")
    organised = tmp_path / "rgb.pcd"
    organised.write_bytes(header.replace("WIDTH 3\nHEIGHT 1", "WIDTH 1\nHEIGHT 3").encode() + rec.tobytes())
    got, _ = read_pcd(organised)
    # the organised cloud's NaN pixel is dropped; R of the packed colour is the intensity
    np.testing.assert_allclose(got, [[1, 0, 0, 0.2], [2, 0, 0, 1.0]], atol=1e-7)
    # an unorganised cloud has no pixels without a return: its NaN point is refused, not dropped
    flat = tmp_path / "flat.pcd"
    flat.write_bytes(header.encode() + rec.tobytes())
    assert "NaN in 1 of 3 points" in str(_error(flat))


def test_lzf_back_reference_overlap():
    # literal "ab", then a back reference of length 6 at distance 2 -> "abababab"
    assert lzf_decompress(bytes([1]) + b"ab" + bytes([(4 << 5) | 0, 1]), 8) == b"abababab"
    with pytest.raises(TypError, match="LZF"):
        lzf_decompress(bytes([(4 << 5) | 0, 9]), 8, where="x.pcd")


def _samples(rng: np.random.Generator) -> list[bytes]:
    """Byte strings that exercise every LZF token: random (literal runs), zero runs (overlapping
    references at distance 1), short periods, repeats further apart than 8 KiB, and a float cloud."""
    cloud = np.round(rng.uniform(-40, 40, (3000, 4)), 1).astype(np.float32).tobytes()
    period = bytes(rng.integers(0, 256, 5, dtype=np.uint8)) * 4000
    far = bytes(rng.integers(0, 256, 9000, dtype=np.uint8))
    return [b"", b"a", b"abc", bytes(rng.integers(0, 256, 5000, dtype=np.uint8)), bytes(70_000), period,
            far + far + far[:100], cloud]


def test_lzf_round_trips_an_independent_compressor():
    from lzf_reference import lzf_compress

    rng = np.random.default_rng(3)
    for data in _samples(rng):
        packed = lzf_compress(data)
        assert lzf_decompress(packed, len(data)) == data
    assert len(lzf_compress(bytes(70_000))) < 1000  # the zero run really is coded as back references


def test_lzf_output_is_bounded_by_the_size_it_must_have():
    from lzf_reference import lzf_compress

    packed = lzf_compress(bytes(10_000))
    for size in (0, 9_999):  # a stream that would write more than promised stops at the bound
        with pytest.raises(TypError, match="valid LZF-compressed data"):
            lzf_decompress(packed, size, where="x.pcd")
    with pytest.raises(TypError, match="10001 bytes after LZF decompression"):
        lzf_decompress(packed, 10_001, where="x.pcd")
    with pytest.raises(TypError, match="corrupt stream at byte"):
        lzf_decompress(packed[:-1], 10_000, where="x.pcd")  # a back reference cut short


def test_binary_compressed_file_round_trips(tmp_path):
    from lzf_reference import lzf_compress

    pts, sem = _cloud(300, seed=4)
    rec = {"x": pts[:, 0], "y": pts[:, 1], "z": pts[:, 2], "intensity": pts[:, 3], "semantic": sem}
    raw = b"".join(np.ascontiguousarray(v).tobytes() for v in rec.values())  # field by field, as PCL lays it out
    packed = lzf_compress(raw)
    path = tmp_path / "c.pcd"
    path.write_bytes(HEADER.format(fields="x y z intensity semantic", size="4 4 4 4 1", type="F F F F U",
                                   count="1 1 1 1 1", n=300, data="binary_compressed").encode()
                     + np.array([len(packed), len(raw)], "<u4").tobytes() + packed)
    got, got_sem = read_pcd(path)
    np.testing.assert_array_equal(got, pts)
    np.testing.assert_array_equal(got_sem, sem)


def _error(path) -> TypError:
    with pytest.raises(TypError) as info:
        read_pcd(path)
    assert info.value.where == str(path)
    return info.value


def test_truncated_binary(tmp_path):
    pts, _ = _cloud(10)
    path = tmp_path / "t.pcd"
    write_pcd(path, pts)
    path.write_bytes(path.read_bytes()[:-5])
    err = _error(path)
    assert err.field == "DATA" and "truncated" in str(err)


def test_header_errors(tmp_path):
    path = tmp_path / "h.pcd"
    path.write_text("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\n")
    assert _error(path).field == "header"
    path.write_text(HEADER.format(fields="x y", size="4 4", type="F F", count="1 1", n=0, data="ascii"))
    assert _error(path).field == "FIELDS"
    path.write_text(HEADER.format(fields="x y z", size="4 4", type="F F F", count="1 1 1", n=0, data="ascii"))
    assert _error(path).field == "SIZE"
    path.write_text(HEADER.format(fields="x y z", size="4 4 3", type="F F F", count="1 1 1", n=0, data="ascii"))
    assert _error(path).field == "TYPE/SIZE"
    path.write_text(HEADER.format(fields="x y z", size="4 4 4", type="F F F", count="1 1 1", n=0, data="lzma"))
    assert _error(path).field == "DATA"
    path.write_text(HEADER.format(fields="x y z", size="4 4 4", type="F F F", count="1 1 1", n=2, data="ascii")
                    + "1 2 3\n4 5\n")
    assert "6 numbers" in str(_error(path))
    path.write_text(HEADER.format(fields="x y z", size="4 4 4", type="F F F", count="1 1 1", n=1, data="ascii")
                    + "1 2 three\n")
    assert _error(path).field == "DATA"


def test_missing_file(tmp_path):
    assert _error(tmp_path / "none.pcd").field == "file"


def test_writer_rejects_bad_arrays(tmp_path):
    pts, sem = _cloud(4)
    with pytest.raises(TypError, match="semantics"):
        write_pcd(tmp_path / "a.pcd", pts, semantics=sem.astype(np.int64))
    with pytest.raises(TypError, match="points"):
        write_pcd(tmp_path / "a.pcd", pts[:, :3])
    pts[1, 1] = np.inf
    with pytest.raises(TypError, match="finite"):
        write_pcd(tmp_path / "a.pcd", pts)
    assert not list(tmp_path.iterdir())
