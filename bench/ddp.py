"""Data-parallel training on the CPU: what sharding the global batch buys.

    python bench/ddp.py [--out reports] [--steps 24] [--batch 8]

Real stage-1 training steps (``tasks.stage1.train``: the tiny profile's UNet, global batch
--batch of random latents shaped like the tiny profile's, 8 x 16 x 16 with a 3 x 16 x 16
condition) in four set-ups, measured side by side in one run, each in its own process(es):

- ``1 process x 1 thread`` and ``1 process x all cores`` (torch intra-op threads);
- ``2 ranks x 1 thread, sharded``: two gloo processes (what ``torchrun --nproc_per_node 2``
  starts), each running its networks on its half of every batch (``typ.distributed.local_batch``);
- ``2 ranks x 1 thread, whole batch``: the same, but every rank runs the whole batch (what the
  stages did before they took their shard; gradients are still averaged, so the steps agree).

s/step: median time between consecutive logged steps after the first two (model building,
imports and process start-up excluded). Speed-up: the 1-process, 1-thread s/step over the
set-up's. max |Δθ|: the largest parameter difference to the 1-process, 1-thread run after the
same steps (float rounding only; ``tests/unit/typ/test_ddp.py`` checks the same within tolerance).
Writes ``<out>/bench_ddp.md`` and ``<out>/bench_ddp.png``.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

from flows.server import free_port  # noqa: E402
from typ.io import atomic_path, write_text  # noqa: E402

SETUPS = (("1 process x 1 thread", 1, 1, True), ("1 process x all cores", 1, 0, True),
          ("2 ranks x 1 thread, sharded", 2, 1, True), ("2 ranks x 1 thread, whole batch", 2, 1, False))


def _worker(rank: int, world: int, port: int, threads: int, sharded: bool, steps: int, batch: int, result: str):
    import numpy as np
    import torch

    from tasks import stage1
    from typ import distributed
    from typ.config import config_from_dict

    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank))
    torch.set_num_threads(threads or os.cpu_count() or 1)
    distributed.setup("cpu", "fp32")
    if not sharded:   # every rank runs the whole batch (the stages before local_batch)
        stage1.distributed.local_batch = lambda *rows: tuple(
            r.to(distributed.device()) if isinstance(r, torch.Tensor) else r for r in rows)
    try:
        cfg = config_from_dict({"stage1": {"batch_size": batch, "checkpoint_every": 10 ** 6,
                                           "epochs": steps}}).stage1
        n = batch  # steps_for(epochs, n, batch) = epochs steps
        gen = torch.Generator().manual_seed(0)
        latents = torch.randn(n, 8, 16, 16, generator=gen)
        cond = torch.randn(n, 3, 16, 16, generator=gen)
        stamps: list[float] = []
        with tempfile.TemporaryDirectory() as tmp:
            model = stage1.train(cfg, latents, cond, seed=cfg.seed, views=len(latents), out=Path(tmp),
                                 log_fn=lambda values, step: stamps.append(time.perf_counter()))
        if distributed.is_main():
            gaps = np.diff(stamps[2:])
            torch.save({"s_per_step": float(statistics.median(gaps)), "steps": len(stamps),
                        "threads": torch.get_num_threads(), "unet": str(list(cfg.unet.block_out_channels)),
                        "params": {k: v.clone() for k, v in model.state_dict().items()}}, result)
    finally:
        distributed.teardown()


def measure(steps: int, batch: int) -> list[dict]:
    import torch
    import torch.multiprocessing as mp

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, world, threads, sharded in SETUPS:
            result = str(Path(tmp) / f"{len(rows)}.pt")
            mp.spawn(_worker, args=(world, free_port(), threads, sharded, steps, batch, result),
                     nprocs=world, join=True)
            rows.append({"setup": name, **torch.load(result)})
    return compare(rows)


def compare(rows: list[dict]) -> list[dict]:
    """Speed-up and largest parameter difference of each set-up against the first (1 process x 1 thread)."""
    ref = rows[0]
    for r in rows:
        r["speedup"] = ref["s_per_step"] / r["s_per_step"]
        r["max_dparam"] = max(float((r["params"][k] - v).abs().max()) for k, v in ref["params"].items())
    return rows


def write(rows: list[dict], out: Path, steps: int, batch: int) -> Path:
    from typ.reporting import markdown_table, subplots

    lines = ["# Data-parallel training on the CPU (stage 1)", "",
             f"Stage-1 steps of the tiny UNet (block_out_channels {rows[0]['unet']}), global batch {batch}, "
             f"{steps} steps per set-up; {os.cpu_count()} cores. Method: `bench/ddp.py`.", "",
             markdown_table(["set-up", "s/step", "speed-up", "max abs param diff"],
                            ([r["setup"], f"{r['s_per_step']:.4f}", f"{r['speedup']:.2f}x", f"{r['max_dparam']:.1e}"]
                             for r in rows))]
    by = {r["setup"]: r for r in rows}
    sharded, whole = by["2 ranks x 1 thread, sharded"], by["2 ranks x 1 thread, whole batch"]
    threads = by["1 process x all cores"]
    lines += ["", f"- **Sharding the batch: {whole['s_per_step'] / sharded['s_per_step']:.2f}x faster steps "
                  f"with 2 ranks than every rank running the whole batch; 2 ranks vs 1 process on all cores: "
                  f"{threads['s_per_step'] / sharded['s_per_step']:.2f}x.**", ""]
    path = out / "bench_ddp.md"
    write_text(path, "\n".join(lines))
    fig, ax = subplots(figsize=(7, 3))
    ax.barh([r["setup"] for r in rows][::-1], [r["s_per_step"] for r in rows][::-1], color="tab:blue")
    ax.set_xlabel("seconds per training step (lower is better)")
    ax.set_title(f"stage-1 steps, global batch {batch}, {os.cpu_count()} cores")
    fig.tight_layout()
    with atomic_path(out / "bench_ddp.png") as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="reports", type=Path)
    parser.add_argument("--steps", type=int, default=24)
    parser.add_argument("--batch", type=int, default=8)
    args = parser.parse_args()
    rows = measure(args.steps, args.batch)
    path = write(rows, args.out, args.steps, args.batch)
    print(path.read_text())


if __name__ == "__main__":
    main()
