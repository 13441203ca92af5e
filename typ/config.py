"""Typed configuration: ``params.yaml`` -> one frozen dataclass per stage.

``params.yaml`` holds ``profile: tiny | paper`` and one block per stage. The profile picks
the defaults from ``typ/profiles.yaml`` (``tiny``: minutes on 2 CPU cores; ``paper``: TYP §4
scale); each block in ``params.yaml`` overrides them key by key. An unknown key, a wrong
type or an impossible value fails at load time with the dotted field name and what was
expected, e.g. ``params.yaml: voxelize.grid.shape: expected 3 positive integers``.
"""
from __future__ import annotations

import copy
import dataclasses
import functools
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import yaml

from typ.errors import TypError
from typ.inputs import MiB, load_yaml

PROFILES_FILE = Path(__file__).with_name("profiles.yaml")
PROFILES = ("tiny", "small", "paper")
#: a params.yaml is a few KB
MAX_PARAMS_BYTES = 1 * MiB
DOMAINS = ("source", "target", "real_cav")
#: ``simulate.sources`` value for a domain the embedded simulator makes
SIMULATE = "simulate"


# ---------------------------------------------------------------- stage blocks


@dataclass(frozen=True)
class GridConfig:
    """The voxel grid of TYP §3.2, in the sensor frame (metres); shape is (H, W, C) = (x, y, z)."""

    x_range: tuple[float, float]
    y_range: tuple[float, float]
    z_range: tuple[float, float]
    shape: tuple[int, int, int]

    def check(self, where: str, name: str) -> None:
        for axis in ("x_range", "y_range", "z_range"):
            lo, hi = getattr(self, axis)
            if not lo < hi:
                raise TypError(where, f"{name}.{axis}", "[min, max] with min < max", [lo, hi])
        if any(n <= 0 for n in self.shape):
            raise TypError(where, f"{name}.shape", "3 positive integers (H, W, C)", list(self.shape))


#: The simulator's plausible ranges, for params.yaml and a simulated scenario's ``_typ.json`` alike:
#: beyond them a scenario allocates gigabytes (an azimuth step of 1e-5 deg casts 8.6 GiB of rays)
#: or runs for hours. Real spinning LiDARs step 0.08 to 0.4 deg; OPV2V's scenarios are ~200 frames.
AZIMUTH_STEP_DEG = (0.05, 10.0)
MAX_FRAMES = 10_000
MAX_AGENTS = 8
MAX_COMM_RANGE = 1_000.0
MAX_DT = 10.0


def check_simulation(where: str, name: str, *, frames: int, agents: tuple[int, int], azimuth_step_deg: float,
                     comm_range: float, dt: float) -> None:
    """The simulation settings against :data:`AZIMUTH_STEP_DEG`, :data:`MAX_FRAMES` and the other caps;
    the error names ``<name>.<field>``."""
    if not 1 <= frames <= MAX_FRAMES:
        raise TypError(where, f"{name}.frames", f"an integer in [1, {MAX_FRAMES}]", frames)
    lo, hi = agents
    if not 1 <= lo <= hi <= MAX_AGENTS:
        raise TypError(where, f"{name}.agents_min/agents_max", f"1 <= agents_min <= agents_max <= {MAX_AGENTS}",
                       [lo, hi])
    low, high = AZIMUTH_STEP_DEG
    if not low <= azimuth_step_deg <= high:
        raise TypError(where, f"{name}.azimuth_step_deg", f"a step in [{low:g}, {high:g}] deg", azimuth_step_deg)
    if not 0 < comm_range <= MAX_COMM_RANGE:
        raise TypError(where, f"{name}.comm_range", f"a distance in (0, {MAX_COMM_RANGE:g}] m", comm_range)
    if not 0 < dt <= MAX_DT:
        raise TypError(where, f"{name}.dt", f"a frame interval in (0, {MAX_DT:g}] s", dt)


@dataclass(frozen=True)
class ElevationRule:
    """``n`` beam elevations from ``low`` to ``high`` degrees: ``uniform`` steps (CARLA's LiDAR) or
    ``horizon_dense``, even steps in asinh(e / scale) that crowd the beams near 0 deg (Waymo's
    top LiDAR, the VLP-32C)."""

    n: int
    low: float
    high: float
    spacing: Literal["uniform", "horizon_dense"] = "uniform"
    scale: float = 4.0

    def check(self, where: str, name: str) -> None:
        _positive(where, f"{name}.n", self.n)
        if not -90 < self.low < self.high < 90:
            raise TypError(where, f"{name}.low/high", "-90 < low < high < 90 degrees", [self.low, self.high])
        _positive(where, f"{name}.scale", self.scale)


@dataclass(frozen=True)
class SensorConfig:
    """A ``sensor:`` block: a spinning LiDAR without a preset (``typ.sensors.SENSORS`` names the
    presets; ``typ.sensors.resolve`` turns either into a SensorSpec). Angles in degrees, lengths
    in metres; noise, dropout and echo detection only matter where typ casts the sensor."""

    #: ascending beam elevations, or ``{n, low, high, spacing, scale}`` (:class:`ElevationRule`)
    elevations_deg: tuple[float, ...] | ElevationRule
    azimuth_step_deg: float
    max_range: float
    #: the sensor origin above the road
    mount_height: float
    min_range: float = 1.0
    #: each beam's origin above the sensor origin, one per elevation (empty: all at the origin)
    beam_heights_m: tuple[float, ...] = ()
    range_noise_std: float = 0.02
    dropout: float = 0.0
    #: echo strength at which a return is kept with probability 1 - 1/e (0: every echo)
    detection_energy: float = 0.0
    #: "attenuation": exp(-0.004 r) as CARLA; "material": reflectivity and incidence angle
    intensity_model: Literal["attenuation", "material"] = "material"
    name: str = "sensor"

    def check(self, where: str, name: str) -> None:
        rule = self.elevations_deg
        if isinstance(rule, ElevationRule):
            rule.check(where, f"{name}.elevations_deg")
        elif not rule or not all(-90 < e < 90 for e in rule) or any(b <= a for a, b in zip(rule, rule[1:])):
            raise TypError(where, f"{name}.elevations_deg", "ascending beam elevations in (-90, 90) degrees", list(rule))
        n_beams = rule.n if isinstance(rule, ElevationRule) else len(rule)
        if self.beam_heights_m and (len(self.beam_heights_m) != n_beams or any(abs(h) >= 1 for h in self.beam_heights_m)):
            raise TypError(where, f"{name}.beam_heights_m", f"empty or {n_beams} heights in (-1, 1) m, one per beam",
                           list(self.beam_heights_m))
        if not 0 < self.azimuth_step_deg <= 10:
            raise TypError(where, f"{name}.azimuth_step_deg", "a step in (0, 10] deg", self.azimuth_step_deg)
        if not 0 < self.mount_height < 10:
            raise TypError(where, f"{name}.mount_height", "a sensor height in (0, 10) m", self.mount_height)
        if not 0 <= self.min_range < self.max_range:
            raise TypError(where, f"{name}.min_range/max_range", "0 <= min_range < max_range metres",
                           [self.min_range, self.max_range])
        if not 0 <= self.dropout < 1:
            raise TypError(where, f"{name}.dropout", "a fraction in [0, 1)", self.dropout)
        for key in ("range_noise_std", "detection_energy"):
            if getattr(self, key) < 0:
                raise TypError(where, f"{name}.{key}", "a number >= 0", getattr(self, key))


@dataclass(frozen=True)
class DomainSimulation:
    """Per-domain overrides of the simulation's ``frames`` and agent counts (unset: the defaults)."""

    frames: int | None = None
    agents_min: int | None = None
    agents_max: int | None = None


#: ``simulate.sources.<domain>.format``: the datasets typ reads a domain from. ``opv2v``: a
#: collaborative root in OPV2V layout (OPV2V, V2V4Real), taken as it is; the others: single-agent
#: datasets, each frame moved into its LiDAR's frame and written as a one-agent scenario
SOURCE_FORMATS = ("kitti", "nuscenes", "waymo", "opv2v")


