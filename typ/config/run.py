"""The run-wide blocks (``tracking``, ``runtime``, ``serve``), ``evaluate``'s, and :class:`Config`,
the whole of a params.yaml."""
from __future__ import annotations

import typing
from dataclasses import dataclass, field
from typing import Annotated, Literal

from typ.config.base import Bound, Length, Replicates, Seed
from typ.config.data import MAX_SCANS, SimulateConfig, VoxelizeConfig
from typ.config.ddpm import DdpmConfig
from typ.config.detection import FusionConfig, SscConfig
from typ.config.generation import (AdaptConfig, GenerateConfig, SelftrainConfig, Stage1Config, Stage2Config,
                                   VQVAEStageConfig)
from typ.errors import TypError
from typ.registry import STAGES as STAGE_REGISTRY


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
class NovelViewSequence:
    """A real drive in the KITTI odometry layout whose scans ``evaluate`` scores generated views
    against (:mod:`tasks.novel_view`): every view made for a scan's pose from another scan."""

    #: the dataset root (``sequences/<sequence>/``), relative to the project root or absolute
    root: str
    sequence: str = "00"
    #: the drive's LiDAR preset (``typ.sensors.SENSORS``); empty: estimated from its first scan
    sensor: str = ""
    #: ``[first, stop)``: score only pairs of these scans (the range the generator did not train on)
    frames: tuple[Annotated[int, Bound(0, MAX_SCANS, "a scan index: a day at 10 Hz is 864,000")],
                  Annotated[int, Bound(0, MAX_SCANS, "a scan index: a day at 10 Hz is 864,000")]] | None = None

    def check(self, where: str, name: str) -> None:
        if not self.root.strip():
            raise TypError(where, f"{name}.root", "the path of a dataset root in the KITTI odometry layout", self.root)
        if self.frames is not None and not self.frames[0] < self.frames[1]:
            raise TypError(where, f"{name}.frames", "[first, stop) with first < stop", list(self.frames))


@dataclass(frozen=True)
class NovelViewConfig:
    """``evaluate``'s real-scan section; no drive, no section: ``make run`` needs no real data."""

    sequences: Annotated[tuple[NovelViewSequence, ...], Length(0, 64, "real drives, each scored whole")] = ()
    #: score the first this many pairs of each drive (0: every pair)
    max_pairs: Annotated[int, Bound(0, 1_000_000, "pairs scored per drive, each about 10 s for every method "
                                    "(0: all)")] = 0
    #: one picture per distance band of each drive
    pictures: bool = True

    def check(self, where: str, name: str) -> None:
        for k, drive in enumerate(self.sequences):
            drive.check(where, f"{name}.sequences[{k}]")


@dataclass(frozen=True)
class EvaluateConfig:
    """Stage ``evaluate``: every benchmark table on held-out data, with bootstrap intervals.

    Generation: (ego, reference) pairs of ``target_domain`` / ``target_split`` (at most
    ``max_pairs``, 0: all), every method sampled once per training seed; ``gallery`` samples
    rendered to ``reports/gallery``; ``n_boot`` bootstrap replicates for each interval.
    """

    seed: Seed
    n_boot: Replicates
    max_pairs: Annotated[int, Bound(0, 1_000_000, "(ego, reference) pairs scored, each sampled once per method "
                                    "and seed (0: all)")]
    gallery: Annotated[int, Bound(0, 1000, "samples rendered to pictures")]
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
    #: real drives the generated views are scored on (``reports/novel_view/<drive>/``); none by default
    novel_view: NovelViewConfig = NovelViewConfig()

    def check(self, where: str, name: str) -> None:
        self.novel_view.check(where, f"{name}.novel_view")   # the bounds beside the fields are the rest


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

    #: stage name -> attribute holding its block, in pipeline order (:data:`typ.registry.STAGES`)
    STAGES: typing.ClassVar[tuple[str, ...]] = tuple(STAGE_REGISTRY)

    def block(self, stage: str):
        if stage not in self.STAGES:
            raise TypError(self.source, "stage", f"one of {list(self.STAGES)}", stage)
        return getattr(self, stage)
