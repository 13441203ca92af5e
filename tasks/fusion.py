"""Stage ``fusion`` (TYP §4.2–4.5, Tables 1–3; V2VSSC §IV): collaborative detection benchmark.

One PointPillars (``models/pointpillars.py``) per fusion method of ``models/fusion.py``:
``none`` (the ego's own cloud), ``early`` (all clouds merged in the ego frame), ``late``
(every agent detects, boxes meet in the ego frame for NMS), ``attfuse`` and ``v2xvit``
(intermediate: BEV features warped into the ego frame and fused). Training targets follow
OpenCOOD: ``none`` learns from the ego's own labels ("ego's gt only"), ``late`` from every
agent's own labels in its own frame (``LateFusionDataset``), the others from the fused ground
truth of :mod:`tasks.fusion_data` in the ego frame. Every method is evaluated against that
fused ground truth with OpenCOOD's AP by range (:func:`typ.metrics.ap_by_range`) at IoU 0.5
and 0.7, after rotated NMS (``typ.boxes_bev.nms_bev``).

Training is :func:`tasks.training.run_loop` (seeded batches, checkpoints, resume); after it,
BatchNorm statistics are re-estimated on the training samples with the final weights (one
pass, cumulative average), since a short run with OpenCOOD's momentum 0.01 leaves the running
statistics far from the data. With ``warm_start`` (tiny profile) early and intermediate fusion
start from the late-fusion detector of the same data (:func:`warm_start`).

Experiments (each a Prefect task of ``flows/fusion.py``): :func:`oracle_vs_generated` (TYP
Tables 1–2), :func:`pretrain_finetune` (Table 3), :func:`robustness` (V2VSSC §IV), then
:func:`write_report`. A :class:`Benchmark` holds what they share: datasets read once, models
trained once by run name (``<out>/models/<run>.pt``, checkpoints ``<out>/checkpoints/<run>/``).

Message compression (intermediate fusion): each cooperating agent's feature maps are
quantised per channel (min/max, ``bits`` levels) before they reach the ego: for V2X-ViT on
the shrunk map the agent sends (before warping), for AttFuse on every backbone level as the
ego receives it (after warping; the warp interpolates, so the value range is the sent one).
Bytes per message count a dense map: ``C * h * w * bits / 8`` plus two float32 per channel;
early fusion sends its points (16 bytes each), late fusion its boxes with scores (32 bytes each).
"""
from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from models.box_coder import AnchorBoxCoder
from models.detection_loss import DetectionLoss
from models.fusion import AttFuse, EarlyFusion, LateFusion, NoFusion, V2XViT, merge_agent_points
from models.pointpillars import PointPillars, pillarize
from tasks.fusion_data import FusionDataset, FusionSample, boxes_in_range
from tasks.training import batch_rng, grad_norm, run_checkpoint_dir, run_loop, save_torch, seed_everything
from typ import distributed
from typ.boxes_bev import nms_bev
from typ.config import FusionConfig, as_dict
from typ.errors import TypError
from typ.formats.opv2v import list_scenarios
from typ.io import hash_obj
from typ.metrics.detection import ap_by_range, pr_curves

METHODS = ("none", "early", "late", "attfuse", "v2xvit")
#: row names of TYP Tables 1–3
METHOD_NAMES = {"none": "No Fusion", "early": "Early Fusion", "late": "Late Fusion", "attfuse": "AttFuse",
                "v2xvit": "V2X-ViT"}
INTERMEDIATE = ("attfuse", "v2xvit")
#: methods that ``warm_start`` starts from the single-agent (late-fusion) detector of the same data
WARM_STARTED = ("early", "attfuse", "v2xvit")
IOU_THRESHOLDS = {"ap50": 0.5, "ap70": 0.7}
BYTES_PER_POINT = 16        # x, y, z, intensity as float32
BYTES_PER_BOX = 32          # 7 box parameters and a score as float32
#: training metrics go to MLflow every this many steps (dozens of runs share one stage run)
LOG_EVERY = 25
WARMUP_STEPS = 10


# ------------------------------------------------------------------ models


