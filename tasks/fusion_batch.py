"""Collaborative samples as network inputs: augmentation, pillars, batches and anchor targets.

A batch is laid out as ``models/fusion`` wants it, for the ``inputs`` its method declares in
the registry (``models.fusion.METHODS``): ``ego`` — one slot per sample, the ego's cloud;
``merged`` — one slot per sample, every agent's cloud moved into the ego frame (early fusion);
``agents`` — L slots per sample, each agent's cloud in its own frame. Its targets follow the
method's ``targets``: ``own`` — a row per present slot, that agent's own labels in its own frame
(the single-agent detector, OpenCOOD's ``LateFusionDataset``); ``fused`` — a row per sample, the
fused ground truth in the ego frame.

Augmentation (OpenCOOD's ``data_augmentor``: ``random_world_flip`` along x, ``random_world_
rotation``, ``random_world_scaling``) is one global similarity ``A`` per sample, drawn from the
step's generator: every agent's cloud is mapped by ``A`` in its own frame, every box (the fused
ground truth in the ego frame, each agent's own labels in its frame) too, and each agent->ego
transform becomes ``A T A⁻¹``, so that it stays rigid and still carries an agent's (mapped) points
onto the ego's (mapped) frame: ``(A T A⁻¹)(A p) = A (T p)``.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from models.box_coder import AnchorBoxCoder
from models.fusion import METHODS, merge_agent_points
from models.pointpillars import pillarize
from tasks.fusion_data import FusionSample
from typ import geometry
from typ.config import AugmentConfig, FusionConfig
from typ.errors import TypError


# ------------------------------------------------------------ augmentation


def draw_similarity(rng: np.random.Generator, aug: AugmentConfig) -> np.ndarray:
    """(4, 4) float64 ``A = s R_z(θ) F``: F flips y with probability 0.5 (when ``aug.flip``),
    θ ~ U(-rotation_deg, rotation_deg), s ~ U(scale)."""
    flip = aug.flip and rng.random() < 0.5
    theta = np.radians(rng.uniform(-aug.rotation_deg, aug.rotation_deg))
    scale = rng.uniform(*aug.scale)
    c, s = np.cos(theta), np.sin(theta)
    a = np.eye(4)
    a[:3, :3] = scale * np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([1.0, -1.0 if flip else 1.0,
                                                                                      1.0])
    return a


def map_boxes(a: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(K, 7) boxes under the similarity ``a``: centre mapped, sizes scaled, yaw from the mapped heading."""
    out = geometry.transform_boxes(a, boxes)
    out[:, 3:6] *= np.cbrt(abs(np.linalg.det(a[:3, :3])))
    return out


def map_cloud(a: np.ndarray, cloud: np.ndarray) -> np.ndarray:
    """(n, F) float32 cloud with xyz mapped by ``a`` (in float64), the other features kept."""
    return geometry.transform_points(a, cloud).astype(np.float32)


def augment(sample: FusionSample, a: np.ndarray) -> FusionSample:
    """``sample`` seen through the global similarity ``a`` (module doc)."""
    inv = np.linalg.inv(a)
    return dataclasses.replace(
        sample, clouds=tuple(map_cloud(a, c) for c in sample.clouds),
        transforms=np.stack([a @ t @ inv for t in sample.transforms]),
        true_transforms=np.stack([a @ t @ inv for t in sample.true_transforms]),
        gt_boxes=map_boxes(a, sample.gt_boxes), agent_boxes=tuple(map_boxes(a, b) for b in sample.agent_boxes))


# ----------------------------------------------------------------- batches


def _collate(parts: Sequence[tuple[dict, int]]) -> dict[str, torch.Tensor]:
    """Single-cloud pillar dicts -> one dict, part k at batch index ``parts[k][1]``."""
    coords = []
    for p, b in parts:
        c = p["voxel_coords"].clone()
        c[:, 0] = b
        coords.append(c)
    return {"voxel_features": torch.cat([p["voxel_features"] for p, _ in parts]),
            "voxel_coords": torch.cat(coords), "voxel_num_points": torch.cat([p["voxel_num_points"] for p, _ in parts])}


