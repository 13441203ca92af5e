"""The trained generator as one object, diffusers-style: ``TYPPipeline``.

A pipeline holds every trained part TYP needs to turn an ego's cloud into a reference view:
E_x, Q_x, G_x (``x_vqvae``), the box-map encoder E_y (``box_encoder``), the stage-1 UNet
ε_θ (``unet``, its EMA weights), the adapter F_AD (``adapter``; none for stage 1 alone), and
the settings that are not weights: the ground-relative voxel grid, the sampler and its step
count, the post-processing thresholds (TYP §4.1), the adapter's conditioning scale and the point
statistics of the target domain that turn occupied voxels into a realistic cloud (:class:`PointStats`).

``adapter_scale`` multiplies F_AD's residuals at sampling time, as diffusers' T2I-Adapter
pipelines' ``adapter_conditioning_scale`` does (1: as trained). The adapter's outputs start at
zero (:class:`models.adapter.ZeroAdapter`) and grow only as far as its short training takes
them; its residuals point the right way but are too small to move the frozen UNet much
(reports/generation_ablation.md measures the scale).

``save_pretrained(dir)`` writes one sub-folder per component (``model.safetensors`` +
``config.json``, :mod:`typ.artifacts`) and ``pipeline.json``; ``from_pretrained(dir)`` reads
them back with a named error for anything missing or damaged. Someone who receives a trained
typ generator runs it in three lines::

    pipe = TYPPipeline.from_pretrained("artifacts/generator/seed_0")
    points = pipe(ego_points, boxes, reference_pose, mount_height=2.2,
                  generator=torch.Generator().manual_seed(0))

Batched work (:meth:`occupancy`) takes dense grids; ``__call__`` takes one ego cloud;
:meth:`generate` makes the views of a batch of references (:mod:`pipelines.typ.reference`) in
any compose mode of :data:`typ.registry.COMPOSE_MODES` (:mod:`pipelines.typ.compose`), as the
generate stage, ``typ generate`` and the real-scan benchmark do.
"""
from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from models.adapter import ZeroAdapter
from models.ldm import LatentDiffusion
from models.postprocess import postprocess
from models.samplers import SCHEDULERS, make_scheduler, sample
from models.schedules import SCHEDULES, betas
from models.vqvae import build_from_config as build_encoder
from typ import distributed
from typ.artifacts import load_module, save_module
from typ.config import MAX_ADAPTER_SCALE, MAX_NOISE_STD, MAX_TIMESTEPS, CastConfig
from typ.errors import TypError
from typ.io import read_json_or_none, seed_dir, write_json
from typ.registry import COMPOSE_MODES, compose_mode
from typ.voxel import Grid, box_map, points_to_reference, voxelize

if TYPE_CHECKING:
    from pipelines.typ.reference import Reference

PIPELINE_JSON = "pipeline.json"
COMPONENTS = ("x_vqvae", "box_encoder", "unet", "adapter")
#: the parts a generator cannot do without (the adapter is absent for stage 1 alone)
REQUIRED = ("x_vqvae", "box_encoder", "unet")
#: range bands of a PointStats (point_statistics writes 5)
MAX_BANDS = 64


