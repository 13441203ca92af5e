"""The run-wide blocks (``tracking``, ``runtime``, ``serve``), ``evaluate``'s, and :class:`Config`,
the whole of a params.yaml."""
from __future__ import annotations

import typing
from dataclasses import dataclass, field
from typing import Literal

from typ.config.base import _positive_fields
from typ.config.data import SimulateConfig, VoxelizeConfig
from typ.config.ddpm import DdpmConfig
from typ.config.detection import FusionConfig, SscConfig
from typ.config.generation import (AdaptConfig, GenerateConfig, SelftrainConfig, Stage1Config, Stage2Config,
                                   VQVAEStageConfig)
from typ.errors import TypError


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
