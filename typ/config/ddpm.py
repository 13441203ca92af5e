"""The block of the ``ddpm`` stage (the LiDAR-DDPM noise-schedule study)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from typ.config.base import Sampler, Schedule, _positive, _positive_fields
from typ.config.data import GridConfig
from typ.errors import TypError


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