@dataclass(frozen=True)
class PointStats:
    """How the target domain's LiDAR fills an occupied voxel, per range band.

    band_edges: (B + 1,) metres from the sensor, planar; points_per_voxel[b]: the probabilities
    of 1, 2, ... points in an occupied voxel of band b; intensity[b]: 21 quantiles (0, 5, ...,
    100 %) of the intensity of band b's points. Generated voxels get that many points, uniform
    inside the voxel, with intensities drawn from the band's distribution, so a detector sees
    the density, the sub-voxel spread and the intensity it sees on real clouds.
    """

    band_edges: tuple[float, ...]
    points_per_voxel: tuple[tuple[float, ...], ...]
    intensity: tuple[tuple[float, ...], ...]

    def to_dict(self) -> dict:
        return {"band_edges": list(self.band_edges), "points_per_voxel": [list(p) for p in self.points_per_voxel],
                "intensity": [list(q) for q in self.intensity]}

    def __post_init__(self) -> None:
        edges = np.asarray(self.band_edges, dtype=np.float64)
        if not 2 <= len(edges) <= MAX_BANDS + 1 or not np.isfinite(edges).all() or (np.diff(edges) <= 0).any():
            raise TypError("point_stats", "band_edges", f"2 to {MAX_BANDS + 1} finite ascending distances",
                           self.band_edges)
        bands = len(edges) - 1
        for name, rows, lo, hi in (("points_per_voxel", self.points_per_voxel, 1, MAX_POINTS_PER_VOXEL),
                                   ("intensity", self.intensity, 2, 1024)):
            if len(rows) != bands or not all(lo <= len(r) <= hi for r in rows) or \
                    not all(np.isfinite(np.asarray(r, dtype=np.float64)).all() for r in rows):
                raise TypError("point_stats", name, f"{bands} rows (one per band) of {lo} to {hi} finite numbers",
                               rows)
        if any(min(p) < 0 or sum(p) <= 0 for p in self.points_per_voxel):
            raise TypError("point_stats", "points_per_voxel", "probabilities >= 0 with a positive sum per band",
                           self.points_per_voxel)
        if any(np.diff(q).min() < 0 for q in self.intensity):
            raise TypError("point_stats", "intensity", "quantiles in ascending order per band", self.intensity)

    @classmethod
    def from_dict(cls, d: dict) -> "PointStats":
        numbers_only = [d["band_edges"], *d["points_per_voxel"], *d["intensity"]]
        if not all(_is_number(v) for row in numbers_only for v in row):
            raise TypError("point_stats", "values", "numbers", d)
        return cls(tuple(float(v) for v in d["band_edges"]),
                   tuple(tuple(float(v) for v in p) for p in d["points_per_voxel"]),
                   tuple(tuple(float(v) for v in q) for q in d["intensity"]))

    @classmethod
    def single(cls) -> "PointStats":
        """One point per voxel, intensity 0: the voxel centres of TYP §4.1 (no statistics known)."""
        return cls((0.0, 1e9), ((1.0,),), ((0.0,) * 21,))


#: range bands of :func:`point_statistics` (metres)
STAT_BANDS = (0.0, 10.0, 20.0, 30.0, 45.0, 1e9)
MAX_POINTS_PER_VOXEL = 32


def point_statistics(clouds, grid: Grid) -> PointStats:
    """:class:`PointStats` of real clouds (N, 4) [x, y, z, intensity], each in its sensor frame
    with ``grid`` that sensor's grid."""
    edges = np.asarray(STAT_BANDS)
    counts = np.zeros((len(edges) - 1, MAX_POINTS_PER_VOXEL))
    intensities: list[list[np.ndarray]] = [[] for _ in range(len(edges) - 1)]
    H, W, C = grid.shape
    for cloud in clouds:
        xyz = np.asarray(cloud[:, :3], dtype=np.float64)
        inside = np.all((xyz >= grid.lower) & (xyz < grid.upper), axis=1)
        xyz, intensity = xyz[inside], np.asarray(cloud[inside, 3], dtype=np.float64)
        if len(xyz) == 0:
            continue
        idx = np.minimum(((xyz - grid.lower) / grid.voxel_size).astype(np.int64), np.array(grid.shape) - 1)
        flat = (idx[:, 0] * W + idx[:, 1]) * C + idx[:, 2]
        voxels, inverse, n = np.unique(flat, return_inverse=True, return_counts=True)
        i, j = voxels // (W * C), (voxels // C) % W
        band = np.clip(np.searchsorted(edges, np.hypot(grid.centers(0)[i], grid.centers(1)[j]), side="right") - 1,
                       0, len(edges) - 2)
        np.add.at(counts, (band, np.minimum(n, MAX_POINTS_PER_VOXEL) - 1), 1)
        point_band = band[inverse]
        for b in range(len(edges) - 1):
            intensities[b].append(intensity[point_band == b])
    def summary(count: np.ndarray, values: list[np.ndarray]) -> tuple[tuple, tuple]:
        values = np.concatenate(values) if values else np.zeros(0)
        return (tuple((count / count.sum()).round(6)),
                tuple(np.percentile(values, np.linspace(0, 100, 21)).round(6)))

    if counts.sum() == 0:
        return PointStats.single()
    pooled = summary(counts.sum(axis=0), [v for band in intensities for v in band])
    # a band no cloud reaches takes the statistics of all bands together
    rows = [summary(counts[b], intensities[b]) if counts[b].sum() else pooled for b in range(len(edges) - 1)]
    return PointStats(tuple(float(e) for e in edges), tuple(r[0] for r in rows), tuple(r[1] for r in rows))


