"""bench/gpu.py's measurements of the networks: samples/s of each stage's real training step, timed
by differences of step counts so that a warm-up or a one-off cost does not count; the generator at
the bench's size; voxelization on the device; and the determinism check (two runs, same bytes).
Imported beside bench/gpu.py (``import gpu_timers``), as bench/gpu_bundle.py is."""
from __future__ import annotations

import tempfile
import time
import warnings
from pathlib import Path

import gpu_bundle
import numpy as np


def per_step_rate(train, *, warmup: int, timed: int) -> float:
    """Steps/s of the steps after ``warmup`` of ``train(steps, log_fn)``, whose log_fn is called
    after every step (the stage reads the loss, so each stamp follows a finished step)."""
    stamps: list[float] = []
    train(warmup + timed, lambda values, step: stamps.append(time.perf_counter()))
    return (len(stamps) - warmup) / (stamps[-1] - stamps[warmup - 1])


def difference_rate(train, *, warmup: int, timed: int) -> float:
    """Steps/s from two runs of ``train(steps)`` (``warmup`` and ``warmup + timed`` steps): for the
    stages that do not log every step; their set-up cancels. Their networks are the tiny profile's:
    at least 2 + 6 steps, so that one slow step does not make the figure."""
    warmup, timed = max(warmup, 2), max(timed, 6)
    seconds = []
    for steps in (warmup, warmup + timed):
        t0 = time.perf_counter()
        train(steps)
        seconds.append(time.perf_counter() - t0)
    return timed / (seconds[1] - seconds[0])