def build_model(method: str, cfg: FusionConfig) -> nn.Module:
    """The fusion module of ``method`` on a fresh PointPillars (weights from the torch seed)."""
    if method not in METHODS:
        raise TypError("fusion", "method", f"one of {list(METHODS)}", method)
    d = cfg.detector
    detector = PointPillars(lidar_range=d.lidar_range, voxel_size=d.voxel_size,
                            max_points_per_pillar=d.max_points_per_pillar, max_pillars=d.max_pillars,
                            pillar_channels=d.pillar_channels, layer_nums=d.layer_nums, layer_strides=d.layer_strides,
                            num_filters=d.num_filters, upsample_strides=d.upsample_strides,
                            num_upsample_filters=d.num_upsample_filters)
    if method == "v2xvit":
        v = cfg.v2xvit
        return V2XViT(detector=detector, dim=v.dim, depth=v.depth, heads=v.heads, dim_head=v.dim_head,
                      window_sizes=v.window_sizes, window_heads=v.window_heads, window_dim_heads=v.window_dim_heads,
                      mlp_dim=v.mlp_dim, dropout=v.dropout)
    return {"none": NoFusion, "early": EarlyFusion, "late": LateFusion, "attfuse": AttFuse}[method](detector=detector)


def box_coder(cfg: FusionConfig, model: nn.Module) -> AnchorBoxCoder:
    """Anchors on the grid of ``model``'s head."""
    d = cfg.detector
    return AnchorBoxCoder(lidar_range=d.lidar_range, voxel_size=d.voxel_size, feature_stride=model.feature_stride,
                          anchor_size=d.anchor_size, anchor_z=d.anchor_z)


# ------------------------------------------------------------------ inputs


def _collate(parts: Sequence[tuple[dict, int]]) -> dict[str, torch.Tensor]:
    """Single-cloud pillar dicts -> one dict, part k at batch index ``parts[k][1]``."""
    coords = []
    for p, b in parts:
        c = p["voxel_coords"].clone()
        c[:, 0] = b
        coords.append(c)
    return {"voxel_features": torch.cat([p["voxel_features"] for p, _ in parts]),
            "voxel_coords": torch.cat(coords), "voxel_num_points": torch.cat([p["voxel_num_points"] for p, _ in parts])}


class Inputs:
    """Samples as network inputs: pillars of every cloud, of the merged early-fusion cloud, and
    anchor targets, each computed once on first use and reused by every batch and method."""

    def __init__(self, samples: Sequence[FusionSample], cfg: FusionConfig):
        self.samples = list(samples)
        if not self.samples:
            raise TypError("fusion", "samples", "at least one collaborative sample", 0)
        d = cfg.detector
        self._pillarize = lambda cloud: pillarize([cloud], lidar_range=d.lidar_range, voxel_size=d.voxel_size,
                                                  max_points_per_pillar=d.max_points_per_pillar,
                                                  max_pillars=d.max_pillars)
        self._pillars: dict[tuple[int, int], dict] = {}
        self._targets: dict[tuple[int, ...], dict] = {}

    def __len__(self) -> int:
        return len(self.samples)

    def pillars(self, i: int, slot: int) -> dict[str, torch.Tensor]:
        """Agent ``slot``'s cloud (slot -1: the early-fusion merge in the ego frame)."""
        key = (i, slot)
        if key not in self._pillars:
            s = self.samples[i]
            cloud = merge_agent_points(s.clouds, s.transforms) if slot < 0 else s.clouds[slot]
            self._pillars[key] = self._pillarize(cloud)
        return self._pillars[key]

    def targets(self, i: int, coder: AnchorBoxCoder, slot: int | None = None) -> dict[str, torch.Tensor]:
        """Anchor targets of the fused ground truth (slot None) or of agent ``slot``'s own labels."""
        key = (i, -1 if slot is None else slot, *coder.shape)
        if key not in self._targets:
            s = self.samples[i]
            self._targets[key] = coder.assign_targets(s.gt_boxes if slot is None else s.agent_boxes[slot])
        return self._targets[key]


@dataclass
class Batch:
    """One forward pass worth of samples, laid out as ``models/fusion.py`` wants them."""

    method: str
    indices: list[int]
    pillars: dict[str, torch.Tensor]
    agent_mask: torch.Tensor          # (B, L) bool
    transforms: torch.Tensor          # (B, L, 4, 4) float64 agent->ego
    time_delay: torch.Tensor          # (B, L) long, frames

    def to(self, device: torch.device) -> "Batch":
        return Batch(self.method, self.indices, {k: v.to(device) for k, v in self.pillars.items()},
                     self.agent_mask.to(device), self.transforms.to(device), self.time_delay.to(device))

    def run(self, model: nn.Module) -> dict[str, torch.Tensor]:
        b = len(self.indices)
        if self.method == "early":
            return model(self.pillars, batch_size=b)
        if self.method == "late":
            return model(self.pillars, agent_mask=self.agent_mask)
        return model(self.pillars, agent_mask=self.agent_mask, transforms=self.transforms,
                     time_delay=self.time_delay)


