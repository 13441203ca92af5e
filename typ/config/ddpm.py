"""The block of the ``ddpm`` stage (the LiDAR-DDPM noise-schedule study)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from typ.config.base import (LEVELS, BatchSize, Bound, Dropout, LayersPerBlock, LearningRate, Length, NormGroups,
                             Sampler, Schedule, Seed, Steps, Timesteps, Views, Width)
from typ.config.data import GridConfig
from typ.errors import TypError

#: space-to-depth blocks the U-Net folds into channels
Patch = tuple[Annotated[int, Bound(1, 64, "pixels of a space-to-depth block along one side")],
              Annotated[int, Bound(1, 64, "pixels of a space-to-depth block along one side")]]
SEEDS = Length(0, 32, "training seeds, each training every model again: the paper's 3")
Samplers = Annotated[tuple[tuple[Sampler, Timesteps], ...], Length(0, 16, "[sampler, steps] rows, each sampling "
                                                                   "every evaluation set again")]


def _check_samplers(where: str, name: str, samplers, train_timesteps: int) -> None:
    for i, (_, steps) in enumerate(samplers):
        if not 1 <= steps <= train_timesteps:
            raise TypError(where, f"{name}[{i}]", f"[sampler, steps] with steps in [1, train_timesteps={train_timesteps}]",
                           list(samplers[i]))


@dataclass(frozen=True)
class DdpmRangeConfig:
    """The equirectangular range image: the sensor's beams (rows) x ``azimuth_bins`` columns."""

    azimuth_bins: Annotated[int, Bound(1, 8192, "columns of a range image, each a ray per beam: the paper's 1024")]
    #: space-to-depth block the U-Net folds into channels ([1, 1]: plain pixels)
    patch: Patch
    #: depth -> pixel: ``linear`` (2·d/max_range - 1) or ``log`` (R2DM's log2(d+1)/log2(max+1)),
    #: see typ.projection.to_unit
    depth: Literal["linear", "log"]


@dataclass(frozen=True)
class DdpmBevConfig:
    """The BEV image: orthographic projection onto ``grid`` (shape [H, W, 1]; z range kept)."""

    grid: GridConfig
    patch: Patch


@dataclass(frozen=True)
class PixelUNetConfig:
    """The lightweight pixel-space U-Net of LiDAR DDPM §IV-2."""

    block_out_channels: Annotated[tuple[Width, ...], LEVELS]
    layers_per_block: LayersPerBlock
    norm_num_groups: NormGroups
    dropout: Dropout
    #: N of the Fourier time embedding (Eq. 4)
    harmonics: Annotated[int, Bound(1, 64, "frequencies of the time embedding: the paper's 4")]
    #: two fixed input channels with each pixel's row and column (beam elevation / azimuth, BEV x / y)
    coordinates: bool

    def check(self, where: str, name: str) -> None:
        if len(self.block_out_channels) < 2 or any(c % self.norm_num_groups for c in self.block_out_channels):
            raise TypError(where, f"{name}.block_out_channels",
                           f">= 2 positive widths divisible by norm_num_groups={self.norm_num_groups}",
                           list(self.block_out_channels))


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
    samplers: Samplers = ()
    seeds: Annotated[tuple[Seed, ...], SEEDS] = ()


@dataclass(frozen=True)
class FeatureNetConfig:
    """typ's FRID (range image) and FPVD (voxel grid) feature networks, trained on the
    simulator's per-point semantics."""

    width: Width
    levels: Annotated[int, Bound(1, 8, "resolution levels: each halves the image")]
    steps: Steps
    batch_size: BatchSize
    lr: LearningRate
    voxel_grid: GridConfig

    def check(self, where: str, name: str) -> None:
        self.voxel_grid.check(where, f"{name}.voxel_grid")


@dataclass(frozen=True)
class LatentRouteConfig:
    """TYP's latent route beside the pixel DDPM: stage 1 (P(x|y) in VQ latents) sampled on the
    same held-out views with their box maps. ``samplers: []`` leaves it out."""

    samplers: Samplers
    views: Views
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
    configs: Annotated[tuple[DdpmRunConfig, ...], Length(1, 64, "Table I rows, each trained and scored: the "
                                                         "paper's 11")]
    samplers: Samplers
    seeds: Annotated[tuple[Seed, ...], SEEDS]
    train_timesteps: Timesteps
    steps: Steps
    batch_size: BatchSize
    lr: LearningRate
    #: what the U-Net outputs: ``epsilon`` (Ho et al., the paper's) or ``v_prediction`` (v = √ᾱ ε -
    #: √(1-ᾱ) x_0, Salimans & Ho); the same minimiser, weighted differently over t (tasks/ddpm.py)
    prediction: Literal["epsilon", "v_prediction"]
    checkpoint_every: Steps
    eval_samples: Annotated[int, Bound(2, 10_000, "samples per set, at least 2 for a covariance: the paper's 1000")]
    bootstrap: Annotated[int, Bound(10, 20_000, "bootstrap replicates, each resampling every scan's kernel terms: "
                                    "the paper's 1000")]
    preset: Literal["r2dm"]  #: the bootstrap resamples its per-scan kernel terms (tasks/ddpm_metrics.py)
    features: FeatureNetConfig
    latent: LatentRouteConfig
    domain: str
    ego_only: bool
    train_split: str
    test_split: str
    seed: Seed
    input: str
    reports: str
    out: str

    def check(self, where: str, name: str) -> None:
        self.unet.check(where, f"{name}.unet")
        self.features.check(where, f"{name}.features")
        self.bev.grid.check(where, f"{name}.bev.grid")
        if self.bev.grid.shape[2] != 1:
            raise TypError(where, f"{name}.bev.grid.shape", "[H, W, 1] (one height channel: the image)",
                           list(self.bev.grid.shape))
        # the range image's height is the sensor's beam count, checked where the sensor is known
        factor = 2 ** (len(self.unet.block_out_channels) - 1)
        for key, (ph, pw), (h, w) in (("bev", self.bev.patch, self.bev.grid.shape[:2]),
                                      ("range_image", self.range_image.patch, (None, self.range_image.azimuth_bins))):
            if w % pw or (w // pw) % factor or (h is not None and (h % ph or (h // ph) % factor)):
                raise TypError(where, f"{name}.{key}.patch", f"a block that divides the image into a size divisible "
                               f"by 2^(levels-1) = {factor}", [ph, pw])
        if not self.seeds:
            raise TypError(where, f"{name}.seeds", "at least one training seed", [])
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
