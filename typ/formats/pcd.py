"""PCD point clouds as OPV2V / V2V4Real store them, without Open3D.

OpenCOOD writes its clouds with Open3D and keeps the LiDAR intensity in the first
**colour** channel (its ``pcd_to_np`` reads ``colors[:, 0]``). :func:`write_pcd` follows
that: fields ``x y z rgb`` (float32; ``rgb`` packed as uint32 ``R<<16 | G<<8 | B``
with R = G = B = round(intensity * 255), so the cloud shows grey in viewers) and,
when semantics are given, one more field ``semantic`` (uint8, codes from
:data:`typ.scene.SEMANTIC_CLASSES`). Open3D 0.20's reader skips the extra field and
still returns the points and colours (verified in tests/test_formats_pcd.py), so no
sidecar file is needed.

:func:`read_pcd` reads ``ascii``, ``binary`` and ``binary_compressed`` (LZF) data, any
field order, with PCL's per-field COUNT. Intensity comes from an ``intensity`` field
if there is one (taken as is), else from the R of ``rgb``/``rgba`` (divided by 255),
else it is 0. Rows whose x, y or z is NaN/Inf are dropped: PCL writes them for the
invalid pixels of organised (``is_dense = false``) clouds. Coordinates beyond
:data:`~typ.formats.binfile.MAX_ABS_COORDINATE` are rejected (millimetres or a world frame).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from typ.errors import TypError
from typ.formats.binfile import MAX_ABS_COORDINATE
from typ.io import write_bytes

_NUMPY_TYPE = {("F", 4): "<f4", ("F", 8): "<f8",
               ("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8",
               ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8"}
_DATA_KINDS = ("ascii", "binary", "binary_compressed")


def read_pcd(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PCD file -> ``(points, semantics)``.

    points:    (N, 4) float32 ``[x, y, z, intensity]`` in the file's sensor frame.
    semantics: (N,) uint8 from a ``semantic`` field, or None when the file has none.
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except FileNotFoundError:
        raise TypError(p, "file", "an existing .pcd file", "no such file") from None
    except OSError as exc:
        raise TypError(p, "file", "a readable .pcd file", f"{type(exc).__name__}: {exc.strerror}") from None
    header, body = _split_header(p, raw)
    fields = _parse_fields(p, header)
    n = _int_entry(p, header, "POINTS") if "POINTS" in header else \
        _int_entry(p, header, "WIDTH") * _int_entry(p, header, "HEIGHT")
    kind = header["DATA"][0].lower() if header["DATA"] else ""
    if kind == "ascii":
        columns = _read_ascii(p, body, fields, n)
    elif kind == "binary":
        columns = _read_binary(p, body, fields, n)
    elif kind == "binary_compressed":
        columns = _read_compressed(p, body, fields, n)
    else:
        raise TypError(p, "DATA", f"one of {_DATA_KINDS}", header["DATA"])
    return _to_points(p, columns, n)


def read_pcd_header(path: str | os.PathLike, *, limit: int = 1 << 16) -> dict:
    """A PCD file's header, checked as :func:`read_pcd` checks it, without reading the points:
    ``{"points": N, "fields": [names], "data": "ascii" | "binary" | "binary_compressed"}``.
    For binary data, the file must also be long enough for its N points."""
    p = Path(path)
    try:
        with open(p, "rb") as f:
            head = f.read(limit)
            size = os.fstat(f.fileno()).st_size
    except FileNotFoundError:
        raise TypError(p, "file", "an existing .pcd file", "no such file") from None
    except OSError as exc:
        raise TypError(p, "file", "a readable .pcd file", f"{type(exc).__name__}: {exc.strerror}") from None
    header, body = _split_header(p, head)
    fields = _parse_fields(p, header)
    n = _int_entry(p, header, "POINTS") if "POINTS" in header else \
        _int_entry(p, header, "WIDTH") * _int_entry(p, header, "HEIGHT")
    kind = header["DATA"][0].lower() if header["DATA"] else ""
    if kind not in _DATA_KINDS:
        raise TypError(p, "DATA", f"one of {_DATA_KINDS}", header["DATA"])
    if kind == "binary":
        row = sum(np.dtype(t).itemsize * c for _, t, c in fields)
        have = size - (len(head) - len(body))
        if have < n * row:
            raise TypError(p, "DATA", f"{n} points x {row} bytes = {n * row} bytes", f"{have} bytes (truncated)")
    return {"points": n, "fields": [name for name, _, _ in fields], "data": kind}


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


def _split_header(p: Path, raw: bytes) -> tuple[dict[str, list[str]], bytes]:
    """Header entries up to and including DATA, and the bytes that follow the DATA line."""
    header: dict[str, list[str]] = {}
    pos = 0
    while pos < len(raw):
        end = raw.find(b"\n", pos)
        end = len(raw) if end < 0 else end
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, raw[pos:]
    raise TypError(p, "header", "a PCD header ending in a 'DATA ascii|binary|binary_compressed' line",
                   "no DATA line")


def _int_entry(p: Path, header: dict[str, list[str]], key: str) -> int:
    values = header.get(key)
    if not values or len(values) != 1 or not values[0].isdigit():
        raise TypError(p, key, "one non-negative integer", values)
    return int(values[0])


def _parse_fields(p: Path, header: dict[str, list[str]]) -> list[tuple[str, str, int]]:
    """[(name, numpy type, count)]; PCL's repeated padding fields ``_`` get unique names."""
    names = header.get("FIELDS") or header.get("COLUMNS")
    if not names:
        raise TypError(p, "FIELDS", "a FIELDS line naming at least x y z", None)
    sizes, types = header.get("SIZE", []), header.get("TYPE", [])
    counts = header.get("COUNT", ["1"] * len(names))
    for key, values in (("SIZE", sizes), ("TYPE", types), ("COUNT", counts)):
        if len(values) != len(names):
            raise TypError(p, key, f"{len(names)} entries, one per field in FIELDS", values)
    out = []
    for i, (name, size, typ, count) in enumerate(zip(names, sizes, types, counts)):
        if not size.isdigit() or not count.isdigit() or int(count) < 1:
            raise TypError(p, "SIZE/COUNT", "positive integers", (name, size, count))
        np_type = _NUMPY_TYPE.get((typ.upper(), int(size)))
        if np_type is None:
            raise TypError(p, "TYPE/SIZE", f"one of {sorted(_NUMPY_TYPE)}", (name, typ, size))
        out.append((f"_pad{i}" if name == "_" else name, np_type, int(count)))
    if len({f[0] for f in out}) != len(out):
        raise TypError(p, "FIELDS", "unique field names", names)
    missing = [c for c in "xyz" if c not in {f[0] for f in out}]
    if missing:
        raise TypError(p, "FIELDS", "fields x, y and z", names)
    return out


