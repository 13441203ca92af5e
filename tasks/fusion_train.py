"""Training the fusion benchmark's networks, and saving / loading them (safetensors + JSON).

One network per trained method of ``models.fusion.METHODS``: the single-agent detector
(trained as late fusion, with every agent's own labels; no fusion runs it on the ego's cloud
only), early fusion, AttFuse and V2X-ViT (each with the fused ground truth in the ego frame).

Training is :func:`tasks.training.run_loop` (a batch a pure function of (seed, step),
checkpoints, resume) with Adam (weight decay 1e-4, as OpenCOOD), a learning rate that is a
function of the step (:func:`detector_learning_rate`: linear warm-up, then cosine decay to 1 % of the
peak, or constant) and OpenCOOD's augmentation (:mod:`tasks.fusion_batch`). BatchNorm running
statistics are *not* re-estimated after training: they are the training loop's own (momentum
0.01, as OpenCOOD), which have converged when a run is long and its learning rate has decayed;
re-estimating them on a mix of real and generated training data, as this stage once did,
changes the network the test scores.

``warm``: early and intermediate fusion may start from a trained single-agent detector
(``FusionModule.warm_start``); ``init``: fine-tuning starts from a trained network of the same
method. Either way the peak learning rate is ``finetune_lr``.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from models.box_coder import AnchorBoxCoder
from models.detection_loss import DetectionLoss
from models.fusion import METHODS, FusionModule, build, get_method
from models.pointpillars import PointPillars
from tasks.fusion_batch import Inputs, draw_similarity
from tasks.training import (batch_rng, grad_norm, learning_rate, run_checkpoint_dir, run_loop, seed_everything,
                            set_learning_rate)
from typ import distributed
from typ.artifacts import load_module, save_module
from typ.config import DetectorConfig, FusionConfig, as_dict
from typ.errors import TypError
from typ.io import hash_obj

STAGE = "fusion"
#: training curves keep (and MLflow gets) the step's losses every this many steps
LOG_EVERY = 25


def build_detector(d: DetectorConfig) -> PointPillars:
    """A fresh PointPillars of the detector config (weights from the torch seed)."""
    return PointPillars(lidar_range=d.lidar_range, voxel_size=d.voxel_size,
                        max_points_per_pillar=d.max_points_per_pillar, max_pillars=d.max_pillars,
                        pillar_channels=d.pillar_channels, layer_nums=d.layer_nums, layer_strides=d.layer_strides,
                        num_filters=d.num_filters, upsample_strides=d.upsample_strides,
                        num_upsample_filters=d.num_upsample_filters)


def model_config(method: str, cfg: FusionConfig) -> dict:
    """What rebuilds ``method``'s module: its name, the detector config and its options block."""
    m = get_method(method)
    return {"method": method, "detector": as_dict(cfg.detector),
            "options": as_dict(getattr(cfg, m.options)) if m.options else None}


def build_from_config(config: dict) -> FusionModule:
    """:func:`model_config`'s dict -> a fresh module."""
    detector = build_detector(DetectorConfig(**{k: tuple(v) if isinstance(v, list) else v
                                                for k, v in config["detector"].items()}))
    options = {k: tuple(v) if isinstance(v, list) else v for k, v in (config["options"] or {}).items()}
    return build(config["method"], detector, options)


def build_model(method: str, cfg: FusionConfig) -> FusionModule:
    """The module of ``method`` on a fresh PointPillars (weights from the torch seed)."""
    return build_from_config(model_config(method, cfg))


def box_coder(cfg: FusionConfig, model: nn.Module) -> AnchorBoxCoder:
    """Anchors on the grid of ``model``'s head."""
    d = cfg.detector
    return AnchorBoxCoder(lidar_range=d.lidar_range, voxel_size=d.voxel_size, feature_stride=model.feature_stride,
                          anchor_size=d.anchor_size, anchor_z=d.anchor_z)


@dataclass
class Trained:
    """A trained network: the module of the method that trained it, its anchors, how it was made
    and its training curve (``{"step", "loss", "cls_loss", "reg_loss", "dir_loss", "lr"}`` rows)."""

    method: str
    model: FusionModule
    coder: AnchorBoxCoder
    key: str
    steps: int
    seed: int = 0
    curve: list[dict] = field(default_factory=list)

    def as_method(self, method: str) -> "Trained":
        """The same network run as ``method`` (no fusion runs the single-agent detector that late
        fusion trained): a module of ``method`` sharing this one's detector."""
        if method == self.method:
            return self
        if METHODS[method].network != self.method:
            raise TypError(STAGE, "method", f"a method that runs the network of {self.method}", method)
        module = METHODS[method].module(detector=self.model.detector)
        return Trained(method, module.train(self.model.training), self.coder, self.key, self.steps, self.seed,
                       self.curve)


def detector_learning_rate(peak: float, step: int, total: int, schedule: str = "cosine", warmup: float = 0.05) -> float:
    """The shared schedule (:func:`tasks.training.learning_rate`) as the detectors run it: linear
    warm-up over the first ``warmup`` fraction of the run (one step at least), then ``cosine``
    decay to 1 % of ``peak`` at the last step, or ``constant``."""
    return learning_rate(peak, step, total, warmup=max(1, int(round(warmup * total))), schedule=schedule,
                         floor=0.01, end=total - 1)


