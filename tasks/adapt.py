"""Stage ``adapt`` (TYP §3.4, Eq. 8–10): bring source (simulated CAV) features into the target space.

E_src and G_src start as copies of the target VQ-VAE's E_tgt and G_tgt; the codebook Q_tgt
is shared and frozen, E_tgt/G_tgt stay frozen. A 4-layer discriminator D on x^f and
(E_src, G_src) are updated in alternation, each batch holding as many source as target
views (target is D's real side, source its fake side):
- D:   L_D = E_tgt[max(0, 1 - D(E_tgt(x)))] + E_src[max(0, 1 + D(E_src(x)))]          (Eq. 8)
- VQ:  L_vq = L_rec(G_src(Q(E_src(x))), x) - E_src[D(E_src(x))] + ||sg[x^z] - E_src(x)||²  (Eq. 9, 10)
Eq. 9's L_rec and commitment term "follow those in Eq. (1)": they are the target VQ-VAE's terms in
its units (:meth:`models.vqvae.BEVVQVAE.loss`: the focal loss summed over the voxels per latent
element, the commitment a mean over latent elements), so they keep Eq. 1's relative weight. The
losses are plain functions of the networks and a batch (:func:`discriminator_loss`,
:func:`generator_loss`, :func:`batch_accuracy`).
Output: ``<out>/source_vq/`` (E_src, Q_tgt, G_src as one BEVVQVAE) and
``<out>/discriminator/``, each config.json + model.safetensors (:mod:`typ.artifacts`). A NaN/Inf loss or a discriminator loss beyond
``max_disc_loss`` stops the stage before any model file is written.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from models.discriminator import LatentDiscriminator
from models.losses import commitment_loss, hinge_d_loss, hinge_g_loss
from models.vqvae import BEVVQVAE, reconstruction_loss
from tasks.training import (Trainings, TrainingDiverged, batch_rng, grad_norm, run_checkpoint_dir, run_loop,
                            seed_everything, steps_for)
from tasks.scene_stage import StageResult
from tasks.voxel_data import ViewSet
from tasks.vqvae import save_model as save_vqvae
from typ import distributed
from typ.artifacts import save_module
from typ.config import AdaptConfig, as_dict
from typ.io import hash_obj
from typ.metrics.bev import jsd_bev, mmd_bev
from typ.voxel import voxel_centers
from typ.registry import TARGET_VOXELS, declare

#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare("adapt", data=("data/voxels/dataset=source/split=train", f"{TARGET_VOXELS}train",
                                     "artifacts/vqvae/x"), outs=("artifacts/adapt",), loss_curves=True)


def source_from_target(target: BEVVQVAE) -> BEVVQVAE:
    """E_src, G_src initialised from E_tgt, G_tgt; the codebook is Q_tgt, frozen."""
    source = copy.deepcopy(target).requires_grad_(True)  # whatever the target's flags were
    source.freeze_codebook()
    for p in target.parameters():
        p.requires_grad_(False)
    return source


def discriminator_loss(disc: LatentDiscriminator, target_vq: BEVVQVAE, source_vq: BEVVQVAE, x_tgt: torch.Tensor,
                       x_src: torch.Tensor) -> torch.Tensor:
    """Eq. 8 on a batch: target views x_tgt (B, C, H, W) through E_tgt are the real side, source
    views x_src through E_src the fake side. The encoders are constants here: L_D trains D alone."""
    with torch.no_grad():
        f_tgt = target_vq.encode_pre_quant(x_tgt)
        f_src = source_vq.encode_pre_quant(x_src)
    return hinge_d_loss(disc(f_tgt), disc(f_src))


@dataclass
class GeneratorLoss:
    """Eq. 9's terms on a source batch, each a scalar tensor; ``total`` is what E_src, G_src minimise."""

    rec: torch.Tensor     # L_rec of x̂ = G_src(Q_tgt(E_src(x))) against x, in Eq. 1's units
    adv: torch.Tensor     # L_src = -E[D(E_src(x))] (Eq. 10)
    commit: torch.Tensor  # ||sg[x^z] - E_src(x)||²

    @property
    def total(self) -> torch.Tensor:
        return self.rec + self.adv + self.commit


def generator_loss(disc: LatentDiscriminator, source_vq: BEVVQVAE, x_src: torch.Tensor, *,
                   gamma: float) -> GeneratorLoss:
    """Eq. 9–10 on source views x_src (B, C, H, W); D scores the pre-quantization x^f = E_src(x)."""
    f_src = source_vq.encode_pre_quant(x_src)
    z_q, _, _ = source_vq.quantize(f_src)
    rec = reconstruction_loss(source_vq.decode_logits(z_q), x_src, f_src, gamma=gamma)
    return GeneratorLoss(rec, hinge_g_loss(disc(f_src)), commitment_loss(f_src, z_q))


