"""PCD point clouds as OPV2V / V2V4Real store them, without Open3D.

OpenCOOD writes its clouds with Open3D and keeps the LiDAR intensity in the first
**colour** channel (its ``pcd_to_np`` reads ``colors[:, 0]``). :func:`write_pcd` follows
that: fields ``x y z rgb`` (float32; ``rgb`` packed as uint32 ``R<<16 | G<<8 | B``
with R = G = B = round(intensity * 255), so the cloud shows grey in viewers) and,
when semantics are given, one more field ``semantic`` (uint8, codes from
:data:`typ.scene.SEMANTIC_CLASSES`). Open3D 0.20's reader skips the extra field and
still returns the points and colours (verified in tests/unit/typ/test_formats_pcd.py), so no
sidecar file is needed.

:func:`read_pcd` reads ``ascii``, ``binary`` and ``binary_compressed`` (LZF) data, any
field order, with PCL's per-field COUNT. Intensity comes from an ``intensity`` field
if there is one (taken as is), else from the R of ``rgb``/``rgba`` (divided by 255),
else it is 0. In an organised cloud (``HEIGHT`` > 1) rows whose x, y or z is NaN are
dropped: PCL writes NaN for the pixels without a return. An unorganised cloud has no such
pixels, so a NaN there is refused, as is an infinite coordinate or one beyond
:data:`~typ.formats.binfile.MAX_ABS_COORDINATE` (millimetres or a world frame), in any cloud.

What the header promises is checked against the data, as PCL does: ``WIDTH``, ``HEIGHT`` and
``POINTS`` are all there and ``POINTS`` equals ``WIDTH x HEIGHT``, binary data holds exactly
``POINTS`` rows, compressed data inflates to exactly that, ascii data has one number per field
and point, and every ascii number fits its field's type (a float beyond float32's range in a
``F 4`` field, 300 in a ``U 1`` field). So a file that reads returns ``POINTS`` points (fewer
only by an organised cloud's NaN pixels). Bounds before any allocation: the file and its
inflated data are at most :data:`MAX_PCD_BYTES`, ascii data at most :data:`MAX_ASCII_BYTES`, a
field's ``COUNT`` at most :data:`MAX_COUNT`. LZF is decoded by compiled code (numba):
reports/bench_pcd_lzf.md compares it with the pure-Python decoder it replaced.
"""
from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from typ.errors import TypError
from typ.formats.binfile import MAX_ABS_COORDINATE, MAX_CLOUD_BYTES
from typ.inputs import MiB, open_regular, read_regular
from typ.io import write_bytes