def _read_binary(p: Path, body: bytes, fields, n: int) -> dict[str, np.ndarray]:
    dtype = np.dtype([(name, t, (c,)) if c > 1 else (name, t) for name, t, c in fields])
    if len(body) < n * dtype.itemsize:
        raise TypError(p, "DATA", f"{n} points x {dtype.itemsize} bytes = {n * dtype.itemsize} bytes",
                       f"{len(body)} bytes (truncated)")
    rec = np.frombuffer(body, dtype=dtype, count=n)
    return {name: rec[name] for name, _, _ in fields}


def _read_ascii(p: Path, body: bytes, fields, n: int) -> dict[str, np.ndarray]:
    width = sum(c for _, _, c in fields)
    try:
        values = np.array(body.split(), dtype=np.float64)
    except ValueError:
        raise TypError(p, "DATA", "whitespace-separated numbers", "non-numeric tokens") from None
    if values.size != n * width:
        raise TypError(p, "DATA", f"{n} points x {width} values = {n * width} numbers", values.size)
    values = values.reshape(n, width)
    out, col = {}, 0
    for name, t, c in fields:
        block = values[:, col:col + c] if c > 1 else values[:, col]
        # rgb written as TYPE F holds the packed bits of a float; keep those bits exact
        out[name] = block.astype(np.float32).view(np.uint32) if name in ("rgb", "rgba") and t == "<f4" \
            else block.astype(t)
        col += c
    return out