def occupancy_to_points(occupancy: np.ndarray, grid: Grid, stats: PointStats, rng: np.random.Generator) -> np.ndarray:
    """(C, H, W) bool on the sensor's ``grid`` -> (N, 4) float32 [x, y, z, intensity], sensor frame.

    Each occupied voxel gets k points (k drawn from its band's ``points_per_voxel``), uniform
    inside the voxel, with intensities drawn by inverse transform from the band's quantiles.
    """
    k_idx, i, j = np.nonzero(occupancy)
    if len(i) == 0:
        return np.zeros((0, 4), np.float32)
    band = _band(grid.centers(0)[i], grid.centers(1)[j], stats)
    n = np.ones(len(i), np.int64)
    for b in np.unique(band):
        p = np.asarray(stats.points_per_voxel[b])
        sel = band == b
        n[sel] = rng.choice(len(p), size=int(sel.sum()), p=p / p.sum()) + 1
    rep = np.repeat(np.arange(len(i)), n)
    lower = grid.lower + np.stack([i, j, k_idx], axis=1).astype(np.float64) * grid.voxel_size
    xyz = lower[rep] + rng.random((len(rep), 3)) * grid.voxel_size
    return np.concatenate([xyz, _intensities(band[rep], stats, rng)[:, None]], axis=1).astype(np.float32)


def _band(x: np.ndarray, y: np.ndarray, stats: PointStats) -> np.ndarray:
    """The range band of :class:`PointStats` that planar positions (x, y) fall in (the outer bands
    extended to 0 and infinity)."""
    edges = np.asarray(stats.band_edges)
    return np.clip(np.searchsorted(edges, np.hypot(x, y), side="right") - 1, 0, len(edges) - 2)


def _intensities(band: np.ndarray, stats: PointStats, rng: np.random.Generator) -> np.ndarray:
    """(N,) intensities drawn by inverse transform from the quantiles of each point's band."""
    u = rng.random(len(band))
    intensity = np.zeros(len(band))
    for b in np.unique(band):
        q = np.asarray(stats.intensity[b])
        sel = band == b
        intensity[sel] = np.interp(u[sel], np.linspace(0, 1, len(q)), q)
    return intensity


def draw_intensities(points: np.ndarray, grid: Grid, stats: PointStats, rng: np.random.Generator) -> np.ndarray:
    """(N, >=3) points in a sensor's frame -> (N, 4) float32 [x, y, z, intensity], the intensity
    drawn as :func:`occupancy_to_points` draws it for the band of the point's BEV range (``grid``
    is the sensor's grid, for the same banding as generated voxels: by the cell centre)."""
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    cell = np.floor((pts[:, :2] - grid.lower[:2]) / grid.voxel_size[:2])
    centre = grid.lower[:2] + (cell + 0.5) * grid.voxel_size[:2]
    band = _band(centre[:, 0], centre[:, 1], stats)
    return np.concatenate([pts, _intensities(band, stats, rng)[:, None]], axis=1).astype(np.float32)


def generator_dir(out: Path, seed: int) -> Path:
    """Where the ``selftrain`` stage saves the trained generator of replica ``seed`` and where
    ``generate`` and ``evaluate`` load it: ``<out>/generator/seed_<seed>``."""
    return seed_dir(Path(out) / "generator", seed)


