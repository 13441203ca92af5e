"""bench/pcd_lzf.py: its baseline decodes as typ does, and one small case runs end to end."""
from __future__ import annotations

import numpy as np
import pytest

from bench_modules import load_bench
from lzf_reference import lzf_compress
from typ.formats.pcd import lzf_decompress

bench = load_bench("pcd_lzf")


def test_the_baseline_and_typ_decode_the_same_bytes():
    rng = np.random.default_rng(0)
    for data in (bytes(5000), bench.synthetic_scan(0.5, n_beams=4, n_azimuths=256).tobytes(),
                 bytes(rng.integers(0, 256, 3000, dtype=np.uint8))):
        packed = lzf_compress(data)
        assert bench.python_lzf_decompress(packed, len(data)) == lzf_decompress(packed, len(data)) == data


def test_a_small_case_runs_and_renders(tmp_path):
    pytest.importorskip("open3d")
    cloud = bench.synthetic_scan(0.9, n_beams=8, n_azimuths=256, seed=2)
    rows, info = bench.run(1, cases=[("small", cloud)])
    (row,) = rows
    assert row["identical"] and row["points"] == 8 * 256 and row["raw"] == 8 * 256 * 16  # xyz float32 + rgb
    assert info["first_call_s"] >= 0
    assert "| small | 2,048 |" in bench.table(rows)
