"""typ's FRID / FPVD feature networks (:mod:`models.lidar_features`): inputs, labels, training, features.

- FRID network: range images of the stage's layout (unit depth, one channel) -> the semantic
  class of every pixel's point (the pixel's nearest point, :func:`typ.projection.range_image`).
- FPVD network: voxel occupancy (``features.voxel_grid``, height bins as channels) -> the
  majority semantic class of every occupied voxel.

Both learn from the simulator's per-point labels (``AgentView.semantics``) of the training
split; the held-out split's mIoU goes to the report so a reader can see the features mean
something. Output: ``<out>/features/{range,voxel}/`` as :mod:`typ.artifacts` writes them (the config
holds the run key; a matching key is loaded instead of retrained) and resumable checkpoints
under ``<out>/checkpoints/features-<kind>/<key>/``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

import models.lidar_features
import typ.artifacts
import typ.projection
from models.lidar_features import SegmentationFeatureNet
from tasks.training import batch_rng, grad_norm, run_checkpoint_dir, run_loop, seed_everything
from typ import distributed
from typ.artifacts import load_if_key, save_module
from typ.config import FeatureNetConfig, as_dict
from typ.io import code_digest, hash_obj
from typ.projection import RangeLayout, range_image, to_unit, voxel_indices
from typ.scene import SEMANTIC_CLASSES
from typ.voxel import Grid, voxelize

IGNORE = 255
NUM_CLASSES = len(SEMANTIC_CLASSES)
KINDS = ("range", "voxel")
STAGE = "ddpm"
#: part of the run key (typ.artifacts: the saved folder's layout, so that a folder in an older
#: layout is retrained, not misread)
_CODE = code_digest(models.lidar_features, typ.projection, typ.artifacts)


def range_input(points: np.ndarray, layout: RangeLayout) -> np.ndarray:
    """(1, H, W) float32 unit depth (-1 = no return); an empty cloud gives an empty image."""
    if len(points) == 0:
        return np.full((1, *layout.shape), -1.0, dtype=np.float32)
    return to_unit(range_image(points, layout), layout)


def voxel_input(points: np.ndarray, grid: Grid) -> np.ndarray:
    """(C, H, W) float32 occupancy, height bins as channels."""
    if len(points) == 0:
        return np.zeros((grid.shape[2], grid.shape[0], grid.shape[1]), dtype=np.float32)
    return voxelize(points, grid).transpose(2, 0, 1).astype(np.float32)


def range_labels(points: np.ndarray, semantics: np.ndarray, layout: RangeLayout) -> np.ndarray:
    """(H, W) int64 class of each pixel's (nearest) point, IGNORE where empty."""
    _, labels = range_image(points, layout, values=semantics, fill=IGNORE)
    return labels.astype(np.int64)


def voxel_labels(points: np.ndarray, semantics: np.ndarray, grid: Grid) -> np.ndarray:
    """(C, H, W) int64 majority class of each occupied voxel (ties: the lower code), IGNORE elsewhere."""
    H, W, C = grid.shape
    i, j, k, inside = voxel_indices(points, grid)
    flat = ((i * W + j) * C + k)[inside]
    pair = flat * NUM_CLASSES + semantics[inside].astype(np.int64)
    pairs, counts = np.unique(pair, return_counts=True)
    voxel, label = pairs // NUM_CLASSES, pairs % NUM_CLASSES
    # per voxel the label with the most points: sort by (voxel, count, -label), take the last of each voxel
    order = np.lexsort((-label, counts, voxel))
    last = np.ones(len(order), dtype=bool)
    last[:-1] = voxel[order][1:] != voxel[order][:-1]
    out = np.full(H * W * C, IGNORE, dtype=np.int64)
    out[voxel[order][last]] = label[order][last]
    return out.reshape(H, W, C).transpose(2, 0, 1)


@dataclass
class FeatureNets:
    """The two trained networks with the layouts their inputs are made on."""

    range_net: SegmentationFeatureNet
    voxel_net: SegmentationFeatureNet
    layout: RangeLayout
    grid: Grid

    @torch.no_grad()
    def features(self, clouds: list[np.ndarray], batch_size: int = 16) -> dict[str, np.ndarray]:
        """{"frid": (N, D), "fpvd": (N, D)} float64 features of (N_i, >=3) point clouds."""
        out = {"frid": [], "fpvd": []}
        for net, make, key, spec in ((self.range_net, range_input, "frid", self.layout),
                                     (self.voxel_net, voxel_input, "fpvd", self.grid)):
            net.eval()
            for start in range(0, len(clouds), batch_size):
                x = np.stack([make(c, spec) for c in clouds[start:start + batch_size]])
                out[key].append(net.features(torch.from_numpy(x)).double().numpy())
        return {k: np.concatenate(v) for k, v in out.items()}


def _dataset(kind: str, scans, layout: RangeLayout, grid: Grid) -> tuple[torch.Tensor, torch.Tensor]:
    """(inputs, labels) of every scan with semantics; labels (N, H, W) or (N, C, H, W) int64."""
    xs, ys = [], []
    for s in scans:
        if kind == "range":
            xs.append(range_input(s.points, layout))
            ys.append(range_labels(s.points, s.semantics, layout))
        else:
            xs.append(voxel_input(s.points, grid))
            ys.append(voxel_labels(s.points, s.semantics, grid))
    return torch.from_numpy(np.stack(xs)), torch.from_numpy(np.stack(ys))


