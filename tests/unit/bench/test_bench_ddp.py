"""bench/ddp.py's comparison and page (the timed runs themselves happen in `make bench`)."""
import torch

from bench_modules import load_bench

ddp_bench = load_bench("ddp")


def test_speedups_parameter_differences_and_verdict(tmp_path):
    params = {"w": torch.zeros(3), "b": torch.zeros(1)}
    seconds = [0.4, 0.25, 0.2, 0.5]
    rows = [{"setup": name, "s_per_step": s, "unet": "[8, 8]",
             "params": {"w": torch.tensor([0.0, 3e-6 * k, 0.0]), "b": torch.zeros(1)} if k else params}
            for k, ((name, *_), s) in enumerate(zip(ddp_bench.SETUPS, seconds))]
    rows = ddp_bench.compare(rows)
    assert [round(r["speedup"], 3) for r in rows] == [1.0, 1.6, 2.0, 0.8]
    assert [round(r["max_dparam"], 9) for r in rows] == [0.0, 3e-6, 6e-6, 9e-6]  # float32 params
    text = ddp_bench.write(rows, tmp_path, steps=4, batch=8).read_text()
    assert "| 2 ranks x 1 thread, sharded | 0.2000 | 2.00x | 6.0e-06 |" in text
    # whole batch 0.5 s vs sharded 0.2 s; all cores 0.25 s vs sharded 0.2 s
    assert "2.50x faster steps" in text and "1.25x" in text
    assert (tmp_path / "bench_ddp.png").stat().st_size > 1000
