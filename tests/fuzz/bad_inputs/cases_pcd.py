"""Bad-input cases: PCD clouds (OPV2V / V2V4Real) (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

import struct

from typ.formats.pcd import read_pcd, write_pcd

from bad_inputs.make_corpus import Probe, case, cloud, pcd_text, write


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
