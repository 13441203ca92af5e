"""The GPU bench's data: made on the CPU by bench/gpu_data.py, read on the GPU machine by bench/gpu.py.

The GPU machine has no open3d (the simulator and the re-simulation cast rays with it), so every
grid the generator trains and is scored on is made here and travels with the working tree, in
one folder:

- ``grids.npz``: every voxel grid, bool, bit-packed along W (about 8.5 KB a 256 x 256 x 20 view):
  the target's training and validation ego views (x, y), the source's training views (every
  agent), the pseudo references of self-training (x_e', y_r, re-simulated), and the held-out
  (ego, reference) pairs (x_r, y_r, x_e', re-simulated, the cells the ego saw) with the
  reference views' labelled vehicles;
- ``source_tuples.npz``: stage 2's training tuples, as :func:`tasks.stage2.save_tuples` writes them;
- ``meta.json``: the config it was made with, the grids, the target's point statistics, the
  pairs' scenes, the baselines' scores on the pairs at this grid, the tiny profile's figures.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import yaml

from tasks.evaluate_generation import EvalSet
from tasks.genscore import true_view_stats
from tasks.selftrain import References
from tasks.stage2 import Tuples, load_tuples, save_tuples
from tasks.voxel_data import ViewSet
from typ import distributed
from typ.config import as_dict, config_from_dict
from typ.errors import TypError
from typ.io import atomic_path, write_json
from typ.voxel import Grid

GRIDS = "grids.npz"
META = "meta.json"
#: the generator's size on the GPU: the ``small`` profile with these blocks overridden
CONFIG = Path(__file__).with_name("gpu.yaml")


def config_dict() -> dict:
    """bench/gpu.yaml as it is written."""
    return yaml.safe_load(CONFIG.read_text(encoding="utf-8"))


def config(overrides: dict | None = None):
    """The checked :class:`typ.config.Config` of bench/gpu.yaml, with ``overrides`` merged over it."""
    return config_from_dict(config_dict(), where=str(CONFIG), overrides=overrides)


def overrides_of(assignments: list[str]) -> dict:
    """``["a.b=1", ...]`` (dotted keys, YAML values) as a nested dict of overrides."""
    out: dict = {}
    for item in assignments:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise TypError("--set", item, "KEY=VALUE with a dotted key", item)
        *parents, last = key.split(".")
        node = out
        for p in parents:
            node = node.setdefault(p, {})
        node[last] = yaml.safe_load(value)
    return out


def config_for(bundle: "Bundle", overrides: dict | None = None):
    """bench/gpu.yaml with the bundle's overrides, then ``overrides``; the blocks that decide the
    data must be the bundle's (:func:`data_fields`), else the bundle is stale."""
    from typ.config import _deep_merge

    cfg = config(_deep_merge(bundle.meta.get("overrides", {}), overrides or {}))
    if json.loads(json.dumps(data_fields(cfg))) != bundle.meta["data"]:
        raise TypError(CONFIG, "simulate/voxelize/selftrain.pseudo_references",
                       "the data the bundle was made with (remake it: python bench/gpu_data.py)",
                       "a different config")
    return cfg


def data_fields(cfg) -> dict:
    """The blocks that decide the bundle's data: a run whose config differs there needs a new bundle."""
    return {k: as_dict(getattr(cfg, k)) for k in ("simulate", "voxelize")} | {
        "pseudo_references": cfg.selftrain.pseudo_references, "stage2.resim": cfg.stage2.resim}


def pack(grids: np.ndarray) -> np.ndarray:
    """(..., W) {0, 1} -> uint8 bit-packed along W."""
    return np.packbits(np.asarray(grids, dtype=bool), axis=-1)


def unpack(packed: np.ndarray, width: int) -> np.ndarray:
    """The inverse of :func:`pack`: (..., W) bool."""
    return np.unpackbits(packed, axis=-1, count=width).view(bool)


