"""bench/attention.py: one round runs, and its page reports what the run measured."""
from __future__ import annotations

from bench_modules import load_bench

bench = load_bench("attention")


def test_one_round_measures_both_processors_and_renders():
    result = bench.run("tiny", rounds=1, steps=1)
    assert set(result["seconds"]) == {bench.FAST, bench.BASELINE}
    assert all(s["train"] > 0 and s["sample"] > 0 for s in result["seconds"].values())
    assert result["forward_diff"] < 1e-5                     # the same network, whichever processor
    assert result["weights_diff"] < 1e-3                     # trained apart by float rounding only
    page = bench.table(result)
    assert f"| {bench.BASELINE} | {result['seconds'][bench.BASELINE]['train']:.3f} | 1.00x |" in page
    assert page.count("| typ (one-token short-cut) |") == 1
