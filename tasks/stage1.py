"""Stage ``stage1`` (TYP Eq. 4): P(x|y), a latent diffusion model on the target domain's ego views.

x^f = E_x(x) and y^f = E_y(y) come from the frozen encoders (pre-quantization latents, as in
LDM; G_x quantizes when decoding). Every view is used under the 8 symmetries of the square
grid (:func:`tasks.voxel_data.apply_dihedral`): a spinning sensor at the centre sees a rotated
or mirrored street the same way. Training predicts ε (Eq. 4) with AdamW, a linear warm-up and
a cosine decay of the learning rate, and keeps an exponential moving average of the weights,
which is the model that samples (as LDM and diffusers' training scripts do). The
post-processing thresholds (TYP §4.1) are tuned on the validation split and stored with the
model. ``replicas`` models are trained with seeds ``seed, seed + 1, ...``, each in its own
folder ``<out>/seed_<s>/``; the first is the one later stages build on, the others give the
evaluation its spread over training seeds.
"""
from __future__ import annotations

import dataclasses
import itertools
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from models.ldm import LatentDiffusion
from models.postprocess import postprocess
from models.samplers import make_scheduler, sample
from models.schedules import alphas_cumprod, betas
from tasks.training import (EMA, Trainings, batch_rng, diffusion_loss, grad_norm, learning_rate, noised_batch,
                            run_checkpoint_dir, run_loop, seed_everything, set_learning_rate, steps_for)
from tasks.scene_stage import StageResult
from tasks.voxel_data import ViewSet, load_views
from typ import distributed
from typ.artifacts import load_module, save_module
from typ.config import Stage1Config, as_dict
from typ.errors import TypError
from typ.io import hash_obj, seed_dir
from typ.metrics.truth import occupancy_iou
from typ.registry import TARGET_VOXELS, declare

STAGE = "stage1"
#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare("stage1", data=(f"{TARGET_VOXELS}train", f"{TARGET_VOXELS}val", "artifacts/vqvae"),
                      outs=("artifacts/stage1",), loss_curves=True)


def replica_seeds(seed: int, replicas: int) -> list[int]:
    """The training seeds of a stage with ``replicas`` models: ``seed, seed + 1, ...``."""
    return [seed + k for k in range(replicas)]


def replica_dir(out: Path, seed: int) -> Path:
    """Where the model trained with ``seed`` lives: ``<out>/seed_<seed>``."""
    return seed_dir(out, seed)


def train_views(block: Stage1Config, root: Path) -> ViewSet:
    """The views stage 1 trains on: the training split's ego views, or every agent's (``ego_only``)."""
    return load_views(Path(root) / block.input, dataset=block.dataset, split=block.train_split,
                      ego_only=block.ego_only)


