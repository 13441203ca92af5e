"""The blocks of the collaborative-perception benchmarks: ``fusion`` (the detectors, Tables 1 and 3)
and ``ssc`` (V2VSSC)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal, get_args

from typ.registry import METHODS
from typ.config.base import (BatchSize, Bound, Coordinate, Dropout, LearningRate, Length, Replicates, Seed, Steps,
                             TrainingSeeds, Width, _check_methods)
from typ.config.data import MAX_SCENARIOS, CommRange
from typ.errors import TypError

#: pillars kept per cloud: a (max_pillars, max_points_per_pillar, 10) float tensor per agent and sample
MAX_PILLARS = 200_000
Pillars = Annotated[int, Bound(1, MAX_PILLARS, "pillars kept per cloud, each a row of the pillar tensor: "
                                "OpenCOOD keeps 32,000")]
#: cells of the detector's BEV grid (x times y): its first feature map holds pillar_channels floats per cell
#: and agent, 4 M cells x 64 channels x 4 B = 1 GB
MAX_BEV_CELLS = 1 << 22
Stride = Annotated[int, Bound(1, 8, "a convolution's stride")]
BLOCKS = Length(1, 8, "backbone levels: OpenCOOD's PointPillars has 3")
Heads = Annotated[int, Bound(1, 64, "attention heads: OpenCOOD's V2X-ViT uses at most 16")]
HeadWidth = Annotated[int, Bound(1, 512, "channels of one attention head")]
MetresStd = Annotated[float, Bound(0, 10, "a standard deviation in metres: V2X-ViT's noisy setting is 0.2")]
DegreesStd = Annotated[float, Bound(0, 180, "a standard deviation in degrees: V2X-ViT's noisy setting is 0.2")]
DelayMs = Annotated[int, Bound(0, 10_000, "milliseconds of message age: 100 frames at 10 Hz")]
SWEEP = Length(0, 32, "points of one robustness curve, each scoring every method again")
AnchorSide = Annotated[float, Bound(0, 50, "metres of a vehicle's length, width or height", low_open=True)]
WINDOWS = Length(0, 8, "window branches of the multi-scale attention: OpenCOOD's has 3")
Scale = Annotated[float, Bound(0, 10, "a scaling of the scene: OpenCOOD's is 0.95 to 1.05", low_open=True)]
LayerNum = Annotated[int, Bound(1, 64, "convolutions per backbone level: OpenCOOD's at most 8")]
Threshold = Annotated[float, Bound(0, 1, "a score or IoU threshold", high_open=True)]


@dataclass(frozen=True)
class DetectorConfig:
    """PointPillars of the fusion benchmark (``models/pointpillars.py``), one per fusion method."""

    lidar_range: tuple[Coordinate, Coordinate, Coordinate, Coordinate, Coordinate, Coordinate]
    voxel_size: Annotated[float, Bound(0.01, 10, "metres of a pillar's side: OpenCOOD's is 0.4")]
    max_points_per_pillar: Annotated[int, Bound(1, 256, "points kept per pillar, each a column of the pillar "
                                                "tensor: OpenCOOD keeps 32")]
    max_pillars: Pillars
    pillar_channels: Width
    layer_nums: Annotated[tuple[Annotated[int, Bound(0, 64, "convolutions per backbone level: OpenCOOD's at most "
                                                     "8")], ...], BLOCKS]
    layer_strides: Annotated[tuple[Stride, ...], BLOCKS]
    num_filters: Annotated[tuple[Width, ...], BLOCKS]
    upsample_strides: Annotated[tuple[Stride, ...], BLOCKS]
    num_upsample_filters: Annotated[tuple[Width, ...], BLOCKS]
    anchor_size: tuple[AnchorSide, AnchorSide, AnchorSide]
    anchor_z: Annotated[float, Bound(-10, 10, "metres from the sensor to an anchor's centre")]

    def check(self, where: str, name: str) -> None:
        r = self.lidar_range
        if not (r[0] < r[3] and r[1] < r[4] and r[2] < r[5]):
            raise TypError(where, f"{name}.lidar_range", "[x_min, y_min, z_min, x_max, y_max, z_max], min < max",
                           list(r))
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
        cells = round((r[3] - r[0]) / self.voxel_size) * round((r[4] - r[1]) / self.voxel_size)
        if cells > MAX_BEV_CELLS:
            raise TypError(where, f"{name}.lidar_range", f"at most {MAX_BEV_CELLS} pillar cells in x times y (each "
                           f"holds pillar_channels floats per agent: OpenCOOD's range has 135,168)", cells)


@dataclass(frozen=True)
class V2XViTConfig:
    """The V2X-ViT fusion transformer (``models/fusion.V2XViT``) on the detector's backbone;
    ``shrink_stride``: the stride of its shrink conv (OpenCOOD's 2; with 1 and ``dim`` equal to the
    backbone's width it starts as the single-agent network, :meth:`V2XViT.warm_start`)."""

    dim: Width
    depth: Annotated[int, Bound(1, 16, "transformer layers: OpenCOOD's V2X-ViT has 3")]
    heads: Heads
    dim_head: HeadWidth
    window_sizes: Annotated[tuple[Annotated[int, Bound(1, 64, "cells along a window's side")], ...], WINDOWS]
    window_heads: Annotated[tuple[Heads, ...], WINDOWS]
    window_dim_heads: Annotated[tuple[HeadWidth, ...], WINDOWS]
    mlp_dim: Annotated[int, Bound(1, 4096, "channels of the feed-forward layer: OpenCOOD's is 256")]
    dropout: Dropout
    shrink_stride: Stride = 2

    def check(self, where: str, name: str) -> None:
        if self.dim % 2 or not self.window_sizes or \
                not len(self.window_sizes) == len(self.window_heads) == len(self.window_dim_heads):
            raise TypError(where, f"{name}.window_sizes", "an even dim and equal-length window lists",
                           [self.dim, list(self.window_sizes)])


@dataclass(frozen=True)
class RobustnessConfig:
    """V2VSSC §IV curves: AP against pose noise, delay and message compression."""

    position_std: Annotated[tuple[MetresStd, ...], SWEEP]
    heading_std_deg: Annotated[tuple[DegreesStd, ...], SWEEP]
    delay_ms: Annotated[tuple[DelayMs, ...], SWEEP]
    quantization_bits: Annotated[tuple[Annotated[int, Bound(1, 16, "bits per feature of a compressed message")],
                                       ...], SWEEP]

    def check(self, where: str, name: str) -> None:
        if any(d % 100 for d in self.delay_ms):
            raise TypError(where, f"{name}.delay_ms", "multiples of 100 ms (one 10 Hz frame)", list(self.delay_ms))


@dataclass(frozen=True)
class AugmentConfig:
    """OpenCOOD's training augmentation, one global similarity per sample: a flip of the y axis
    with probability 0.5 (``flip``), a rotation about z drawn from U(-rotation_deg, rotation_deg)
    and a scaling from U(scale[0], scale[1]); applied to every agent's cloud in its own frame, to
    the boxes, and conjugated into the agent->ego transforms so that they stay rigid."""

    flip: bool
    rotation_deg: Annotated[float, Bound(0, 180, "degrees either way: OpenCOOD's is 45")]
    scale: tuple[Scale, Scale]

    def check(self, where: str, name: str) -> None:
        if not self.scale[0] <= self.scale[1]:
            raise TypError(where, f"{name}.scale", "[low, high] with 0 < low <= high", list(self.scale))


#: the names of the fusion-method registry (``typ.registry.METHODS``, torch-free) in its order
FUSION_METHODS = tuple(METHODS)


#: Table 3's pre-training sets (TYP §4.5), each a row of the table: the generated target split (the
#: ColWaymo analogue), the simulated source domain (the OPV2V analogue), or the two together in one
#: training set (the same ``pretrain_steps``, so each is seen half as often)
PretrainSource = Literal["colwaymo", "source", "both"]
PRETRAIN_SOURCES: tuple[str, ...] = get_args(PretrainSource)


@dataclass(frozen=True)
class FusionConfig:
    """Stage ``fusion`` (TYP §4.2–4.5, Tables 1–3; V2VSSC §IV): collaborative detection benchmark.

    ``methods``: names of ``models.fusion.METHODS`` (no and late fusion share one single-agent
    detector). Every network is trained ``seeds`` times (seeds ``seed``, ``seed + 1``, ...).
    The single-agent detector trains ``steps`` from scratch (``pretrain_steps`` on a pre-training
    set); early and intermediate fusion start from it (``warm_start``) and train
    ``warm_start_steps`` more at ``finetune_lr``, or from scratch for ``steps`` /
    ``pretrain_steps`` like it (off, as OpenCOOD trains them). Table 3 fine-tunes a pre-trained
    network (pre-trained on each of ``pretrain_sources``: :data:`PRETRAIN_SOURCES`) on each of
    ``finetune_scenes`` and on all N real_cav training scenarios with the steps
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
    comm_range: CommRange
    max_agents: Annotated[int, Bound(1, 64, "agents fused per sample, each a cloud through the backbone: "
                                     "OpenCOOD's 5")]
    batch_size: BatchSize
    lr: LearningRate
    finetune_lr: LearningRate
    lr_schedule: Literal["constant", "cosine"]
    warmup: Annotated[float, Bound(0, 1, "the share of the run spent warming up", high_open=True,
                                   what="a fraction")]
    steps: Steps
    pretrain_steps: Steps
    pretrain_sources: tuple[PretrainSource, ...]
    finetune_scenes: Annotated[tuple[Annotated[int, Bound(1, MAX_SCENARIOS, "scenarios of a fine-tuning subset")],
                                     ...], Length(0, 16, "fine-tuning subsets, each training every method again")]
    warm_start: bool
    warm_start_steps: Steps
    seeds: TrainingSeeds
    generated_extent: Annotated[float, Bound(0, 1000, "metres: 1 km is past every LiDAR's range", low_open=True)]
    min_gt_points: Annotated[int, Bound(0, 100_000, "points in a box: a close car holds a few thousand")]
    score_threshold: Threshold
    nms_threshold: Threshold
    max_boxes: Annotated[int, Bound(1, 1000, "boxes kept per frame, compared pairwise by NMS: OpenCOOD keeps 100")]
    bootstrap: Replicates
    seed: Seed
    checkpoint_every: Steps
    processes: Annotated[int, Bound(0, 256, "trainings at once, one process each (0: one per CPU thread)")]
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
        _check_methods(where, f"{name}.pretrain_sources", self.pretrain_sources, PRETRAIN_SOURCES, allow_empty=True)

    @property
    def training_seeds(self) -> tuple[int, ...]:
        """The seeds every network is trained with."""
        return tuple(self.seed + k for k in range(self.seeds))


#: the fusion methods semantic scene completion runs (every one of the registry): no and late
#: fusion share one single-agent network
SSC_METHODS = FUSION_METHODS


@dataclass(frozen=True)
class SscNetworkConfig:
    """The SSC network (``models.ssc.ssc_detector``): PointPillars on V2VSSC's grid, three backbone
    levels (strides 2, 4, 8 over the 0.78125 m pillars), an occupancy head of ``head_hidden``."""

    layer_nums: tuple[LayerNum, LayerNum, LayerNum]
    num_filters: tuple[Width, Width, Width]
    num_upsample_filters: tuple[Width, Width, Width]
    pillar_channels: Width
    head_hidden: Width
    max_pillars: Pillars


@dataclass(frozen=True)
class SscNoisyConfig:
    """Table I's noisy setting: the cooperating agents' pose noise and message age (V2X-ViT's
    0.2 m / 0.2 deg / 100 ms unless changed)."""

    position_std: MetresStd
    heading_std_deg: DegreesStd
    delay_ms: DelayMs

    def check(self, where: str, name: str) -> None:
        if self.delay_ms % 100:
            raise TypError(where, f"{name}.delay_ms", "a multiple of 100 ms >= 0 (10 Hz frames)", self.delay_ms)


@dataclass(frozen=True)
class SscConfig:
    """Stage ``ssc`` (V2VSSC §III–IV, Table I, Figs. 4–5): collaborative semantic scene completion on
    ``domain``'s simulated scenarios and their semantic occupancy maps (``simulate.occupancy``).

    The single-agent network trains ``steps`` steps of one agent view (every agent's own cloud
    against its own map) with class-balanced cross-entropy (weights ``1 / ln(class_weight_eps +
    share)``), Adam at ``lr`` with cosine decay; no and late fusion run it. Early fusion, AttFuse
    and V2X-ViT (``v2xvit``: its transformer) start from it and train ``warm_start_steps`` on the
    ego's map at ``finetune_lr``. Training resumes from the newest of its checkpoints, taken every
    ``checkpoint_every`` steps (:func:`tasks.training.run_loop`). Every network is trained ``seeds`` times (``seed``, ``seed + 1``, ...). Each method is scored
    on the test split in the perfect setting and in ``noisy``; the ``robustness`` sweeps (pose
    noise, delay, the feature-sending methods' message bits) use the first seed's networks.
    Intervals: ``bootstrap`` replicates over test scenarios (and seeds). ``test_scenarios``: score
    on the first n scenarios of ``test_split`` only (None: all of them; the split may be larger for
    the fusion benchmark, which reads it whole).

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
    comm_range: CommRange
    steps: Steps
    warm_start_steps: Steps
    checkpoint_every: Steps
    lr: LearningRate
    finetune_lr: LearningRate
    #: 1 / ln(eps + share) is finite for eps > 1 only, and past 100 every class weighs the same
    class_weight_eps: Annotated[float, Bound(1, 100, "1 / ln(eps + share) needs eps > 1: V2VSSC's is 1.02",
                                             low_open=True)]
    seeds: TrainingSeeds
    bootstrap: Replicates
    seed: Seed
    sim: str
    generated: str
    domain: str
    train_split: str
    test_split: str
    test_scenarios: Annotated[int, Bound(1, MAX_SCENARIOS, "test scenarios scored (null: all)")] | None
    reports: str
    out: str

    def check(self, where: str, name: str) -> None:
        self.v2xvit.check(where, f"{name}.v2xvit")
        if not self.data or self.data[0] != "oracle" or len(set(self.data)) != len(self.data):
            raise TypError(where, f"{name}.data", "oracle first (Table I, the robustness sweeps), then generated "
                           "or nothing", list(self.data))
        self.robustness.check(where, f"{name}.robustness")
        self.noisy.check(where, f"{name}.noisy")
        _check_methods(where, f"{name}.methods", self.methods, SSC_METHODS)

    @property
    def training_seeds(self) -> tuple[int, ...]:
        """The seeds every network is trained with."""
        return tuple(self.seed + k for k in range(self.seeds))
