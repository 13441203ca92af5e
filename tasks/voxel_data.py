"""Voxelized views as training tensors: sparse in memory, dense one batch at a time.

The target domain is single-agent data: training code reads only each scenario's ego view
(OpenCOOD's ego, the agent that sorts first); the other agents of simulated target
scenarios are hidden truth for evaluation (``ego_only=False``).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from typ.errors import TypError
from typ.store import SparseRecord, densify, list_scenes, read_scene_indices
from typ.voxel import Grid


def _ego_order(agent_ids) -> list[str]:
    """OpenCOOD's agent order (see typ.formats.opv2v.list_agents): sorted strings, RSUs last."""
    def rsu(a: str) -> bool:
        return a.lstrip("-").isdigit() and int(a) < 0

    names = sorted(set(agent_ids))
    return [a for a in names if not rsu(a)] + [a for a in names if rsu(a)]


@dataclass
class ViewSet:
    """Views of one dataset/split: ``keys[i] = (scene, agent_id, timestamp)``, sparse records."""

    grid: Grid
    keys: list[tuple[str, str, str]]
    records: list[SparseRecord]

    def __len__(self) -> int:
        return len(self.keys)

    def head(self, n: int) -> "ViewSet":
        """The first ``n`` views, as a new set."""
        return ViewSet(self.grid, self.keys[:n], self.records[:n])

    def occupancy(self, index) -> np.ndarray:
        """(B, C, H, W) float32 occupancy x for the given view indices (height as channels)."""
        return np.stack([densify(self.records[i], self.grid)[0].transpose(2, 0, 1) for i in index]).astype(np.float32)

    def box_maps(self, index) -> np.ndarray:
        """(B, 1, H, W) float32 box maps y."""
        return np.stack([densify(self.records[i], self.grid)[1].transpose(2, 0, 1) for i in index]).astype(np.float32)

    def batch(self, index, *, flips: np.ndarray | None = None,
              dihedral: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(x, y) tensors of views ``index``, optionally transformed per sample.

        flips[b]: mirror sample b across the x axis (y -> -y). dihedral[b] in 0..7: one of the
        8 symmetries of the square grid (:func:`dihedral`). Both are valid LiDAR augmentations:
        a spinning sensor at the grid's centre sees a rotated or mirrored street the same way,
        and the boxes turn with it.
        """
        x, y = self.occupancy(index), self.box_maps(index)
        if flips is not None:
            x[flips] = x[flips][:, :, :, ::-1]
            y[flips] = y[flips][:, :, :, ::-1]
        if dihedral is not None:
            x = np.stack([apply_dihedral(v, int(k)) for v, k in zip(x, dihedral)])
            y = np.stack([apply_dihedral(v, int(k)) for v, k in zip(y, dihedral)])
        return torch.from_numpy(np.ascontiguousarray(x)), torch.from_numpy(np.ascontiguousarray(y))


def apply_dihedral(grid: np.ndarray, k: int) -> np.ndarray:
    """Symmetry ``k`` (0..7) of the square BEV grid about its centre: (..., H, W) -> same shape.

    k = 0..3 rotate by k·90° (x towards y); k = 4..7 mirror across the x axis first (y -> -y).
    k = 0 is the identity. With H = W and the sensor at the centre, every k maps a view to a
    view the same sensor could have taken.
    """
    if not 0 <= k < 8:
        raise TypError("apply_dihedral", "k", "an integer in 0..7", k)
    if k >= 4:
        grid = grid[..., ::-1]
    return np.rot90(grid, k % 4, axes=(-2, -1))


def load_views(store_root: Path, *, dataset: str, split: str, ego_only: bool = True) -> ViewSet:
    """Every (scene, agent, timestamp) of ``dataset/split`` in the voxel store, in a stable order."""
    scenes = list_scenes(store_root, dataset=dataset, split=split)
    if not scenes:
        raise TypError(store_root, f"dataset={dataset}/split={split}",
                       "voxelized scenes of that dataset and split (check simulate.scenarios and voxelize)",
                       "none found")
    grid = None
    keys, records = [], []
    for s in scenes:
        g, _, sparse = read_scene_indices(s.path)
        if grid is None:
            grid = g
        elif g != grid:
            raise TypError(s.path, "grid", f"the same grid as the other scenes {grid.to_dict()}", g.to_dict())
        ego = _ego_order(a for a, _ in sparse)[0]
        for (agent, ts), rec in sparse.items():
            if ego_only and agent != ego:
                continue
            keys.append((s.scene, agent, ts))
            records.append(rec)
    return ViewSet(grid, keys, records)