@dataclass(frozen=True)
class SourceConfig:
    """A real dataset a domain's scenarios come from (``simulate.sources.<domain>``, or one entry of
    a list of them), with how its own splits become typ's."""

    format: Literal["kitti", "nuscenes", "waymo", "opv2v"]
    #: the dataset root, relative to the project root or absolute
    root: str
    #: typ split -> the dataset's split names (a list: KITTI ImageSets files or training/testing,
    #: Waymo's training/validation/testing folders, nuScenes info files *_train/*_val/*_test,
    #: OPV2V's split folders), or a fraction of the scenarios that no listed split takes (by a
    #: hash of the scenario name). Unset: each typ split takes the dataset split of its name
    #: (train/training, val/validation, test/testing), and a dataset without splits is shared
    #: out by ``DEFAULT_FRACTIONS``
    splits: dict[str, list[str] | float] = field(default_factory=dict)

    def check(self, where: str, name: str) -> None:
        if not self.root.strip():
            raise TypError(where, f"{name}.root", "the path of the dataset root", self.root)
        fractions = {split: v for split, v in self.splits.items() if isinstance(v, float)}
        for split, value in self.splits.items():
            if isinstance(value, float) and not 0 < value <= 1:
                raise TypError(where, f"{name}.splits.{split}", "a fraction in (0, 1]", value)
            if isinstance(value, list) and not (value and all(v.strip() for v in value)):
                raise TypError(where, f"{name}.splits.{split}", "a list of the dataset's split names", value)
        if sum(fractions.values()) > 1 + 1e-9:
            raise TypError(where, f"{name}.splits", "fractions that add up to at most 1", fractions)
        if self.format == "opv2v" and fractions:
            raise TypError(where, f"{name}.splits", "split folder names (an OPV2V root's splits are its folders)",
                           fractions)


@dataclass(frozen=True)
class SimulateConfig:
    """Embedded simulator: which scenarios of which sensor domain go to which split."""

    seed: int
    frames: int
    agents_min: int
    agents_max: int
    azimuth_step_deg: float
    comm_range: float
    dt: float
    #: domain -> split -> number of scenarios, e.g. {"target": {"train": 4, "test": 2}}; for a domain
    #: read from a real dataset (``sources``), the first that many scenarios of each split folder
    scenarios: dict[str, dict[str, int]]
    workers: int
    out: str
    #: domain -> ``simulate`` (the embedded simulator); the root of a real dataset in OPV2V layout
    #: (``<root>/<split>/<scenario>/<agent>/<timestamp>.pcd|.yaml``: OPV2V, V2V4Real), relative to
    #: the project root or absolute, its scenarios linked into ``out``; or a :class:`SourceConfig`
    #: (``{format, root, splits}``), or a list of them whose scenarios the domain's splits share.
    #: A real dataset is checked whole at start, before anything is written
    sources: dict[str, str | SourceConfig | list[SourceConfig]] = field(default_factory=dict)
    #: domain -> frames / agents_min / agents_max for that domain's scenarios
    domains: dict[str, DomainSimulation] = field(default_factory=dict)
    #: the simulated domains whose views also get semantic occupancy ground truth (:mod:`typ.ssc`,
    #: 0.15-0.4 s a view): only the domains that semantic scene completion trains and scores on
    occupancy: tuple[str, ...] = ("real_cav",)

    def source_blocks(self, domain: str) -> tuple[SourceConfig, ...]:
        """The real datasets ``domain`` is read from, in order (a plain root is an ``opv2v`` block);
        empty when the simulator makes it."""
        source = self.sources.get(domain, SIMULATE)
        if source == SIMULATE:
            return ()
        if isinstance(source, str):
            return (SourceConfig(format="opv2v", root=source),)
        return tuple(source) if isinstance(source, list) else (source,)

    def source_field(self, domain: str, index: int) -> str:
        """The params field of ``source_blocks(domain)[index]``, for errors."""
        return f"simulate.sources.{domain}" + (f"[{index}]" if isinstance(self.sources.get(domain), list) else "")

    def for_domain(self, domain: str) -> tuple[int, int, int]:
        """(frames, agents_min, agents_max) of ``domain``'s scenarios."""
        d = self.domains.get(domain, DomainSimulation())
        return (d.frames if d.frames is not None else self.frames,
                d.agents_min if d.agents_min is not None else self.agents_min,
                d.agents_max if d.agents_max is not None else self.agents_max)

    def check(self, where: str, name: str) -> None:
        checks = [(name, self.frames, self.agents_min, self.agents_max)]
        for domain in self.domains:
            if domain not in DOMAINS:
                raise TypError(where, f"{name}.domains.{domain}", f"a sensor domain in {list(DOMAINS)}", domain)
            checks.append((f"{name}.domains.{domain}", *self.for_domain(domain)))
        for label, frames, lo, hi in checks:
            check_simulation(where, label, frames=frames, agents=(lo, hi), azimuth_step_deg=self.azimuth_step_deg,
                             comm_range=self.comm_range, dt=self.dt)
        _positive(where, f"{name}.workers", self.workers)
        for domain, splits in self.scenarios.items():
            if domain not in DOMAINS:
                raise TypError(where, f"{name}.scenarios.{domain}", f"a sensor domain in {list(DOMAINS)}", domain)
            for split, count in splits.items():
                if count < 0:
                    raise TypError(where, f"{name}.scenarios.{domain}.{split}", "a count >= 0", count)
        for domain in self.occupancy:
            if domain not in DOMAINS:
                raise TypError(where, f"{name}.occupancy", f"sensor domains in {list(DOMAINS)}", domain)
        for domain, source in self.sources.items():
            if domain not in DOMAINS:
                raise TypError(where, f"{name}.sources.{domain}", f"a sensor domain in {list(DOMAINS)}", domain)
            if isinstance(source, str) and not source.strip():
                raise TypError(where, f"{name}.sources.{domain}",
                               f"{SIMULATE!r} or the path of a dataset root in OPV2V layout", source)
            if isinstance(source, list) and not source:
                raise TypError(where, f"{name}.sources.{domain}", "at least one dataset block", source)
            for index, block in enumerate(self.source_blocks(domain)):
                block.check(where, self.source_field(domain, index).replace("simulate", name, 1))


@dataclass(frozen=True)
class VoxelizeConfig:
    """Voxelize stage: every agent view under ``input`` onto ``grid``, stored per scene under ``out``.

    ``grid.z_range`` is height above the ground under the sensor; ``mount_height`` gives each
    dataset's LiDAR height above its ground (metres), so the ground lands in the same height
    channel in every domain (TYP §4.1: the z range is dataset-dependent)."""

    grid: GridConfig
    mount_height: dict[str, float]
    input: str
    out: str
    workers: int

    def check(self, where: str, name: str) -> None:
        self.grid.check(where, f"{name}.grid")
        _positive(where, f"{name}.workers", self.workers)
        for dataset, height in self.mount_height.items():
            if not (math.isfinite(height) and 0 <= height < 10):
                raise TypError(where, f"{name}.mount_height.{dataset}", "a sensor height in [0, 10) m", height)

    def sensor_grid(self, dataset: str, where: str = "voxelize") -> "Grid":
        """The grid in the sensor frame of ``dataset``'s LiDAR (see :meth:`typ.voxel.Grid.for_sensor`)."""
        from typ.voxel import Grid
        if dataset not in self.mount_height:
            raise TypError(where, f"voxelize.mount_height.{dataset}",
                           f"the sensor height of dataset {dataset!r} (known: {sorted(self.mount_height)})", "missing")
        g = self.grid
        return Grid(g.x_range, g.y_range, g.z_range, g.shape).for_sensor(self.mount_height[dataset])