@dataclass
class DenseViews(ViewSet):
    """A :class:`tasks.voxel_data.ViewSet` held as dense bool grids: x (N, C, H, W), y (N, 1, H, W).

    :meth:`batch` gathers on the runtime device, where the grids are copied once: at 256 x 256 x
    20 a batch's float conversion and symmetries on the CPU cost more than the training step on a
    GPU. Its tensors are on that device (the stages move their inputs there anyway)."""

    x: np.ndarray | None = None
    y: np.ndarray | None = None
    _on_device: dict = field(default_factory=dict, repr=False, compare=False)

    def occupancy(self, index) -> np.ndarray:
        return self.x[np.asarray(index, dtype=np.int64)].astype(np.float32)

    def box_maps(self, index) -> np.ndarray:
        return self.y[np.asarray(index, dtype=np.int64)].astype(np.float32)

    def head(self, n: int) -> "DenseViews":
        return DenseViews(self.grid, self.keys[:n], [], self.x[:n], self.y[:n])

    def batch(self, index, *, flips: np.ndarray | None = None,
              dihedral: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """:meth:`ViewSet.batch`'s tensors (same values), on the runtime device."""
        dev = distributed.device()
        if dev not in self._on_device:
            self._on_device[dev] = (torch.from_numpy(self.x).to(dev), torch.from_numpy(self.y).to(dev))
        at = torch.as_tensor(np.asarray(index, dtype=np.int64), device=dev)
        out = []
        for grids in self._on_device[dev]:
            g = grids[at]
            if flips is not None:
                g = torch.where(torch.as_tensor(np.asarray(flips, dtype=bool), device=dev)[:, None, None, None],
                                g.flip(-1), g)
            if dihedral is not None:
                g = torch.stack([_dihedral(v, int(k)) for v, k in zip(g, dihedral)])
            out.append(g.float())
        return out[0], out[1]


def _dihedral(grid: torch.Tensor, k: int) -> torch.Tensor:
    """:func:`tasks.voxel_data.apply_dihedral` on a tensor (..., H, W)."""
    return torch.rot90(grid.flip(-1) if k >= 4 else grid, k % 4, dims=(-2, -1))


def dense(views: ViewSet) -> DenseViews:
    """Every view of ``views`` as dense bool grids."""
    index = np.arange(len(views))
    return DenseViews(views.grid, list(views.keys), [], views.occupancy(index) > 0.5, views.box_maps(index) > 0.5)


@dataclass
class Bundle:
    meta: dict
    train: DenseViews        # target training ego views, target sensor grid
    val: DenseViews          # target validation ego views (stage 1 tunes its thresholds on them)
    source: DenseViews       # source training views, every agent, source sensor grid
    tuples: Tuples           # stage 2's (x_r, y_r, x_e', re-simulated) source tuples
    references: References   # self-training's pseudo references
    pairs: EvalSet           # the held-out pairs, without clouds (the baselines are scored in meta)


def write(folder: Path, *, meta: dict, train: ViewSet, val: ViewSet, source: ViewSet, tuples: Tuples,
          references: References, pairs: EvalSet) -> Path:
    """The bundle under ``folder`` (each file atomically)."""
    folder = Path(folder)
    save_tuples(tuples, folder)
    arrays = {}
    for name, views in (("train", train), ("val", val), ("source", source)):
        d = dense(views)
        arrays |= {f"{name}_x": pack(d.x), f"{name}_y": pack(d.y),
                   f"{name}_keys": np.array(["/".join(k) for k in d.keys])}
    arrays |= {"ref_x_e": pack(references.x_e), "ref_y_r": pack(references.y_r)}
    if references.resim is not None:
        arrays["ref_resim"] = pack(references.resim)
    arrays |= {f"pair_{k}": pack(getattr(pairs, k)) for k in ("x_r", "y_r", "x_e", "resim", "seen")}
    arrays |= {"pair_boxes": np.concatenate(pairs.boxes).astype(np.float64) if pairs.boxes else np.zeros((0, 7)),
               "pair_box_counts": np.array([len(b) for b in pairs.boxes], dtype=np.int64),
               "pair_scenes": np.array(pairs.scenes)}
    with atomic_path(folder / GRIDS) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)
    write_json(folder / META, {**meta, "grid": train.grid.to_dict(), "source_grid": source.grid.to_dict()})
    return folder