@dataclass
class TYPPipeline:
    """P(x_r | x_e', y_r) with everything it needs (module doc)."""

    x_vqvae: torch.nn.Module
    box_encoder: torch.nn.Module
    unet: LatentDiffusion
    adapter: ZeroAdapter | None
    grid: Grid                      # ground-relative grid (the configured ``voxelize.grid``)
    schedule: str
    train_timesteps: int
    sampler: str
    num_inference_steps: int
    thresholds: dict
    point_stats: PointStats = dataclasses.field(default_factory=PointStats.single)
    adapter_scale: float = 1.0

    @property
    def conditions(self) -> int:
        """1: x_e' only (TYP); 2: x_e' and the re-simulated view; 0: no adapter (stage 1 alone)."""
        return 0 if self.adapter is None else self.adapter.config.get("conditions", 1)

    def with_adapter(self, adapter: ZeroAdapter | None) -> "TYPPipeline":
        return dataclasses.replace(self, adapter=adapter)

    # ------------------------------------------------------------------ sampling

    @torch.no_grad()
    def logits(self, x_e: np.ndarray, y_r: np.ndarray, *, seed: int, resim: np.ndarray | None = None,
               num_inference_steps: int | None = None, sampler: str | None = None) -> torch.Tensor:
        """Decoded logits (N, C, H, W) of samples of P(x_r | x_e', y_r) for dense grids
        x_e (N, C, H, W), y_r (N, 1, H, W) [and the re-simulated views (N, C, H, W)]."""
        models = [m for m in (self.x_vqvae, self.box_encoder, self.unet, self.adapter) if m is not None]
        with distributed.on_device(*models) as dev, distributed.autocast():
            y = torch.from_numpy(np.asarray(y_r, dtype=np.float32)).to(dev)
            features = None
            if self.adapter is not None:
                grids = [x_e] + ([resim] if self.conditions == 2 else [])
                if self.conditions == 2 and resim is None:
                    raise TypError("TYPPipeline", "resim", "the re-simulated views this adapter is conditioned on",
                                   "none")
                latents = [self.unet.normalize(self.x_vqvae.encode_pre_quant(
                    torch.from_numpy(np.asarray(g, dtype=np.float32)).to(dev))) for g in grids]
                features = [self.adapter_scale * f for f in self.adapter(torch.cat(latents, dim=1))]
            scheduler = make_scheduler(sampler or self.sampler, betas(self.schedule, self.train_timesteps),
                                       prediction_type=self.unet.config.get("prediction", "epsilon"))
            cond = self.unet.normalize_cond(self.box_encoder.encode_pre_quant(y))
            # the generator stays on the CPU: the same seed draws the same noise on every device
            z = sample(self.unet, scheduler, shape=(len(y), self.unet.config["latent_channels"], *cond.shape[2:]),
                       num_steps=num_inference_steps or self.num_inference_steps,
                       generator=torch.Generator().manual_seed(seed), cond=cond, adapter_features=features, device=dev)
            return self.x_vqvae.decode_latents(self.unet.denormalize(z)).float().cpu()

    def occupancy(self, x_e: np.ndarray, y_r: np.ndarray, *, seed: int, resim: np.ndarray | None = None,
                  batch_size: int = 8, **kw) -> np.ndarray:
        """Post-processed samples (N, C, H, W) bool; batch b is seeded ``seed + b``."""
        out = []
        t = self.thresholds
        for start in range(0, len(x_e), batch_size):
            sl = slice(start, start + batch_size)
            logits = self.logits(x_e[sl], y_r[sl], seed=seed + start, resim=None if resim is None else resim[sl], **kw)
            out.append(postprocess(logits, low=t["low"], high=t["high"], noise_std=t["noise_std"],
                                   generator=torch.Generator().manual_seed(seed + start)).numpy())
        return np.concatenate(out) if out else np.zeros((0, *np.asarray(x_e).shape[1:]), bool)

    def points(self, occupancy: np.ndarray, sensor_grid: Grid, seed: int) -> np.ndarray:
        """(C, H, W) occupancy on a sensor's grid -> (N, 4) float32 cloud in that sensor's frame."""
        return occupancy_to_points(occupancy, sensor_grid, self.point_stats, np.random.default_rng(seed))

    def intensities(self, points: np.ndarray, sensor_grid: Grid, rng: np.random.Generator) -> np.ndarray:
        """(N, >=3) points in a sensor's frame -> (N, 4) float32, intensities drawn as :meth:`points`
        draws them for generated voxels (:func:`draw_intensities`, the target's point statistics)."""
        return draw_intensities(points, sensor_grid, self.point_stats, rng)

    def needs_sensor(self, compose: str) -> bool:
        """Whether :meth:`generate` casts the reference sensor: to re-simulate the ego's cloud for a
        re-simulation-conditioned generator or a mode that re-simulates, or to cast a cast view."""
        return self.conditions == 2 or compose_mode(compose).casts

    def generate(self, refs: Sequence[Reference], grid: Grid, seed: int, *, compose: str = "generated",
                 sensor=None, cast: CastConfig = CastConfig()) -> list[np.ndarray]:
        """The reference views of a batch of references (:func:`pipelines.typ.reference.reference_at`),
        composed as ``compose`` says (:data:`typ.registry.COMPOSE_MODES`): (N, 4) float32 clouds in
        each reference's sensor frame (``grid``: that sensor's grid), with the domain's point
        density and intensity. ``sensor``: the reference LiDAR (SensorSpec) that re-simulation and
        cast views cast with (:meth:`needs_sensor`); ``cast``: the cast view's scene
        (:class:`typ.config.CastConfig`). Batch b of the samples is seeded ``seed + b``
        (:meth:`occupancy`); the same arguments give the same bytes."""
        from pipelines.typ.compose import Batch, composer
        from typ.distributed import threaded_map
        from typ.resim import EGO_CAR_LWH, resimulated_points

        compose_fn = composer(compose)
        if self.needs_sensor(compose) and sensor is None:
            raise TypError("TYPPipeline.generate", "sensor", "the reference sensor re-simulation and cast views cast "
                           "with", None)
        resim_points = None
        if self.conditions == 2 or COMPOSE_MODES[compose].resimulates:
            resim_points = list(threaded_map(lambda r: resimulated_points(r.ego_points, sensor, EGO_CAR_LWH), refs))
        resim = None
        if self.conditions == 2:
            resim = np.stack([voxelize(p, grid).transpose(2, 0, 1) for p in resim_points]).astype(np.float32)
        occupancy = self.occupancy(np.stack([r.x_e for r in refs]), np.stack([r.y_r for r in refs]), seed=seed,
                                   resim=resim)
        clouds = [self.points(occ, grid, seed + k) for k, occ in enumerate(occupancy)]
        return compose_fn(Batch(self, refs, grid, seed, occupancy, clouds, sensor=sensor, cast=cast,
                                resim_points=resim_points))

    def __call__(self, ego_points: np.ndarray, boxes: np.ndarray, reference_pose: np.ndarray, *, mount_height: float,
                 num_inference_steps: int | None = None, generator: torch.Generator | None = None,
                 resim_spec=None) -> np.ndarray:
        """The reference view's cloud (N, 4) float32, in the reference sensor's frame.

        ego_points: (N, >=3) the ego's cloud in its sensor frame; boxes: (K, 7) the objects the
        view must show, in the ego frame; reference_pose: (4, 4) float64 the reference sensor in
        the ego frame; mount_height: both sensors' height above their ground (m);
        resim_spec: the reference sensor's SensorSpec, needed by a re-simulation-conditioned adapter.
        """
        from typ.geometry import invert, transform_boxes

        grid = self.grid.for_sensor(mount_height)
        identity = np.eye(4)
        moved = points_to_reference(np.asarray(ego_points), identity, reference_pose)
        ref_boxes = transform_boxes(invert(np.asarray(reference_pose, dtype=np.float64)),
                                    np.asarray(boxes, dtype=np.float64).reshape(-1, 7))
        x_e = voxelize(moved, grid).transpose(2, 0, 1)[None]
        y_r = box_map(ref_boxes, grid).transpose(2, 0, 1)[None]
        resim = None
        if self.conditions == 2:
            from typ.resim import resimulate

            if resim_spec is None:
                raise TypError("TYPPipeline", "resim_spec", "the reference sensor (SensorSpec) to re-simulate with",
                               None)
            resim = voxelize(resimulate(moved[:, :3], resim_spec), grid).transpose(2, 0, 1)[None]
        seed = int(torch.randint(0, 2 ** 31 - 1, (1,), generator=generator)) if generator is not None else 0
        occ = self.occupancy(x_e, y_r, seed=seed, resim=resim, num_inference_steps=num_inference_steps)[0]
        return self.points(occ, grid, seed)

    # ------------------------------------------------------------------ disk

    def save_pretrained(self, folder: Path) -> Path:
        """One sub-folder per component plus ``pipeline.json`` (the settings), atomically each."""
        folder = Path(folder)
        for name in COMPONENTS:
            module = getattr(self, name)
            if module is not None:
                save_module(folder / name, module, module.config)
        write_json(folder / PIPELINE_JSON, {
            "grid": self.grid.to_dict(), "schedule": self.schedule, "train_timesteps": self.train_timesteps,
            "sampler": self.sampler, "num_inference_steps": self.num_inference_steps,
            "thresholds": self.thresholds, "point_stats": self.point_stats.to_dict(),
            "adapter_scale": self.adapter_scale, "components": [n for n in COMPONENTS if getattr(self, n) is not None]})
        return folder

    @classmethod
    def from_pretrained(cls, folder: Path, stage: str = "selftrain") -> "TYPPipeline":
        """Read a folder written by :meth:`save_pretrained`; ``stage`` is named in errors.

        Every value of ``pipeline.json`` is checked (:func:`read_settings`) before any module is built."""
        folder = Path(folder)
        settings = read_settings(folder / PIPELINE_JSON, stage)
        components = settings.pop("components")
        builders = {"x_vqvae": build_encoder, "box_encoder": build_encoder, "unet": LatentDiffusion.from_config,
                    "adapter": ZeroAdapter.from_config}
        parts = {name: (load_module(folder / name, builders[name], stage)[0] if name in components else None)
                 for name in COMPONENTS}
        return cls(**parts, **settings)