@dataclass(frozen=True)
class AutoencoderConfig:
    """One VQ-VAE of TYP §3.2 (x or y): widths per level (``len - 1`` halvings), code size."""

    block_out_channels: tuple[int, ...]
    latent_channels: int
    num_codes: int
    norm_num_groups: int
    gamma: float
    epochs: int
    #: "ema": EMA codebook with k-means init and dead-code restarts; "vq": Eq. 1's codebook term
    quantizer: Literal["ema", "vq"] = "ema"
    #: y only: "vqvae" (TYP: E_y, Q_y, G_y) or "pool" (the box map averaged per latent cell)
    encoding: Literal["vqvae", "pool"] = "vqvae"
    ema_decay: float = 0.9
    dead_code_threshold: float = 1.0

    def check(self, where: str, name: str) -> None:
        if not 0 < self.ema_decay < 1:
            raise TypError(where, f"{name}.ema_decay", "a decay in (0, 1)", self.ema_decay)
        if self.dead_code_threshold < 0:
            raise TypError(where, f"{name}.dead_code_threshold", "an EMA cluster size >= 0", self.dead_code_threshold)
        if len(self.block_out_channels) < 1 or any(c <= 0 or c % self.norm_num_groups for c in self.block_out_channels):
            raise TypError(where, f"{name}.block_out_channels",
                           f"positive widths divisible by norm_num_groups={self.norm_num_groups}",
                           list(self.block_out_channels))
        _positive_fields(self, where, name, "latent_channels", "num_codes", "norm_num_groups", "epochs")
        if self.gamma < 0:
            raise TypError(where, f"{name}.gamma", "a focal-loss gamma >= 0 (0 is plain BCE)", self.gamma)


@dataclass(frozen=True)
class VQVAEStageConfig:
    """Stage ``vqvae``: E_x,Q_x,G_x and E_y,Q_y,G_y trained on the target domain's ego views."""

    x: AutoencoderConfig
    y: AutoencoderConfig
    batch_size: int
    lr: float
    seed: int
    checkpoint_every: int
    threshold: float
    input: str
    dataset: str
    train_split: str
    eval_split: str
    out: str

    def check(self, where: str, name: str) -> None:
        self.x.check(where, f"{name}.x")
        self.y.check(where, f"{name}.y")
        if len(self.x.block_out_channels) != len(self.y.block_out_channels):
            raise TypError(where, f"{name}.y.block_out_channels",
                           "as many levels as x (x^f and y^f must share one latent resolution)",
                           list(self.y.block_out_channels))
        _positive_fields(self, where, name, "batch_size", "lr", "checkpoint_every")
        if not 0 < self.threshold < 1:
            raise TypError(where, f"{name}.threshold", "a probability in (0, 1)", self.threshold)


@dataclass(frozen=True)
class UNetConfig:
    """ε_θ's UNet: widths per level (latents are halved ``len - 1`` times), time embedding."""

    block_out_channels: tuple[int, ...]
    layers_per_block: int
    cross_attention_dim: int
    attention_head_dim: int
    norm_num_groups: int
    time_embedding: Literal["sinusoidal", "fourier"]
    #: the transformer blocks' self-attention over latent cells (off: cross-attention only, 2x faster)
    self_attention: bool = True
    #: x, y, range channels as input (the scan pattern depends on where a cell is)
    coordinates: bool = False

    def check(self, where: str, name: str) -> None:
        if len(self.block_out_channels) < 2 or any(c <= 0 or c % self.norm_num_groups for c in self.block_out_channels):
            raise TypError(where, f"{name}.block_out_channels",
                           f">= 2 positive widths divisible by norm_num_groups={self.norm_num_groups}",
                           list(self.block_out_channels))
        _positive_fields(self, where, name, "layers_per_block", "cross_attention_dim", "attention_head_dim",
                         "norm_num_groups")


@dataclass(frozen=True)
class PostprocessConfig:
    """TYP §4.1: thresholds low/high chosen from ``candidates`` on the validation split."""

    noise_std: float
    candidates: tuple[float, ...]

    def check(self, where: str, name: str) -> None:
        if self.noise_std < 0:
            raise TypError(where, f"{name}.noise_std", "a standard deviation >= 0", self.noise_std)
        if not self.candidates or any(not 0 < c < 1 for c in self.candidates):
            raise TypError(where, f"{name}.candidates", "probabilities in (0, 1)", list(self.candidates))


@dataclass(frozen=True)
class Stage1Config:
    """Stage ``stage1`` (TYP Eq. 4): P(x|y) as a latent diffusion model on the target's ego views."""

    unet: UNetConfig
    schedule: Literal["constant", "linear", "quadratic", "cosine", "sigmoid", "hyperbolic", "time_dependent", "ramp"]
    train_timesteps: int
    epochs: int
    batch_size: int
    lr: float
    seed: int
    checkpoint_every: int
    sampler: Literal["ddim", "ddpm", "dpmsolver++", "unipc"]
    sample_steps: int
    eta: float
    postprocess: PostprocessConfig
    eval_views: int
    input: str
    vqvae: str
    dataset: str
    train_split: str
    val_split: str
    out: str
    #: weights averaged with this decay sample the model (the training weights do not)
    ema_decay: float = 0.999
    warmup_steps: int = 100
    lr_schedule: Literal["constant", "cosine"] = "cosine"
    #: models trained with seeds seed, seed + 1, ... (the first feeds later stages)
    replicas: int = 1
    #: what the UNet outputs (Eq. 4's minimiser either way): epsilon, sample (z_0) or v_prediction
    prediction: Literal["epsilon", "sample", "v_prediction"] = "epsilon"
    #: Min-SNR-γ loss weighting (0: the plain mean squared error of Eq. 4)
    min_snr: float = 0.0
    #: train on the ego views of the training split only (True), or on every agent's view, each
    #: taken alone as one more single-agent scan of the target domain (no pairing is used)
    ego_only: bool = True

    def check(self, where: str, name: str) -> None:
        self.unet.check(where, f"{name}.unet")
        self.postprocess.check(where, f"{name}.postprocess")
        _positive_fields(self, where, name, "train_timesteps", "epochs", "batch_size", "lr", "checkpoint_every",
                         "eval_views", "warmup_steps", "replicas")
        if not 0 <= self.ema_decay < 1:
            raise TypError(where, f"{name}.ema_decay", "a decay in [0, 1) (0: no averaging)", self.ema_decay)
        if not 1 <= self.sample_steps <= self.train_timesteps:
            raise TypError(where, f"{name}.sample_steps", f"an integer in [1, train_timesteps={self.train_timesteps}]",
                           self.sample_steps)
        if self.eta < 0 or (self.eta and self.sampler != "ddim"):
            raise TypError(where, f"{name}.eta", "0, or >= 0 with sampler ddim", self.eta)


@dataclass(frozen=True)
class AdaptConfig:
    """Stage ``adapt`` (TYP Eq. 8–10): E_src, G_src against a hinge discriminator on x^f."""

    disc_width: int
    epochs: int
    batch_size: int
    lr: float
    lr_disc: float
    gamma: float
    seed: int
    checkpoint_every: int
    max_disc_loss: float
    eval_views: int
    input: str
    vqvae: str
    source_dataset: str
    source_split: str
    target_dataset: str
    target_split: str
    out: str

    def check(self, where: str, name: str) -> None:
        _positive_fields(self, where, name, "disc_width", "epochs", "batch_size", "lr", "lr_disc", "checkpoint_every",
                         "max_disc_loss", "eval_views")
        if self.gamma < 0:
            raise TypError(where, f"{name}.gamma", "a focal-loss gamma >= 0", self.gamma)


@dataclass(frozen=True)
class Stage2Config:
    """Stage ``stage2`` (TYP Eq. 5–7): a T2I-Adapter on x^f_e' trained on source tuples, UNet frozen.

    One adapter per stage-1 replica. ``resim`` also trains the re-simulation-conditioned
    adapter (x^f_e' beside the re-simulated view's latent); ``one_stage`` also trains TYP
    Table 5's one-stage model (UNet and adapter together from scratch on the source tuples,
    for as many steps as stage 1 and stage 2 together); ``augment``: 1, 2 (mirror) or 8
    (rotations and mirrors) symmetries per tuple; ``max_pairs``: source tuples used (0: all).
    """

    adapter_res_blocks: int
    epochs: int
    batch_size: int
    lr: float
    seed: int
    checkpoint_every: int
    sim: str
    voxels: str
    vqvae: str
    adapt: str
    stage1: str
    source_domain: str
    source_split: str
    out: str
    warmup_steps: int = 100
    lr_schedule: Literal["constant", "cosine"] = "cosine"
    ema_decay: float = 0.999
    augment: Literal[1, 2, 8] = 2
    max_pairs: int = 0
    resim: bool = False
    one_stage: bool = False

    def check(self, where: str, name: str) -> None:
        _positive_fields(self, where, name, "adapter_res_blocks", "epochs", "batch_size", "lr", "checkpoint_every",
                         "warmup_steps")
        if not 0 <= self.ema_decay < 1:
            raise TypError(where, f"{name}.ema_decay", "a decay in [0, 1) (0: no averaging)", self.ema_decay)
        if self.max_pairs < 0:
            raise TypError(where, f"{name}.max_pairs", "a number of tuples >= 0 (0: all)", self.max_pairs)