_NUMPY_TYPE = {("F", 4): "<f4", ("F", 8): "<f8",
               ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8",
               ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8"}
_DATA_KINDS = ("ascii", "binary", "binary_compressed")
#: a file, and its data once inflated
MAX_PCD_BYTES = MAX_CLOUD_BYTES
#: ascii data: parsing holds every number as a Python object (~50 bytes each) for a moment;
#: 16 MiB is about 400,000 points of four fields. Larger clouds belong in binary files.
MAX_ASCII_BYTES = 16 * MiB
#: a PCL header is a few hundred bytes; the DATA line must come within this
MAX_HEADER_BYTES = 1 << 16
#: values per field and point: PCL's largest descriptors (ESF, 640) fit
MAX_COUNT = 4096
#: WIDTH, HEIGHT and POINTS are uint32 in PCL
_MAX_UINT32 = 2**32 - 1
#: fields that hold one value per point
_SCALAR_FIELDS = ("x", "y", "z", "intensity", "semantic", "rgb", "rgba")


@dataclass(frozen=True)
class _Header:
    fields: list[tuple[str, str, int]]   # (name, numpy type, COUNT)
    points: int
    organised: bool                      # HEIGHT > 1: NaN marks a pixel without a return
    kind: str                            # one of _DATA_KINDS
    offset: int                          # bytes before the data

    @property
    def row(self) -> int:
        return sum(np.dtype(t).itemsize * c for _, t, c in self.fields)

    @property
    def data_bytes(self) -> int:
        return self.points * self.row


def read_pcd(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PCD file -> ``(points, semantics)``.

    points:    (N, 4) float32 ``[x, y, z, intensity]`` in the file's sensor frame.
    semantics: (N,) uint8 from a ``semantic`` field, or None when the file has none.
    """
    p = Path(path)
    raw = read_regular(p, ".pcd file", max_bytes=MAX_PCD_BYTES)
    header = _parse_header(p, raw[:MAX_HEADER_BYTES])
    body = raw[header.offset:]
    _check_data_size(p, header, len(body), body[:8])
    read = {"ascii": _read_ascii, "binary": _read_binary, "binary_compressed": _read_compressed}[header.kind]
    return _to_points(p, read(p, body, header), header)


def read_pcd_header(path: str | os.PathLike) -> dict:
    """A PCD file's header, checked as :func:`read_pcd` checks it, without reading the points:
    ``{"points": N, "fields": [names], "data": "ascii" | "binary" | "binary_compressed"}``.
    The size of the data must also be what the header promises (binary: N rows exactly;
    compressed: the stored sizes)."""
    p = Path(path)
    with open_regular(p, ".pcd file", max_bytes=MAX_PCD_BYTES) as (f, size):
        head = f.read(MAX_HEADER_BYTES + 8)  # the header, and binary_compressed's sizes after it
    header = _parse_header(p, head[:MAX_HEADER_BYTES])
    _check_data_size(p, header, size - header.offset, head[header.offset:header.offset + 8])
    return {"points": header.points, "fields": [name for name, _, _ in header.fields], "data": header.kind}


def write_pcd(path: str | os.PathLike, points: np.ndarray, *, semantics: np.ndarray | None = None) -> None:
    """Write ``(N, 4)`` ``[x, y, z, intensity in [0, 1]]`` (+ ``(N,)`` uint8 semantics) as binary PCD, atomically.

    xyz are stored as float32 exactly; intensity is quantised to 1/255 (clipped to [0, 1]).
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 4:
        raise TypError(path, "points", "array of shape (N, 4) [x, y, z, intensity]", pts.shape)
    if not np.isfinite(pts).all():
        raise TypError(path, "points", "finite values (no NaN/Inf)", "non-finite entries")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")]
    if semantics is not None:
        sem = np.asarray(semantics)
        if sem.shape != (len(pts),) or sem.dtype != np.uint8:
            raise TypError(path, "semantics", f"({len(pts)},) uint8", f"{sem.shape} {sem.dtype}")
        fields.append(("semantic", "u1"))
    rec = np.zeros(len(pts), dtype=np.dtype(fields))
    rec["x"], rec["y"], rec["z"] = (pts[:, i].astype(np.float32) for i in range(3))
    grey = np.round(np.clip(pts[:, 3].astype(np.float64), 0.0, 1.0) * 255.0).astype(np.uint32)
    rec["rgb"] = (grey << 16) | (grey << 8) | grey
    if semantics is not None:
        rec["semantic"] = sem
    names = [f for f, _ in fields]
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
              f"FIELDS {' '.join(names)}\n"
              f"SIZE {' '.join(str(np.dtype(t).itemsize) for _, t in fields)}\n"
              f"TYPE {' '.join('F' if t == '<f4' else 'U' for _, t in fields)}\n"
              f"COUNT {' '.join('1' for _ in fields)}\n"
              f"WIDTH {len(pts)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
              f"POINTS {len(pts)}\nDATA binary\n")
    write_bytes(path, header.encode("ascii") + rec.tobytes())


def _parse_header(p: Path, head: bytes) -> _Header:
    """The header entries up to and including DATA, checked against each other."""
    entries, offset = _split_header(p, head)
    fields = _parse_fields(p, entries)
    points, width, height = (_uint_entry(p, entries, key) for key in ("POINTS", "WIDTH", "HEIGHT"))
    if points != width * height:
        raise TypError(p, "POINTS", f"WIDTH x HEIGHT = {width} x {height} = {width * height} (as PCL requires)",
                       points)
    kind = entries["DATA"][0].lower() if entries["DATA"] else ""
    if kind not in _DATA_KINDS:
        raise TypError(p, "DATA", f"one of {_DATA_KINDS}", entries["DATA"])
    return _Header(fields, points, organised=height > 1, kind=kind, offset=offset)


def _split_header(p: Path, head: bytes) -> tuple[dict[str, list[str]], int]:
    """Header entries up to and including DATA, and the offset of the byte after the DATA line."""
    entries: dict[str, list[str]] = {}
    pos = 0
    while pos < len(head):
        end = head.find(b"\n", pos)
        end = len(head) if end < 0 else end
        line = head[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        entries[key.upper()] = values
        if key.upper() == "DATA":
            return entries, min(pos, len(head))
    raise TypError(p, "header", "a PCD header ending in a 'DATA ascii|binary|binary_compressed' line "
                   f"within its first {MAX_HEADER_BYTES} bytes", "no DATA line")


def _uint_entry(p: Path, entries: dict[str, list[str]], key: str) -> int:
    values = entries.get(key)
    if not values or len(values) != 1 or not _is_uint(values[0], _MAX_UINT32):
        raise TypError(p, key, f"one integer in [0, {_MAX_UINT32}]", values)
    return int(values[0])


def _is_uint(text: str, limit: int) -> bool:
    # isdigit alone would let int() meet a 5,000-digit string (ValueError) or a giant value
    return text.isascii() and text.isdigit() and len(text) <= len(str(limit)) and int(text) <= limit


def _parse_fields(p: Path, entries: dict[str, list[str]]) -> list[tuple[str, str, int]]:
    """[(name, numpy type, count)]; PCL's repeated padding fields ``_`` get unique names."""
    names = entries.get("FIELDS") or entries.get("COLUMNS")
    if not names:
        raise TypError(p, "FIELDS", "a FIELDS line naming at least x y z", None)
    sizes, types = entries.get("SIZE", []), entries.get("TYPE", [])
    counts = entries.get("COUNT", ["1"] * len(names))
    for key, values in (("SIZE", sizes), ("TYPE", types), ("COUNT", counts)):
        if len(values) != len(names):
            raise TypError(p, key, f"{len(names)} entries, one per field in FIELDS", values)
    out = []
    for i, (name, size, typ, count) in enumerate(zip(names, sizes, types, counts)):
        if not _is_uint(size, 8) or not _is_uint(count, MAX_COUNT) or int(count) < 1:
            raise TypError(p, "SIZE/COUNT", f"SIZE 1, 2, 4 or 8 and COUNT in [1, {MAX_COUNT}]", (name, size, count))
        np_type = _NUMPY_TYPE.get((typ.upper(), int(size)))
        if np_type is None:
            raise TypError(p, "TYPE/SIZE", f"one of {sorted(_NUMPY_TYPE)}", (name, typ, size))
        if name in _SCALAR_FIELDS and int(count) != 1:
            raise TypError(p, "COUNT", f"1 for field {name!r}", int(count))
        out.append((f"_pad{i}" if name == "_" else name, np_type, int(count)))
    if len({f[0] for f in out}) != len(out):
        raise TypError(p, "FIELDS", "unique field names", names)
    if any(c not in {f[0] for f in out} for c in "xyz"):
        raise TypError(p, "FIELDS", "fields x, y and z", names)
    return out


def _check_data_size(p: Path, header: _Header, have: int, sizes: bytes) -> None:
    """The data's size against the header's promise, before anything is parsed or allocated."""
    need = header.data_bytes
    if header.kind == "binary":
        if have != need:
            raise TypError(p, "DATA", f"{header.points} points x {header.row} bytes = {need} bytes",
                           f"{have} bytes ({'truncated' if have < need else f'{have - need} bytes too many'})")
    elif header.kind == "ascii":
        if have > MAX_ASCII_BYTES:
            raise TypError(p, "DATA", f"ascii data of at most {MAX_ASCII_BYTES // MiB} MiB "
                           "(write larger clouds as binary)", f"{have} bytes")
    else:
        if have < 8:
            raise TypError(p, "DATA", "binary_compressed sizes (8 bytes)", f"{have} bytes")
        packed, unpacked = np.frombuffer(sizes, dtype="<u4").tolist()
        if unpacked != need:
            raise TypError(p, "DATA", f"{need} bytes after decompression for {header.points} points "
                           f"of {header.row} bytes", f"{unpacked} (the stored uncompressed size)")
        if need > MAX_PCD_BYTES:
            raise TypError(p, "DATA", f"at most {MAX_PCD_BYTES // MiB} MiB of data once inflated", need)
        if have - 8 != packed:
            raise TypError(p, "DATA", f"{packed} compressed bytes (the stored compressed size)",
                           f"{have - 8} bytes{' (truncated)' if have - 8 < packed else ''}")


def _read_binary(p: Path, body: bytes, header: _Header) -> dict[str, np.ndarray]:
    dtype = np.dtype([(name, t, (c,)) if c > 1 else (name, t) for name, t, c in header.fields])
    rec = np.frombuffer(body, dtype=dtype, count=header.points)
    return {name: rec[name] for name, _, _ in header.fields}


def _read_ascii(p: Path, body: bytes, header: _Header) -> dict[str, np.ndarray]:
    n, width = header.points, sum(c for _, _, c in header.fields)
    try:
        values = np.array(body.split(), dtype=np.float64)
    except ValueError:
        raise TypError(p, "DATA", "whitespace-separated numbers", "non-numeric tokens") from None
    if values.size != n * width:
        raise TypError(p, "DATA", f"{n} points x {width} values = {n * width} numbers", values.size)
    values = values.reshape(n, width)
    out, col = {}, 0
    for name, t, c in header.fields:
        block = values[:, col:col + c] if c > 1 else values[:, col]
        _check_fits(p, name, block, np.dtype(t))
        # rgb written as TYPE F holds the packed bits of a float; keep those bits exact
        out[name] = block.astype(np.float32).view(np.uint32) if name in ("rgb", "rgba") and t == "<f4" \
            else block.astype(t)
        col += c
    return out


def _check_fits(p: Path, name: str, values: np.ndarray, dtype: np.dtype) -> None:
    """Ascii numbers that the field's type cannot hold would change silently when cast: refuse them."""
    if dtype.kind == "f":
        limit = np.finfo(dtype).max
        with np.errstate(invalid="ignore"):
            bad = np.isfinite(values) & (np.abs(values) > limit)
        expected = f"numbers within {dtype.name}'s range (|v| <= {float(limit):.4g})"
    else:
        info = np.iinfo(dtype)
        with np.errstate(invalid="ignore"):
            bad = ~((values >= info.min) & (values <= info.max) & (values == np.round(values)))
        expected = f"integers in [{info.min}, {info.max}] ({dtype.name})"
    if bad.any():
        raise TypError(p, f"DATA field {name!r}", expected, f"{int(bad.sum())} values such as {values[bad].flat[0]!r}")


def _read_compressed(p: Path, body: bytes, header: _Header) -> dict[str, np.ndarray]:
    """``binary_compressed``: uint32 compressed size, uint32 raw size, LZF data laid out field by field."""
    data = lzf_decompress(body[8:], header.data_bytes, where=p)
    n, out, pos = header.points, {}, 0
    for name, t, c in header.fields:
        arr = np.frombuffer(data, dtype=t, count=n * c, offset=pos)
        out[name] = arr.reshape(n, c) if c > 1 else arr
        pos += n * np.dtype(t).itemsize * c
    return out


def lzf_decompress(src: bytes, size: int, *, where: object = None) -> bytes:
    """Decompress LZF (liblzf's format, used by PCL's binary_compressed) into exactly ``size`` bytes.

    The output never grows past ``size``: a stream that would inflate further is corrupt."""
    out = np.empty(size, dtype=np.uint8)
    written = _lzf_kernel()(np.frombuffer(src, dtype=np.uint8), out)
    if written < 0:
        raise TypError(where, "DATA", "valid LZF-compressed data", f"corrupt stream at byte {-written - 1}")
    if written != size:
        raise TypError(where, "DATA", f"{size} bytes after LZF decompression", written)
    return out.tobytes()


@functools.cache
def _lzf_kernel():
    """:func:`_lzf_decode` compiled on first use (numba's import and cache load cost a few tenths
    of a second that a run reading no compressed cloud should not pay)."""
    import numba

    return numba.njit(cache=True, nogil=True, boundscheck=False)(_lzf_decode)


def _lzf_decode(src, out):
    """liblzf's ``lzf_decompress`` over uint8 arrays: bytes written, or ``-(i + 1)`` when the token at
    input byte ``i`` is cut short, reaches before the output's start or would write past its end.

    Token: ctrl < 32 -> a literal run of ctrl + 1 bytes; else a back reference of length
    ``ctrl >> 5`` (7: plus the next byte) + 2 at distance ``((ctrl & 31) << 8 | next byte) + 1``,
    which may overlap the bytes it produces (copied byte by byte, as liblzf does).
    """
    n, m = src.shape[0], out.shape[0]
    i, o = 0, 0
    while i < n:
        start = i
        ctrl = np.int64(src[i])
        i += 1
        if ctrl < 32:
            run = ctrl + 1
            if i + run > n or o + run > m:
                return -(start + 1)
            out[o:o + run] = src[i:i + run]
            i += run
            o += run
            continue
        length = ctrl >> 5
        if length == 7:
            if i >= n:
                return -(start + 1)
            length += np.int64(src[i])
            i += 1
        if i >= n:
            return -(start + 1)
        ref = o - ((ctrl & 31) << 8) - np.int64(src[i]) - 1
        i += 1
        length += 2
        if ref < 0 or o + length > m:
            return -(start + 1)
        for k in range(length):
            out[o + k] = out[ref + k]
        o += length
    return o


def _to_points(p: Path, columns: dict[str, np.ndarray], header: _Header) -> tuple[np.ndarray, np.ndarray | None]:
    n = header.points
    xyz = np.stack([columns[c].astype(np.float64) for c in "xyz"], axis=1)  # checked before float32 can overflow
    missing = np.isnan(xyz).any(axis=1)
    if missing.any() and not header.organised:
        raise TypError(p, "points", "x, y, z numbers in every row (NaN marks a pixel without a return, which "
                       "only an organised cloud, HEIGHT > 1, has)", f"NaN in {int(missing.sum())} of {n} points")
    with np.errstate(invalid="ignore"):
        far = ~missing & ~(np.abs(xyz) <= MAX_ABS_COORDINATE).all(axis=1)
    if far.any():
        worst = float(np.abs(xyz[far]).max())
        raise TypError(p, "points",
                       f"x, y, z in metres in the sensor frame, |x|, |y|, |z| <= {MAX_ABS_COORDINATE:g} m",
                       f"{int(far.sum())} of {n} points beyond that (max {worst:.3g}); "
                       "the cloud may be in millimetres or in a world frame")
    if "intensity" in columns:
        intensity = columns["intensity"].astype(np.float64)
    elif "rgb" in columns or "rgba" in columns:
        packed = columns.get("rgb", columns.get("rgba"))
        bits = packed.view(np.uint32) if packed.dtype == np.float32 else packed.astype(np.uint32)
        intensity = ((bits >> 16) & 0xFF) / 255.0
    else:
        intensity = np.zeros(n)
    semantics = None
    if "semantic" in columns:
        sem = columns["semantic"]
        if sem.dtype.kind == "f" or sem.min(initial=0) < 0 or sem.max(initial=0) > 255:
            raise TypError(p, "semantic", "unsigned integer codes 0..255", sem.dtype)
        semantics = sem.astype(np.uint8)
    keep = ~missing
    with np.errstate(over="ignore", invalid="ignore"):
        bad_intensity = ~np.isfinite(intensity[keep].astype(np.float32))
    if bad_intensity.any():
        raise TypError(p, "intensity", "finite values", f"NaN/Inf or beyond float32 in {int(bad_intensity.sum())} "
                       f"of {n} points")
    points = np.concatenate([xyz, intensity[:, None]], axis=1).astype(np.float32)
    if keep.all():
        return points, semantics
    return np.ascontiguousarray(points[keep]), (semantics[keep] if semantics is not None else None)
