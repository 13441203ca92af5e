"""The data of stage ``ssc`` (module :mod:`tasks.ssc`): the fusion samples on V2VSSC's grid with their
semantic occupancy maps, the methods' networks and names, and what the networks learn from
(:class:`TrainingSet`: every agent's view, every sample with its ego map; generated views and
their footprints)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from models.ssc import SSC_LIDAR_RANGE
from tasks.fusion_data import FusionDataset, FusionSample
from typ.config import SscConfig
from typ.errors import TypError
from typ.io import hash_obj
from typ.metrics.ssc import FIGURES as SSC_FIGURES, SSC_CLASSES
from typ.registry import METHODS, SINGLE_AGENT
from typ.ssc import SSC_GRID, occupancy_path, read_occupancy


STAGE = "ssc"
#: the network each method runs (no and late fusion share the single-agent one), from the registry
NETWORK = {m.name: "single" if m.network == SINGLE_AGENT else m.network for m in METHODS.values()}
#: display names of the methods, V2VSSC Table I's rows
DISPLAY = {m.name: m.intermediate_display for m in METHODS.values()}
#: the figures scored, each with an interval: geometric, semantic and per class (declared in typ.metrics.ssc)
FIGURES = tuple(SSC_FIGURES)
N_CLASSES = len(SSC_CLASSES)


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


def ego_map(ds: FusionDataset, i: int, sample: FusionSample) -> np.ndarray:
    """The ego's true (X, Y, Z) map of sample ``i`` (its current frame)."""
    return read_occupancy(occupancy_path(ds.scenarios[ds.index[i][0]][0], sample.agent_ids[0], sample.timestamp))


def model_kwargs(block: SscConfig) -> dict:
    """:func:`models.ssc.ssc_detector` arguments of the config's network."""
    n = block.network
    return dict(layer_nums=tuple(n.layer_nums), num_filters=tuple(n.num_filters),
                num_upsample_filters=tuple(n.num_upsample_filters), pillar_channels=n.pillar_channels,
                head_hidden=n.head_hidden, max_pillars=n.max_pillars)


# ---------------------------------------------------------------- training data


#: the label ignored by the loss (voxels a generated view is not scored on)
IGNORE = 255
#: BEV cells (0.78 m) around a generated view's points that its map is scored on (``footprint``)
FOOTPRINT_CELLS = 2


def footprint(cloud: np.ndarray, cells: int = FOOTPRINT_CELLS) -> np.ndarray:
    """(X, Y) bool: the map columns within ``cells`` columns of one of ``cloud``'s points (own frame)."""
    from scipy import ndimage

    idx = np.floor((np.asarray(cloud[:, :2], dtype=np.float64) - SSC_GRID.lower[:2]) / SSC_GRID.voxel[:2]).astype(int)
    shape = SSC_GRID.shape[:2]
    keep = np.all((idx >= 0) & (idx < np.asarray(shape)), axis=1)
    hit = np.zeros(shape, dtype=bool)
    hit[idx[keep, 0], idx[keep, 1]] = True
    disc = np.hypot(*np.mgrid[-cells:cells + 1, -cells:cells + 1]) <= cells
    return ndimage.binary_dilation(hit, structure=disc)


@dataclass
class TrainingSet:
    """What the networks learn from: every agent's (cloud, own map) and every sample with its ego
    map; ``ego[k]``: view ``k`` is a sample's ego (its cloud is never generated)."""

    views: list[tuple[np.ndarray, np.ndarray]]
    samples: list[FusionSample]
    ego_maps: list[np.ndarray]
    key: str = ""
    ego: list[bool] = field(default_factory=list)

    @classmethod
    def read(cls, ds: FusionDataset) -> "TrainingSet":
        views, samples, maps, ego = [], [], [], []
        ident = []
        for i in range(len(ds)):
            sample = ds[i]
            own = sample_maps(ds, i, sample)
            views += list(zip(sample.clouds, own))
            ego += [j == 0 for j in range(len(own))]
            samples.append(sample)
            maps.append(own[0])
            ident.append((sample.scenario, sample.timestamp, list(sample.agent_ids), [len(c) for c in sample.clouds],
                          round(float(sum(np.sum(c[:, :3], dtype=np.float64) for c in sample.clouds)), 2),
                          [int(np.count_nonzero(m)) for m in own], [int(m.sum(dtype=np.int64)) for m in own]))
        if not views:
            raise TypError(ds.root, "samples", "at least one training sample", "none")
        return cls(views, samples, maps, hash_obj(ident)[:16], ego)

    def class_counts(self) -> np.ndarray:
        """Voxels of each class over every agent's map (ignored voxels left out)."""
        return sum(np.bincount(m.reshape(-1), minlength=IGNORE + 1)[:N_CLASSES] for _, m in self.views)

    def with_generated_views(self, mode: str) -> "TrainingSet":
        """What the single-agent network learns of a set whose cooperating clouds are generated
        (``ssc.generated_views``): ``all`` every view on its whole map; ``footprint`` the generated
        views scored only on the columns near their points (:func:`footprint`; the rest
        :data:`IGNORE`); ``ego`` the ego views only. The samples (the fused networks') are kept."""
        if mode == "all":
            return self
        if mode not in ("ego", "footprint"):
            raise TypError("tasks.ssc.TrainingSet", "generated_views", "all, footprint or ego", mode)
        views, ego = [], []
        for (c, m), e in zip(self.views, self.ego):
            if not e:
                seen = footprint(c) if mode == "footprint" else None
                if seen is None or not seen.any():   # ego mode, or a generated view with no point in the grid
                    continue
                m = np.where(seen[:, :, None], m, np.uint8(IGNORE))
            views.append((c, m))
            ego.append(e)
        extra = {"footprint_cells": FOOTPRINT_CELLS} if mode == "footprint" else {}
        return TrainingSet(views, self.samples, self.ego_maps, hash_obj([self.key, mode, extra])[:16], ego)