@dataclass(frozen=True)
class SelftrainConfig:
    """Stage ``selftrain`` (TYP §3.4): fine-tune the adapter on source tuples plus target data.

    Switches (TYP Table 4): ``discriminator`` — source tuples encoded by the adapted E_src
    (stage ``adapt``; off: by E_tgt, the adapter trained anew: "no adaptation");
    ``self_training`` — pseudo references (x̂_r, x_e', y_r) sampled in target scenes;
    ``dummy_ego`` — target ego views (x_r, y_r) with an empty ego, x_e = 0. ``ablation``
    also trains every row of Table 4, whatever the switches say. ``generator``: which adapter
    the written generator (``<out>/generator``) carries: ``typ`` (the switches' variant) or
    ``typ_resim`` (the same recipe on the re-simulation-conditioned adapter; needs
    ``stage2.resim``). The generator samples with ``sampler`` / ``sample_steps`` and multiplies the
    adapter's residuals by ``adapter_scale`` (diffusers' ``adapter_conditioning_scale``; 1: as trained).
    """

    discriminator: bool
    self_training: bool
    dummy_ego: bool
    ablation: bool
    pseudo_references: int
    min_distance: float
    max_distance: float
    epochs: int
    batch_size: int
    lr: float
    seed: int
    checkpoint_every: int
    sampler: Literal["ddim", "ddpm", "dpmsolver++", "unipc"]
    sample_steps: int
    sim: str
    voxels: str
    vqvae: str
    adapt: str
    stage1: str
    stage2: str
    source_domain: str
    source_split: str
    target_domain: str
    target_split: str
    out: str
    warmup_steps: int = 50
    lr_schedule: Literal["constant", "cosine"] = "cosine"
    ema_decay: float = 0.999
    generator: Literal["typ", "typ_resim"] = "typ"
    adapter_scale: float = 1.0

    def check(self, where: str, name: str) -> None:
        _positive_fields(self, where, name, "pseudo_references", "epochs", "batch_size", "lr", "checkpoint_every",
                         "sample_steps", "max_distance", "warmup_steps", "adapter_scale")
        if not 0 <= self.min_distance < self.max_distance:
            raise TypError(where, f"{name}.min_distance", f"0 <= min_distance < max_distance={self.max_distance}",
                           self.min_distance)
        if not 0 <= self.ema_decay < 1:
            raise TypError(where, f"{name}.ema_decay", "a decay in [0, 1) (0: no averaging)", self.ema_decay)


@dataclass(frozen=True)
class GenerateSet:
    """One (dataset, split) of single-agent scenarios to turn collaborative.

    references: ``vehicles`` — reference poses sampled from the ego's labelled vehicles
    (TYP §4.5, the ColWaymo analogue); ``cavs`` — the scenario's own cooperating agents, each
    replaced by a cloud generated from the ego's at its true pose (only their poses are read:
    the oracle comparison of TYP Tables 1–2).
    """

    dataset: str
    split: str
    references: Literal["vehicles", "cavs"]


@dataclass(frozen=True)
class CastConfig:
    """The scene a cast reference view is cast from (``generate.compose: cast``, :mod:`typ.castview`);
    ``reports/generation_ablation.md`` measures each choice."""

    #: labelled vehicles (y_r) as closed boxes, each edge scaled by this; 0: none
    label_boxes: float = 0.9
    #: the road surface lies under ``generated`` ground voxels only, every cell the ego did not
    #: see (``unseen``) or ``everywhere`` (under the ego's surfels too)
    road: Literal["generated", "unseen", "everywhere"] = "unseen"
    #: drop generated voxels an ego ray crossed before its return: the ego saw them empty
    carve: bool = True

    def check(self, where: str, name: str) -> None:
        if isinstance(self.label_boxes, bool) or not isinstance(self.label_boxes, (int, float)) \
                or not 0.0 <= self.label_boxes <= 2.0:
            raise TypError(where, f"{name}.label_boxes", "a scale in [0, 2] (0: no label boxes)", self.label_boxes)
        if not isinstance(self.carve, bool):
            raise TypError(where, f"{name}.carve", "true or false", self.carve)


@dataclass(frozen=True)
class GenerateConfig:
    """Stage ``generate`` (TYP §4.5): reference views for single-agent frames, written as OPV2V agents."""

    references_per_frame: int
    #: roadside units per scenario (``vehicles`` sets): virtual sensors on observed ground, facing the ego
    roadside_units: int
    min_distance: float
    max_distance: float
    sampler: Literal["ddim", "ddpm", "dpmsolver++", "unipc"]
    sample_steps: int
    seed: int
    input: str
    sets: tuple[GenerateSet, ...]
    #: the folder selftrain writes the trained generators to (``<generator>/generator/seed_<s>``)
    generator: str
    out: str
    workers: int
    #: what a reference view is made of: ``generated`` — the generator's sample alone (TYP);
    #: ``hybrid`` — the ego's cloud re-simulated from the reference pose in the BEV cells the ego
    #: saw, the generator's sample elsewhere (the ``hybrid`` row of reports/generation_accuracy.md);
    #: ``cast`` — one scene of both (the ego's surfels, the generated cells), cast once with the
    #: reference LiDAR (:mod:`typ.castview`, shaped by ``cast``)
    compose: Literal["generated", "hybrid", "cast"] = "generated"
    cast: CastConfig = dataclasses.field(default_factory=CastConfig)

    def check(self, where: str, name: str) -> None:
        _positive_fields(self, where, name, "references_per_frame", "sample_steps", "max_distance", "workers")
        self.cast.check(where, f"{name}.cast")
        if self.roadside_units < 0:
            raise TypError(where, f"{name}.roadside_units", "a count >= 0", self.roadside_units)
        if not 0 <= self.min_distance < self.max_distance:
            raise TypError(where, f"{name}.min_distance", f"0 <= min_distance < max_distance={self.max_distance}",
                           self.min_distance)
        if not self.sets:
            raise TypError(where, f"{name}.sets", "at least one {dataset, split, references}", [])
        seen = set()
        for i, s in enumerate(self.sets):
            if (s.dataset, s.split) in seen:
                raise TypError(where, f"{name}.sets[{i}]", "each (dataset, split) once", [s.dataset, s.split])
            seen.add((s.dataset, s.split))


@dataclass(frozen=True)
class DetectorConfig:
    """PointPillars of the fusion benchmark (``models/pointpillars.py``), one per fusion method."""

    lidar_range: tuple[float, float, float, float, float, float]
    voxel_size: float
    max_points_per_pillar: int
    max_pillars: int
    pillar_channels: int
    layer_nums: tuple[int, ...]
    layer_strides: tuple[int, ...]
    num_filters: tuple[int, ...]
    upsample_strides: tuple[int, ...]
    num_upsample_filters: tuple[int, ...]
    anchor_size: tuple[float, float, float]
    anchor_z: float

    def check(self, where: str, name: str) -> None:
        r = self.lidar_range
        if not (r[0] < r[3] and r[1] < r[4] and r[2] < r[5]):
            raise TypError(where, f"{name}.lidar_range", "[x_min, y_min, z_min, x_max, y_max, z_max], min < max",
                           list(r))
        _positive_fields(self, where, name, "voxel_size", "max_points_per_pillar", "max_pillars", "pillar_channels")
        lists = (self.layer_nums, self.layer_strides, self.num_filters, self.upsample_strides,
                 self.num_upsample_filters)
        if not self.layer_nums or len({len(v) for v in lists}) != 1:
            raise TypError(where, f"{name}.layer_nums", "layer_nums, layer_strides, num_filters, upsample_strides "
                           "and num_upsample_filters of one equal, non-zero length", [len(v) for v in lists])
        stride = 1
        for s in self.layer_strides:
            stride *= s
        for axis, lo, hi in (("x", r[0], r[3]), ("y", r[1], r[4])):
            cells = (hi - lo) / self.voxel_size
            if abs(cells - round(cells)) > 1e-6 or round(cells) % stride:
                raise TypError(where, f"{name}.lidar_range", f"an {axis} extent of a multiple of voxel_size x "
                               f"total backbone stride = {self.voxel_size} x {stride} m", [lo, hi])
        if any(v <= 0 for v in self.anchor_size):
            raise TypError(where, f"{name}.anchor_size", "3 positive sizes (l, w, h) in metres", list(self.anchor_size))


