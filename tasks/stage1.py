"""Stage ``stage1`` (TYP Eq. 4): P(x|y), a latent diffusion model on the target domain's ego views.

x^f = E_x(x) and y^f = E_y(y) come from the frozen VQ-VAEs (pre-quantization latents, as in
LDM; G_x quantizes when decoding). Training predicts ε (Eq. 4); the post-processing
thresholds (TYP §4.1) are tuned on the validation split and stored with the model; the
held-out split is sampled for the stage metrics. Output: ``<out>/model.pt`` (config,
weights, schedule, thresholds), ``<out>/postprocess.json``, ``<out>/checkpoints/<key>/``.
"""
from __future__ import annotations

import dataclasses

import itertools
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from models.ldm import LatentDiffusion
from models.postprocess import postprocess
from models.samplers import make_scheduler, sample
from models.schedules import alphas_cumprod, betas
from models.vqvae import BEVVQVAE
from tasks.training import batch_rng, grad_norm, load_torch, run_checkpoint_dir, run_loop, save_torch, seed_everything, steps_for
from tasks.voxel_data import ViewSet
from typ import distributed
from typ.config import Stage1Config, as_dict
from typ.errors import TypError
from typ.io import hash_obj, write_json
from typ.metrics import chamfer_distance, jsd_bev, mmd_bev, occupancy_iou
from typ.voxel import Grid, voxel_centers


@torch.no_grad()
def encode_views(x_vq: BEVVQVAE, y_vq: BEVVQVAE, views: ViewSet, *, mirror: bool = False,
                 batch_size: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """(x^f, y^f) pre-quantization latents of every view, optionally with mirrored copies."""
    xs, ys = [], []
    for flip in ([False, True] if mirror else [False]):
        for start in range(0, len(views), batch_size):
            index = np.arange(start, min(start + batch_size, len(views)))
            x, y = views.batch(index, flips=np.full(len(index), flip))
            xs.append(x_vq.encode_pre_quant(x))
            ys.append(y_vq.encode_pre_quant(y))
    return torch.cat(xs), torch.cat(ys)


def build(cfg: Stage1Config, latent_channels: int, cond_channels: int, sample_size: int) -> LatentDiffusion:
    u = cfg.unet
    return LatentDiffusion(latent_channels=latent_channels, cond_channels=cond_channels, sample_size=sample_size,
                           block_out_channels=u.block_out_channels, layers_per_block=u.layers_per_block,
                           cross_attention_dim=u.cross_attention_dim, attention_head_dim=u.attention_head_dim,
                           norm_num_groups=u.norm_num_groups, time_embedding=u.time_embedding)


def check_latents(cfg: Stage1Config, sample_size: int, where: str) -> None:
    factor = 2 ** (len(cfg.unet.block_out_channels) - 1)
    if sample_size % factor:
        raise TypError(where, "stage1.unet.block_out_channels",
                       f"a downsampling factor ({factor}) that divides the latent size {sample_size}", factor)


def noised_batch(rng: np.random.Generator, z0: torch.Tensor, abar: torch.Tensor, batch_size: int):
    """One training batch of the forward process q(z_t | z_0) = N(√ᾱ_t z_0, (1 - ᾱ_t) I).

    Returns (index (B,), t (B,), ε (B, ...), z_t) drawn from ``rng`` alone, so resumed runs
    draw the same batches.
    """
    index = torch.from_numpy(rng.choice(len(z0), size=batch_size, replace=len(z0) < batch_size))
    t = torch.from_numpy(rng.integers(0, len(abar), batch_size))
    eps = torch.from_numpy(rng.standard_normal(z0[index].shape).astype(np.float32))
    a = abar[t].view(-1, 1, 1, 1)
    return index, t, eps, a.sqrt() * z0[index] + (1 - a).sqrt() * eps


def train(cfg: Stage1Config, latents: torch.Tensor, cond: torch.Tensor, *, out: Path,
          log_fn: Callable[[dict, int], None]) -> LatentDiffusion:
    """Eq. 4: E_{t, ε} ||ε - ε_θ(√ᾱ_t x^f + √(1-ᾱ_t) ε, y^f, t)||², resuming from checkpoints."""
    seed_everything(cfg.seed)
    model = build(cfg, latents.shape[1], cond.shape[1], latents.shape[-1])
    model.set_statistics(latents, cond)
    z0, c = model.normalize(latents), model.normalize_cond(cond)
    abar = torch.from_numpy(alphas_cumprod(betas(cfg.schedule, cfg.train_timesteps))).float()
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr)
    total = steps_for(cfg.epochs, len(z0), cfg.batch_size)
    key = hash_obj({"cfg": as_dict(cfg), "latents": float(latents.double().sum()), "n": len(latents)})[:16]
    ckpt_dir = run_checkpoint_dir(out / "checkpoints", key)

    def step_fn(step: int) -> dict[str, float]:
        index, t, eps, z_t = noised_batch(batch_rng(cfg.seed, step), z0, abar, cfg.batch_size)
        t, eps, z_t, cond_t = distributed.local_batch(t, eps, z_t, c[index])
        model.train()
        loss = F.mse_loss(model(z_t, t, cond_t), eps)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        norm = grad_norm(model.parameters())
        return {"loss": float(loss.detach()), "grad_norm": norm}

    with distributed.on_device(model):
        run_loop(name="stage1", total_steps=total, step_fn=step_fn,
                 get_state=lambda: {"model": model.state_dict(), "opt": opt.state_dict()},
                 set_state=lambda s: (model.load_state_dict(s["model"]), opt.load_state_dict(s["opt"])),
                 checkpoint_dir=ckpt_dir, checkpoint_every=cfg.checkpoint_every,
                 log_fn=lambda values, step: log_fn({f"stage1.{k}": v for k, v in values.items()}, step))
    return model.eval()


