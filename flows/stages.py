"""The pipeline's stages, declared once: what each reads, writes and draws.

``dvc.yaml`` is generated from this table (``typ dvc-yaml``, :mod:`flows.dvcyaml`; a test fails
when the committed file differs), with each stage's code deps taken from its flow's import
closure and its profile keys from ``typ/profiles.yaml``. The flow runner takes each stage's kind
and whether it needs torch from here too (:mod:`flows.pipeline`, the CLI).

Adding a stage is a task module ``tasks/<name>.py``, a config block of the same name, its name
and kind in :data:`typ.registry.STAGES` (the one ordered list: the config's and this table's
follow it) and one declaration here: a stage with no flow module of its own runs through
:mod:`flows.generic` (the task module's ``scene_stage`` or ``run``). A flow ``flows/<name>.py``
is for a stage that needs more.

The method lists it draws come from the torch-free registries (:mod:`typ.registry`, through
:mod:`typ.config`), so building dvc.yaml imports no torch. No stage's flow imports this module,
so it is no stage's code dep and editing it re-runs nothing by itself.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from typ.errors import TypError
from typ.registry import STAGES


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
    """One pipeline stage (module doc). Paths are relative to the project root."""

    name: str
    #: ``per-scene`` (incremental over scenes, content hashes), ``training`` (resumable
    #: checkpoints) or ``scoring`` (reads trained models, writes reports)
    kind: str
    data: tuple[str, ...] = ()                  #: data and artifact deps
    params: tuple[str, ...] = ()                #: config blocks read besides its own
    outs: tuple[str, ...] = ()                  #: persisted outputs (DVC cache, kept between runs)
    reports: tuple[str, ...] = ()               #: report files and folders (not cached)
    images: tuple[str, ...] = ()                #: figures dvc declares as plots (not cached)
    loss_curves: bool = False                   #: ``<out>/loss/*.csv``, one per network
    #: whether its code imports torch: a stage that does not gets no device set up, and one that is
    #: also per-scene is settled without Prefect when every scene is unchanged
    torch: bool = True
    plots: tuple[Plot, ...] = field(default_factory=tuple)

    @property
    def metrics(self) -> str:
        return f"metrics/{self.name}.json"

    @property
    def blocks(self) -> tuple[str, ...]:
        """The params blocks it reads: its own first."""
        return (self.name, *self.params)


def _sweep(name: str, x: str, x_label: str, title: str, methods) -> Plot:
    return Plot(f"fusion_{name}", x, {f"reports/plots/fusion_{name}.csv": list(methods)}, "linear", x_label,
                "AP@0.5", title)


def _stage(name: str, **declared) -> Stage:
    """The declaration of registered stage ``name``: its kind and torch from :data:`typ.registry.STAGES`."""
    spec = STAGES[name]
    return Stage(name, spec.kind, torch=spec.torch, **declared)


def stages() -> tuple[Stage, ...]:
    """Every stage in the order ``dvc repro`` runs them, :data:`typ.registry.STAGES`' (the method
    and column lists come from the modules that own them)."""
    from typ.config import FUSION_METHODS
    from typ.registry import PLOTTED_GENERATION_METHODS

    plotted = list(PLOTTED_GENERATION_METHODS)

    target = "data/voxels/dataset=target/split="
    cooperative = [m for m in FUSION_METHODS if m != "none"]
    declared = {s.name: s for s in (
        _stage("simulate", outs=("data/sim",)),
        _stage("voxelize", data=("data/sim",), outs=("data/voxels",)),
        _stage("vqvae", data=(f"{target}train", f"{target}val"), outs=("artifacts/vqvae",), loss_curves=True),
        _stage("stage1", data=(f"{target}train", f"{target}val", "artifacts/vqvae"), outs=("artifacts/stage1",),
               loss_curves=True),
        _stage("adapt",
               data=("data/voxels/dataset=source/split=train", f"{target}train", "artifacts/vqvae/x"),
               outs=("artifacts/adapt",), loss_curves=True),
        _stage("stage2",
               data=("data/sim/source/train", "artifacts/vqvae", "artifacts/adapt/source_vq", "artifacts/stage1"),
               params=("stage1", "voxelize"), outs=("artifacts/stage2",), loss_curves=True),
        _stage("selftrain",
               data=("data/sim/target/train", f"{target}train", "artifacts/vqvae", "artifacts/adapt/source_vq",
                     "artifacts/stage1", "artifacts/stage2"),
               params=("stage2", "stage1", "voxelize"), outs=("artifacts/selftrain",), loss_curves=True),
        _stage("generate",
               data=("data/sim/target/pretrain", "data/sim/real_cav/train", "artifacts/selftrain/generator"),
               params=("stage1", "voxelize"), outs=("data/generated",)),
        _stage("fusion",
               data=("data/sim/real_cav/train", "data/sim/real_cav/test", "data/sim/source/train",
                     "data/generated/real_cav/train", "data/generated/target/pretrain"),
               outs=("artifacts/fusion",),
               plots=(Plot("fusion_loss", "step", {"artifacts/fusion/loss.csv": ["oracle", "generated"]}, "smooth",
                           "step", "loss", "single-agent detector training loss, true vs generated cooperating views"),)),
        _stage("ssc",
               data=("data/sim/real_cav/train", "data/sim/real_cav/test", "data/generated/real_cav/train"),
               outs=("artifacts/ssc",), reports=("reports/ssc.md",),
               images=("reports/ssc_robustness.png", "reports/ssc_gallery.png")),
        _stage("ddpm",
               data=("data/sim/target/train", "data/sim/target/test", f"{target}test", "artifacts/vqvae",
                     "artifacts/stage1"),
               params=("stage1",), outs=("artifacts/ddpm",), reports=("reports/ddpm.md",),
               images=("reports/ddpm_pareto.png", "reports/ddpm_samples.png"), loss_curves=True),
        _stage("evaluate",
               data=("data/sim", "data/voxels", "artifacts/vqvae", "artifacts/adapt/source_vq", "artifacts/stage1",
                     "artifacts/stage2", "artifacts/selftrain", "artifacts/fusion/models",
                     "artifacts/fusion/training.json", "artifacts/ddpm/features"),
               params=("fusion", "ddpm", "stage1", "selftrain", "stage2", "voxelize", "simulate"),
               reports=("reports/generation_accuracy.md", "reports/gallery", "reports/plots", "reports/fusion.md"),
               images=("reports/fusion_pr.png", "reports/fusion_robustness.png"),
               plots=(
                   Plot("iou_by_band", "range_m", {"reports/plots/iou_by_band.csv": plotted}, "linear",
                        "range band centre (m from the sensor)", "IoU",
                        "IoU to the truth by range band, held-out target pairs"),
                   Plot("row_profile", "elevation_deg", {"reports/plots/row_profile.csv": ["truth", *plotted]},
                        "linear", "beam elevation (deg)", "share of azimuth bins with a return",
                        "range-image row occupancy of generated reference views, held-out target pairs"),
                   Plot("fusion_pr", "recall",
                        {"reports/plots/fusion_pr.csv": ["none_ego", *(f"{m}_{d}" for m in cooperative
                                                                       for d in ("oracle", "generated"))]},
                        "simple", "recall", "precision (interpolated)",
                        "PR curves on real_cav/test, AP@0.5, all ranges (first seed)"),
                   _sweep("position_std", "position_std_m", "position noise sigma (m)", "AP vs pose noise",
                          FUSION_METHODS),
                   _sweep("heading_std", "heading_std_deg", "heading noise sigma (deg)", "AP vs heading noise",
                          FUSION_METHODS),
                   _sweep("delay", "delay_ms", "time delay applied (ms)", "AP vs time delay", FUSION_METHODS),
                   _sweep("bits", "bits", "feature bits per value", "AP vs feature quantisation", FUSION_METHODS),
               )),
    )}
    unregistered, undeclared = set(declared) - set(STAGES), [n for n in STAGES if n not in declared]
    if unregistered or undeclared:
        raise TypError("flows/stages.py", "stages", "one declaration per stage of typ.registry.STAGES",
                       f"unregistered {sorted(unregistered)}, undeclared {undeclared}")
    return tuple(declared[name] for name in STAGES)


def by_name() -> dict[str, Stage]:
    """Every stage by name, in pipeline order."""
    return {s.name: s for s in stages()}


#: plots of files no stage writes (``make bench``)
BENCH_PLOTS = (
    Plot("reports/bench_sampling.csv", "seconds", "error", "scatter", "seconds per sample",
         "1 - voxel IoU to the truth", "stage-1 samplers x steps x schedules, time against error"),
)
