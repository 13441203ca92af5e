"""Stage ``vqvae`` (TYP §3.2, Eq. 1–3): train E_x,Q_x,G_x on occupancy x and E_y,Q_y,G_y on box maps y.

Trained on the target domain's ego views only; reconstruction IoU/precision/recall on the
held-out split go to the stage metrics. Output per model (``<out>/x``, ``<out>/y``):
``model.pt`` (config + weights, written atomically once training finished) and
``checkpoints/<run key>/step_*.pt`` (resume points; a changed config or data starts a new key).
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np
import torch

from models.vqvae import BEVVQVAE
from tasks.training import batch_rng, grad_norm, load_torch, run_checkpoint_dir, run_loop, save_torch, seed_everything, steps_for
from tasks.voxel_data import ViewSet
from typ import distributed
from typ.config import AutoencoderConfig, VQVAEStageConfig, as_dict
from typ.errors import TypError
from typ.io import hash_obj, write_json
from typ.metrics import occupancy_iou

KINDS = ("x", "y")


def build(kind: str, cfg: AutoencoderConfig, grid_channels: int) -> BEVVQVAE:
    return BEVVQVAE(in_channels=grid_channels if kind == "x" else 1, latent_channels=cfg.latent_channels,
                    block_out_channels=cfg.block_out_channels, num_codes=cfg.num_codes,
                    norm_num_groups=cfg.norm_num_groups)


def check_grid(views: ViewSet, cfg: VQVAEStageConfig, where: str) -> None:
    factor = 2 ** (len(cfg.x.block_out_channels) - 1)
    H, W, _ = views.grid.shape
    if H % factor or W % factor:
        raise TypError(where, "vqvae.x.block_out_channels",
                       f"a downsampling factor ({factor}) that divides the grid's H, W = {H}, {W}", factor)


def _inputs(views: ViewSet, kind: str, index, flips=None) -> torch.Tensor:
    x, y = views.batch(index, flips=flips)
    return x if kind == "x" else y


def train_one(kind: str, cfg: VQVAEStageConfig, views: ViewSet, *, out: Path,
              log_fn: Callable[[dict, int], None]) -> BEVVQVAE:
    """Train one VQ-VAE (resuming if a checkpoint of the same run key exists); returns it."""
    ae = getattr(cfg, kind)
    seed_everything(cfg.seed)
    model = build(kind, ae, views.grid.shape[2])
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    total = steps_for(ae.epochs, len(views), cfg.batch_size)
    key = hash_obj({"ae": as_dict(ae), "lr": cfg.lr, "batch": cfg.batch_size, "seed": cfg.seed,
                    "data": [list(k) for k in views.keys], "grid": views.grid.to_dict()})[:16]
    ckpt_dir = run_checkpoint_dir(out / kind / "checkpoints", key)

    def step_fn(step: int) -> dict[str, float]:
        rng = batch_rng(cfg.seed, step)
        index = rng.choice(len(views), size=cfg.batch_size, replace=len(views) < cfg.batch_size)
        flips = rng.random(cfg.batch_size) < 0.5
        index, flips = distributed.local_batch(index, flips)  # only this rank's views are read
        model.train()
        loss, _, parts = model.loss(_inputs(views, kind, index, flips).to(distributed.device()), gamma=ae.gamma)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        parts["grad_norm"] = grad_norm(model.parameters())
        return parts

    with distributed.on_device(model):
        run_loop(name=f"vqvae-{kind}", total_steps=total, step_fn=step_fn,
                 get_state=lambda: {"model": model.state_dict(), "opt": opt.state_dict()},
                 set_state=lambda s: (model.load_state_dict(s["model"]), opt.load_state_dict(s["opt"])),
                 checkpoint_dir=ckpt_dir, checkpoint_every=cfg.checkpoint_every,
                 log_fn=lambda values, step: log_fn({f"{kind}.{k}": v for k, v in values.items()}, step))
    save_model(model, out / kind)
    return model


def save_model(model: BEVVQVAE, folder: Path) -> None:
    save_torch(folder / "model.pt", {"config": model.config, "state_dict": model.state_dict()})
    write_json(folder / "config.json", model.config)


def load_model(folder: Path) -> BEVVQVAE:
    saved = load_torch(folder / "model.pt", "VQ-VAE (run the vqvae stage")
    model = BEVVQVAE.from_config(saved["config"])
    model.load_state_dict(saved["state_dict"])
    return model.eval()


@torch.no_grad()
def evaluate(model: BEVVQVAE, kind: str, views: ViewSet, *, threshold: float, batch_size: int) -> dict:
    """Reconstruction IoU / precision / recall (voxel level, summed over the split) and codebook use."""
    model.eval()
    preds, truths = [], []
    used: set[int] = set()
    for start in range(0, len(views), batch_size):
        index = np.arange(start, min(start + batch_size, len(views)))
        target = _inputs(views, kind, index)
        out = model(target)
        preds.append((torch.sigmoid(out.logits) > threshold).numpy())
        truths.append((target > 0.5).numpy())
        used.update(out.indices.unique().tolist())
    # one IoU over every voxel of the split (not a mean of per-view IoUs)
    scores = occupancy_iou(np.concatenate(preds), np.concatenate(truths))
    scores["codes_used"] = len(used) / model.config["num_codes"]
    scores["views"] = len(views)
    return scores