def make_batch(method: str, inputs: Inputs, indices: Sequence[int]) -> Batch:
    """Samples ``indices`` of ``inputs`` as one batch for ``method``: no fusion the ego's cloud and
    early fusion the merged one, one slot per sample; the others every agent, cloud ``b * L + l``."""
    indices = list(indices)
    samples = [inputs.samples[i] for i in indices]
    b = len(indices)
    width = 1 if method in ("none", "early") else max(s.num_agents for s in samples)
    mask = torch.zeros(b, width, dtype=torch.bool)
    transforms = torch.eye(4, dtype=torch.float64).repeat(b, width, 1, 1)
    delay = torch.zeros(b, width, dtype=torch.long)
    parts = []
    for k, (i, s) in enumerate(zip(indices, samples)):
        if method == "early":
            parts.append((inputs.pillars(i, -1), k))
            mask[k, 0] = True
            continue
        for slot in range(min(width, s.num_agents)):
            parts.append((inputs.pillars(i, slot), k * width + slot))
            mask[k, slot] = True
            transforms[k, slot] = torch.from_numpy(s.transforms[slot])
            delay[k, slot] = int(s.time_delay[slot])
    return Batch(method, indices, _collate(parts), mask, transforms, delay)


def batch_targets(batch: Batch, inputs: Inputs, coder: AnchorBoxCoder) -> dict[str, torch.Tensor]:
    """Stacked targets matching ``batch.run``'s output rows."""
    if batch.method == "late":      # one row per present agent, b-major, each with its own labels
        rows = [inputs.targets(batch.indices[k], coder, slot)
                for k, slot in batch.agent_mask.nonzero().tolist()]
    elif batch.method == "none":
        rows = [inputs.targets(i, coder, 0) for i in batch.indices]
    else:
        rows = [inputs.targets(i, coder) for i in batch.indices]
    return {k: torch.stack([r[k] for r in rows]) for k in rows[0]}


# ---------------------------------------------------------------- training


@dataclass
class Trained:
    """A trained method: the module, its anchors, and how it was made."""

    method: str
    model: nn.Module
    coder: AnchorBoxCoder
    key: str
    steps: int


def data_key(inputs: Inputs) -> str:
    """Identity of a training set for checkpoint keys: which frames, and a digest of their content."""
    items = [(s.scenario, s.timestamp, list(s.agent_ids), [len(c) for c in s.clouds],
              round(float(np.sum(s.gt_boxes)), 4), round(float(sum(np.sum(c[:, :3], dtype=np.float64)
                                                                  for c in s.clouds)), 2)) for s in inputs.samples]
    return hash_obj(items)[:16]


