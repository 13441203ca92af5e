"""Data-parallel training: 2 CPU processes (gloo) take the same steps as 1 process on the global batch.

Each rank draws the global batch from ``batch_rng(seed, step)``, trains on its shard
(``typ.distributed.shard``) and ``run_loop`` averages gradients before every Adam step; the
parameters after N steps must match a single process's within float tolerance, also when the
batch does not split evenly. Only rank 0 logs and writes checkpoints. The real stage-1 and
adaptation steps do the same, each rank's networks seeing only its half of every batch.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch
import torch.multiprocessing as mp
import torch.nn.functional as F

from flows.server import free_port
from models.discriminator import LatentDiscriminator
from models.ldm import LatentDiffusion
from models.vqvae import BEVVQVAE
from tasks import adapt, stage1
from tasks.training import batch_rng, checkpoints, run_loop
from tasks.voxel_data import ViewSet
from typ import distributed
from typ.config import config_from_dict
from typ.voxel import Grid

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
             state={"model": model, "opt": opt},
             checkpoint_dir=out / "checkpoints", checkpoint_every=2, log_fn=lambda values, step: logged.append(step))
    return {k: v.detach().clone() for k, v in model.state_dict().items()}, logged


BATCHES = {"even": 8, "uneven": 5}  # a global batch of 5 splits 3 + 2 over two ranks
GRID = Grid((-16.0, 16.0), (-16.0, 16.0), (-3.0, 1.0), (32, 32, 4))


def _rows_seen(kind: type, rows: list[int]):
    """Record the batch size of every forward of a ``kind`` module (the networks a stage builds)."""
    return torch.nn.modules.module.register_module_forward_pre_hook(
        lambda module, args: rows.append(int(args[0].shape[0])) if isinstance(module, kind) else None)


def _stage1(out: Path) -> tuple[dict[str, torch.Tensor], list[int]]:
    """Four real stage-1 steps (Eq. 4) on a global batch of 4 latents."""
    cfg = config_from_dict({"stage1": {"unet": {"block_out_channels": [8, 8], "norm_num_groups": 4,
                                                 "cross_attention_dim": 8, "attention_head_dim": 4},
                                        "epochs": 2, "batch_size": 4, "checkpoint_every": 100}}).stage1
    gen = torch.Generator().manual_seed(1)
    x, y = torch.randn(8, 4, 8, 8, generator=gen), torch.randn(8, 3, 8, 8, generator=gen)
    rows: list[int] = []
    handle = _rows_seen(LatentDiffusion, rows)
    try:
        model = stage1.train(cfg, x, y, seed=cfg.seed, views=len(x), out=out, log_fn=lambda values, step: None)
    finally:
        handle.remove()
    return {k: v.detach().clone() for k, v in model.state_dict().items()}, rows


def _views(seed: int) -> ViewSet:
    rng = np.random.default_rng(seed)
    records = [(np.argwhere(rng.random(GRID.shape) < 0.1), np.zeros((0, 2), dtype=np.intp)) for _ in range(4)]
    return ViewSet(GRID, [("s", str(i), "000000") for i in range(4)], records)


def _adapt(out: Path) -> tuple[dict[str, torch.Tensor], list[int]]:
    """Real adaptation steps (Eq. 8–10): discriminator and source VQ, two optimizers, batch of 4."""
    cfg = config_from_dict({"adapt": {"epochs": 3, "batch_size": 4, "checkpoint_every": 100,
                                      "disc_width": 8}}).adapt
    torch.manual_seed(0)
    target = BEVVQVAE(in_channels=4, latent_channels=3, block_out_channels=(8, 8), num_codes=16, norm_num_groups=4)
    rows: list[int] = []
    handle = _rows_seen(LatentDiscriminator, rows)
    try:
        source, disc = adapt.train(cfg, target, _views(1), _views(2), out=out, log_fn=lambda values, step: None)
    finally:
        handle.remove()
    state = {f"source.{k}": v for k, v in source.state_dict().items()}
    state.update({f"disc.{k}": v for k, v in disc.state_dict().items()})
    return {k: v.detach().clone() for k, v in state.items()}, rows


STAGES = {"stage1": _stage1, "adapt": _adapt}


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
        for name, run in STAGES.items():
            params, rows = run(Path(out) / name / f"rank{rank}")
            torch.save({"params": params, "rows": rows}, Path(out) / name / f"rank{rank}.pt")
    finally:
        distributed.teardown()


def test_two_gloo_ranks_match_one_process(tmp_path, one_torch_thread):
    ddp = tmp_path / "ddp"
    for case in (*BATCHES, *STAGES):
        (ddp / case).mkdir(parents=True)
    mp.spawn(_rank_main, args=(2, free_port(), str(ddp)), nprocs=2, join=True)
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
    for name, run in STAGES.items():
        single, single_rows = run(tmp_path / "single" / name)
        for rank in (0, 1):
            got = torch.load(ddp / name / f"rank{rank}.pt")
            # every forward on a rank saw half of what the one process's forward saw
            assert got["rows"] == [n // 2 for n in single_rows] and single_rows, (name, got["rows"], single_rows)
            for key, value in single.items():
                torch.testing.assert_close(got["params"][key], value, rtol=1e-4, atol=1e-5,
                                           msg=f"{name}, rank {rank}: {key}")


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