def network_timers(cfg, tiny, bundle, scratch: Path, batch: dict) -> dict:
    """name -> (batch, rate(warmup, timed) -> steps/s): each network's step through its stage."""
    import dataclasses

    import torch

    from tasks import adapt, ddpm, fusion_train, ssc, stage1, stage2, vqvae
    from tasks.fusion_batch import Inputs
    from tasks.fusion_data import FusionDataset

    def folder(name):
        return Path(tempfile.mkdtemp(prefix=f"{name}-", dir=scratch))

    def vqvae_rate(warmup, timed):
        b = batch["vqvae"]
        block = dataclasses.replace(cfg.vqvae, batch_size=b, checkpoint_every=10 ** 6)
        views = bundle.train.head(b)

        def train(steps, log):
            c = dataclasses.replace(block, x=dataclasses.replace(block.x, epochs=steps))
            vqvae.train_one("x", c, views, out=folder("vqvae"), log_fn=log)
        return per_step_rate(train, warmup=warmup, timed=timed)

    size = cfg.voxelize.grid.shape[0] // 2 ** (len(cfg.vqvae.x.block_out_channels) - 1)
    c_x = cfg.vqvae.x.latent_channels

    def latents(n):
        gen = torch.Generator().manual_seed(0)
        return [torch.randn(n, c, size, size, generator=gen) for c in (c_x, 1, c_x)]

    def stage1_rate(warmup, timed):
        b = batch["stage1"]
        x, y, _ = latents(b)

        def train(steps, log):
            c = dataclasses.replace(cfg.stage1, epochs=steps, batch_size=b, checkpoint_every=10 ** 6)
            stage1.train(c, x, y, seed=0, views=b, out=folder("stage1"), log_fn=log)
        return per_step_rate(train, warmup=warmup, timed=timed)

    def stage2_rate(warmup, timed):
        b = batch["stage2"]
        x, y, ego = latents(b)
        ldm = stage1.build(cfg.stage1, c_x, 1, size)
        ldm.set_statistics(x, y)

        def train(steps, log):
            settings = dataclasses.replace(stage2.settings_of(cfg.stage2, 0, 0.0), epochs=steps, batch_size=b,
                                           checkpoint_every=10 ** 6)
            stage2.fit_adapter(stage2.build_adapter(ldm, res_blocks=cfg.stage2.adapter_res_blocks, seed=0), ldm,
                               "linear", 1000, stage2.Latents(x, y, ego), name="adapter", settings=settings, views=b,
                               key_extra={}, out=folder("stage2"), log_fn=log)
        return per_step_rate(train, warmup=warmup, timed=timed)

    def adapt_rate(warmup, timed):
        b = batch["adapt"]
        target = vqvae.build("x", cfg.vqvae.x, bundle.train.grid.shape[2])

        def train(steps, log):
            c = dataclasses.replace(cfg.adapt, epochs=steps, batch_size=b, checkpoint_every=10 ** 6)
            adapt.train(c, target, bundle.source.head(b), bundle.train.head(b), out=folder("adapt"), log_fn=log)
        return per_step_rate(train, warmup=warmup, timed=timed)

    cav = scratch / "cav" / "train"
    if not cav.is_dir():
        gpu_bundle.synthetic_cav_scenario(cav, seed=0, agents=3, frames=2, points=40000)

    def fusion_rate(method):
        def rate(warmup, timed):
            block = dataclasses.replace(tiny.fusion, batch_size=batch["fusion"], checkpoint_every=10 ** 6)
            data = FusionDataset(cav, lidar_range=block.detector.lidar_range, comm_range=block.comm_range, seed=0)
            inputs = Inputs(list(data), block)
            return difference_rate(lambda steps: fusion_train.train(method, block, inputs, steps=steps,
                                                                    out=folder("fusion"), name=method),
                                   warmup=warmup, timed=timed)
        return rate

    def ssc_rate(warmup, timed):
        block = tiny.ssc
        data = ssc.TrainingSet.read(ssc.ssc_dataset(cav))
        weights = ssc.class_weights(data.class_counts(), eps=block.class_weight_eps)
        return difference_rate(lambda steps: ssc.train_single(data, steps=steps, seed=0, lr=block.lr,
                                                              model_kw=ssc.model_kwargs(block), weights=weights),
                               warmup=warmup, timed=timed)

    def ddpm_rate(warmup, timed):
        block = dataclasses.replace(tiny.ddpm, batch_size=batch["ddpm"], checkpoint_every=10 ** 6)
        run_cfg = block.configs[0]
        rep = ddpm.representations(block)[run_cfg.representation]
        pixels = torch.rand(batch["ddpm"], *rep.shape, generator=torch.Generator().manual_seed(0)) * 2 - 1

        def train(steps, log):
            ddpm.train_model(dataclasses.replace(block, steps=steps), run_cfg, rep, 0, pixels, ["timing"],
                             out=folder("ddpm"), log_fn=log)
        return per_step_rate(train, warmup=warmup, timed=timed)

    return {"x VQ-VAE": ("vqvae", vqvae_rate), "stage-1 UNet": ("stage1", stage1_rate),
            "adaptation (E_src, G_src and D)": ("adapt", adapt_rate),
            "stage-2 / self-training adapter": ("stage2", stage2_rate),
            "PointPillars (no / late fusion)": ("fusion", fusion_rate("late")),
            "AttFuse": ("fusion", fusion_rate("attfuse")), "SSC single-agent network": ("ssc", ssc_rate),
            "pixel DDPM (range image)": ("ddpm", ddpm_rate)}


def generator_at_size(cfg, bundle):
    """A TYPPipeline of freshly initialised networks at bench/gpu.yaml's size (timing only)."""
    import torch

    from models.vqvae import PooledBoxMap
    from tasks import stage1, stage2, vqvae
    from pipelines.typ.pipeline_typ import PointStats, TYPPipeline

    torch.manual_seed(0)
    x_vq = vqvae.build("x", cfg.vqvae.x, bundle.train.grid.shape[2]).eval()
    factor = 2 ** (len(cfg.vqvae.x.block_out_channels) - 1)
    size = bundle.train.grid.shape[0] // factor
    ldm = stage1.build(cfg.stage1, cfg.vqvae.x.latent_channels, 1, size).eval()
    adapter = stage2.build_adapter(ldm, res_blocks=cfg.stage2.adapter_res_blocks, seed=0).eval()
    return TYPPipeline(x_vq, PooledBoxMap(downsample=factor), ldm, adapter, bundle.train.grid, cfg.stage1.schedule,
                       cfg.stage1.train_timesteps, "dpmsolver++", 10, {"low": 0.5, "high": 0.5, "noise_std": 0.0},
                       PointStats.single())


