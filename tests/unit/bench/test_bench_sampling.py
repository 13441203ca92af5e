"""bench/sampling.py's pure helpers: Pareto front, the "within 2 % of DDIM-200" pick, tables.

The bench itself (training, sampling) is run by hand; these load the file without torch.
"""
from __future__ import annotations

import math

import pytest

from bench_modules import load_bench

bench = load_bench("sampling")


def row(sampler, steps, seconds, jsd, iou, mmd=1e-3, dp=0.01, iou_ref=0.9):
    return {"sampler": sampler, "steps": steps, "seconds": seconds, "jsd": jsd, "iou": iou, "mmd": mmd,
            "dp": dp, "iou_ref": iou_ref}


REF = row("ddim", 200, 2.0, 0.20, 0.50, dp=0.0, iou_ref=1.0)


def test_pareto_front_by_hand():
    # (cost, error): (3, 1) beats nothing cheaper; (2, 5) is beaten by (1, 4); (4, 1) ties (3, 1) on error
    points = [(2.0, 5.0), (1.0, 4.0), (3.0, 1.0), (4.0, 1.0), (1.5, 2.0)]
    assert bench.pareto_front(points) == [1, 4, 2]


def test_pareto_front_skips_nan_and_keeps_first_of_equal_points():
    assert bench.pareto_front([(1.0, math.nan), (2.0, 1.0), (2.0, 1.0)]) == [1]
    assert bench.pareto_front([]) == []


def test_fastest_within_picks_the_fastest_qualifying_row_at_most_20_steps():
    rows = [REF,
            row("unipc", 10, 0.20, 0.2039, 0.4901),   # just inside both 2 % bounds: qualifies
            row("dpmsolver++", 5, 0.10, 0.2100, 0.50),  # JSD 5 % worse
            row("ddim", 20, 0.30, 0.19, 0.55),          # better than the reference: qualifies
            row("ddim", 50, 0.01, 0.20, 0.50)]          # fastest, but over 20 steps
    assert bench.fastest_within(rows, REF)["sampler"] == "unipc"
    assert bench.fastest_within(rows[2:3], REF) is None
    assert bench.fastest_within([row("ddpm", 5, 0.1, 0.2, 0.48)], REF) is None  # IoU 4 % worse


def test_fastest_within_rejects_missing_metrics():
    assert bench.fastest_within([row("ddim", 5, 0.1, math.nan, 0.5)], REF) is None


def test_relative_gap_is_the_worse_of_jsd_and_iou():
    assert bench.relative_gap(row("ddim", 5, 0.1, 0.22, 0.49), REF) == pytest.approx(0.10)
    assert bench.relative_gap(row("ddim", 5, 0.1, 0.18, 0.40), REF) == pytest.approx(0.20)


def test_sampling_table_speedups_and_pareto_marks():
    rows = [REF, row("unipc", 10, 0.5, 0.21, 0.45), row("ddpm", 10, 0.5, 0.30, 0.30)]
    lines = bench.sampling_table(rows, REF, decode_s=0.25).splitlines()
    assert len(lines) == 2 + len(rows)
    assert all(line.count("|") == lines[0].count("|") for line in lines)
    unipc = lines[3].split(" | ")
    assert unipc[3] == "4.0×"      # 2.0 / 0.5
    assert unipc[4] == "7.0×"      # (2.0 - 0.25) / (0.5 - 0.25)
    assert lines[3].endswith("| JI |") and lines[4].endswith("|  |")
    assert lines[2].endswith("| JI |")  # the reference: nothing beats its JSD or IoU


def test_summary_line_found_and_not_found():
    spread = {"jsd": 0.21, "iou": 0.49}
    found = bench.summary_line("linear", [REF, row("unipc", 10, 0.1, 0.2, 0.5)], REF, spread)
    assert "unipc at 10 steps" in found and "20.0× faster" in found and "short" not in found
    slow = bench.summary_line("linear", [REF, row("unipc", 20, 0.5, 0.2, 0.5)], REF, spread)
    assert "4.0× faster (short of the 10× target)" in slow
    none = bench.summary_line("cosine", [REF, row("ddim", 5, 0.1, 0.3, 0.5)], REF, spread)
    assert "none at <= 20 steps" in none and "ddim 5 steps, JSD +50.0%" in none


def test_schedules_table_marks_missing_steps():
    results = {"linear": {"rows": [REF, row("ddim", 5, 0.1, 0.3, 0.4), row("unipc", 10, 0.1, 0.3, 0.4)]}}
    recon = {"jsd": 0.1, "mmd": 2e-4, "iou": 0.7}
    lines = bench.schedules_table(results, [5, 10, 200], recon).splitlines()
    assert lines[2] == "| linear | JSD ↓ | 0.3000 | – | 0.2000 |"
    assert lines[-1].startswith("| VQ-VAE reconstruction of the truth | JSD / MMD / IoU | 0.1000 / 2.00e-04 / 0.7000 |")


def test_parse_list():
    assert bench.parse_list("5, 10,20,", int) == [5, 10, 20]
    assert bench.parse_list("ddim,unipc") == ["ddim", "unipc"]


def test_plot_data_has_one_row_per_measured_setting_with_error_one_minus_iou(tmp_path):
    import csv

    results = {"linear": {"rows": [REF, row("unipc", 10, 0.25, 0.21, 0.40)]},
               "cosine": {"rows": [row("ddim", 5, 0.125, 0.3, 0.25)]}}
    path = bench.plot_data(results, tmp_path / "bench_sampling.csv")
    got = list(csv.DictReader(path.open()))
    assert [r["setting"] for r in got] == ["linear ddim-200", "linear unipc-10", "cosine ddim-5"]
    assert [float(r["seconds"]) for r in got] == [2.0, 0.25, 0.125]
    assert [float(r["error"]) for r in got] == [0.5, 0.6, 0.75]  # 1 - IoU
    assert [r["schedule"] for r in got] == ["linear", "linear", "cosine"]