@torch.no_grad()
def batch_accuracy(disc: LatentDiscriminator, target_vq: BEVVQVAE, source_vq: BEVVQVAE, x_tgt: torch.Tensor,
                   x_src: torch.Tensor) -> float:
    """Share of views D puts on their side of 0: E_tgt(x_tgt) above (real), E_src(x_src) below
    (fake). 0.5 = features indistinguishable, 1 = D separates them all, 0 = D has them swapped."""
    correct = torch.cat([disc(target_vq.encode_pre_quant(x_tgt)) > 0, disc(source_vq.encode_pre_quant(x_src)) < 0])
    return float(correct.float().mean())


def _pick(views: ViewSet, rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.choice(len(views), size=n, replace=len(views) < n)


def train(cfg: AdaptConfig, target_vq: BEVVQVAE, source_views: ViewSet, target_views: ViewSet, *,
          out: Path, log_fn: Callable[[dict, int], None]) -> tuple[BEVVQVAE, LatentDiscriminator]:
    seed_everything(cfg.seed)
    source_vq = source_from_target(target_vq)
    disc = LatentDiscriminator(in_channels=target_vq.config["latent_channels"], width=cfg.disc_width)
    trainable = [p for p in source_vq.parameters() if p.requires_grad]
    opt_g = torch.optim.Adam(trainable, lr=cfg.lr, betas=(0.5, 0.9))
    opt_d = torch.optim.Adam(disc.parameters(), lr=cfg.lr_disc, betas=(0.5, 0.9))
    total = steps_for(cfg.epochs, len(source_views), cfg.batch_size)
    key = hash_obj({"cfg": as_dict(cfg), "src": [list(k) for k in source_views.keys],
                    "tgt": [list(k) for k in target_views.keys],
                    "tgt_model": float(sum(p.double().sum() for p in target_vq.parameters()))})[:16]
    ckpt_dir = run_checkpoint_dir(out / "checkpoints", key)
    target_vq.eval()

    def step_fn(step: int) -> dict[str, float]:
        rng = batch_rng(cfg.seed, step)
        src, src_flips = _pick(source_views, rng, cfg.batch_size), rng.random(cfg.batch_size) < 0.5
        tgt, tgt_flips = _pick(target_views, rng, cfg.batch_size), rng.random(cfg.batch_size) < 0.5
        # as many source as target views on every rank, so both hinge terms shard alike
        src, src_flips, tgt, tgt_flips = distributed.local_batch(src, src_flips, tgt, tgt_flips)
        x_src = source_views.batch(src, flips=src_flips)[0].to(distributed.device())
        x_tgt = target_views.batch(tgt, flips=tgt_flips)[0].to(distributed.device())
        source_vq.train()
        d_loss = discriminator_loss(disc, target_vq, source_vq, x_tgt, x_src)
        opt_d.zero_grad(set_to_none=True)
        d_loss.backward()
        opt_d.step()
        d_value = distributed.all_reduce_mean({"d": float(d_loss.detach())})["d"]  # every rank stops alike
        if d_value > cfg.max_disc_loss:
            raise TrainingDiverged(f"adapt: step {step}: discriminator loss {d_value:.3g} > "
                                   f"max_disc_loss={cfg.max_disc_loss}; stopped before writing a model")

        g = generator_loss(disc, source_vq, x_src, gamma=cfg.gamma)
        loss = g.total
        opt_g.zero_grad(set_to_none=True)
        loss.backward()
        opt_g.step()
        norm = grad_norm(trainable)
        return {"loss": float(loss.detach()), "rec": float(g.rec.detach()), "adv": float(g.adv.detach()),
                "commit": float(g.commit.detach()), "disc_loss": d_value, "grad_norm": norm}

    with distributed.on_device(source_vq, disc, target_vq):
        run_loop(name="adapt", total_steps=total, step_fn=step_fn,
                 state={"source": source_vq, "disc": disc, "opt_g": opt_g, "opt_d": opt_d},
                 checkpoint_dir=ckpt_dir, curve=out / "loss" / "adapt.csv", checkpoint_every=cfg.checkpoint_every,
                 log_fn=lambda values, step: log_fn({f"adapt.{k}": v for k, v in values.items()}, step))
    return source_vq.eval(), disc.eval()


def save(source_vq: BEVVQVAE, disc: LatentDiscriminator, out: Path) -> None:
    save_vqvae(source_vq, out / "source_vq")
    save_module(out / "discriminator", disc, disc.config)


def _clouds(occupancy: np.ndarray, grid) -> list[np.ndarray]:
    return [voxel_centers(o.transpose(1, 2, 0), grid) for o in occupancy]


@torch.no_grad()
def translation_scores(encoder_vq: BEVVQVAE, target_vq: BEVVQVAE, source_views: ViewSet, target_views: ViewSet, *,
                       n: int | None = None, batch_size: int = 8) -> dict[str, float]:
    """How target-like source scenes look through ``encoder_vq``'s encoder and the TARGET decoder.

    jsd/mmd (r2dm preset): clouds G_tgt(Q(E(x_src))) vs the true target clouds, both as occupied
    voxel centres on the target's grid (the height channels mean the same in both domains);
    this is what the generator will see, since stage 1 generates in the target's latent space.
    rec_iou_source: E, G of ``encoder_vq`` reconstructing the source views (threshold 0.5).
    """
    n_src = len(source_views) if n is None else min(n, len(source_views))
    n_tgt = len(target_views) if n is None else min(n, len(target_views))
    grid = target_views.grid
    gen, own_tp, own_union = [], 0, 0
    with distributed.on_device(encoder_vq, target_vq) as dev:
        for start in range(0, n_src, batch_size):
            src = source_views.batch(np.arange(start, min(start + batch_size, n_src)))[0]
            f_src = encoder_vq.encode_pre_quant(src.to(dev))
            gen += _clouds((torch.sigmoid(target_vq.decode_latents(f_src)) > 0.5).cpu().numpy(), grid)
            own = (torch.sigmoid(encoder_vq.decode_latents(f_src)) > 0.5).cpu().numpy()
            truth = src.numpy() > 0.5
            own_tp += int((own & truth).sum())
            own_union += int((own | truth).sum())
    real = []
    for start in range(0, n_tgt, batch_size):
        real += _clouds(target_views.batch(np.arange(start, min(start + batch_size, n_tgt)))[0].numpy() > 0.5, grid)
    gen = [g for g in gen if len(g)] or [np.zeros((1, 3))]
    return {"jsd_r2dm": jsd_bev(real, gen, preset="r2dm"), "mmd_r2dm": mmd_bev(real, gen, preset="r2dm"),
            "rec_iou_source": own_tp / own_union if own_union else float("nan")}


@torch.no_grad()
def discriminator_accuracy(disc: LatentDiscriminator, encoder_vq: BEVVQVAE, target_vq: BEVVQVAE,
                           source_views: ViewSet, target_views: ViewSet, *, n: int) -> float:
    """:func:`batch_accuracy` on the first ``n`` views of each set, source views through ``encoder_vq``."""
    src = source_views.batch(np.arange(min(n, len(source_views))))[0]
    tgt = target_views.batch(np.arange(min(n, len(target_views))))[0]
    with distributed.on_device(disc, encoder_vq, target_vq) as dev:
        return batch_accuracy(disc, target_vq, encoder_vq, tgt.to(dev), src.to(dev))


def run(cfg, root: Path, *, run, trainings: Trainings = Trainings()) -> StageResult:
    """The stage (:mod:`flows.generic`): the source encoder/decoder adapted to the target latent
    space (one task of ``trainings``), the translation figures before and after on training views
    (held-out ones are the evaluate stage's), saved and logged as an MLflow model of ``run``."""
    from tasks.voxel_data import load_views
    from tasks.vqvae import load_model as load_vqvae

    block = cfg.adapt
    store, out = Path(root) / block.input, Path(root) / block.out
    target_vq = load_vqvae(Path(root) / block.vqvae / "x")
    # source scenarios are multi-agent: every agent's view is a training sample
    src_train = load_views(store, dataset=block.source_dataset, split=block.source_split, ego_only=False)
    tgt_train = load_views(store, dataset=block.target_dataset, split=block.target_split)
    metrics: dict = {"source_views": len(src_train), "target_views": len(tgt_train)}
    t0 = time.perf_counter()
    source_vq, disc = trainings.run(f"train-source_vq-seed{block.seed}", lambda: train(
        block, target_vq, src_train, tgt_train, out=out, log_fn=run.metrics))
    metrics["seconds_training"] = round(time.perf_counter() - t0, 3)
    # "before" = no adaptation, the target VQ-VAE applied to source views as they are
    for name, encoder in (("before", target_vq), ("after", source_vq)):
        metrics[name] = {**translation_scores(encoder, target_vq, src_train, tgt_train, n=block.eval_views),
                         "disc_accuracy": discriminator_accuracy(disc, encoder, target_vq, src_train, tgt_train,
                                                                 n=block.eval_views)}
    save(source_vq, disc, out)
    run.log_model("adapt-source-vq", source_vq, src_train.batch(np.arange(min(2, len(src_train))))[0],
                  output="logits")
    return StageResult(metrics)