def device_voxelize(points, grid, device):
    """typ.voxel.voxelize's bins (module doc there) with torch on ``device``: (H, W, C) bool."""
    import torch

    p = torch.as_tensor(points[:, :3], device=device).double()
    lo = torch.as_tensor(grid.lower, device=device)
    size = torch.as_tensor(grid.voxel_size, device=device)
    shape = torch.as_tensor(grid.shape, device=device)
    idx = torch.floor((p - lo) / size).long()
    edge = lo + idx.double() * size       # a point within rounding of an edge goes where the edges put it
    idx = idx - (p < edge).long() + (p >= edge + size).long()
    keep = ((idx >= 0) & (idx < shape)).all(1) & (p < torch.as_tensor(grid.upper, device=device)).all(1)
    idx = idx[keep]
    out = torch.zeros(grid.shape, dtype=torch.bool, device=device)
    out[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return out


def determinism(cfg, bundle, scratch: Path) -> dict:
    """Two identical short trainings of the stage-1 UNet and of the x VQ-VAE on CUDA, with
    typ's reproducibility flags on and off: how far apart their weights end, the time per run,
    and the ops torch ran without a deterministic kernel (its warnings)."""
    import dataclasses

    import torch

    from tasks import stage1, vqvae
    from typ import distributed

    size = cfg.voxelize.grid.shape[0] // 2 ** (len(cfg.vqvae.x.block_out_channels) - 1)
    gen = torch.Generator().manual_seed(0)
    x, y = torch.randn(8, cfg.vqvae.x.latent_channels, size, size, generator=gen), torch.randn(8, 1, size, size)

    def unet(folder):
        c = dataclasses.replace(cfg.stage1, epochs=12, batch_size=8, checkpoint_every=10 ** 6)
        return stage1.train(c, x, y, seed=0, views=8, out=folder, log_fn=lambda v, s: None)

    def vq(folder):
        block = dataclasses.replace(cfg.vqvae, batch_size=4, checkpoint_every=10 ** 6,
                                    x=dataclasses.replace(cfg.vqvae.x, epochs=6))
        return vqvae.train_one("x", block, bundle.train.head(4), out=folder, log_fn=lambda v, s: None)

    out = {}
    for flags in (True, False):
        distributed.setup("cuda", "bf16")
        distributed.reproducible_cuda(flags)
        row = {}
        for name, train in (("stage-1 UNet, 12 steps", unet), ("x VQ-VAE, 6 steps", vq)):
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                weights, seconds = [], []
                for _ in range(2):
                    t0 = time.perf_counter()
                    weights.append(torch.cat([t.double().reshape(-1) for t in train(Path(tempfile.mkdtemp(
                        dir=scratch))).state_dict().values() if t.is_floating_point()]))
                    seconds.append(time.perf_counter() - t0)
            diff = (weights[1] - weights[0]).abs()
            row[name] = {"max_abs_diff": float(diff.max()), "bitwise_equal": bool(diff.max() == 0),
                         "relative_l2": float(torch.linalg.vector_norm(weights[1] - weights[0])
                                              / torch.linalg.vector_norm(weights[0])),
                         "seconds_per_run": round(float(np.mean(seconds)), 3),
                         "nondeterministic_ops": sorted({str(w.message).split(" does not have")[0][:120]
                                                         for w in caught if "deterministic" in str(w.message)})}
        out["flags on" if flags else "flags off"] = row
    distributed.reproducible_cuda(True)
    return out


# ------------------------------------------------------------------ phase: train
