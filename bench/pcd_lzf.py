"""LZF decoding of binary_compressed PCDs: typ's compiled decoder against the pure-Python one it replaced.

    python bench/pcd_lzf.py [--out reports] [--repeats 5]

Same LZF payloads, one process, the two decoders taking turns:
- typ: ``typ.formats.pcd.lzf_decompress`` (a numba kernel, output bounded by the size the header
  promises).
- pure Python: the decoder typ used before the vectorised one, kept below verbatim as the baseline (a
  ``bytearray`` grown token by token; a back reference that overlaps its output is copied one
  period at a time, so a run of zeros at distance 1 costs one Python iteration per byte).

Payloads, each the ``binary_compressed`` data of a PCD written by Open3D (its own liblzf, so the
stream is one a user meets, not one typ's tests made): the real KITTI frames in shared/data when
present (x y z + reflectance as grey colour) and synthetic 64-beam-like clouds: 100k points
unorganised, and organised 64 x 2048 images with 40 %, 90 % and 100 % of their pixels without a
return, in runs, stored as zeros (long zero runs: the baseline's worst case, the one the issue
measured at about 30 s per compressed MB). Each case is timed ``--repeats`` times (fewer once a
decoder's calls pass ~3 s) after one untimed warm-up of typ (numba's compile or cache load,
reported apart); the table gives median seconds and the decoders' outputs are compared byte for
byte. Writes ``<out>/bench_pcd_lzf.md`` atomically and prints the table.
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

from typ.formats.pcd import lzf_decompress  # noqa: E402
from typ.io import write_text  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REAL = [("KITTI 000000", "kitti_object_vis/training/velodyne/000000.bin"),
        ("KITTI 000001", "kitti_object_vis/training/velodyne/000001.bin")]


def python_lzf_decompress(src: bytes, size: int) -> bytes:
    """typ's LZF decoder before the vectorised one (typ/formats/pcd.py at ccd3eeb), errors reduced to ValueError."""
    out = bytearray()
    i, end = 0, len(src)
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
            raise ValueError("corrupt stream")
        # a back reference may overlap the bytes it produces: copy in whole periods
        while length > 0:
            chunk = out[ref:ref + min(length, len(out) - ref)]
            out += chunk
            ref += len(chunk)
            length -= len(chunk)
    if len(out) != size:
        raise ValueError(f"{len(out)} bytes, not {size}")
    return bytes(out)