@torch.no_grad()
def recalibrate_batchnorm(model: nn.Module, method: str, inputs: Inputs, batch_size: int) -> None:
    """Running BatchNorm statistics := the exact average over ``inputs`` under the current weights."""
    norms = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)]
    if not norms:
        return
    saved = [m.momentum for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None                       # cumulative moving average
    model.train()
    with distributed.on_device(model) as dev:
        for start in range(0, len(inputs), batch_size):
            make_batch(method, inputs, range(start, min(start + batch_size, len(inputs)))).to(dev).run(model)
    for m, momentum in zip(norms, saved):
        m.momentum = momentum
    model.eval()


def learning_rate(peak: float, step: int, total: int) -> float:
    """Linear warm-up to ``peak`` over the first tenth of the run (at most :data:`WARMUP_STEPS`),
    then constant; a function of the step, so a resumed run continues on the same curve. (Runs
    of a few hundred steps or less end better at a constant rate than decayed.)"""
    warmup = max(1, min(WARMUP_STEPS, total // 10))
    return peak * min(1.0, (step + 1) / warmup)


def warm_start(model: nn.Module, single: Trained) -> None:
    """Copy a single-agent detector's PointPillars (pillar net, backbone and, where the shapes
    agree, head) into ``model``; the fusion layers keep their fresh initialisation."""
    source = single.model.detector.state_dict()
    if isinstance(model, V2XViT):           # its own head sits on the transformer's width
        model.pillar_net.load_state_dict({k[len("pillar_net."):]: v for k, v in source.items()
                                          if k.startswith("pillar_net.")})
        model.backbone.load_state_dict({k[len("backbone."):]: v for k, v in source.items()
                                        if k.startswith("backbone.")})
    else:
        model.detector.load_state_dict(source)


def train(method: str, cfg: FusionConfig, inputs: Inputs, *, steps: int, out: Path, name: str,
          init: Trained | None = None, warm: Trained | None = None,
          log_fn: Callable[[dict, int], None] | None = None) -> Trained:
    """Train ``method`` for ``steps`` on ``inputs``, resumably under ``out/checkpoints/<name>/``.

    init: a trained model of the same method to fine-tune; warm: a single-agent (late-fusion)
    detector whose PointPillars weights start the model (:func:`warm_start`). Either way the peak
    learning rate is ``finetune_lr`` (``lr`` from scratch). Returns the model in eval mode."""
    if init is not None and init.method != method:
        raise TypError("fusion", "init", f"a pretrained {method} model", init.method)
    seed_everything(cfg.seed)
    model = build_model(method, cfg)
    if init is not None:
        model.load_state_dict(init.model.state_dict())
    elif warm is not None:
        warm_start(model, warm)
    if distributed.world_size() > 1 and distributed.device().type == "cuda":
        model = nn.SyncBatchNorm.convert_sync_batchnorm(model)  # batch statistics over the global batch
    coder = box_coder(cfg, model)
    criterion = DetectionLoss()
    peak = cfg.lr if init is None and warm is None else cfg.finetune_lr
    opt = torch.optim.Adam(model.parameters(), lr=peak, weight_decay=1e-4)
    key = hash_obj({"method": method, "cfg": as_dict(cfg), "steps": steps, "data": data_key(inputs),
                    "init": None if init is None else init.key, "warm": None if warm is None else warm.key})[:16]
    batch_size = min(cfg.batch_size, len(inputs))

    def step_fn(step: int) -> dict[str, float]:
        for group in opt.param_groups:
            group["lr"] = learning_rate(peak, step, steps)
        indices = batch_rng(cfg.seed, step).choice(len(inputs), size=batch_size, replace=False)
        (indices,) = distributed.local_batch(indices)
        batch = make_batch(method, inputs, indices)
        dev = distributed.device()
        targets = {k: v.to(dev) for k, v in batch_targets(batch, inputs, coder).items()}
        model.train()
        losses = criterion(batch.to(dev).run(model), targets)
        opt.zero_grad(set_to_none=True)
        losses["total_loss"].backward()
        opt.step()
        norm = grad_norm(model.parameters())
        return {"loss": float(losses["total_loss"].detach()), "cls_loss": float(losses["cls_loss"].detach()),
                "reg_loss": float(losses["reg_loss"].detach()), "grad_norm": norm}

    with distributed.on_device(model):
        run_loop(name=f"fusion {name}", total_steps=steps, step_fn=step_fn,
                 get_state=lambda: {"model": model.state_dict(), "opt": opt.state_dict()},
                 set_state=lambda s: (model.load_state_dict(s["model"]), opt.load_state_dict(s["opt"])),
                 checkpoint_dir=run_checkpoint_dir(out / "checkpoints" / name, key),
                 checkpoint_every=cfg.checkpoint_every,
                 log_fn=None if log_fn is None else
                 (lambda values, step: log_fn({f"{name}.{k}": v for k, v in values.items()}, step)
                  if step % LOG_EVERY == 0 or step == steps - 1 else None))
    recalibrate_batchnorm(model, method, inputs, batch_size)
    return Trained(method, model, coder, key, steps)


class ServedDetector(nn.Module):
    """A trained method called with a batch's arrays by name (``make_batch``'s layout), returning
    its head dict: what ``StageRun.log_model`` logs, so the MLflow model runs without typ's Batch."""

    def __init__(self, trained: Trained):
        super().__init__()
        self.method, self.model = trained.method, trained.model

    def forward(self, voxel_features, voxel_coords, voxel_num_points, agent_mask, transforms, time_delay):
        pillars = {"voxel_features": voxel_features.float(), "voxel_coords": voxel_coords.long(),
                   "voxel_num_points": voxel_num_points.long()}
        batch = Batch(self.method, list(range(agent_mask.shape[0])), pillars, agent_mask.bool(),
                      transforms.double(), time_delay.long())
        return batch.run(self.model)

    @staticmethod
    def example(method: str, inputs: Inputs, n: int = 2) -> dict[str, torch.Tensor]:
        """The named arrays of the first ``n`` samples of ``inputs``, as ``forward`` takes them."""
        batch = make_batch(method, inputs, range(min(n, len(inputs))))
        return {**batch.pillars, "agent_mask": batch.agent_mask, "transforms": batch.transforms,
                "time_delay": batch.time_delay}


def save(trained: Trained, path: Path) -> None:
    save_torch(path, {"method": trained.method, "key": trained.key, "steps": trained.steps,
                      "state_dict": trained.model.state_dict()})


# --------------------------------------------------------------- inference


def quantize(x: torch.Tensor, bits: int, dims: tuple[int, ...]) -> torch.Tensor:
    """Uniform min/max quantisation to ``2**bits`` levels and back, one (min, step) per slice
    reduced over ``dims`` (the spatial dims: one pair per channel)."""
    lo, hi = x.amin(dims, keepdim=True), x.amax(dims, keepdim=True)
    step = (hi - lo).clamp(min=1e-12) / (2 ** bits - 1)
    return torch.round((x - lo) / step) * step + lo


class _QuantizedAttFuse(AttFuse):
    """AttFuse whose cooperating agents' maps arrive quantised to ``bits`` (weights shared)."""

    def __init__(self, trained: AttFuse, bits: int):
        nn.Module.__init__(self)
        self.detector, self.feature_stride, self.bits = trained.detector, trained.feature_stride, bits

    def attend(self, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        others = quantize(x[:, 1:], self.bits, (3, 4))
        return AttFuse.attend(torch.cat([x[:, :1], others], 1), mask)


@contextlib.contextmanager
def compressed(trained: Trained, bits: int | None, batch_holder: list):
    """The model to run with cooperating agents' features quantised to ``bits`` (None: as is)."""
    model = trained.model
    if bits is None:
        yield model
        return
    if trained.method == "attfuse":
        yield _QuantizedAttFuse(model, bits).eval()
        return
    if trained.method != "v2xvit":
        raise TypError("fusion", "compression", "an intermediate-fusion method (attfuse, v2xvit)", trained.method)

    def hook(module, args, output):          # rows: present slots, b-major; quantise all but the egos
        mask = batch_holder[0].agent_mask
        ego = torch.zeros_like(mask)
        ego[:, 0] = True
        sent = ~ego[mask]
        if sent.any():
            output = output.clone()
            output[sent] = quantize(output[sent], bits, (2, 3))
        return output

    handle = model.shrink.register_forward_hook(hook)
    try:
        yield model
    finally:
        handle.remove()


@torch.no_grad()
def predict(trained: Trained, inputs: Inputs, cfg: FusionConfig, *, bits: int | None = None,
            batch_size: int = 4) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per sample (boxes (K, 7) float64 in the ego frame, scores (K,)): boxes above the score
    threshold, inside the detection range in x/y (OpenCOOD drops the others), after rotated NMS."""
    trained.model.eval()
    holder: list = [None]
    out = []
    with compressed(trained, bits, holder) as model, distributed.on_device(trained.model) as dev:
        for start in range(0, len(inputs), batch_size):
            batch = make_batch(trained.method, inputs, range(start, min(start + batch_size, len(inputs))))
            holder[0] = batch.to(dev)
            head = {k: v.cpu() for k, v in holder[0].run(model).items()}   # decoded on the CPU with ``batch``
            if trained.method == "late":
                per = LateFusion.boxes_in_ego(head, trained.coder, agent_mask=batch.agent_mask,
                                              transforms=batch.transforms, score_threshold=cfg.score_threshold,
                                              max_boxes_per_agent=cfg.max_boxes)
            else:
                per = trained.coder.decode_predictions(head, score_threshold=cfg.score_threshold,
                                                       max_boxes=cfg.max_boxes)
            for boxes, scores in per:
                b, s = boxes.double().numpy(), scores.double().numpy()
                inside = boxes_in_range(b, cfg.detector.lidar_range, xy_only=True)
                b, s = b[inside], s[inside]
                keep = nms_bev(b, s, cfg.nms_threshold)[:cfg.max_boxes] if len(b) else np.zeros(0, np.int64)
                out.append((b[keep], s[keep]))
    return out


def _finite(v: float) -> float | None:
    return None if v is None or not math.isfinite(v) else round(float(v), 4)


def evaluate(preds, inputs: Inputs) -> dict[str, dict[str, float | None]]:
    """``{"ap50": {"overall", "0-30", "30-50", "50-100"}, "ap70": {...}}``; None where a band has no gt."""
    gts = [s.gt_boxes for s in inputs.samples]
    return {name: {k: _finite(v) for k, v in ap_by_range(preds, gts, iou_thr=thr).items()}
            for name, thr in IOU_THRESHOLDS.items()}


def pr_curve(preds, inputs: Inputs, iou_thr: float = 0.5) -> dict[str, list[float]]:
    """Overall precision (interpolated: OpenCOOD's ``mpre``) against recall after each detection of
    the ranking; without OpenCOOD's padding point (recall 1, precision 0), which no detection reached."""
    c = pr_curves(preds, [s.gt_boxes for s in inputs.samples], iou_thr=iou_thr)["overall"]
    return {"recall": c.mrec[1:-1].round(4).tolist(), "precision": c.mpre[1:-1].round(4).tolist()}


def bytes_per_message(trained: Trained, inputs: Inputs, cfg: FusionConfig, *, bits: int | None = None,
                      preds_per_agent: float | None = None) -> float:
    """Mean bytes one cooperating agent sends the ego per frame (0 without cooperating agents)."""
    sent = [(i, slot) for i, s in enumerate(inputs.samples) for slot in range(1, s.num_agents)]
    if not sent or trained.method == "none":
        return 0.0
    if trained.method == "early":
        return float(np.mean([len(inputs.samples[i].clouds[slot]) for i, slot in sent]) * BYTES_PER_POINT)
    if trained.method == "late":
        return float((preds_per_agent or 0.0) * BYTES_PER_BOX)
    model = trained.model
    if trained.method == "v2xvit":
        stride = model.feature_stride
        maps = [(cfg.v2xvit.dim, model.ny // stride, model.nx // stride)]
    else:
        det = model.detector
        maps = [(c, det.ny // s, det.nx // s) for c, s in zip(det.backbone.level_channels, det.backbone.level_strides)]
    value_bits = 32 if bits is None else bits
    return float(sum(c * h * w * value_bits / 8 + (0 if bits is None else 8 * c) for c, h, w in maps))


@torch.no_grad()
def late_boxes_per_agent(trained: Trained, inputs: Inputs, cfg: FusionConfig) -> float:
    """Mean boxes (score > threshold) a cooperating agent sends in late fusion."""
    counts = []
    with distributed.on_device(trained.model) as dev:
        for start in range(0, len(inputs), 4):
            batch = make_batch("late", inputs, range(start, min(start + 4, len(inputs))))
            head = {k: v.cpu() for k, v in batch.to(dev).run(trained.model).items()}
            per = trained.coder.decode_predictions(head, score_threshold=cfg.score_threshold, max_boxes=cfg.max_boxes)
            slots = batch.agent_mask.nonzero()[:, 1].tolist()
            counts += [len(boxes) for slot, (boxes, _) in zip(slots, per) if slot > 0]
    return float(np.mean(counts)) if counts else 0.0


# ------------------------------------------------------------- experiments


@dataclass(frozen=True)
class Roots:
    """The OPV2V-layout split folders the benchmark reads."""

    real_train: Path        # real_cav/train: the collaborative training data (V2V4Real analogue)
    real_test: Path         # real_cav/test: every evaluation, true clouds
    generated_cavs: Path    # the same scenarios with TYP-generated cooperating clouds
    source: Path            # simulated source/train (OPV2V analogue)
    colwaymo: Path          # generated target/train: real ego + generated references (ColWaymo analogue)

    @classmethod
    def from_config(cls, cfg: FusionConfig, root: Path) -> "Roots":
        sim, gen = root / cfg.sim, root / cfg.generated
        return cls(sim / cfg.real_domain / cfg.train_split, sim / cfg.real_domain / cfg.test_split,
                   gen / cfg.real_domain / cfg.train_split, sim / cfg.source_domain / cfg.source_split,
                   gen / cfg.colwaymo_domain / cfg.colwaymo_split)


def unavailable(folder: Path) -> str | None:
    """Why ``folder`` holds no scenarios to use (None: it does)."""
    if not folder.is_dir():
        return f"{folder} does not exist (the generate stage writes it)"
    if not list_scenarios(folder):
        return f"{folder} holds no scenario"
    return None


class Benchmark:
    """The runs of one stage execution: datasets read once, models trained once and kept by name."""

    def __init__(self, cfg: FusionConfig, roots: Roots, out: Path, *,
                 log_fn: Callable[[dict, int], None] | None = None):
        self.cfg, self.roots, self.out, self.log_fn = cfg, roots, out, log_fn
        self._datasets: dict[tuple, FusionDataset] = {}
        self._inputs: dict[tuple, Inputs] = {}
        self.models: dict[str, Trained] = {}
        self.seconds: dict[str, float] = {}
        self.test = self.inputs(roots.real_test)

    def dataset(self, root: Path, *, cav_root: Path | None = None, max_scenarios: int | None = None,
                **perturbation) -> FusionDataset:
        """A split, read once; perturbed variants share its files in memory."""
        base_key = (str(root), str(cav_root), max_scenarios)
        if base_key not in self._datasets:
            self._datasets[base_key] = FusionDataset(
                root, lidar_range=self.cfg.detector.lidar_range, comm_range=self.cfg.comm_range, cav_root=cav_root,
                seed=self.cfg.seed, max_scenarios=max_scenarios, max_agents=self.cfg.max_agents)
        base = self._datasets[base_key]
        return base.with_options(**perturbation) if perturbation else base

    def inputs(self, root: Path, **kw) -> Inputs:
        key = (str(root), *sorted((k, str(v)) for k, v in kw.items()))
        if key not in self._inputs:
            self._inputs[key] = Inputs(list(self.dataset(root, **kw)), self.cfg)
        return self._inputs[key]

    def run(self, name: str, method: str, inputs: Inputs, steps: int, *, init: Trained | None = None,
            warm: Trained | None = None) -> Trained:
        """Train (or return the already trained) run ``name``; its weights go to ``<out>/models/<name>.pt``."""
        if name not in self.models:
            t0 = time.perf_counter()
            trained = train(method, self.cfg, inputs, steps=steps, out=self.out, name=name, init=init, warm=warm,
                            log_fn=self.log_fn)
            save(trained, self.out / "models" / f"{name}.pt")
            self.models[name] = trained
            self.seconds[name] = round(time.perf_counter() - t0, 3)
        return self.models[name]

    def score(self, trained: Trained, inputs: Inputs | None = None, *, bits: int | None = None) -> dict:
        inputs = self.test if inputs is None else inputs
        return evaluate(predict(trained, inputs, self.cfg, bits=bits), inputs)

    def from_scratch(self, prefix: str, method: str, inputs: Inputs, steps: int) -> Trained:
        """``method`` trained on ``inputs`` without pre-training, as run ``<prefix>-<method>``.

        With ``warm_start``, early and intermediate fusion start from the single-agent detector of
        the same data (the late-fusion run ``<prefix>-late``, ``steps`` long) and train for
        ``warm_start_steps``; no and late fusion always start from random weights."""
        if self.cfg.warm_start and method in WARM_STARTED:
            single = self.run(f"{prefix}-late", "late", inputs, steps)
            return self.run(f"{prefix}-{method}", method, inputs, self.cfg.warm_start_steps, warm=single)
        return self.run(f"{prefix}-{method}", method, inputs, steps)

    def oracle(self, method: str) -> Trained:
        """``method`` trained on real_cav/train with the true clouds (Table 2's oracle row)."""
        return self.from_scratch("oracle", method, self.inputs(self.roots.real_train), self.cfg.steps)


def oracle_vs_generated(bench: Benchmark) -> dict:
    """TYP Tables 1–2: every method trained on real_cav/train with the true cooperating clouds
    (``oracle``) or with TYP's generated ones (``generated``), all evaluated on real_cav/test with
    true clouds; No Fusion sees the ego only (``ego``). Generated rows without generated data
    are ``{"skipped": reason}``. Also keeps each row's PR curve (AP@0.5, overall)."""
    cfg, roots = bench.cfg, bench.roots
    reason = unavailable(roots.generated_cavs)
    table: dict = {}
    for method in cfg.methods:
        oracle = bench.oracle(method)
        preds = predict(oracle, bench.test, cfg)
        row = {"ego" if method == "none" else "oracle": {**evaluate(preds, bench.test),
                                                         "pr": pr_curve(preds, bench.test)}}
        if method != "none":
            if reason:
                row["generated"] = {"skipped": reason}
            else:
                generated = bench.from_scratch("generated", method,
                                               bench.inputs(roots.real_train, cav_root=roots.generated_cavs), cfg.steps)
                preds = predict(generated, bench.test, cfg)
                row["generated"] = {**evaluate(preds, bench.test), "pr": pr_curve(preds, bench.test)}
        table[method] = row
    return table


def finetune_sets(bench: Benchmark) -> dict[str, int | None]:
    """Fine-tuning set name -> number of real_cav/train scenarios (None: all)."""
    n_all = len(list_scenarios(bench.roots.real_train))
    return {"0": 0, **{str(n): n for n in sorted(set(bench.cfg.finetune_scenes)) if n < n_all}, "all": None}


def pretrain_finetune(bench: Benchmark) -> dict:
    """TYP Table 3: pre-train on generated target data (``colwaymo``) or simulated source data
    (``source``) or not at all (``scratch``), fine-tune on 0, ``finetune_scenes`` and all
    real_cav/train scenarios, evaluate on real_cav/test. No Fusion is trained from scratch on
    the ego's data only, as TYP's "ego's gt only" row. A scratch model fine-tuned on 0 scenes
    does not exist (None); scratch on all scenes is the oracle run of Tables 1–2."""
    cfg, roots = bench.cfg, bench.roots
    sets = finetune_sets(bench)
    real = {name: bench.inputs(roots.real_train, max_scenarios=n) if n else bench.inputs(roots.real_train)
            for name, n in sets.items() if n != 0}
    table: dict = {m: {} for m in cfg.methods}
    for source, root in (("colwaymo", roots.colwaymo), ("source", roots.source)):
        reason = unavailable(root)
        for method in cfg.methods:
            if method == "none":
                continue
            if reason:
                table[method][source] = {"skipped": reason}
                continue
            pre = bench.from_scratch(f"pretrain-{source}", method, bench.inputs(root), cfg.pretrain_steps)
            row = {"0": bench.score(pre)}
            for name, inputs in real.items():
                row[name] = bench.score(bench.run(f"finetune{name}-{source}-{method}", method, inputs,
                                                  cfg.finetune_steps, init=pre))
            table[method][source] = row
    for method in cfg.methods:
        row = {"0": None}
        for name, inputs in real.items():
            trained = bench.oracle(method) if name == "all" else \
                bench.from_scratch(f"scratch{name}", method, inputs, cfg.steps)
            row[name] = bench.score(trained)
        table[method]["scratch"] = row
    return table


def robustness(bench: Benchmark) -> dict:
    """V2VSSC §IV on the oracle models: AP against cooperating agents' position noise σ (m),
    heading noise σ (deg), time delay (ms; earlier frames, clamped at the sequence start) and, for
    intermediate fusion, feature quantisation, with the bytes each message takes."""
    cfg, r = bench.cfg, bench.cfg.robustness
    test_root = bench.roots.real_test
    sweeps = {"position_std": [(v, {"position_std": v}) for v in r.position_std],
              "heading_std_deg": [(v, {"heading_std_deg": v}) for v in r.heading_std_deg],
              "delay_ms": [(v, {"delay_frames": v // 100}) for v in r.delay_ms]}
    out: dict = {"levels": {k: [v for v, _ in levels] for k, levels in sweeps.items()},
                 "quantization_bits": [32, *r.quantization_bits], "methods": {}}
    for method in cfg.methods:
        trained = bench.oracle(method)
        clean = bench.score(trained)
        entry: dict = {}
        for sweep, levels in sweeps.items():
            entry[sweep] = [clean if not any(kw.values()) else bench.score(trained, bench.inputs(test_root, **kw))
                            for _, kw in levels]
        boxes = late_boxes_per_agent(trained, bench.test, cfg) if method == "late" else None
        entry["bytes_per_message"] = bytes_per_message(trained, bench.test, cfg, preds_per_agent=boxes)
        if method in INTERMEDIATE:
            entry["quantization"] = [{"bits": 32, "bytes_per_message": entry["bytes_per_message"], **clean}]
            for bits in r.quantization_bits:
                entry["quantization"].append({"bits": bits, **bench.score(trained, bits=bits),
                                              "bytes_per_message": bytes_per_message(trained, bench.test, cfg,
                                                                                     bits=bits)})
        out["methods"][method] = entry
    return out


# ------------------------------------------------------------------ report

def summarize(bench: Benchmark, table2: dict, table3: dict, curves: dict) -> dict:
    """Everything the stage measured, JSON-able: ``results.json`` and the source of the report."""
    test = bench.test.samples
    return {"test_frames": len(test), "test_gt_boxes": int(sum(len(s.gt_boxes) for s in test)),
            "test_gt_boxes_by_band": {b: int(sum(((lo < d) & (d < hi)).sum() for d in
                                                 (np.hypot(s.gt_boxes[:, 0], s.gt_boxes[:, 1]) for s in test)))
                                      for b, (lo, hi) in (("0-30", (0, 30)), ("30-50", (30, 50)),
                                                          ("50-100", (50, 100)))},
            "train_frames": len(bench.inputs(bench.roots.real_train)),
            "finetune_sets": {k: ("all" if v is None else v) for k, v in finetune_sets(bench).items()},
            "runs": len(bench.models), "seconds_per_run": dict(bench.seconds),
            "table2": table2, "table3": table3, "robustness": curves}