@dataclass(frozen=True)
class V2XViTConfig:
    """The V2X-ViT fusion transformer (``models/fusion.V2XViT``) on the detector's backbone;
    ``shrink_stride``: the stride of its shrink conv (OpenCOOD's 2; with 1 and ``dim`` equal to the
    backbone's width it starts as the single-agent network, :meth:`V2XViT.warm_start`)."""

    dim: int
    depth: int
    heads: int
    dim_head: int
    window_sizes: tuple[int, ...]
    window_heads: tuple[int, ...]
    window_dim_heads: tuple[int, ...]
    mlp_dim: int
    dropout: float
    shrink_stride: int = 2

    def check(self, where: str, name: str) -> None:
        _positive_fields(self, where, name, "dim", "depth", "heads", "dim_head", "mlp_dim", "shrink_stride")
        if self.dim % 2 or not self.window_sizes or \
                not len(self.window_sizes) == len(self.window_heads) == len(self.window_dim_heads):
            raise TypError(where, f"{name}.window_sizes", "an even dim and equal-length window lists",
                           [self.dim, list(self.window_sizes)])
        if not 0 <= self.dropout < 1:
            raise TypError(where, f"{name}.dropout", "a probability in [0, 1)", self.dropout)


@dataclass(frozen=True)
class RobustnessConfig:
    """V2VSSC §IV curves: AP against pose noise, delay and message compression."""

    position_std: tuple[float, ...]
    heading_std_deg: tuple[float, ...]
    delay_ms: tuple[int, ...]
    quantization_bits: tuple[int, ...]

    def check(self, where: str, name: str) -> None:
        for key in ("position_std", "heading_std_deg", "delay_ms"):
            values = getattr(self, key)
            if any(v < 0 for v in values):
                raise TypError(where, f"{name}.{key}", "values >= 0", list(values))
        if any(d % 100 for d in self.delay_ms):
            raise TypError(where, f"{name}.delay_ms", "multiples of 100 ms (one 10 Hz frame)", list(self.delay_ms))
        if any(not 1 <= b <= 16 for b in self.quantization_bits):
            raise TypError(where, f"{name}.quantization_bits", "bit widths in [1, 16]", list(self.quantization_bits))


@dataclass(frozen=True)
class AugmentConfig:
    """OpenCOOD's training augmentation, one global similarity per sample: a flip of the y axis
    with probability 0.5 (``flip``), a rotation about z drawn from U(-rotation_deg, rotation_deg)
    and a scaling from U(scale[0], scale[1]); applied to every agent's cloud in its own frame, to
    the boxes, and conjugated into the agent->ego transforms so that they stay rigid."""

    flip: bool
    rotation_deg: float
    scale: tuple[float, float]

    def check(self, where: str, name: str) -> None:
        if not 0 <= self.rotation_deg <= 180:
            raise TypError(where, f"{name}.rotation_deg", "an angle in [0, 180] degrees", self.rotation_deg)
        if not 0 < self.scale[0] <= self.scale[1]:
            raise TypError(where, f"{name}.scale", "[low, high] with 0 < low <= high", list(self.scale))


#: the names of ``models.fusion.METHODS`` in its order, here so that checking params needs no torch
#: (tests/test_fusion.py holds the two equal)
FUSION_METHODS = ("none", "early", "late", "attfuse", "v2xvit")


@dataclass(frozen=True)
class FusionConfig:
    """Stage ``fusion`` (TYP §4.2–4.5, Tables 1–3; V2VSSC §IV): collaborative detection benchmark.

    ``methods``: names of ``models.fusion.METHODS`` (no and late fusion share one single-agent
    detector). Every network is trained ``seeds`` times (seeds ``seed``, ``seed + 1``, ...).
    The single-agent detector trains ``steps`` from scratch (``pretrain_steps`` on a pre-training
    set); early and intermediate fusion start from it (``warm_start``) and train
    ``warm_start_steps`` more at ``finetune_lr``, or from scratch for ``steps`` /
    ``pretrain_steps`` like it (off, as OpenCOOD trains them). Table 3 fine-tunes a pre-trained
    network on each of ``finetune_scenes`` and on all N real_cav training scenarios with the steps
    training from scratch on the same scenarios takes (TYP §4.5: the paper's arms differ only in
    where they start): on n of the N scenarios, every run trains n / N of its steps on all N (the
    same epochs, as OpenCOOD trains by epochs), the fine-tuned single-agent detector at
    ``finetune_lr`` and the warm-started methods from it, as from scratch.
    ``lr_schedule``: ``cosine`` (linear warm-up over ``warmup`` of the run, then cosine decay to
    1 % of the peak) or ``constant`` (after the same warm-up). ``generated_extent``: half the side
    (m) of the square around a cooperating agent that its generated cloud covers (the generator's
    grid); its labels outside are not used with generated clouds. ``min_gt_points``: a vehicle is
    ground truth when at least this many points of all agents' true clouds fall in its box
    (V2V4Real labels what the fused LiDAR sees; 0: every vehicle within range, as OPV2V).
    ``processes``: trainings run at once, each in its own process on one thread (0: torch's thread
    count on the CPU, 1 on an accelerator); the trained bytes do not depend on it.
    """

    methods: tuple[str, ...]
    detector: DetectorConfig
    v2xvit: V2XViTConfig
    robustness: RobustnessConfig
    augment: AugmentConfig
    comm_range: float
    max_agents: int
    batch_size: int
    lr: float
    finetune_lr: float
    lr_schedule: Literal["constant", "cosine"]
    warmup: float
    steps: int
    pretrain_steps: int
    finetune_scenes: tuple[int, ...]
    warm_start: bool
    warm_start_steps: int
    seeds: int
    generated_extent: float
    min_gt_points: int
    score_threshold: float
    nms_threshold: float
    max_boxes: int
    bootstrap: int
    seed: int
    checkpoint_every: int
    processes: int
    sim: str
    generated: str
    real_domain: str
    train_split: str
    test_split: str
    source_domain: str
    source_split: str
    colwaymo_domain: str
    colwaymo_split: str
    reports: str
    out: str

    def check(self, where: str, name: str) -> None:
        self.detector.check(where, f"{name}.detector")
        self.v2xvit.check(where, f"{name}.v2xvit")
        self.robustness.check(where, f"{name}.robustness")
        self.augment.check(where, f"{name}.augment")
        _check_methods(where, f"{name}.methods", self.methods, FUSION_METHODS)
        _positive_fields(self, where, name, "comm_range", "max_agents", "batch_size", "lr", "finetune_lr", "steps",
                         "pretrain_steps", "warm_start_steps", "max_boxes", "checkpoint_every",
                         "seeds", "generated_extent", "bootstrap")
        if any(n < 1 for n in self.finetune_scenes):
            raise TypError(where, f"{name}.finetune_scenes", "scenario counts >= 1 (0 and all are always run)",
                           list(self.finetune_scenes))
        for key in ("score_threshold", "nms_threshold", "warmup"):
            if not 0 <= getattr(self, key) < 1:
                raise TypError(where, f"{name}.{key}", "a number in [0, 1)", getattr(self, key))
        if self.min_gt_points < 0:
            raise TypError(where, f"{name}.min_gt_points", "a point count >= 0", self.min_gt_points)
        if self.processes < 0:
            raise TypError(where, f"{name}.processes", "a process count >= 0 (0: one per CPU thread)",
                           self.processes)

    @property
    def training_seeds(self) -> tuple[int, ...]:
        """The seeds every network is trained with."""
        return tuple(self.seed + k for k in range(self.seeds))


#: the fusion methods semantic scene completion runs (``models.fusion.METHODS`` names, every one):
#: no and late fusion share one single-agent network
SSC_METHODS = ("none", "early", "late", "attfuse", "v2xvit")