def synthetic_scan(empty: float, n_beams: int = 64, n_azimuths: int = 2048, seed: int = 0) -> np.ndarray:
    """(n_beams * n_azimuths, 4) float32 organised scan, row by row: ground below the horizon,
    obstacles, and a fraction ``empty`` of pixels without a return, in runs along the azimuth (open
    sky, a gap between buildings), all zeros as an organised cloud's empty pixels once NaN is replaced."""
    rng = np.random.default_rng(seed)
    elev = np.radians(np.linspace(-24.9, 2.0, n_beams))[:, None]
    az = np.linspace(-np.pi, np.pi, n_azimuths, endpoint=False)[None, :]
    r = np.where(elev < 0, 1.73 / np.tan(-np.minimum(elev, -1e-3)), 60.0) * np.ones_like(az)
    r = np.where(rng.random(r.shape) < 0.3, rng.uniform(3.0, 60.0, r.shape), np.minimum(r, 120.0))
    sector = rng.random((n_beams, n_azimuths // 64)) < empty  # runs of 64 empty pixels
    r = np.where(np.repeat(sector, 64, axis=1), 0.0, r)
    xyz = np.stack([r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az), r * np.sin(elev)], axis=-1)
    grey = np.where(r > 0, rng.random(r.shape), 0.0)
    return np.concatenate([xyz, grey[..., None]], axis=-1).astype(np.float32).reshape(-1, 4)


def clouds() -> list[tuple[str, np.ndarray]]:
    """(name, (N, 4) float32) clouds."""
    out = []
    for name, rel in REAL:
        path = DATA / rel
        if path.is_file():
            out.append((name, np.fromfile(path, dtype=np.float32).reshape(-1, 4)))
        else:
            print(f"skipping {name}: {path} not found", file=sys.stderr)
    scan = synthetic_scan(0.0)
    out.append(("synthetic 100k unorganised", scan[:100_000]))
    for empty in (0.4, 0.9, 1.0):
        out.append((f"synthetic 64x2048 organised, {empty:.0%} empty", synthetic_scan(empty, seed=1)))
    return out


def open3d_payload(points: np.ndarray) -> tuple[bytes, int]:
    """(LZF payload, inflated size) of the binary_compressed PCD Open3D writes for ``points``."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(points[:, :3].astype(np.float64))
    cloud.colors = o3d.utility.Vector3dVector(np.repeat(points[:, 3:4].astype(np.float64), 3, axis=1))
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "c.pcd"
        if not o3d.io.write_point_cloud(str(path), cloud, compressed=True):
            raise RuntimeError("Open3D could not write a compressed PCD")
        raw = path.read_bytes()
    body = raw[raw.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n"):]
    packed, unpacked = np.frombuffer(body[:8], dtype="<u4").tolist()
    return body[8:8 + packed], unpacked


def median_seconds(fn, repeats: int, budget_s: float = 3.0) -> tuple[float, bytes]:
    """Median seconds of ``fn()`` over ``repeats`` calls (fewer once they pass ``budget_s``), and its result."""
    times, result = [], b""
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
        if sum(times) > budget_s:
            break
    return statistics.median(times), result


def run(repeats: int, cases: list[tuple[str, np.ndarray]] | None = None) -> tuple[list[dict], dict]:
    t0 = time.perf_counter()
    lzf_decompress(bytes([0, 7]), 1)
    info = {"first_call_s": time.perf_counter() - t0}
    rows = []
    for name, points in clouds() if cases is None else cases:
        payload, size = open3d_payload(points)
        typ_s, ours = median_seconds(lambda: lzf_decompress(payload, size), repeats)
        python_s, theirs = median_seconds(lambda: python_lzf_decompress(payload, size), repeats)
        rows.append({"cloud": name, "points": len(points), "packed": len(payload), "raw": size,
                     "typ_s": typ_s, "python_s": python_s, "identical": ours == theirs})
    return rows, info


def table(rows: list[dict]) -> str:
    head = ("| cloud | points | compressed MB | inflated MB | pure Python s | typ s | speed-up "
            "| pure Python s / compressed MB | typ inflated MB/s | same bytes |")
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for r in rows:
        mb_packed, mb_raw = r["packed"] / 1e6, r["raw"] / 1e6
        lines.append(f"| {r['cloud']} | {r['points']:,} | {mb_packed:.2f} | {mb_raw:.2f} | {r['python_s']:.3f} "
                     f"| {r['typ_s']:.4f} | {r['python_s'] / r['typ_s']:,.0f}× | {r['python_s'] / mb_packed:.1f} "
                     f"| {mb_raw / r['typ_s']:,.0f} | {'yes' if r['identical'] else 'NO'} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="reports", help="folder for bench_pcd_lzf.md")
    ap.add_argument("--repeats", type=int, default=5, help="timed calls per decoder and case")
    args = ap.parse_args(argv)
    rows, info = run(args.repeats)
    text = table(rows)
    print(text)
    notes = (f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python "
             f"{platform.python_version()}, numpy {np.__version__}. typ's first call (numba compile or cache "
             f"load) took {info['first_call_s']:.2f} s and is not in the table.\n"
             "Seconds are medians of the repeats; 'same bytes': the two decoders' outputs are identical.\n")
    write_text(Path(args.out) / "bench_pcd_lzf.md",
               f"# PCD LZF decoding\n\n{__doc__.split(chr(10) * 2, 1)[1]}\n{notes}\n{text}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