def read_settings(path: Path, stage: str) -> dict:
    """``pipeline.json`` as :class:`TYPPipeline`'s keyword arguments besides its modules (plus
    ``components``), each value checked for its type and a plausible range: nothing in the file is
    trusted, and a wrong value names the file and field instead of allocating or failing later."""
    meta = read_json_or_none(path)
    if meta is None:
        raise TypError(path, "file", f"a trained generator (run the {stage} stage: dvc repro)", "missing")
    expected = f"the settings the {stage} stage writes"
    if not isinstance(meta, dict):
        raise TypError(path, "pipeline", expected, type(meta).__name__)
    missing = [k for k in ("components", "grid", "schedule", "train_timesteps", "sampler", "num_inference_steps",
                           "thresholds", "point_stats") if k not in meta]
    if missing:
        raise TypError(path, "pipeline", f"{expected}, with {missing[0]}", f"no key {missing[0]!r}")
    components = meta["components"]
    if not isinstance(components, list) or not set(REQUIRED) <= set(components) <= set(COMPONENTS):
        raise TypError(path, "components", f"a list of {list(REQUIRED)}, and 'adapter' or not", components)
    if meta["schedule"] not in SCHEDULES or meta["sampler"] not in SCHEDULERS:
        raise TypError(path, "schedule/sampler", f"a schedule of {sorted(SCHEDULES)} and a sampler of "
                       f"{sorted(SCHEDULERS)}", [meta["schedule"], meta["sampler"]])
    steps = _count(path, "train_timesteps", meta["train_timesteps"], MAX_TIMESTEPS)
    thresholds = meta["thresholds"]
    if not isinstance(thresholds, dict) or \
            not all(_is_number(thresholds.get(k)) for k in ("low", "high", "noise_std")) or \
            not 0 <= thresholds["low"] <= thresholds["high"] <= 1 or not 0 <= thresholds["noise_std"] <= MAX_NOISE_STD:
        raise TypError(path, "thresholds", f"low, high, noise_std with 0 <= low <= high <= 1 and noise_std in "
                       f"[0, {MAX_NOISE_STD:g}]", thresholds)
    scale = meta.get("adapter_scale", 1.0)
    if not _is_number(scale) or not 0 <= scale <= MAX_ADAPTER_SCALE:
        raise TypError(path, "adapter_scale", f"a number in [0, {MAX_ADAPTER_SCALE:g}]", scale)
    try:
        point_stats = PointStats.from_dict(meta["point_stats"])
    except (KeyError, TypeError):
        raise TypError(path, "point_stats", "band_edges, points_per_voxel and intensity lists", meta["point_stats"]) \
            from None
    except TypError as exc:
        raise TypError(path, f"point_stats.{exc.field}", exc.expected, exc.got) from None
    try:
        grid = Grid.from_dict(meta["grid"], where=str(path))
    except TypError as exc:  # the grid's own checks name no file
        raise TypError(path, f"grid.{exc.field}", exc.expected, exc.got) from None
    return {"components": components, "grid": grid,
            "schedule": meta["schedule"], "train_timesteps": steps, "sampler": meta["sampler"],
            "num_inference_steps": _count(path, "num_inference_steps", meta["num_inference_steps"], steps),
            "thresholds": dict(thresholds), "point_stats": point_stats, "adapter_scale": float(scale)}


def _is_number(value) -> bool:
    """A finite int or float (no bool, no integer beyond float's range)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool) and \
        (not isinstance(value, int) or abs(value) < 2**53) and math.isfinite(value)


def _count(path: Path, field: str, value, most: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= most:
        raise TypError(path, field, f"an integer in [1, {most}]", value)
    return value