@torch.no_grad()
def sample_logits(model: LatentDiffusion, x_vq: BEVVQVAE, cond: torch.Tensor, *, cfg: Stage1Config,
                  generator: torch.Generator, adapter_features: list[torch.Tensor] | None = None,
                  num_steps: int | None = None, sampler: str | None = None) -> torch.Tensor:
    """Sample x^f for a batch of y^f (pre-quant, unnormalised) and decode: logits (B, C, H, W).

    y^f is normalised once for the whole reverse process (it does not change across steps).
    """
    scheduler = make_scheduler(sampler or cfg.sampler, betas(cfg.schedule, cfg.train_timesteps))
    c = model.normalize_cond(cond)
    z = sample(model, scheduler, shape=(cond.shape[0], model.config["latent_channels"], *cond.shape[2:]),
               num_steps=num_steps or cfg.sample_steps, generator=generator, cond=c,
               adapter_features=adapter_features, eta=cfg.eta if (sampler or cfg.sampler) == "ddim" else 0.0,
               device=cond.device)
    return x_vq.decode_latents(model.denormalize(z))


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


def generation_metrics(occupancy: np.ndarray, truth: np.ndarray, grid: Grid) -> dict[str, float]:
    """IoU/precision/recall over the split, JSD/MMD (r2dm preset) and mean Chamfer to the truth.

    occupancy, truth: (B, C, H, W) bool. Clouds are the occupied voxel centres (TYP §4.1) on
    both sides, so the numbers measure generation, not voxelization.
    """
    scores = occupancy_iou(occupancy, truth)
    gen = [voxel_centers(o.transpose(1, 2, 0), grid) for o in occupancy]
    real = [voxel_centers(t.transpose(1, 2, 0), grid) for t in truth]
    usable = [i for i in range(len(gen)) if len(gen[i]) and len(real[i])]
    scores["empty_generated"] = sum(len(g) == 0 for g in gen)
    if usable:
        scores["jsd_r2dm"] = jsd_bev([real[i] for i in usable], [gen[i] for i in usable], preset="r2dm")
        scores["mmd_r2dm"] = mmd_bev([real[i] for i in usable], [gen[i] for i in usable], preset="r2dm")
        scores["chamfer_m"] = float(np.mean([chamfer_distance(gen[i], real[i]) for i in usable]))
    return scores


def sampling_config(cfg: Stage1Config, saved: dict, sampler: str, steps: int) -> Stage1Config:
    """Stage 1's sampling settings with another sampler and step count, for the model ``saved``
    (:func:`load_model`): its own β schedule and T, whatever params.yaml says now; DDIM's η = 0."""
    return dataclasses.replace(cfg, sampler=sampler, sample_steps=steps, schedule=saved["schedule"],
                               train_timesteps=saved["train_timesteps"], eta=0.0)


def save_model(model: LatentDiffusion, cfg: Stage1Config, thresholds: dict, folder: Path) -> None:
    save_torch(folder / "model.pt", {"config": model.config, "state_dict": model.state_dict(), "schedule": cfg.schedule,
                                     "train_timesteps": cfg.train_timesteps, "postprocess": thresholds})
    write_json(folder / "postprocess.json", thresholds)


def load_model(folder: Path) -> tuple[LatentDiffusion, dict]:
    saved = load_torch(folder / "model.pt", "stage-1 model (run the stage1 stage")
    model = LatentDiffusion.from_config(saved["config"])
    model.load_state_dict(saved["state_dict"])
    return model.eval(), saved
