"""Stage ``stage2`` (TYP Eq. 5–7): ground P(x|y) on the ego's view with a T2I-Adapter.

F_AD = diffusers' ``T2IAdapter`` (full adapter, ``downscale_factor=1``) maps the standardised
x^f_e' = E_src(x_e') to one feature map per UNet encoder level; they are added to the frozen
stage-1 UNet's encoder features at every denoising step (Eq. 6). Only F_AD learns, on source
(simulated CAV) tuples encoded with the adapted source encoder (stage ``adapt``). At
inference on the target domain, x_e' is encoded with the target encoder E_tgt (TYP §3.4).
Output: ``<out>/adapter.pt`` and resumable ``<out>/checkpoints/<key>/``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from diffusers import T2IAdapter

from models.ldm import LatentDiffusion
from models.schedules import alphas_cumprod, betas
from models.vqvae import BEVVQVAE
from tasks.stage1 import noised_batch
from tasks.training import (batch_rng, grad_norm, load_torch, run_checkpoint_dir, run_loop, save_torch, seed_everything,
                            steps_for)
from typ import distributed
from typ.config import Stage2Config, as_dict
from typ.errors import TypError
from typ.io import hash_obj


def build_adapter(cfg: Stage2Config, ldm: LatentDiffusion) -> T2IAdapter:
    """Feature widths follow the UNet's levels, so residual i matches encoder level i."""
    return T2IAdapter(in_channels=ldm.config["latent_channels"], channels=list(ldm.config["block_out_channels"]),
                      num_res_blocks=cfg.adapter_res_blocks, downscale_factor=1, adapter_type="full_adapter")


@torch.no_grad()
def encode(x_encoder: BEVVQVAE, y_vq: BEVVQVAE, x_r: np.ndarray, y_r: np.ndarray, x_e: np.ndarray,
           batch_size: int = 8) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pre-quantization latents (x_r^f, y_r^f, x_e'^f) of stacked (N, C, H, W) grids."""
    out: list[list[torch.Tensor]] = [[], [], []]
    for start in range(0, len(x_r), batch_size):
        sl = slice(start, start + batch_size)
        out[0].append(x_encoder.encode_pre_quant(torch.from_numpy(x_r[sl])))
        out[1].append(y_vq.encode_pre_quant(torch.from_numpy(y_r[sl])))
        out[2].append(x_encoder.encode_pre_quant(torch.from_numpy(x_e[sl])))
    return tuple(torch.cat(o) for o in out)


def train(cfg: Stage2Config, ldm: LatentDiffusion, schedule: str, train_timesteps: int, x_r: torch.Tensor,
          y_r: torch.Tensor, x_e: torch.Tensor, *, out: Path, log_fn: Callable[[dict, int], None]) -> T2IAdapter:
    """Eq. 7 with the UNet frozen; returns the trained adapter."""
    if len(x_r) == 0:
        raise TypError(out, "stage2 training pairs", "at least one (ego, reference) pair in the source split", 0)
    seed_everything(cfg.seed)  # before the adapter's initial weights are drawn
    return fit_adapter(build_adapter(cfg, ldm), ldm, schedule, train_timesteps, x_r, y_r, x_e, name="stage2",
                       seed=cfg.seed, lr=cfg.lr, epochs=cfg.epochs, batch_size=cfg.batch_size,
                       checkpoint_every=cfg.checkpoint_every, key_extra=as_dict(cfg), out=out, log_fn=log_fn)


def fit_adapter(adapter: T2IAdapter, ldm: LatentDiffusion, schedule: str, train_timesteps: int, x_r: torch.Tensor,
                y_r: torch.Tensor, x_e: torch.Tensor, *, name: str, seed: int, lr: float, epochs: int,
                batch_size: int, checkpoint_every: int, key_extra: dict, out: Path,
                log_fn: Callable[[dict, int], None]) -> T2IAdapter:
    """Minimise Eq. 7 over ``adapter`` alone on latents (x_r^f, y_r^f, x_e'^f), the UNet frozen.

    Checkpoints go to ``<out>/checkpoints/<key>``, the key covering the data, the frozen UNet,
    the adapter's starting weights and ``key_extra`` (the config), so a resumed run continues
    exactly the run that was interrupted.
    """
    seed_everything(seed)
    ldm.eval().requires_grad_(False)
    z0, c, ce = ldm.normalize(x_r), ldm.normalize_cond(y_r), ldm.normalize(x_e)
    abar = torch.from_numpy(alphas_cumprod(betas(schedule, train_timesteps))).float()
    opt = torch.optim.AdamW(adapter.parameters(), lr=lr)
    total = steps_for(epochs, len(z0), batch_size)
    key = hash_obj({"cfg": key_extra, "data": float(x_r.double().sum() + x_e.double().sum() + y_r.double().sum()),
                    "n": len(x_r), "ldm": float(sum(p.double().sum() for p in ldm.parameters())),
                    "init": float(sum(p.detach().double().sum() for p in adapter.parameters()))})[:16]
    ckpt_dir = run_checkpoint_dir(out / "checkpoints", key)

    def step_fn(step: int) -> dict[str, float]:
        index, t, eps, z_t = noised_batch(batch_rng(seed, step), z0, abar, batch_size)
        t, eps, z_t, cond, ego = distributed.local_batch(t, eps, z_t, c[index], ce[index])
        adapter.train()
        loss = F.mse_loss(ldm(z_t, t, cond, list(adapter(ego))), eps)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        norm = grad_norm(adapter.parameters())
        return {"loss": float(loss.detach()), "grad_norm": norm}

    with distributed.on_device(adapter, ldm):
        run_loop(name=name, total_steps=total, step_fn=step_fn,
                 get_state=lambda: {"adapter": adapter.state_dict(), "opt": opt.state_dict()},
                 set_state=lambda s: (adapter.load_state_dict(s["adapter"]), opt.load_state_dict(s["opt"])),
                 checkpoint_dir=ckpt_dir, checkpoint_every=checkpoint_every,
                 log_fn=lambda values, step: log_fn({f"{name}.{k}": v for k, v in values.items()}, step))
    return adapter.eval()


@torch.no_grad()
def adapter_features(adapter: T2IAdapter, ldm: LatentDiffusion, x_e_latents: torch.Tensor) -> list[torch.Tensor]:
    """F_c = F_AD(x^f_e') (Eq. 5), computed once per sample and reused at every step."""
    return list(adapter(ldm.normalize(x_e_latents)))


def save(adapter: T2IAdapter, cfg: Stage2Config, folder: Path) -> None:
    save_adapter(adapter, cfg.adapter_res_blocks, folder)


def save_adapter(adapter: T2IAdapter, res_blocks: int, folder: Path) -> None:
    save_torch(folder / "adapter.pt", {"config": {"adapter_res_blocks": res_blocks},
                                       "state_dict": adapter.state_dict()})


def load_adapter(path: Path, ldm: LatentDiffusion) -> T2IAdapter:
    """An adapter saved by :func:`save_adapter`, shaped for ``ldm``'s UNet."""
    saved = load_torch(path, "stage-2 adapter (run the stage2 or selftrain stage)")
    adapter = T2IAdapter(in_channels=ldm.config["latent_channels"], channels=list(ldm.config["block_out_channels"]),
                         num_res_blocks=saved["config"]["adapter_res_blocks"], downscale_factor=1,
                         adapter_type="full_adapter")
    adapter.load_state_dict(saved["state_dict"])
    return adapter.eval()