@torch.no_grad()
def encode_views(x_vq, y_vq, views: ViewSet, *, dihedral: bool = False,
                 batch_size: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """(x^f, y^f) pre-quantization latents of every view; with ``dihedral``, of each view under
    all 8 symmetries (8 N rows, symmetry-major). Encoded on the runtime device, returned on the CPU."""
    xs, ys = [], []
    with distributed.on_device(x_vq, y_vq) as dev:
        for k in (range(8) if dihedral else [0]):
            for start in range(0, len(views), batch_size):
                index = np.arange(start, min(start + batch_size, len(views)))
                x, y = views.batch(index, dihedral=np.full(len(index), k))
                xs.append(x_vq.encode_pre_quant(x.to(dev)).cpu())
                ys.append(y_vq.encode_pre_quant(y.to(dev)).cpu())
    return torch.cat(xs), torch.cat(ys)


def build(cfg: Stage1Config, latent_channels: int, cond_channels: int, sample_size: int) -> LatentDiffusion:
    u = cfg.unet
    return LatentDiffusion(latent_channels=latent_channels, cond_channels=cond_channels, sample_size=sample_size,
                           block_out_channels=u.block_out_channels, layers_per_block=u.layers_per_block,
                           cross_attention_dim=u.cross_attention_dim, attention_head_dim=u.attention_head_dim,
                           norm_num_groups=u.norm_num_groups, time_embedding=u.time_embedding,
                           self_attention=u.self_attention, coordinates=u.coordinates, prediction=cfg.prediction)


def check_latents(cfg: Stage1Config, sample_size: int, where: str) -> None:
    factor = 2 ** (len(cfg.unet.block_out_channels) - 1)
    if sample_size % factor:
        raise TypError(where, "stage1.unet.block_out_channels",
                       f"a downsampling factor ({factor}) that divides the latent size {sample_size}", factor)


def train(cfg: Stage1Config, latents: torch.Tensor, cond: torch.Tensor, *, seed: int, views: int, out: Path,
          log_fn: Callable[[dict, int], None]) -> LatentDiffusion:
    """Eq. 4: E_{t, ε} ||ε - ε_θ(√ᾱ_t x^f + √(1-ᾱ_t) ε, y^f, t)||², resuming from checkpoints.

    latents, cond: (N, c, h, w) training x^f and y^f (augmented rows included); views: how many
    distinct views they come from (an epoch is ``views / batch_size`` steps). Returns the EMA
    weights in eval mode.
    """
    seed_everything(seed)
    model = build(cfg, latents.shape[1], cond.shape[1], latents.shape[-1])
    model.set_statistics(latents, cond)
    ema = EMA(model, cfg.ema_decay)
    z0, c = model.normalize(latents), model.normalize_cond(cond)
    abar = torch.from_numpy(alphas_cumprod(betas(cfg.schedule, cfg.train_timesteps))).float()
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=0.0)
    total = steps_for(cfg.epochs, views, cfg.batch_size)
    key = hash_obj({"cfg": as_dict(cfg), "seed": seed, "latents": float(latents.double().sum()),
                    "cond": float(cond.double().sum()), "n": len(latents)})[:16]
    ckpt_dir = run_checkpoint_dir(seed_dir(out / "checkpoints", seed), key)

    def step_fn(step: int) -> dict[str, float]:
        lr = learning_rate(cfg.lr, step, total, warmup=cfg.warmup_steps, schedule=cfg.lr_schedule, floor=0.1)
        set_learning_rate(opt, lr)
        index, t, eps, z_t = noised_batch(batch_rng(seed, step), z0, abar, cfg.batch_size)
        t, eps, z_t, cond_t, z0_t = distributed.local_batch(t, eps, z_t, c[index], z0[index])
        dev = distributed.device()
        model.train()
        loss = diffusion_loss(model(z_t.to(dev), t.to(dev), cond_t.to(dev)), eps.to(dev), z0_t.to(dev), t, abar,
                              prediction=cfg.prediction, min_snr=cfg.min_snr)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        ema.update(model)
        return {"loss": float(loss.detach()), "grad_norm": grad_norm(model.parameters()), "lr": lr}

    with distributed.on_device(model, ema.shadow):
        run_loop(name=f"stage1 seed {seed}", total_steps=total, step_fn=step_fn,
                 state={"model": model, "ema": ema.shadow, "opt": opt},
                 checkpoint_dir=ckpt_dir, curve=Path(out) / "loss" / f"seed_{seed}.csv", checkpoint_every=cfg.checkpoint_every,
                 log_fn=lambda values, step: log_fn({f"stage1.seed_{seed}.{k}": v for k, v in values.items()}, step))
    return ema.shadow.eval()


@torch.no_grad()
def sample_logits(model: LatentDiffusion, x_vq, cond: torch.Tensor, *, cfg: Stage1Config,
                  generator: torch.Generator, adapter_features: list[torch.Tensor] | None = None,
                  num_steps: int | None = None, sampler: str | None = None) -> torch.Tensor:
    """Sample x^f for a batch of y^f (pre-quant, unnormalised) and decode: logits (B, C, H, W) on
    the CPU, sampled on the runtime device under its autocast precision.

    y^f is normalised once for the whole reverse process (it does not change across steps).
    """
    scheduler = make_scheduler(sampler or cfg.sampler, betas(cfg.schedule, cfg.train_timesteps),
                               prediction_type=model.config.get("prediction", "epsilon"))
    with distributed.on_device(model, x_vq) as dev, distributed.autocast():
        c = model.normalize_cond(cond.to(dev))
        features = None if adapter_features is None else [f.to(dev) for f in adapter_features]
        z = sample(model, scheduler, shape=(cond.shape[0], model.config["latent_channels"], *cond.shape[2:]),
                   num_steps=num_steps or cfg.sample_steps, generator=generator, cond=c,
                   adapter_features=features, eta=cfg.eta if (sampler or cfg.sampler) == "ddim" else 0.0, device=dev)
        return x_vq.decode_latents(model.denormalize(z)).float().cpu()


