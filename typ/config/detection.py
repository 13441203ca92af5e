"""The blocks of the collaborative-perception benchmarks: ``fusion`` (the detectors, Tables 1 and 3)
and ``ssc`` (V2VSSC)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

from models.registry import METHODS
from typ.config.base import _check_methods, _positive_fields
from typ.errors import TypError


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


#: the names of the fusion-method registry (``models.registry.METHODS``, torch-free) in its order
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
    comm_range: float
    max_agents: int
    batch_size: int
    lr: float
    finetune_lr: float
    lr_schedule: Literal["constant", "cosine"]
    warmup: float
    steps: int
    pretrain_steps: int
    pretrain_sources: tuple[PretrainSource, ...]
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
        _check_methods(where, f"{name}.pretrain_sources", self.pretrain_sources, PRETRAIN_SOURCES, allow_empty=True)
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


#: the fusion methods semantic scene completion runs (every one of the registry): no and late
#: fusion share one single-agent network
SSC_METHODS = FUSION_METHODS


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
    comm_range: float
    steps: int
    warm_start_steps: int
    checkpoint_every: int
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
    test_scenarios: int | None
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
        _positive_fields(self, where, name, "comm_range", "steps", "warm_start_steps", "checkpoint_every", "lr",
                         "finetune_lr", "seeds", "bootstrap")
        if self.test_scenarios is not None and self.test_scenarios < 1:
            raise TypError(where, f"{name}.test_scenarios", "None (every scenario) or a count >= 1",
                           self.test_scenarios)
        if not self.class_weight_eps > 1:
            raise TypError(where, f"{name}.class_weight_eps", "a number > 1 (1 / ln(eps + share) stays finite)",
                           self.class_weight_eps)

    @property
    def training_seeds(self) -> tuple[int, ...]:
        """The seeds every network is trained with."""
        return tuple(self.seed + k for k in range(self.seeds))