@dataclass
class Batch:
    """One forward pass worth of samples, laid out as ``models/fusion`` wants them."""

    method: str
    samples: list[FusionSample]
    pillars: dict[str, torch.Tensor]
    agent_mask: torch.Tensor          # (B, L) bool
    transforms: torch.Tensor          # (B, L, 4, 4) float64 agent->ego
    time_delay: torch.Tensor          # (B, L) long, frames

    def to(self, device: torch.device) -> "Batch":
        return Batch(self.method, self.samples, {k: v.to(device) for k, v in self.pillars.items()},
                     self.agent_mask.to(device), self.transforms.to(device), self.time_delay.to(device))

    def run(self, model: torch.nn.Module) -> dict[str, torch.Tensor]:
        """The module's head dict: every method takes the same arguments."""
        return model(self.pillars, agent_mask=self.agent_mask, transforms=self.transforms, time_delay=self.time_delay)

    def targets(self, coder: AnchorBoxCoder) -> dict[str, torch.Tensor]:
        """Stacked anchor targets matching :meth:`run`'s output rows (module doc)."""
        if METHODS[self.method].targets == "own":   # one row per present slot, b-major, its own labels
            rows = [coder.assign_targets(self.samples[k].agent_boxes[slot])
                    for k, slot in self.agent_mask.nonzero().tolist()]
        else:
            rows = [coder.assign_targets(s.gt_boxes) for s in self.samples]
        return {k: torch.stack([r[k] for r in rows]) for k in rows[0]}


class Inputs:
    """Samples as network inputs; the pillars of every un-augmented cloud (and merged early-fusion
    cloud) are computed once on first use and reused by every batch and method."""

    def __init__(self, samples: Sequence[FusionSample], cfg: FusionConfig):
        self.samples = list(samples)
        if not self.samples:
            raise TypError("fusion", "samples", "at least one collaborative sample", 0)
        d = cfg.detector
        self._pillarize = lambda cloud: pillarize([cloud], lidar_range=d.lidar_range, voxel_size=d.voxel_size,
                                                  max_points_per_pillar=d.max_points_per_pillar,
                                                  max_pillars=d.max_pillars)
        self._pillars: dict[tuple[int, int], dict] = {}

    def __len__(self) -> int:
        return len(self.samples)

    @property
    def scenarios(self) -> list[str]:
        """The scenario of each sample."""
        return [s.scenario for s in self.samples]

    def _cloud_pillars(self, s: FusionSample, slot: int, key: tuple[int, int] | None) -> dict[str, torch.Tensor]:
        """Agent ``slot``'s cloud (-1: the merge in the ego frame), cached under ``key`` (None: not)."""
        if key is not None and key in self._pillars:
            return self._pillars[key]
        cloud = merge_agent_points(s.clouds, s.transforms) if slot < 0 else s.clouds[slot]
        out = self._pillarize(cloud)
        if key is not None:
            self._pillars[key] = out
        return out

    def batch(self, method: str, indices: Sequence[int], similarities: Sequence[np.ndarray] | None = None) -> Batch:
        """Samples ``indices`` as one batch for ``method`` (module doc), each seen through its
        similarity of ``similarities`` (None: as they are, with cached pillars)."""
        indices = list(indices)
        samples = [self.samples[i] for i in indices]
        if similarities is not None:
            samples = [augment(s, a) for s, a in zip(samples, similarities)]
        inputs = METHODS[method].inputs
        b = len(indices)
        width = 1 if inputs in ("ego", "merged") else max(s.num_agents for s in samples)
        mask = torch.zeros(b, width, dtype=torch.bool)
        transforms = torch.eye(4, dtype=torch.float64).repeat(b, width, 1, 1)
        delay = torch.zeros(b, width, dtype=torch.long)
        parts = []
        for k, (i, s) in enumerate(zip(indices, samples)):
            cache = similarities is None
            if inputs == "merged":
                parts.append((self._cloud_pillars(s, -1, (i, -1) if cache else None), k))
                mask[k, 0] = True
                continue
            for slot in range(min(width, s.num_agents)):
                parts.append((self._cloud_pillars(s, slot, (i, slot) if cache else None), k * width + slot))
                mask[k, slot] = True
                transforms[k, slot] = torch.from_numpy(s.transforms[slot])
                delay[k, slot] = int(s.time_delay[slot])
        return Batch(method, samples, _collate(parts), mask, transforms, delay)
