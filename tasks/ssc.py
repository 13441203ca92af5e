"""Collaborative semantic scene completion (V2VSSC): samples with their maps, training, no/late fusion, scores.

Data: the fusion samples of :class:`tasks.fusion_data.FusionDataset` (OPV2V layout, 70 m
communication range, delay and pose noise as there) on V2VSSC's grid, each with the semantic
occupancy maps written beside the clouds (:mod:`typ.ssc`). The network is one single-agent
model, :func:`models.ssc.ssc_detector` under :class:`models.fusion.NoFusion`, trained on every
agent's own cloud against its own map with class-balanced cross-entropy (the weights from the
training maps' class counts, :func:`models.ssc.class_weights`). No fusion runs it on the ego's
cloud; late fusion runs it on every agent in range and merges the maps in the ego frame,
keeping per voxel the most confident agent (:func:`models.ssc.merge_max_confidence`).
Early and intermediate fusion (AttFuse, V2X-ViT) are not built here yet.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from models.fusion import NoFusion
from models.ssc import SSC_LIDAR_RANGE, class_weights, merge_max_confidence, ssc_detector, warp_to_ego
from tasks.fusion_data import FusionDataset, FusionSample
from typ.errors import TypError
from typ.metrics.ssc import SSC_CLASSES, ssc_iou
from typ.ssc import SSC_GRID, occupancy_path, read_occupancy

#: fusion methods this module runs
METHODS: tuple[str, ...] = ("no_fusion", "late_fusion")


def ssc_dataset(root, **kw) -> FusionDataset:
    """:class:`FusionDataset` of a split folder on V2VSSC's range (other options as there)."""
    return FusionDataset(root, lidar_range=SSC_LIDAR_RANGE, **kw)


def sample_maps(ds: FusionDataset, i: int, sample: FusionSample | None = None) -> list[np.ndarray]:
    """(X, Y, Z) uint8 maps of sample ``i``'s agents, each in its own frame at the frame its cloud
    was sent (the ego's: now); index 0 is the ego's ground truth."""
    sample = ds[i] if sample is None else sample
    s, t = ds.index[i]
    folder, _, stamps = ds.scenarios[s]
    return [read_occupancy(occupancy_path(folder, agent, stamps[t - int(d)]))
            for agent, d in zip(sample.agent_ids, sample.time_delay)]


@dataclass
class SscModel:
    """A trained single-agent SSC network and how it was trained."""

    model: NoFusion
    weights: np.ndarray
    losses: list[float]


def train(ds: FusionDataset, *, steps: int, seed: int, lr: float = 2e-3, model_kw: dict | None = None) -> SscModel:
    """Train :func:`models.ssc.ssc_detector` for ``steps`` steps of one agent view each (the views of
    every sample in turn, order from ``seed``) with class-weighted cross-entropy; Adam, cosine decay."""
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise TypError("tasks.ssc.train", "steps", "an integer >= 1", steps)
    torch.manual_seed(seed)
    views = []
    for i in range(len(ds)):
        sample = ds[i]
        for cloud, labels in zip(sample.clouds, sample_maps(ds, i, sample)):
            views.append((cloud, labels))
    counts = np.bincount(np.concatenate([v[1].reshape(-1) for v in views]), minlength=len(SSC_CLASSES))
    weights = class_weights(counts)
    det = ssc_detector(**(model_kw or {}))
    model = NoFusion(detector=det)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=steps)
    order = np.random.default_rng(seed).permutation(np.resize(np.arange(len(views)), steps))
    w = torch.tensor(weights, dtype=torch.float32)
    one = torch.ones(1, 1, dtype=torch.bool)
    losses = []
    model.train()
    for k in order:
        cloud, labels = views[k]
        logits = model(det.pillarize([cloud]), agent_mask=one)["occ"]
        loss = F.cross_entropy(logits, torch.as_tensor(labels, dtype=torch.long)[None], weight=w)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(loss.item())
    model.eval()
    return SscModel(model, weights, losses)


@torch.no_grad()
def _predict_own(trained: SscModel, clouds: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """(L, X, Y, Z) labels and max-softmax confidences of each cloud in its own frame."""
    det = trained.model.detector
    mask = torch.ones(len(clouds), 1, dtype=torch.bool)
    probs = trained.model(det.pillarize(list(clouds)), agent_mask=mask)["occ"].softmax(1)
    conf, labels = probs.max(1)
    return labels, conf


def predict(trained: SscModel, sample: FusionSample, method: str) -> np.ndarray:
    """(X, Y, Z) uint8 ego-frame map of ``sample`` by ``method`` (:data:`METHODS`)."""
    if method not in METHODS:
        raise TypError("tasks.ssc.predict", "method", f"one of {METHODS}", method)
    clouds = sample.clouds[:1] if method == "no_fusion" else sample.clouds
    labels, conf = _predict_own(trained, clouds)
    if method == "no_fusion":
        return labels[0].numpy().astype(np.uint8)
    kw = dict(lower=SSC_GRID.lower, voxel=SSC_GRID.voxel.tolist())
    warped = [warp_to_ego(labels[j], conf[j], sample.transforms[j], **kw) for j in range(len(clouds))]
    merged, _ = merge_max_confidence(torch.stack([w[0] for w in warped]), torch.stack([w[1] for w in warped]))
    return merged.numpy().astype(np.uint8)


def evaluate(trained: SscModel, ds: FusionDataset, method: str) -> dict:
    """:func:`typ.metrics.ssc_iou` of ``method``'s ego maps against the ego's truth, pooled over ``ds``;
    ``iou_per_class`` as a {class: IoU} dict, the confusion matrix dropped."""
    preds, gts = [], []
    for i in range(len(ds)):
        sample = ds[i]
        preds.append(predict(trained, sample, method))
        gts.append(read_occupancy(occupancy_path(ds.scenarios[ds.index[i][0]][0], sample.agent_ids[0],
                                                 sample.timestamp)))
    r = ssc_iou(preds, gts, len(SSC_CLASSES))
    return {"iou": r["iou"], "miou": r["miou"], "ciou": r["ciou"], "precision": r["precision"],
            "recall": r["recall"], "iou_per_class": dict(zip(SSC_CLASSES[1:], r["iou_per_class"].tolist())),
            "frames": len(gts)}
