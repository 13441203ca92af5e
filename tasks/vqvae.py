"""Stage ``vqvae`` (TYP §3.2, Eq. 1–3): train E_x,Q_x,G_x on occupancy x and E_y,Q_y,G_y on box maps y.

Trained on the target domain's ego views only; reconstruction IoU/precision/recall on the
held-out split go to the stage metrics. Output per model (``<out>/x``, ``<out>/y``):
``config.json`` + ``model.safetensors`` (:mod:`typ.artifacts`, written atomically once
training finished) and
``checkpoints/<run key>/step_*.pt`` (resume points; a changed config or data starts a new key).
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from models.vqvae import BEVVQVAE, PooledBoxMap, build_from_config
from tasks.scene_stage import StageResult
from tasks.training import (Trainings, batch_rng, grad_norm, run_checkpoint_dir, run_loop, seed_everything,
                            steps_for)
from tasks.voxel_data import ViewSet
from typ import distributed
from typ.artifacts import load_module, save_module
from typ.config import AutoencoderConfig, VQVAEStageConfig, as_dict
from typ.errors import TypError
from typ.io import hash_obj
from typ.metrics.truth import occupancy_iou
from typ.registry import TARGET_VOXELS, declare

#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare("vqvae", data=(f"{TARGET_VOXELS}train", f"{TARGET_VOXELS}val"), outs=("artifacts/vqvae",),
                      loss_curves=True)

KINDS = ("x", "y")


def build(kind: str, cfg: AutoencoderConfig, grid_channels: int) -> BEVVQVAE:
    return BEVVQVAE(in_channels=grid_channels if kind == "x" else 1, latent_channels=cfg.latent_channels,
                    block_out_channels=cfg.block_out_channels, num_codes=cfg.num_codes,
                    norm_num_groups=cfg.norm_num_groups, quantizer=cfg.quantizer, ema_decay=cfg.ema_decay,
                    dead_code_threshold=cfg.dead_code_threshold)


def check_grid(views: ViewSet, cfg: VQVAEStageConfig, where: str) -> None:
    factor = 2 ** (len(cfg.x.block_out_channels) - 1)
    H, W, _ = views.grid.shape
    if H % factor or W % factor:
        raise TypError(where, "vqvae.x.block_out_channels",
                       f"a downsampling factor ({factor}) that divides the grid's H, W = {H}, {W}", factor)


def _inputs(views: ViewSet, kind: str, index, dihedral=None) -> torch.Tensor:
    x, y = views.batch(index, dihedral=dihedral)
    return x if kind == "x" else y


def train_one(kind: str, cfg: VQVAEStageConfig, views: ViewSet, *, out: Path,
              log_fn: Callable[[dict, int], None]) -> BEVVQVAE | PooledBoxMap:
    """Train one VQ-VAE (resuming if a checkpoint of the same run key exists); returns it."""
    ae = getattr(cfg, kind)
    if kind == "y" and ae.encoding == "pool":
        pooled = PooledBoxMap(downsample=2 ** (len(cfg.x.block_out_channels) - 1))
        save_model(pooled, out / kind)
        return pooled
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
        dihedral = rng.integers(0, 8, cfg.batch_size)  # rotations and mirrors of the view (apply_dihedral)
        index, dihedral = distributed.local_batch(index, dihedral)  # only this rank's views are read
        model.train()
        loss, _, parts = model.loss(_inputs(views, kind, index, dihedral).to(distributed.device()), gamma=ae.gamma)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        parts["grad_norm"] = grad_norm(model.parameters())
        return parts

    with distributed.on_device(model):
        run_loop(name=f"vqvae-{kind}", total_steps=total, step_fn=step_fn,
                 state={"model": model, "opt": opt},
                 checkpoint_dir=ckpt_dir, curve=out / "loss" / f"{kind}.csv", checkpoint_every=cfg.checkpoint_every,
                 log_fn=lambda values, step: log_fn({f"{kind}.{k}": v for k, v in values.items()}, step))
    save_model(model, out / kind)
    return model


def save_model(model: BEVVQVAE | PooledBoxMap, folder: Path) -> None:
    """``folder/model.safetensors`` + ``folder/config.json`` (:mod:`typ.artifacts`)."""
    save_module(folder, model, model.config)


def load_model(folder: Path, stage: str = "vqvae") -> BEVVQVAE | PooledBoxMap:
    """A VQ-VAE (or the pooled box-map encoder) saved by :func:`save_model`; a missing or
    damaged folder raises TypError naming the file and ``stage``, the stage that writes it."""
    return load_module(folder, build_from_config, stage)[0]


@torch.no_grad()
def evaluate(model: BEVVQVAE, kind: str, views: ViewSet, *, threshold: float, batch_size: int) -> dict:
    """Reconstruction IoU / precision / recall (voxel level, pooled over the split) and codebook
    use on ``views``: ``codes_used`` (share of the codebook that some cell picks) and
    ``perplexity`` (exp of the entropy of the code histogram: the number of equally used codes
    that would give the same entropy). The model runs on the runtime device."""
    model.eval()
    preds, truths = [], []
    counts = torch.zeros(model.config["num_codes"], dtype=torch.float64)
    with distributed.on_device(model) as dev:
        for start in range(0, len(views), batch_size):
            index = np.arange(start, min(start + batch_size, len(views)))
            target = _inputs(views, kind, index)
            out = model(target.to(dev))
            preds.append((torch.sigmoid(out.logits) > threshold).cpu().numpy())
            truths.append((target > 0.5).cpu().numpy())
            counts += torch.bincount(out.indices.flatten().cpu(), minlength=len(counts)).double()
    # one IoU over every voxel of the split (not a mean of per-view IoUs)
    scores = occupancy_iou(np.concatenate(preds), np.concatenate(truths))
    p = counts[counts > 0] / counts.sum()
    scores["codes_used"] = float((counts > 0).double().mean())
    scores["perplexity"] = float(torch.exp(-(p * p.log()).sum()))
    scores["views"] = len(views)
    return scores


def run(cfg, root: Path, *, run, trainings: Trainings = Trainings()) -> StageResult:
    """The stage (:mod:`flows.generic`): the x and y VQ-VAEs trained on the target ego views (each a
    task of ``trainings``), their reconstruction measured on the held-out split, and each logged
    as an MLflow model of the stage's ``run``."""
    from tasks.voxel_data import load_views

    block = cfg.vqvae
    store, out = Path(root) / block.input, Path(root) / block.out
    train = load_views(store, dataset=block.dataset, split=block.train_split)
    held_out = load_views(store, dataset=block.dataset, split=block.eval_split)
    check_grid(train, block, cfg.source)
    metrics: dict = {"train_views": len(train), "eval_views": len(held_out)}
    for kind in KINDS:
        t0 = time.perf_counter()
        model = trainings.run(f"train-{kind}-seed{block.seed}",
                              lambda: train_one(kind, block, train, out=out, log_fn=run.metrics))
        seconds = time.perf_counter() - t0
        if isinstance(model, PooledBoxMap):  # nothing learned: y^f is the box map averaged per cell
            metrics[kind] = {"encoding": "pool"}
            continue
        scores = trainings.step(f"validate-{kind}", lambda: evaluate(model, kind, held_out, threshold=block.threshold,
                                                                     batch_size=block.batch_size))
        metrics[kind] = {**scores, "seconds_training": round(seconds, 3)}
        x_example, y_example = train.batch(np.arange(min(2, len(train))))
        run.log_model(f"vqvae-{kind}", model, x_example if kind == "x" else y_example, output="logits")
    return StageResult(metrics, artifacts=[(out / "x" / "config.json", "x"), (out / "y" / "config.json", "y")])
