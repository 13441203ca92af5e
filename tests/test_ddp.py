"""Data-parallel training: 2 CPU processes (gloo) take the same steps as 1 process on the global batch.

Each rank draws the global batch from ``batch_rng(seed, step)``, trains on its shard
(``typ.distributed.shard``) and ``run_loop`` averages gradients before every Adam step; the
parameters after N steps must match a single process's within float tolerance, also when the
batch does not split evenly. Only rank 0 logs and writes checkpoints.
"""
from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import numpy as np
import torch
import torch.multiprocessing as mp
import torch.nn.functional as F

from tasks.training import batch_rng, checkpoints, run_loop
from typ import distributed

STEPS = 6


def _train(out: Path, batch_size: int) -> tuple[dict[str, torch.Tensor], list[int]]:
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(6, 16), torch.nn.Tanh(), torch.nn.Linear(16, 1))
    opt = torch.optim.Adam(model.parameters(), lr=0.05)
    data = np.random.default_rng(1)
    x = torch.from_numpy(data.standard_normal((40, 6)).astype(np.float32))
    y = torch.from_numpy(data.standard_normal((40, 1)).astype(np.float32))
    logged: list[int] = []

    def step_fn(step: int) -> dict[str, float]:
        index = distributed.shard(batch_rng(0, step).choice(len(x), size=batch_size, replace=False))
        loss = F.mse_loss(model(x[index]), y[index])
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return {"loss": float(loss.detach())}

    run_loop(name="ddp-test", total_steps=STEPS, step_fn=step_fn,
             get_state=lambda: {"model": model.state_dict(), "opt": opt.state_dict()},
             set_state=lambda s: (model.load_state_dict(s["model"]), opt.load_state_dict(s["opt"])),
             checkpoint_dir=out / "checkpoints", checkpoint_every=2, log_fn=lambda values, step: logged.append(step))
    return {k: v.detach().clone() for k, v in model.state_dict().items()}, logged


BATCHES = {"even": 8, "uneven": 5}  # a global batch of 5 splits 3 + 2 over two ranks


def _rank_main(rank: int, world: int, port: int, out: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    distributed.setup("cpu", "fp32")
    try:
        for case, batch_size in BATCHES.items():
            params, logged = _train(Path(out) / case, batch_size)
            torch.save(params, Path(out) / case / f"params_rank{rank}.pt")
            (Path(out) / case / f"logged_rank{rank}.json").write_text(json.dumps(logged))
    finally:
        distributed.teardown()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_gloo_ranks_match_one_process(tmp_path, one_torch_thread):
    ddp = tmp_path / "ddp"
    for case in BATCHES:
        (ddp / case).mkdir(parents=True)
    mp.spawn(_rank_main, args=(2, _free_port(), str(ddp)), nprocs=2, join=True)
    for case, batch_size in BATCHES.items():
        single, _ = _train(tmp_path / "single" / case, batch_size)
        for rank in (0, 1):
            got = torch.load(ddp / case / f"params_rank{rank}.pt")
            for name, value in single.items():
                torch.testing.assert_close(got[name], value, rtol=1e-5, atol=1e-6, msg=f"{case}, rank {rank}: {name}")
        # rank 0 logs every step and writes the checkpoints; rank 1 neither
        assert json.loads((ddp / case / "logged_rank0.json").read_text()) == list(range(STEPS))
        assert json.loads((ddp / case / "logged_rank1.json").read_text()) == []
        assert [s for s, _ in checkpoints(ddp / case / "checkpoints")] == [STEPS - 2, STEPS]


def test_shard_and_autocast_outside_torchrun():
    distributed.setup("cpu", "bf16")
    try:
        index = np.arange(7)
        assert distributed.shard(index) is index  # one process: the whole batch
        with distributed.autocast():
            out = torch.nn.Linear(4, 4)(torch.ones(2, 4))
        assert out.dtype == torch.bfloat16
    finally:
        distributed.setup("cpu", "fp32")