def training_fields(method: str, cfg: FusionConfig) -> dict:
    """What a trained network depends on besides its data, steps and seed: its module and the
    optimisation (changing how it is scored does not retrain it)."""
    return {**model_config(method, cfg), "augment": as_dict(cfg.augment),
            **{k: getattr(cfg, k) for k in ("batch_size", "lr", "finetune_lr", "lr_schedule", "warmup",
                                            "max_agents", "comm_range")}}


def data_key(inputs: Inputs) -> str:
    """Identity of a training set for checkpoint keys: which frames, and a digest of their content."""
    items = [(s.scenario, s.timestamp, list(s.agent_ids), [len(c) for c in s.clouds],
              round(float(np.sum(s.gt_boxes)), 4), round(float(sum(np.sum(c[:, :3], dtype=np.float64)
                                                                  for c in s.clouds)), 2)) for s in inputs.samples]
    return hash_obj(items)[:16]


def train(method: str, cfg: FusionConfig, inputs: Inputs, *, steps: int, out: Path, name: str, seed: int | None = None,
          init: Trained | None = None, warm: Trained | None = None,
          log_fn: Callable[[dict, int], None] | None = None) -> Trained:
    """Train ``method``'s network for ``steps`` on ``inputs`` with ``seed`` (default ``cfg.seed``),
    resumably under ``out/checkpoints/<name>/``; returns it in eval mode (module doc)."""
    m = get_method(method)
    if m.trained_as is not None:
        raise TypError(STAGE, "method", f"a method trained itself (not {method}: it runs {m.trained_as}'s network)",
                       method)
    if init is not None and init.method != method:
        raise TypError(STAGE, "init", f"a pretrained {method} model", init.method)
    seed = cfg.seed if seed is None else int(seed)
    seed_everything(seed)
    model = build_model(method, cfg)
    if init is not None:
        model.load_state_dict(init.model.state_dict())
    elif warm is not None:
        model.warm_start(warm.model.detector)
    if distributed.world_size() > 1 and distributed.device().type == "cuda":
        model = nn.SyncBatchNorm.convert_sync_batchnorm(model)  # batch statistics over the global batch
    coder = box_coder(cfg, model)
    criterion = DetectionLoss()
    peak = cfg.lr if init is None and warm is None else cfg.finetune_lr
    opt = torch.optim.Adam(model.parameters(), lr=peak, weight_decay=1e-4)
    key = hash_obj({"training": training_fields(method, cfg), "steps": steps, "seed": seed,
                    "data": data_key(inputs), "init": None if init is None else init.key,
                    "warm": None if warm is None else warm.key})[:16]
    batch_size = min(cfg.batch_size, len(inputs))

    def step_fn(step: int) -> dict[str, float]:
        lr = detector_learning_rate(peak, step, steps, cfg.lr_schedule, cfg.warmup)
        set_learning_rate(opt, lr)
        rng = batch_rng(seed, step)
        indices = rng.choice(len(inputs), size=batch_size, replace=False)
        similarities = np.stack([draw_similarity(rng, cfg.augment) for _ in indices])
        indices, similarities = distributed.local_batch(indices, similarities)
        batch = inputs.batch(method, indices, list(similarities))
        dev = distributed.device()
        targets = {k: v.to(dev) for k, v in batch.targets(coder).items()}
        model.train()
        losses = criterion(batch.to(dev).run(model), targets)
        opt.zero_grad(set_to_none=True)
        losses["total_loss"].backward()
        opt.step()
        values = {"loss": float(losses["total_loss"].detach()), "cls_loss": float(losses["cls_loss"].detach()),
                  "reg_loss": float(losses["reg_loss"].detach()), "dir_loss": float(losses["dir_loss"].detach()),
                  "grad_norm": grad_norm(model.parameters()), "lr": lr}
        return values

    def logged(step: int) -> bool:
        return step % LOG_EVERY == 0 or step == steps - 1

    def log(values: dict, step: int) -> None:
        if log_fn is not None and logged(step):
            log_fn({f"{name}.{k}": v for k, v in values.items()}, step)

    with distributed.on_device(model):
        result = run_loop(name=f"fusion {name}", total_steps=steps, step_fn=step_fn,
                          state={"model": model, "opt": opt},
                          checkpoint_dir=run_checkpoint_dir(out / "checkpoints" / name, key),
                          checkpoint_every=cfg.checkpoint_every, log_fn=log)
    model.eval()
    # the loop's history (kept across a resume by its checkpoints), every LOG_EVERY steps and the last
    curve = [{"step": h["step"], **{k: round(v, 6) for k, v in h.items() if k != "step"}}
             for h in result.history if logged(h["step"])]
    return Trained(method, model, coder, key, steps, seed, curve)


# -------------------------------------------------------------- on disk


def save(trained: Trained, folder: Path, cfg: FusionConfig) -> Path:
    """``folder/model.safetensors`` + ``config.json`` (what rebuilds it, its key, steps, seed, curve)."""
    return save_module(folder, trained.model, model_config(trained.method, cfg), key=trained.key,
                       steps=trained.steps, seed=trained.seed, curve=trained.curve)


def load(folder: Path, cfg: FusionConfig) -> Trained:
    """A network :func:`save` wrote; a missing or damaged file raises naming it and this stage."""
    model, meta = load_module(folder, build_from_config, STAGE)
    return Trained(meta["config"]["method"], model, box_coder(cfg, model), meta.get("key", ""),
                   int(meta.get("steps", 0)), int(meta.get("seed", 0)), list(meta.get("curve", [])))