def _read_compressed(p: Path, body: bytes, fields, n: int) -> dict[str, np.ndarray]:
    """``binary_compressed``: uint32 compressed size, uint32 raw size, LZF data laid out field by field."""
    if len(body) < 8:
        raise TypError(p, "DATA", "binary_compressed sizes (8 bytes)", f"{len(body)} bytes")
    packed, unpacked = np.frombuffer(body[:8], dtype="<u4").tolist()
    if len(body) < 8 + packed:
        raise TypError(p, "DATA", f"{packed} compressed bytes", f"{len(body) - 8} bytes (truncated)")
    data = lzf_decompress(body[8:8 + packed], unpacked, where=p)
    need = sum(n * np.dtype(t).itemsize * c for _, t, c in fields)
    if len(data) != need:
        raise TypError(p, "DATA", f"{need} bytes after decompression for {n} points", len(data))
    out, pos = {}, 0
    for name, t, c in fields:
        size = n * np.dtype(t).itemsize * c
        arr = np.frombuffer(data, dtype=t, count=n * c, offset=pos)
        out[name] = arr.reshape(n, c) if c > 1 else arr
        pos += size
    return out


def lzf_decompress(src: bytes, size: int, *, where: object = None) -> bytes:
    """Decompress LZF (liblzf's format, used by PCL's binary_compressed) into exactly ``size`` bytes."""
    out = bytearray()
    i, end = 0, len(src)
    try:
        while i < end:
            ctrl = src[i]
            i += 1
            if ctrl < 32:  # literal run of ctrl + 1 bytes
                out += src[i:i + ctrl + 1]
                i += ctrl + 1
                continue
            length = ctrl >> 5
            if length == 7:
                length += src[i]
                i += 1
            ref = len(out) - ((ctrl & 0x1F) << 8) - src[i] - 1
            i += 1
            length += 2
            if ref < 0:
                raise IndexError
            # a back reference may overlap the bytes it produces: copy in whole periods
            while length > 0:
                chunk = out[ref:ref + min(length, len(out) - ref)]
                out += chunk
                ref += len(chunk)
                length -= len(chunk)
    except IndexError:
        raise TypError(where, "DATA", "valid LZF-compressed data", f"corrupt stream at byte {i}") from None
    if len(out) != size:
        raise TypError(where, "DATA", f"{size} bytes after LZF decompression", len(out))
    return bytes(out)


def _to_points(p: Path, columns: dict[str, np.ndarray], n: int) -> tuple[np.ndarray, np.ndarray | None]:
    for name in ("x", "y", "z", "intensity", "semantic"):
        if name in columns and columns[name].ndim != 1:
            raise TypError(p, "COUNT", f"1 for field {name!r}", columns[name].shape[1])
    xyz = np.stack([columns[c].astype(np.float32) for c in "xyz"], axis=1)
    if "intensity" in columns:
        intensity = columns["intensity"].astype(np.float32)
    elif "rgb" in columns or "rgba" in columns:
        packed = columns.get("rgb", columns.get("rgba"))
        bits = packed.view(np.uint32) if packed.dtype == np.float32 else packed.astype(np.uint32)
        intensity = (((bits >> 16) & 0xFF) / 255.0).astype(np.float32)
    else:
        intensity = np.zeros(n, dtype=np.float32)
    semantics = None
    if "semantic" in columns:
        sem = columns["semantic"]
        if sem.dtype.kind == "f" or sem.min(initial=0) < 0 or sem.max(initial=0) > 255:
            raise TypError(p, "semantic", "unsigned integer codes 0..255", sem.dtype)
        semantics = sem.astype(np.uint8)
    keep = np.isfinite(xyz).all(axis=1)
    far = keep & (np.abs(xyz) > MAX_ABS_COORDINATE).any(axis=1)
    if far.any():
        raise TypError(p, "points",
                       f"x, y, z in metres in the sensor frame, |x|, |y|, |z| <= {MAX_ABS_COORDINATE:g} m",
                       f"{int(far.sum())} of {n} points beyond that (max {float(np.abs(xyz[far]).max()):.3g}); "
                       "the cloud may be in millimetres or in a world frame")
    points = np.concatenate([xyz, intensity[:, None]], axis=1)
    if not np.isfinite(points[keep, 3]).all():
        raise TypError(p, "intensity", "finite values", "NaN/Inf")
    if keep.all():
        return np.ascontiguousarray(points), semantics
    return np.ascontiguousarray(points[keep]), (semantics[keep] if semantics is not None else None)