def _mirror(kind: str, x: torch.Tensor, flips: torch.Tensor) -> torch.Tensor:
    """Mirror across the x axis (y -> -y) where ``flips``: azimuth c -> (W - c) mod W in a range
    image, j -> W - 1 - j in a voxel grid symmetric in y."""
    if not bool(flips.any()):
        return x
    W = x.shape[-1]
    index = (W - torch.arange(W)) % W if kind == "range" else torch.arange(W - 1, -1, -1)
    x = x.clone()
    x[flips] = x[flips][..., index]
    return x


def _logits(kind: str, net: SegmentationFeatureNet, x: torch.Tensor) -> torch.Tensor:
    """(B, classes, H, W) for range; (B, classes, C, H, W) for voxel (classes x height channels)."""
    out = net(x)
    if kind == "voxel":
        b, _, h, w = out.shape
        out = out.view(b, NUM_CLASSES, -1, h, w)
    return out


def build(kind: str, cfg: FeatureNetConfig, grid: Grid) -> SegmentationFeatureNet:
    channels = 1 if kind == "range" else grid.shape[2]
    out = NUM_CLASSES if kind == "range" else NUM_CLASSES * grid.shape[2]
    return SegmentationFeatureNet(in_channels=channels, out_channels=out, width=cfg.width, levels=cfg.levels)


def _train_one(kind: str, cfg: FeatureNetConfig, seed: int, x: torch.Tensor, y: torch.Tensor, *, key: str,
               out: Path, log_fn: Callable[[dict, int], None]) -> SegmentationFeatureNet:
    seed_everything(seed)
    net = build(kind, cfg, _grid(cfg))
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr)
    ckpt_dir = run_checkpoint_dir(out / "checkpoints" / f"features-{kind}", key)

    def step_fn(step: int) -> dict[str, float]:
        rng = batch_rng(seed, step, stream=KINDS.index(kind) + 1)
        index = torch.from_numpy(rng.choice(len(x), size=cfg.batch_size, replace=len(x) < cfg.batch_size))
        flips = torch.from_numpy(rng.random(cfg.batch_size) < 0.5)
        xb, yb = _mirror(kind, x[index], flips), _mirror(kind, y[index], flips)
        xb, yb = distributed.local_batch(xb, yb)
        net.train()
        loss = F.cross_entropy(_logits(kind, net, xb), yb, ignore_index=IGNORE)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return {"loss": float(loss.detach()), "grad_norm": grad_norm(net.parameters())}

    with distributed.on_device(net):
        run_loop(name=f"ddpm features-{kind}", total_steps=cfg.steps, step_fn=step_fn,
                 state={"model": net, "opt": opt},
                 checkpoint_dir=ckpt_dir, curve=out / "loss" / f"features-{kind}.csv", checkpoint_every=max(1, cfg.steps // 4),
                 log_fn=lambda v, step: log_fn({f"ddpm.features_{kind}.{k}": val for k, val in v.items()}, step))
    return net.eval()


def _grid(cfg: FeatureNetConfig) -> Grid:
    g = cfg.voxel_grid
    return Grid(g.x_range, g.y_range, g.z_range, g.shape)


@torch.no_grad()
def miou(kind: str, net: SegmentationFeatureNet, x: torch.Tensor, y: torch.Tensor) -> dict[str, float]:
    """Mean IoU over the classes present in ``y`` (and per class) of the network's predictions."""
    net.eval()
    pred = torch.cat([_logits(kind, net, x[i:i + 16]).argmax(1) for i in range(0, len(x), 16)])
    valid = y != IGNORE
    scores = {}
    for c, name in enumerate(SEMANTIC_CLASSES):
        truth, guess = (y == c) & valid, (pred == c) & valid
        union = int((truth | guess).sum())
        if int(truth.sum()):
            scores[name] = int((truth & guess).sum()) / union
    return {"miou": float(np.mean(list(scores.values()))) if scores else float("nan"), **scores}


def train_feature_nets(cfg: FeatureNetConfig, seed: int, layout: RangeLayout, train_scans, test_scans, *,
                       out: Path, log_fn: Callable[[dict, int], None]) -> tuple[FeatureNets, dict]:
    """Train (or load, when the run key matches) both networks; returns them and their test mIoU."""
    grid = _grid(cfg)
    nets, scores = {}, {}
    data_key = [[list(s.key), int(len(s.points))] for s in train_scans]
    for kind in KINDS:
        folder = out / "features" / kind
        key = hash_obj({"cfg": as_dict(cfg), "seed": seed, "kind": kind, "layout": layout.to_dict(),
                        "data": data_key, "code": _CODE})[:16]
        found = load_if_key(folder, SegmentationFeatureNet.from_config, STAGE, key)
        if found is not None:
            net = found[0]
        else:
            x, y = _dataset(kind, train_scans, layout, grid)
            net = _train_one(kind, cfg, seed, x, y, key=key, out=out, log_fn=log_fn)
            if distributed.is_main():
                save_module(folder, net, net.config, key=key, layout=layout.to_dict(), voxel_grid=grid.to_dict(),
                            classes=list(SEMANTIC_CLASSES))
        nets[kind] = net
        scores[kind] = miou(kind, net, *_dataset(kind, test_scans, layout, grid))
    return FeatureNets(nets["range"], nets["voxel"], layout, grid), scores