def read(folder: Path) -> Bundle:
    """A bundle :func:`write` made; a missing folder or file names it and the script that makes it."""
    folder = Path(folder)
    for name in (GRIDS, META):
        if not (folder / name).is_file():
            raise TypError(folder / name, "file", "the GPU bench's data (make it with: python bench/gpu_data.py)",
                           "missing")
    meta = json.loads((folder / META).read_text())
    grid, source_grid = Grid.from_dict(meta["grid"]), Grid.from_dict(meta["source_grid"])
    width = grid.shape[1]
    with np.load(folder / GRIDS) as z:
        def views(name: str, g: Grid) -> DenseViews:
            keys = [tuple(k.split("/")) for k in z[f"{name}_keys"]]
            return DenseViews(g, keys, [], unpack(z[f"{name}_x"], width), unpack(z[f"{name}_y"], width))

        train, val, source = views("train", grid), views("val", grid), views("source", source_grid)
        references = References(unpack(z["ref_x_e"], width), unpack(z["ref_y_r"], width),
                                unpack(z["ref_resim"], width) if "ref_resim" in z.files else None)
        counts = z["pair_box_counts"]
        boxes = np.split(z["pair_boxes"], np.cumsum(counts)[:-1]) if len(counts) else []
        grids = {k: unpack(z[f"pair_{k}"], width) for k in ("x_r", "y_r", "x_e", "resim", "seen")}
        pairs = EvalSet(grid, [str(s) for s in z["pair_scenes"]], **grids, boxes=list(boxes), ego_points=[],
                        resim_points=[])
    pairs.truth_stats = [true_view_stats(x, grid) for x in pairs.x_r]
    return Bundle(meta, train, val, source, load_tuples(folder), references, pairs)


def synthetic_cav_scenario(split_root: Path, *, seed: int, agents: int = 2, frames: int = 2,
                           points: int = 20000) -> Path:
    """One OPV2V-layout scenario of random clouds and boxes, with random semantic occupancy maps,
    under ``split_root``: input of the fusion, ssc and ddpm networks where the simulator cannot
    run (it casts rays with open3d, which the GPU machine lacks). The values mean nothing; their
    sizes are a simulated real_cav scan's, so a training step costs what it costs on real data."""
    from typ.formats.opv2v import write_scene
    from typ.geometry import invert, pose_to_matrix, transform_boxes
    from typ.metrics.ssc import SSC_CLASSES
    from typ.scene import AgentView, Scene
    from typ.ssc import SSC_GRID, occupancy_path, write_occupancy

    rng = np.random.default_rng(seed)
    name = f"synthetic_{seed:04d}"
    cars = np.column_stack([rng.uniform(-30, 30, 8), rng.uniform(-15, 15, 8), np.full(8, 0.8),
                            np.full(8, 4.5), np.full(8, 1.9), np.full(8, 1.6), rng.uniform(-np.pi, np.pi, 8)])
    for t in range(frames):
        views = {}
        for k in range(agents):
            pose = pose_to_matrix([12.0 * k + 0.5 * t, 3.0 * (-1) ** k, 1.8, 0.0, 5.0 * k, 0.0])
            cloud = np.column_stack([rng.uniform(-50, 50, points), rng.uniform(-50, 50, points),
                                     rng.uniform(-1.8, 1.5, points), rng.random(points)]).astype(np.float32)
            views[str(100 + k)] = AgentView(str(100 + k), cloud, pose, transform_boxes(invert(pose), cars),
                                            ("car",) * len(cars), np.arange(200, 200 + len(cars)))
        folder = write_scene(Scene(name, f"{t:06d}", views), Path(split_root))
        for agent in views:
            labels = rng.choice(len(SSC_CLASSES), size=SSC_GRID.shape, p=[0.9] + [0.1 / (len(SSC_CLASSES) - 1)]
                                * (len(SSC_CLASSES) - 1)).astype(np.uint8)
            write_occupancy(occupancy_path(folder, agent, f"{t:06d}"), labels)
    return Path(split_root) / name