def tune_thresholds(logits: torch.Tensor, truth: torch.Tensor, cfg: Stage1Config, seed: int) -> dict:
    """Grid search low <= high over ``postprocess.candidates`` for the best voxel IoU to truth."""
    best = None
    truth_np = truth.numpy() > 0.5
    for low, high in itertools.combinations_with_replacement(sorted(cfg.postprocess.candidates), 2):
        occ = postprocess(logits, low=low, high=high, noise_std=cfg.postprocess.noise_std,
                          generator=torch.Generator().manual_seed(seed)).numpy()
        iou = occupancy_iou(occ, truth_np)["iou"]
        if best is None or (iou == iou and iou > best["iou"]):
            best = {"low": low, "high": high, "iou": iou}
    return {**best, "noise_std": cfg.postprocess.noise_std}


def sampling_config(cfg: Stage1Config, saved: dict, sampler: str, steps: int) -> Stage1Config:
    """Stage 1's sampling settings with another sampler and step count, for the model ``saved``
    (:func:`load_model`): its own β schedule and T, whatever params.yaml says now; DDIM's η = 0."""
    return dataclasses.replace(cfg, sampler=sampler, sample_steps=steps, schedule=saved["schedule"],
                               train_timesteps=saved["train_timesteps"], eta=0.0)


def save_model(model: LatentDiffusion, cfg: Stage1Config, thresholds: dict, folder: Path) -> None:
    save_module(folder, model, model.config, schedule=cfg.schedule, train_timesteps=cfg.train_timesteps,
                postprocess=thresholds)


def load_model(folder: Path) -> tuple[LatentDiffusion, dict]:
    """(the EMA model, its saved fields: ``schedule``, ``train_timesteps``, ``postprocess``)."""
    return load_module(folder, LatentDiffusion.from_config, STAGE)


def run(cfg, root: Path, *, run, trainings: Trainings = Trainings()) -> StageResult:
    """The stage (:mod:`flows.generic`): the target ego views encoded, P(x|y) trained per replica
    seed (each a task of ``trainings``), its post-processing thresholds tuned on the val split,
    saved, and the first seed's network logged as an MLflow model of ``run``."""
    from tasks.vqvae import load_model as load_vqvae

    block = cfg.stage1
    store, out = Path(root) / block.input, Path(root) / block.out
    x_vq, y_vq = (load_vqvae(Path(root) / block.vqvae / k) for k in ("x", "y"))
    views = train_views(block, Path(root))
    val = load_views(store, dataset=block.dataset, split=block.val_split).head(block.eval_views)
    metrics: dict = {"train_views": len(views), "val_views": len(val)}
    latents, cond = trainings.step("encode", lambda: encode_views(x_vq, y_vq, views, dihedral=True))
    check_latents(block, latents.shape[-1], cfg.source)
    val_true, _ = val.batch(np.arange(len(val)))
    _, val_cond = encode_views(x_vq, y_vq, val)
    for seed in replica_seeds(block.seed, block.replicas):
        t0 = time.perf_counter()
        model = trainings.run(f"train-ldm-seed{seed}", lambda: train(
            block, latents, cond, seed=seed, views=len(views), out=out, log_fn=run.metrics))
        seconds = time.perf_counter() - t0
        logits = trainings.step("sample-val", lambda: sample_logits(
            model, x_vq, val_cond, cfg=block, generator=torch.Generator().manual_seed(seed + 1)))
        thresholds = tune_thresholds(logits, val_true, block, seed)
        save_model(model, block, thresholds, replica_dir(out, seed))
        metrics[f"seed_{seed}"] = {"seconds_training": round(seconds, 3), "val_iou": thresholds["iou"],
                                   "postprocess": thresholds}
        if seed == block.seed:
            run.log_model("stage1-ldm", model, {"z_t": model.normalize(latents[:2]),
                                                "t": torch.tensor([0, block.train_timesteps - 1]),
                                                "cond": model.normalize_cond(cond[:2])})
    return StageResult(metrics, artifacts=[replica_dir(out, block.seed) / "config.json"])