@dataclass(frozen=True)
class SscNetworkConfig:
    """The SSC network (``models.ssc.ssc_detector``): PointPillars on V2VSSC's grid, three backbone
    levels (strides 2, 4, 8 over the 0.78125 m pillars), an occupancy head of ``head_hidden``."""

    layer_nums: tuple[int, int, int]
    num_filters: tuple[int, int, int]
    num_upsample_filters: tuple[int, int, int]
    pillar_channels: int
    head_hidden: int
    max_pillars: int

    def check(self, where: str, name: str) -> None:
        _positive_fields(self, where, name, "pillar_channels", "head_hidden", "max_pillars")
        for key in ("layer_nums", "num_filters", "num_upsample_filters"):
            if any(v < 1 for v in getattr(self, key)):
                raise TypError(where, f"{name}.{key}", "3 counts >= 1", list(getattr(self, key)))


@dataclass(frozen=True)
class SscNoisyConfig:
    """Table I's noisy setting: the cooperating agents' pose noise and message age (V2X-ViT's
    0.2 m / 0.2 deg / 100 ms unless changed)."""

    position_std: float
    heading_std_deg: float
    delay_ms: int

    def check(self, where: str, name: str) -> None:
        if self.position_std < 0 or self.heading_std_deg < 0:
            raise TypError(where, f"{name}.position_std", "standard deviations >= 0",
                           [self.position_std, self.heading_std_deg])
        if self.delay_ms < 0 or self.delay_ms % 100:
            raise TypError(where, f"{name}.delay_ms", "a multiple of 100 ms >= 0 (10 Hz frames)", self.delay_ms)


@dataclass(frozen=True)
class SscConfig:
    """Stage ``ssc`` (V2VSSC §III–IV, Table I, Figs. 4–5): collaborative semantic scene completion on
    ``domain``'s simulated scenarios and their semantic occupancy maps (``simulate.occupancy``).

    The single-agent network trains ``steps`` steps of one agent view (every agent's own cloud
    against its own map) with class-balanced cross-entropy (weights ``1 / ln(class_weight_eps +
    share)``), Adam at ``lr`` with cosine decay; no and late fusion run it. Early fusion, AttFuse
    and V2X-ViT (``v2xvit``: its transformer) start from it and train ``warm_start_steps`` on the
    ego's map at ``finetune_lr``. Every network is trained ``seeds`` times (``seed``, ``seed + 1``, ...). Each method is scored
    on the test split in the perfect setting and in ``noisy``; the ``robustness`` sweeps (pose
    noise, delay, the feature-sending methods' message bits) use the first seed's networks.
    Intervals: ``bootstrap`` replicates over test scenarios (and seeds).

    ``data``: what the networks train on, each scored on the true test split: ``oracle`` (every
    agent's true cloud) and ``generated`` (the cooperating agents' clouds TYP generated for the
    same frames under ``generated``, the ego's true; TYP Table 1 for SSC). Maps are true in both.
    ``generated_views``: what the single-agent network of the generated arm learns from
    (:meth:`tasks.ssc.TrainingSet.with_generated_views`): ``all`` every agent's view, ``footprint``
    the generated views scored only near their points, ``ego`` the ego's true views only."""

    methods: tuple[str, ...]
    data: tuple[Literal["oracle", "generated"], ...]
    generated_views: Literal["all", "footprint", "ego"]
    network: SscNetworkConfig
    v2xvit: V2XViTConfig
    robustness: RobustnessConfig
    noisy: SscNoisyConfig
    comm_range: float
    steps: int
    warm_start_steps: int
    lr: float
    finetune_lr: float
    class_weight_eps: float
    seeds: int
    bootstrap: int
    seed: int
    sim: str
    generated: str
    domain: str
    train_split: str
    test_split: str
    reports: str
    out: str

    def check(self, where: str, name: str) -> None:
        self.network.check(where, f"{name}.network")
        self.v2xvit.check(where, f"{name}.v2xvit")
        if not self.data or self.data[0] != "oracle" or len(set(self.data)) != len(self.data):
            raise TypError(where, f"{name}.data", "oracle first (Table I, the robustness sweeps), then generated "
                           "or nothing", list(self.data))
        self.robustness.check(where, f"{name}.robustness")
        self.noisy.check(where, f"{name}.noisy")
        _check_methods(where, f"{name}.methods", self.methods, SSC_METHODS)
        _positive_fields(self, where, name, "comm_range", "steps", "warm_start_steps", "lr", "finetune_lr", "seeds",
                         "bootstrap")
        if not self.class_weight_eps > 1:
            raise TypError(where, f"{name}.class_weight_eps", "a number > 1 (1 / ln(eps + share) stays finite)",
                           self.class_weight_eps)

    @property
    def training_seeds(self) -> tuple[int, ...]:
        """The seeds every network is trained with."""
        return tuple(self.seed + k for k in range(self.seeds))


Schedule = Literal["constant", "linear", "quadratic", "cosine", "sigmoid", "hyperbolic", "time_dependent", "ramp"]
Sampler = Literal["ddim", "ddpm", "dpmsolver++", "unipc"]


def _check_samplers(where: str, name: str, samplers, train_timesteps: int) -> None:
    for i, (_, steps) in enumerate(samplers):
        if not 1 <= steps <= train_timesteps:
            raise TypError(where, f"{name}[{i}]", f"[sampler, steps] with steps in [1, train_timesteps={train_timesteps}]",
                           list(samplers[i]))


@dataclass(frozen=True)
class DdpmRangeConfig:
    """The equirectangular range image: the sensor's beams (rows) x ``azimuth_bins`` columns."""

    azimuth_bins: int
    #: space-to-depth block the U-Net folds into channels ([1, 1]: plain pixels)
    patch: tuple[int, int]
    #: depth -> pixel: ``linear`` (2·d/max_range - 1) or ``log`` (R2DM's log2(d+1)/log2(max+1)),
    #: see typ.projection.to_unit
    depth: Literal["linear", "log"]


@dataclass(frozen=True)
class DdpmBevConfig:
    """The BEV image: orthographic projection onto ``grid`` (shape [H, W, 1]; z range kept)."""

    grid: GridConfig
    patch: tuple[int, int]


@dataclass(frozen=True)
class PixelUNetConfig:
    """The lightweight pixel-space U-Net of LiDAR DDPM §IV-2."""

    block_out_channels: tuple[int, ...]
    layers_per_block: int
    norm_num_groups: int
    dropout: float
    harmonics: int  #: N of the Fourier time embedding (Eq. 4)
    #: two fixed input channels with each pixel's row and column (beam elevation / azimuth, BEV x / y)
    coordinates: bool

    def check(self, where: str, name: str) -> None:
        if len(self.block_out_channels) < 2 or any(c <= 0 or c % self.norm_num_groups for c in self.block_out_channels):
            raise TypError(where, f"{name}.block_out_channels",
                           f">= 2 positive widths divisible by norm_num_groups={self.norm_num_groups}",
                           list(self.block_out_channels))
        _positive_fields(self, where, name, "layers_per_block", "norm_num_groups", "harmonics")
        if not 0 <= self.dropout < 1:
            raise TypError(where, f"{name}.dropout", "a probability in [0, 1)", self.dropout)


@dataclass(frozen=True)
class DdpmRunConfig:
    """One configuration of LiDAR DDPM Table I: schedule x time embedding on one representation.

    Configurations with the same (representation, schedule, embedding) share their trained
    models (the paper's E* is F sampled with 800 DDPM steps). ``samplers`` / ``seeds``: empty
    means the stage's lists.
    """

    name: str
    representation: Literal["range", "bev"]
    schedule: Schedule
    embedding: Literal["sinusoidal", "fourier"]
    samplers: tuple[tuple[Sampler, int], ...] = ()
    seeds: tuple[int, ...] = ()


@dataclass(frozen=True)
class FeatureNetConfig:
    """typ's FRID (range image) and FPVD (voxel grid) feature networks, trained on the
    simulator's per-point semantics."""

    width: int
    levels: int
    steps: int
    batch_size: int
    lr: float
    voxel_grid: GridConfig

    def check(self, where: str, name: str) -> None:
        _positive_fields(self, where, name, "width", "levels", "steps", "batch_size", "lr")
        self.voxel_grid.check(where, f"{name}.voxel_grid")


