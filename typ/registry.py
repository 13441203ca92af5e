"""The extensible kinds typ's config names, each declared once, torch-free, below the config.

``typ.config`` (and so ``typ check``, ``typ --help`` and the params schema) offers exactly the names
of these tables, and the code that runs them reads the same entries; nothing here imports torch,
numpy or any layer above ``typ`` (the implementation an entry names is imported where it runs):

- :data:`STAGES`: the pipeline's stages in run order, with their kind (what each reads and writes
  is its task module's ``DECLARATION``, :func:`declare`).
- :data:`READERS`: the single-agent dataset formats, each naming its functions in :mod:`tasks.ingest`.
- :data:`SAMPLERS`: the diffusion samplers, as diffusers schedulers (:mod:`models.samplers` builds
  them; :mod:`tasks.ddpm` adds ``pixel`` for samples that live in [-1, 1]).
- :data:`SCHEDULES`: the noise schedules, each the β(T) function of :mod:`models.schedules` it names.
- :data:`METHODS`: the collaborative fusion methods of the detection and SSC benchmarks; each
  entry names its module class in its own file ``models/fusion/<name>.py`` (imported only when a
  module is built).
- :data:`GENERATION_METHODS`: the reference-view methods and baselines ``evaluate`` scores
  (:mod:`tasks.evaluate_generation` runs them), with the rows and curves the reports give them.
- :data:`COMPOSE_MODES`: what a generated reference view is made of (``generate.compose``,
  ``typ generate --compose``, ``typ edit --compose``), with the sentence the reports give it.

A new sampler or schedule is one entry here (and, for a schedule, its function); a new fusion
method is its module and one entry here (plus a config block if it has options).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any, Literal

from typ.errors import TypError


@dataclass(frozen=True)
class StageSpec:
    """One pipeline stage, as the config and the runner know it: ``kind`` is ``per-scene``
    (incremental over scenes, content hashes), ``training`` (resumable checkpoints) or
    ``scoring`` (reads trained models, writes reports); ``torch`` whether its code imports torch
    (a stage that does not gets no device set up, and one that is also per-scene is settled
    without Prefect when every scene is unchanged). What it reads and writes is its task module's
    ``DECLARATION`` (:func:`declare`), which dvc.yaml is generated from (:mod:`flows.dvcyaml`)."""

    kind: Literal["per-scene", "training", "scoring"]
    torch: bool = True


@dataclass(frozen=True)
class Plot:
    """One item of dvc.yaml's top-level ``plots:``: ``y`` is {csv path: [columns]}, or one
    column of the file or folder of CSVs ``id`` names (a folder: one curve per file)."""

    id: str
    x: str
    y: dict | str
    template: str
    x_label: str
    y_label: str
    title: str


@dataclass(frozen=True)
class Stage:
    """What one stage reads and writes, declared beside its code (``tasks/<name>.py``'s
    ``DECLARATION``). Paths are relative to the project root."""

    name: str
    kind: str                                   #: :attr:`StageSpec.kind`
    data: tuple[str, ...] = ()                  #: data and artifact deps
    params: tuple[str, ...] = ()                #: config blocks read besides its own
    outs: tuple[str, ...] = ()                  #: persisted outputs (DVC cache, kept between runs)
    reports: tuple[str, ...] = ()               #: report files and folders (not cached)
    images: tuple[str, ...] = ()                #: figures dvc declares as plots (not cached)
    loss_curves: bool = False                   #: ``<out>/loss/*.csv``, one per network
    torch: bool = True                          #: :attr:`StageSpec.torch`
    plots: tuple[Plot, ...] = ()

    @property
    def metrics(self) -> str:
        return f"metrics/{self.name}.json"

    @property
    def blocks(self) -> tuple[str, ...]:
        """The params blocks it reads: its own first."""
        return (self.name, *self.params)


def declare(name: str, **declared) -> Stage:
    """The declaration of registered stage ``name`` (what it reads and writes, :class:`Stage`'s
    fields), with its kind and torch from :data:`STAGES`."""
    if name not in STAGES:
        raise TypError("typ.registry.STAGES", name, "an entry for every stage a task module declares", "none")
    spec = STAGES[name]
    return Stage(name, spec.kind, torch=spec.torch, **declared)


#: the voxel folders of the target domain's splits (``f"{TARGET_VOXELS}train"``)
TARGET_VOXELS = "data/voxels/dataset=target/split="


#: every stage, in the order ``dvc repro`` runs them; the config has a block of each name
STAGES: dict[str, StageSpec] = {
    "simulate": StageSpec("per-scene", torch=False),
    "voxelize": StageSpec("per-scene", torch=False),
    "vqvae": StageSpec("training"),
    "stage1": StageSpec("training"),
    "adapt": StageSpec("training"),
    "stage2": StageSpec("training"),
    "selftrain": StageSpec("training"),
    "generate": StageSpec("per-scene"),
    "fusion": StageSpec("training"),
    "ssc": StageSpec("training"),
    "ddpm": StageSpec("training"),
    "evaluate": StageSpec("scoring"),
}


@dataclass(frozen=True)
class ReaderSpec:
    """One single-agent dataset format (``simulate.sources.<domain>.format``, ``typ generate
    --format``): ``find`` and ``frames`` its functions (``module:function``): ``find(root)`` ->
    (its scenarios, its own splits), ``frames(scenario)`` its frames in time order; ``layout`` what
    a root holds (for the error when it holds nothing); ``sensor`` the preset of its LiDAR
    (:mod:`typ.sensors.presets`; empty: the preset of the format's name), or, with ``estimate``,
    the function that finds it in a scenario's scans. ``vehicle_frame``: points come in the
    vehicle frame, origin on the ground; ``own_timestamps``: the dataset's stamps are in file order
    and kept; ``keyed_records``: a scenario's key hashes its parts' records too; ``one_file``:
    ``typ generate --input`` may name one file of it."""

    find: str
    frames: str
    layout: str
    vehicle_frame: bool = False
    own_timestamps: bool = False
    keyed_records: bool = False
    one_file: bool = False
    sensor: str = ""
    estimate: str = ""


#: every single-agent format typ reads, by config name (:mod:`tasks.ingest` runs them)
READERS: dict[str, ReaderSpec] = {
    "kitti": ReaderSpec("tasks.ingest:find_kitti", "tasks.ingest:kitti_frames",
                        "training/ or testing/ with velodyne/*.bin"),
    "nuscenes": ReaderSpec("tasks.ingest:find_nuscenes", "tasks.ingest:nuscenes_frames",
                           "mmdet3d *info*.json files beside their .pcd.bin clouds", keyed_records=True),
    "waymo": ReaderSpec("tasks.ingest:find_waymo", "tasks.ingest:waymo_frames",
                        "*.tfrecord segments in the root or in training/, validation/, testing/",
                        vehicle_frame=True, own_timestamps=True, one_file=True),
    # KITTI odometry's own drives are KITTI's HDL-64E; another car's drive in the layout is told by
    # its scans (or --sensor)
    "kitti-odometry": ReaderSpec("tasks.ingest:find_kitti_odometry", "tasks.ingest:kitti_odometry_frames",
                                 "sequences/<seq>/ with velodyne/*.bin, calib.txt (Tr) and poses.txt",
                                 sensor="kitti", estimate="tasks.ingest:estimate_odometry_sensor"),
}


@dataclass(frozen=True)
class SamplerSpec:
    """One sampler: ``scheduler`` the diffusers class name; ``latent`` its options for typ's latents
    (diffusers clips x̂_0 to [-1, 1] by default, wrong for latents); ``pixel`` the options that
    clip x̂_0 to [-1, 1] at each step for pixel samples (Ho et al.'s clip, or dynamic thresholding
    with a maximum of 1 for the multistep solvers)."""

    scheduler: str
    latent: dict[str, Any] = field(default_factory=dict)
    pixel: dict[str, Any] = field(default_factory=dict)


#: every sampler typ runs, by config name
SAMPLERS: dict[str, SamplerSpec] = {
    "ddim": SamplerSpec("DDIMScheduler", {"clip_sample": False}, {"clip_sample": True}),
    "ddpm": SamplerSpec("DDPMScheduler", {"clip_sample": False}, {"clip_sample": True}),
    "dpmsolver++": SamplerSpec("DPMSolverMultistepScheduler", {"algorithm_type": "dpmsolver++"},
                               {"thresholding": True, "sample_max_value": 1.0}),
    "unipc": SamplerSpec("UniPCMultistepScheduler", {}, {"thresholding": True, "sample_max_value": 1.0}),
}


@dataclass(frozen=True)
class ScheduleSpec:
    """One noise schedule: ``function`` the name of its β(T) in :mod:`models.schedules` (numpy),
    which :data:`models.schedules.SCHEDULES` maps the config name to."""

    function: str


#: every noise schedule, by config name (LiDAR-DDPM's and the common ones)
SCHEDULES: dict[str, ScheduleSpec] = {name: ScheduleSpec(name) for name in (
    "constant", "linear", "quadratic", "cosine", "sigmoid", "hyperbolic", "time_dependent", "ramp")}


@dataclass(frozen=True)
class FusionMethod:
    """One fusion method of the benchmark: what it is called, what it takes and learns from, and
    what it sends.

    name: the config's name; display: the row name in TYP Tables 1–3; module_name: its
    :class:`models.fusion.FusionModule` class (:attr:`module`); inputs: the clouds of a batch —
    ``ego`` (the ego's only), ``merged`` (all agents' moved into the ego frame, early fusion) or
    ``agents`` (each in its own frame); targets: ``own`` (a head row per present agent, its own
    labels in its own frame: the single-agent detector) or ``fused`` (a row per sample, the fused
    ground truth in the ego frame); trained_as: another method whose trained network this one runs
    (None: it is trained itself); options: the config block of the module's extra constructor
    arguments (None: none); message: what a cooperating agent sends (``nothing``, ``points``,
    ``boxes``, ``features``); warm_start: whether it may start from the single-agent detector
    (:meth:`models.fusion.FusionModule.warm_start`); short: its row in the one-page summary
    (``reports/summary.md``; empty: ``display``).

    The order of :data:`METHODS` is the order of the tables and benches.
    """

    name: str
    display: str
    module_name: str
    inputs: Literal["ego", "merged", "agents"]
    targets: Literal["own", "fused"]
    message: Literal["nothing", "points", "boxes", "features"]
    trained_as: str | None = None
    options: str | None = None
    warm_start: bool = False
    short: str = ""

    @property
    def summary_name(self) -> str:
        """Its row in the one-page summary."""
        return self.short or self.display

    @property
    def network(self) -> str:
        """The method whose training run makes the network this method runs."""
        return self.trained_as or self.name

    @property
    def module(self) -> type:
        """The module class, from the method's own file ``models/fusion/<name>.py`` (imports torch)."""
        return getattr(importlib.import_module(f"models.fusion.{self.name}"), self.module_name)

    @property
    def intermediate_display(self) -> str:
        """The row name in V2VSSC's tables: feature-sending methods are ``Intermediate (<name>)``."""
        return f"Intermediate ({self.display})" if self.message == "features" else self.display


#: every fusion method, in bench order
METHODS: dict[str, FusionMethod] = {m.name: m for m in (
    FusionMethod("none", "No Fusion", "NoFusion", inputs="ego", targets="own", message="nothing", trained_as="late",
                 short="No fusion"),
    FusionMethod("early", "Early Fusion", "EarlyFusion", inputs="merged", targets="fused", message="points",
                 warm_start=True, short="Early"),
    FusionMethod("late", "Late Fusion", "LateFusion", inputs="agents", targets="own", message="boxes", short="Late"),
    FusionMethod("attfuse", "AttFuse", "AttFuse", inputs="agents", targets="fused", message="features",
                 warm_start=True),
    FusionMethod("v2xvit", "V2X-ViT", "V2XViT", inputs="agents", targets="fused", message="features",
                 options="v2xvit", warm_start=True),
)}
#: the method that trains the single-agent detector every warm start begins from
SINGLE_AGENT = "late"


@dataclass(frozen=True)
class GenerationMethod:
    """One way to produce a reference view that ``evaluate`` scores: ``label`` its row in the
    generation report; ``plotted`` whether dvc.yaml's per-band and row-profile plots draw it."""

    label: str
    plotted: bool = False


#: every generation method and baseline, in the report's order
GENERATION_METHODS: dict[str, GenerationMethod] = {
    "naive_copy": GenerationMethod("naive copy", plotted=True),
    "resim": GenerationMethod("re-simulation", plotted=True),
    "stage1_only": GenerationMethod("stage 1 only (boxes, no ego)", plotted=True),
    "no_adaptation": GenerationMethod("stage 2 without adaptation"),
    "disc": GenerationMethod("stage 2 (adapted source encoder)"),
    "disc_st": GenerationMethod("+ self-training"),
    "disc_st_dummy": GenerationMethod("TYP: + self-training + dummy ego", plotted=True),
    "typ_resim": GenerationMethod("TYP + re-simulated conditioning", plotted=True),
    "one_stage": GenerationMethod("one-stage (TYP Table 5 baseline)"),
    "hybrid": GenerationMethod("hybrid: re-simulation where the ego saw, TYP elsewhere", plotted=True),
    "cast": GenerationMethod("cast: the ego's surfels and TYP's cells in one scene, cast with the reference LiDAR",
                             plotted=True),
}
#: the methods dvc.yaml's per-band and row-profile plots draw, in the report's order
PLOTTED_GENERATION_METHODS = tuple(k for k, m in GENERATION_METHODS.items() if m.plotted)


@dataclass(frozen=True)
class ComposeMode:
    """One way a reference view is composed: ``text`` what the reports say it is; ``implementation``
    the function that composes a batch (``module:function``, :mod:`pipelines.typ.compose`);
    ``casts`` whether it casts the reference LiDAR (through the dataset's sensor preset);
    ``resimulates`` whether it needs the ego's cloud re-simulated from the reference pose;
    ``editable`` whether ``typ edit`` can remake an edited footprint with it."""

    text: str
    implementation: str
    casts: bool = False
    resimulates: bool = False
    editable: bool = False


def load(path: str) -> Any:
    """The object an entry names by ``module:name`` (imported here, where it runs)."""
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def compose_mode(name: str) -> ComposeMode:
    """The entry of compose mode ``name``; any other name is a named error (``generate.compose``)."""
    if name not in COMPOSE_MODES:
        raise TypError("params.yaml", "generate.compose", f"one of {tuple(COMPOSE_MODES)}", name)
    return COMPOSE_MODES[name]


#: every compose mode, by config name (``generate.compose``)
COMPOSE_MODES: dict[str, ComposeMode] = {
    "generated": ComposeMode("TYP's sample alone", "pipelines.typ.compose:generated", editable=True),
    "hybrid": ComposeMode("the ego's cloud re-simulated from the cooperating pose where the ego saw, TYP's sample "
                          "elsewhere", "pipelines.typ.compose:hybrid", casts=True, resimulates=True),
    "cast": ComposeMode("one scene of the ego's surfaces where it saw and TYP's cells elsewhere, cast with the "
                        "cooperating agent's LiDAR", "pipelines.typ.compose:cast", casts=True, editable=True),
}