@dataclass(frozen=True)
class LatentRouteConfig:
    """TYP's latent route beside the pixel DDPM: stage 1 (P(x|y) in VQ latents) sampled on the
    same held-out views with their box maps. ``samplers: []`` leaves it out."""

    samplers: tuple[tuple[Sampler, int], ...]
    views: int
    stage1: str
    vqvae: str
    voxels: str


@dataclass(frozen=True)
class DdpmConfig:
    """Stage ``ddpm`` (LiDAR DDPM, Aghanouri & Olaverri-Monreal): pixel-space diffusion on range
    and BEV images of the target domain, every ``configs`` row x ``samplers`` x ``seeds`` scored
    with JSD / MMD (``preset``), FRID and FPVD (typ's feature networks), beside TYP's latent route."""

    range_image: DdpmRangeConfig
    bev: DdpmBevConfig
    unet: PixelUNetConfig
    configs: tuple[DdpmRunConfig, ...]
    samplers: tuple[tuple[Sampler, int], ...]
    seeds: tuple[int, ...]
    train_timesteps: int
    steps: int
    batch_size: int
    lr: float
    #: what the U-Net outputs: ``epsilon`` (Ho et al., the paper's) or ``v_prediction`` (v = √ᾱ ε -
    #: √(1-ᾱ) x_0, Salimans & Ho); the same minimiser, weighted differently over t (tasks/ddpm.py)
    prediction: Literal["epsilon", "v_prediction"]
    checkpoint_every: int
    eval_samples: int
    bootstrap: int
    preset: Literal["r2dm"]  #: the bootstrap resamples its per-scan kernel terms (tasks/ddpm_metrics.py)
    features: FeatureNetConfig
    latent: LatentRouteConfig
    domain: str
    ego_only: bool
    train_split: str
    test_split: str
    seed: int
    input: str
    reports: str
    out: str

    def check(self, where: str, name: str) -> None:
        self.unet.check(where, f"{name}.unet")
        self.features.check(where, f"{name}.features")
        self.bev.grid.check(where, f"{name}.bev.grid")
        _positive_fields(self, where, name, "train_timesteps", "steps", "batch_size", "lr", "checkpoint_every")
        _positive(where, f"{name}.range_image.azimuth_bins", self.range_image.azimuth_bins)
        if self.eval_samples < 2:
            raise TypError(where, f"{name}.eval_samples", "at least 2 (a covariance needs 2 samples)", self.eval_samples)
        if self.bootstrap < 10:
            raise TypError(where, f"{name}.bootstrap", "at least 10 bootstrap replicates", self.bootstrap)
        if self.bev.grid.shape[2] != 1:
            raise TypError(where, f"{name}.bev.grid.shape", "[H, W, 1] (one height channel: the image)",
                           list(self.bev.grid.shape))
        # the range image's height is the sensor's beam count, checked where the sensor is known
        factor = 2 ** (len(self.unet.block_out_channels) - 1)
        for key, (ph, pw), (h, w) in (("bev", self.bev.patch, self.bev.grid.shape[:2]),
                                      ("range_image", self.range_image.patch, (None, self.range_image.azimuth_bins))):
            if ph < 1 or pw < 1 or w % pw or (w // pw) % factor or (h is not None and (h % ph or (h // ph) % factor)):
                raise TypError(where, f"{name}.{key}.patch", f"a block that divides the image into a size divisible "
                               f"by 2^(levels-1) = {factor}", [ph, pw])
        if not self.seeds:
            raise TypError(where, f"{name}.seeds", "at least one training seed", [])
        if not self.configs:
            raise TypError(where, f"{name}.configs", "at least one {name, representation, schedule, embedding}", [])
        seen = set()
        for i, run in enumerate(self.configs):
            if (run.name, run.representation) in seen:
                raise TypError(where, f"{name}.configs[{i}]", "each (name, representation) once",
                               [run.name, run.representation])
            seen.add((run.name, run.representation))
            _check_samplers(where, f"{name}.configs[{i}].samplers", run.samplers, self.train_timesteps)
        _check_samplers(where, f"{name}.samplers", self.samplers, self.train_timesteps)
        if not self.samplers:
            raise TypError(where, f"{name}.samplers", "at least one [sampler, steps]", [])
        _positive(where, f"{name}.latent.views", self.latent.views)


@dataclass(frozen=True)
class TrackingConfig:
    """Where runs are logged; ``MLFLOW_TRACKING_URI`` in the environment wins over ``uri``."""

    experiment: str
    uri: str

    def check(self, where: str, name: str) -> None:
        if not self.experiment:
            raise TypError(where, f"{name}.experiment", "a non-empty experiment name", self.experiment)


@dataclass(frozen=True)
class RuntimeConfig:
    """Where training runs: ``device`` (auto picks cuda, then mps, then cpu) and the autocast
    ``precision`` of each training step (bf16 needs no loss scaling; fp16 has none here)."""

    device: Literal["auto", "cpu", "cuda", "mps"]
    precision: Literal["fp32", "bf16", "fp16"]

    def check(self, where: str, name: str) -> None:
        pass  # the Literal types are the whole check; whether the device exists is known at run time


@dataclass(frozen=True)
class ServeConfig:
    """``typ serve``: cron schedules of the deployments, and the folder watched for new
    single-agent scenarios (``<watch>/<dataset>/<split>/<scenario>``, OPV2V layout) whose
    collaborative versions ``generate`` writes under ``watch_out``."""

    pipeline_cron: str
    watch_cron: str
    watch: str
    watch_out: str

    def check(self, where: str, name: str) -> None:
        for key in ("pipeline_cron", "watch_cron"):
            if len(getattr(self, key).split()) != 5:
                raise TypError(where, f"{name}.{key}", "a 5-field cron expression, e.g. '0 3 * * *'",
                               getattr(self, key))


@dataclass(frozen=True)
class EvaluateConfig:
    """Stage ``evaluate``: every benchmark table on held-out data, with bootstrap intervals.

    Generation: (ego, reference) pairs of ``target_domain`` / ``target_split`` (at most
    ``max_pairs``, 0: all), every method sampled once per training seed; ``gallery`` samples
    rendered to ``reports/gallery``; ``n_boot`` bootstrap replicates for each interval.
    """

    seed: int
    n_boot: int
    max_pairs: int
    gallery: int
    target_domain: str
    target_split: str
    source_domain: str
    source_split: str
    sim: str
    voxels: str
    vqvae: str
    adapt: str
    stage1: str
    stage2: str
    selftrain: str
    reports: str
    out: str

    def check(self, where: str, name: str) -> None:
        _positive_fields(self, where, name, "n_boot")
        for key in ("max_pairs", "gallery"):
            if getattr(self, key) < 0:
                raise TypError(where, f"{name}.{key}", "a count >= 0", getattr(self, key))


@dataclass(frozen=True)
class Config:
    profile: Literal["tiny", "small", "paper"]
    tracking: TrackingConfig
    simulate: SimulateConfig
    voxelize: VoxelizeConfig
    vqvae: VQVAEStageConfig
    stage1: Stage1Config
    adapt: AdaptConfig
    stage2: Stage2Config
    selftrain: SelftrainConfig
    generate: GenerateConfig
    fusion: FusionConfig
    ssc: SscConfig
    evaluate: EvaluateConfig
    ddpm: DdpmConfig
    runtime: RuntimeConfig
    serve: ServeConfig
    source: str = field(default="params.yaml", compare=False)

    #: stage name -> attribute holding its block, in pipeline order
    STAGES: typing.ClassVar[tuple[str, ...]] = ("simulate", "voxelize", "vqvae", "stage1", "adapt", "stage2", "selftrain",
                                                 "generate", "fusion", "ssc", "ddpm", "evaluate")

    def block(self, stage: str):
        if stage not in self.STAGES:
            raise TypError(self.source, "stage", f"one of {list(self.STAGES)}", stage)
        return getattr(self, stage)


def _positive(where: str, name: str, value) -> None:
    if not value > 0:
        raise TypError(where, name, "a value > 0", value)


def _check_methods(where: str, name: str, methods, allowed: tuple[str, ...]) -> None:
    """``methods``: at least one, each of ``allowed`` and none twice; the error names the entry."""
    for i, method in enumerate(methods):
        if method not in allowed:
            raise TypError(where, f"{name}[{i}]", f"one of {list(allowed)}", method)
    if not methods or len(set(methods)) != len(methods):
        raise TypError(where, name, f"each of {'/'.join(allowed)} at most once", list(methods))


def _positive_fields(block, where: str, name: str, *keys: str) -> None:
    """Every ``block.<key>`` must be > 0; the error names ``<name>.<key>``."""
    for key in keys:
        _positive(where, f"{name}.{key}", getattr(block, key))


# ---------------------------------------------------------------- loading


def load_config(path: str | Path = "params.yaml", *, overrides: dict | None = None) -> Config:
    """Read ``path``, merge it over its profile's defaults, and return a checked :class:`Config`."""
    return config_from_dict(read_params(path), where=str(path), overrides=overrides)


def read_params(path: str | Path) -> dict:
    """The mapping in a params.yaml, as written (before the profile's defaults are merged in).

    A missing, unreadable, oversized, malformed or alias-bombed file raises TypError."""
    raw = load_yaml(path, "UTF-8 params.yaml", max_bytes=MAX_PARAMS_BYTES,
                    missing="a params.yaml in the project root (run typ from there)") or {}
    if not isinstance(raw, dict):
        raise TypError(path, "<top level>", "a mapping of stage blocks", type(raw).__name__)
    return raw


def config_from_dict(raw: dict, *, where: str = "params.yaml", overrides: dict | None = None) -> Config:
    raw = _deep_merge(raw, overrides or {})
    profile = raw.get("profile", "tiny")
    if profile not in PROFILES:
        raise TypError(where, "profile", f"one of {list(PROFILES)}", profile)
    defaults = profile_defaults(profile)
    merged = _deep_merge(defaults, {k: v for k, v in raw.items() if k != "profile"}, where=where)
    merged["profile"] = profile
    cfg = _build(Config, merged, where, "")
    cfg = dataclasses.replace(cfg, source=where)
    for name in ("tracking", "runtime", "serve") + Config.STAGES:
        getattr(cfg, name).check(where, name)
    return cfg


def profile_defaults(profile: str) -> dict:
    """The defaults of ``profile`` in typ/profiles.yaml; a profile with ``extends: <other>``
    is that profile's defaults with its own keys merged over them."""
    data = _profiles()
    if profile not in data:
        raise TypError(PROFILES_FILE, "profile", f"one of {sorted(data)}", profile)
    own = copy.deepcopy(data[profile])
    parent = own.pop("extends", None)
    if parent is None:
        return own
    if parent == profile or parent not in data:
        raise TypError(PROFILES_FILE, f"{profile}.extends", f"another profile of {sorted(data)}", parent)
    return _deep_merge(profile_defaults(parent), own, whole=frozenset())  # a profile refines its parent


@functools.lru_cache(maxsize=1)
def _profiles() -> dict:
    # parsed once per process (a stage loads its params three times: CLI, stage, flow), with
    # libyaml when PyYAML has it: the pure-Python parser takes a tenth of a second on this file
    return yaml.load(PROFILES_FILE.read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


#: mappings that params.yaml replaces whole instead of key by key: ``simulate.domains: {}``
#: drops the profile's per-domain lengths, so the block's frames / agents apply to every domain
WHOLE = frozenset({"simulate.domains"})


def _deep_merge(base: dict, over: dict, *, where: str = "", prefix: str = "", whole: frozenset = WHOLE) -> dict:
    out = dict(base)
    for key, value in over.items():
        if f"{prefix}{key}" in whole:
            out[key] = copy.deepcopy(value)
        elif isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value, where=where, prefix=f"{prefix}{key}.", whole=whole)
        else:
            out[key] = value
    return out


def _build(tp, value, where: str, name: str):
    """Convert ``value`` to type ``tp`` or raise TypError naming ``name``."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise TypError(where, name or "<top level>", f"a mapping for {tp.__name__}", value)
        hints = typing.get_type_hints(tp)
        fields = {f.name: f for f in dataclasses.fields(tp) if f.init and f.name != "source"}
        unknown = sorted(set(value) - set(fields))
        if unknown:
            raise TypError(where, _join(name, unknown[0]), f"one of the known keys {sorted(fields)}",
                           "an unknown key")
        kwargs = {}
        for fname, f in fields.items():
            if fname not in value:
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                    raise TypError(where, _join(name, fname), "a value (key missing)")
                continue
            kwargs[fname] = _build(hints[fname], value[fname], where, _join(name, fname))
        return tp(**kwargs)
    if origin is Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            raise TypError(where, name, f"one of {list(allowed)}", value)
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            if not isinstance(value, (list, tuple)):
                raise TypError(where, name, f"a list of {_tname(args[0])}s", value)
            return tuple(_build(args[0], v, where, f"{name}[{i}]") for i, v in enumerate(value))
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise TypError(where, name, f"a list of {len(args)} {_tname(args[0])}s", value)
        return tuple(_build(a, v, where, f"{name}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if origin is list:
        (arg,) = typing.get_args(tp)
        if not isinstance(value, list):
            raise TypError(where, name, f"a list of {_tname(arg)}", value)
        return [_build(arg, v, where, f"{name}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        karg, varg = typing.get_args(tp)
        if not isinstance(value, dict):
            raise TypError(where, name, f"a mapping of {_tname(karg)} to {_tname(varg)}", value)
        return {_build(karg, k, where, name): _build(varg, v, where, _join(name, str(k))) for k, v in value.items()}
    if origin in (typing.Union, types.UnionType):
        fitting = [arg for arg in typing.get_args(tp) if _fits(arg, value)]
        if len(fitting) == 1:  # one alternative of this shape: its own error names the bad field inside
            return _build(fitting[0], value, where, name)
        errors = []
        for arg in typing.get_args(tp):
            try:
                return _build(arg, value, where, name)
            except TypError as exc:
                errors.append(exc.expected)
        raise TypError(where, name, " or ".join(errors), value)
    if tp is type(None):
        if value is not None:
            raise TypError(where, name, "null", value)
        return None
    if tp is bool:
        if not isinstance(value, bool):
            raise TypError(where, name, "true or false", value)
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypError(where, name, "an integer", value)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypError(where, name, "a number", value)
        try:
            number = float(value)
        except OverflowError:  # an integer beyond float's range
            raise TypError(where, name, "a finite number", value) from None
        if not math.isfinite(number):
            raise TypError(where, name, "a finite number", value)
        return number
    if tp is str:
        if not isinstance(value, str):
            raise TypError(where, name, "a string", value)
        return value
    if tp is Any:
        return value
    raise TypeError(f"config type {tp!r} for {name} is not supported")


def _fits(tp, value) -> bool:
    """Whether ``value`` has the shape of ``tp`` (a mapping for a dataclass or dict, a list for a
    list or tuple), so that a union's error can come from the one alternative it could be."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp) or origin is dict:
        return isinstance(value, dict)
    if origin in (list, tuple):
        return isinstance(value, (list, tuple))
    return not isinstance(value, (dict, list, tuple))


def build_typed(tp, value, where: str, name: str = ""):
    """``value`` as type ``tp`` (a dataclass: from a mapping) by the rules params blocks are built with:
    a missing or unknown key, or a value of the wrong type, raises TypError naming ``where`` and the field."""
    return _build(tp, value, where, name)


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _tname(tp) -> str:
    return getattr(tp, "__name__", str(tp))


def flatten(obj, prefix: str = "") -> dict[str, Any]:
    """Dotted-name view of a config (``voxelize.grid.shape`` -> ``[128, 128, 8]``), for MLflow."""
    if dataclasses.is_dataclass(obj):
        obj = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj) if f.name != "source"}
    out: dict[str, Any] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(flatten(v, _join(prefix, str(k))))
    else:
        out[prefix] = list(obj) if isinstance(obj, tuple) else obj
    return out


def as_dict(obj) -> dict:
    """Plain JSON-able dict of a config block (tuples become lists)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: as_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.name != "source"}
    if isinstance(obj, dict):
        return {k: as_dict(v) for k, v in obj.items()}
    if isinstance(obj, (tuple, list)):
        return [as_dict(v) for v in obj]
    return obj
