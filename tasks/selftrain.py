"""Stage ``selftrain`` (TYP §3.4): enhance the stage-2 adapter in the target domain.

The target domain is single-agent: no reference agent's cloud exists there. Two ways to
still fine-tune the adapter F_AD on it, jointly with the source (simulated CAV) tuples:

- **dummy ego** — for the target's own views, (x_r, y_r) = (the ego's view, its box map)
  with an empty ego, x_e = 0^{H×W×C}: the output side sees real target clouds;
- **self-training** — sample a reference pose on a labelled vehicle of a target scene,
  generate x̂_r with the current model from (x_e', y_r), and train on (x̂_r, x_e', y_r): the
  input side sees real target ego clouds.

Each can be switched off, as can the adversarial adaptation of the source encoder (then the
source tuples are encoded by E_tgt and the adapter is trained anew: "no adaptation"), so
TYP Table 4's ablation is one params change. The UNet stays frozen throughout. The same
recipe enhances the re-simulation-conditioned adapter (``typ_resim``) when stage 2 trained
one: its pseudo references and dummy egos carry re-simulated views too (an empty one for the
dummy ego). Adapters go to ``<out>/seed_<s>/<variant>/``; the generator ``generate`` uses, a
:class:`pipelines.typ.pipeline_typ.TYPPipeline`, to ``<out>/generator/seed_<s>/``.
"""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from pipelines.typ import Reference
from pipelines.typ.pipeline_typ import PointStats, TYPPipeline, generator_dir, point_statistics
from tasks import generate, stage1, stage2
from tasks.scene_stage import StageResult
from tasks.stage2 import Latents, Tuples
from tasks.voxel_data import ViewSet, load_views
from tasks.training import Trainings
from typ.config import SelftrainConfig, as_dict
from typ.errors import TypError
from typ.formats.opv2v import list_agents, list_scenarios, list_timestamps, read_scene, scenario_sensor
from typ.voxel import Grid
from typ.registry import TARGET_VOXELS, declare

STAGE = "selftrain"
#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare("selftrain", data=("data/sim/target/train", f"{TARGET_VOXELS}train", "artifacts/vqvae",
                                         "artifacts/adapt/source_vq", "artifacts/stage1", "artifacts/stage2"),
                      params=("stage2", "stage1", "voxelize"), outs=("artifacts/selftrain",), loss_curves=True)


@dataclass(frozen=True)
class Variant:
    """One row of TYP Table 4 (``conditions = 2``: the re-simulation-conditioned adapter)."""

    name: str
    discriminator: bool
    self_training: bool
    dummy_ego: bool
    conditions: int = 1


#: TYP Table 4's rows, in its order
TABLE4 = (Variant("no_adaptation", False, False, False), Variant("disc", True, False, False),
          Variant("disc_st", True, True, False), Variant("disc_st_dummy", True, True, True))


def variant_of(cfg: SelftrainConfig) -> Variant:
    """The variant the switches in params ask for (named like its Table 4 row when it is one)."""
    for v in TABLE4:
        if (v.discriminator, v.self_training, v.dummy_ego) == (cfg.discriminator, cfg.self_training, cfg.dummy_ego):
            return v
    name = "_".join(n for n, on in (("disc", cfg.discriminator), ("st", cfg.self_training),
                                    ("dummy", cfg.dummy_ego)) if on) or "no_adaptation"
    return Variant(name, cfg.discriminator, cfg.self_training, cfg.dummy_ego)


def resim_variant(cfg: SelftrainConfig) -> Variant:
    """The switches' recipe on the re-simulation-conditioned adapter."""
    v = variant_of(cfg)
    return dataclasses.replace(v, name="typ_resim", discriminator=True, conditions=2)


def variants_to_run(cfg: SelftrainConfig, *, resim: bool) -> list[Variant]:
    chosen = variant_of(cfg)
    out = list(TABLE4) + ([chosen] if chosen not in TABLE4 else []) if cfg.ablation else [chosen]
    return out + ([resim_variant(cfg)] if resim else [])


def dummy_ego_tuples(views: ViewSet) -> Tuples:
    """Target ego views as (x_r, y_r) with an empty ego (and an empty re-simulated view)."""
    index = np.arange(len(views))
    x, y = views.occupancy(index), views.box_maps(index)
    return Tuples(x, y, np.zeros_like(x), np.zeros_like(x))


def target_frames(split_root: Path, heights: dict[str, float] | None = None, domain: str = "") -> list:
    """Every frame's ego view (the only real cloud of single-agent target scenes).

    heights: ``voxelize.mount_height``. A scenario whose yaml names its LiDAR (a real dataset's,
    :func:`typ.formats.opv2v.scenario_sensor`) is then seen from a sensor at ``domain``'s height
    straight above or below that LiDAR, so that one grid (``sensor_grid(domain)``) puts every
    frame's ground in the same channel, as voxelize put it.
    """
    from tasks.ingest import to_sensor_frame
    from typ.sensors import mount_height

    frames = []
    for folder in list_scenarios(split_root):
        ego_id = list_agents(folder)[0]
        sensor = scenario_sensor(folder) if heights is not None else None
        lift = mount_height(domain, heights) - mount_height(sensor, heights) if sensor else 0.0
        frames += [to_sensor_frame(read_scene(folder, ts, agents=[ego_id]), lift).ego for ts in list_timestamps(folder)]
    return frames


def pseudo_references(frames: list, cfg: SelftrainConfig, grid: Grid,
                      rng: np.random.Generator) -> list[Reference]:
    """Up to ``cfg.pseudo_references`` reference poses, one per target frame in turn, each on a
    labelled vehicle inside [min_distance, max_distance] drawn with ``rng``."""
    skipped = generate.new_skip_counts()
    refs: list[Reference] = []
    for ego in frames:
        if len(refs) == cfg.pseudo_references:
            break
        ids = sorted(generate.candidate_ids(ego, cfg, skipped))
        if ids:
            vid = int(rng.choice(ids))
            refs.append(generate.build_reference(ego, int(np.flatnonzero(ego.box_ids == vid)[0]), grid))
    if not refs:
        raise TypError("selftrain", "selftrain.min_distance/max_distance",
                       "target scenes with labelled vehicles inside the distance band (for pseudo references)",
                       f"none in {len(frames)} frames")
    return refs


@dataclass
class References:
    """The pseudo references' inputs: x_e' (R, C, H, W) and y_r (R, 1, H, W) float32 in each
    reference frame, and the re-simulated views (R, C, H, W) when the adapter takes them."""

    x_e: np.ndarray
    y_r: np.ndarray
    resim: np.ndarray | None = None

    @classmethod
    def of(cls, refs: list[Reference], resim: np.ndarray | None = None) -> "References":
        return cls(np.stack([r.x_e for r in refs]).astype(np.float32), np.stack([r.y_r for r in refs]).astype(np.float32),
                   resim)


def pseudo_tuples(refs: References, pipe: TYPPipeline, seed: int, conditions: int) -> Tuples:
    """(x̂_r, y_r, x_e'[, re-simulated]) with x̂_r sampled by ``pipe``, the model being enhanced."""
    resim = refs.resim if conditions == 2 else None
    x_hat = pipe.occupancy(refs.x_e, refs.y_r, seed=seed, resim=resim).astype(np.float32)
    return Tuples(x_hat, refs.y_r, refs.x_e, resim)


def tuple_encoders(v: Variant, source_x, target_x) -> dict:
    """The x encoder of each kind of training tuple (TYP §3.4): the source CAV tuples through the
    adapted E_src (E_tgt in the "no adaptation" row), the target domain's pseudo references and
    dummy egos through E_tgt, the encoder the generator conditions with on target data."""
    return {"source": source_x if v.discriminator else target_x, "pseudo": target_x, "dummy": target_x}


def encode_kinds(v: Variant, kinds: dict[str, Tuples], source_x, target_x, y_encoder, ldm, *,
                 augment: int) -> list[Latents]:
    """:func:`stage2.encode` of each kind of tuple (``"source"``, ``"pseudo"``, ``"dummy"``), in the
    given order, with its encoder from :func:`tuple_encoders`."""
    encoders = tuple_encoders(v, source_x, target_x)
    return [stage2.encode(t, encoders[kind], y_encoder, ldm, augment=augment, conditions=v.conditions)
            for kind, t in kinds.items()]


def concat(*parts: Latents) -> Latents:
    import torch

    return Latents(*(torch.cat([getattr(p, k) for p in parts]) for k in ("z0", "cond", "ego")))


def training_fields(block: SelftrainConfig) -> dict:
    """The ``selftrain`` settings an adapter's training depends on: all but the sampling-time
    ``adapter_scale`` (changing it re-samples, it does not retrain)."""
    return {k: v for k, v in as_dict(block).items() if k != "adapter_scale"}


def base_pipeline(cfg, root: Path, seed: int, x_vq, y_encoder, stats) -> TYPPipeline:
    """Stage 1 of replica ``seed`` as a pipeline without an adapter, sampling as the generator will
    (with ``selftrain.adapter_scale`` once it is given one)."""
    block = cfg.selftrain
    ldm, saved = stage1.load_model(stage1.replica_dir(root / block.stage1, seed))
    g = cfg.voxelize.grid
    return TYPPipeline(x_vq, y_encoder, ldm, None, Grid(g.x_range, g.y_range, g.z_range, g.shape),
                       saved["schedule"], int(saved["train_timesteps"]), block.sampler, block.sample_steps,
                       saved["postprocess"], stats, block.adapter_scale)


@dataclass
class Inputs:
    """What self-training learns from, gathered once for every replica and variant (:func:`gather`):
    stage 2's source tuples, the pseudo references, the target's ego views as dummy-ego tuples,
    and the target's point statistics (the generator's :class:`pipelines.typ.pipeline_typ.PointStats`)."""

    tuples: Tuples
    references: References
    dummy: Tuples
    stats: PointStats


@dataclass
class Encoders:
    """E_tgt (``target_x``), E_src from the adaptation (``source_x``) and the box-map encoder."""

    target_x: torch.nn.Module
    source_x: torch.nn.Module
    y: torch.nn.Module


def gather(cfg, root: Path) -> Inputs:
    """:class:`Inputs` from the project's data: stage 2's tuples, the target's simulated frames
    (pseudo references on their labelled vehicles, re-simulated when stage 2 re-simulated) and
    its voxelized ego views."""
    from typ.sim.sensor import domain_spec

    block = cfg.selftrain
    target_grid = cfg.voxelize.sensor_grid(block.target_domain)
    tuples = stage2.load_tuples(root / block.stage2)
    frames = target_frames(root / block.sim / block.target_domain / block.target_split, cfg.voxelize.mount_height,
                           block.target_domain)
    stats = point_statistics([f.points for f in frames], target_grid)
    refs = pseudo_references(frames, block, target_grid, np.random.default_rng(block.seed))
    resim = None
    if tuples.resim is not None:
        spec = domain_spec(block.target_domain, azimuth_step_deg=cfg.simulate.azimuth_step_deg).sensor
        resim = np.stack(list(stage2.resimulated_views((r.ego_points for r in refs), spec, target_grid))).astype(np.float32)
    dummy = dummy_ego_tuples(load_views(root / block.voxels, dataset=block.target_domain, split=block.target_split))
    return Inputs(tuples, References.of(refs, resim), dummy, stats)


def enhance(v: Variant, cfg, data: Inputs, encoders: Encoders, base_pipe: TYPPipeline, base_adapter, *, seed: int,
            out: Path, log_fn: Callable[[dict, int], None]):
    """The adapter of variant ``v`` for the replica ``seed`` whose stage-1 model ``base_pipe`` holds;
    ``base_adapter``: stage 2's adapter with ``v.conditions`` (unused by "no adaptation"). Returns
    (adapter, an example of its input for the model registry)."""
    block, augment = cfg.selftrain, cfg.stage2.augment
    ldm, schedule, T = base_pipe.unet, base_pipe.schedule, base_pipe.train_timesteps
    if not v.discriminator:  # "no adaptation": stage 2's recipe on tuples encoded by E_tgt
        [encoded] = encode_kinds(v, {"source": data.tuples}, encoders.source_x, encoders.target_x, encoders.y, ldm,
                                 augment=augment)
        adapter = stage2.fit_adapter(stage2.build_adapter(ldm, res_blocks=cfg.stage2.adapter_res_blocks, seed=seed), ldm,
                                     schedule, T, encoded, name=f"selftrain.seed_{seed}.{v.name}",
                                     settings=stage2.settings_of(cfg.stage2, seed, cfg.stage1.min_snr),
                                     views=len(data.tuples), key_extra=as_dict(cfg.stage2), out=out, log_fn=log_fn)
        return adapter, _dummy_example(data, encoders, ldm, v)
    if not (v.self_training or v.dummy_ego):
        return base_adapter, _dummy_example(data, encoders, ldm, v)
    kinds = {"source": data.tuples}
    if v.self_training:  # x̂_r generated by the model being enhanced, as trained
        as_trained = dataclasses.replace(base_pipe, adapter=base_adapter, adapter_scale=1.0)
        kinds["pseudo"] = pseudo_tuples(data.references, as_trained, seed, v.conditions)
    if v.dummy_ego:
        kinds["dummy"] = data.dummy
    parts = encode_kinds(v, kinds, encoders.source_x, encoders.target_x, encoders.y, ldm, augment=augment)
    n_views = sum(len(t) for t in kinds.values())
    # fine-tuned from stage 2's weights, trainable whatever flags they came with (an EMA copy is frozen)
    adapter = stage2.fit_adapter(copy.deepcopy(base_adapter).requires_grad_(True), ldm, schedule, T, concat(*parts),
                                 name=f"selftrain.seed_{seed}.{v.name}",
                                 settings=stage2.settings_of(block, seed, cfg.stage1.min_snr), views=n_views,
                                 key_extra={**training_fields(block), "variant": v.name}, out=out, log_fn=log_fn)
    return adapter, parts[0].ego[:2]


def _dummy_example(data: Inputs, encoders: Encoders, ldm, v: Variant):
    return stage2.encode(data.dummy, encoders.target_x, encoders.y, ldm, conditions=v.conditions).ego[:2]


def run(cfg, root: Path, *, run, trainings: Trainings = Trainings()) -> StageResult:
    """The stage (:mod:`flows.generic`): :func:`train_variants` inside its MLflow ``run``; the
    generator's ``pipeline.json`` kept with the run."""
    metrics = train_variants(cfg, root, log_fn=run.metrics, log_model=run.log_model, trainings=trainings)
    return StageResult(metrics, artifacts=[generator_dir(root / cfg.selftrain.out, cfg.stage1.seed) / "pipeline.json"])


def train_variants(cfg, root: Path, *, log_fn: Callable[[dict, int], None], log_model=None,
                   trainings: Trainings = Trainings()) -> dict:
    """Every variant for every stage-1 replica (each reported to ``trainings`` as
    ``train-<variant>-seed<k>``), and the generator pipeline for each replica."""
    from tasks.vqvae import load_model as load_vqvae

    block = cfg.selftrain
    out = root / block.out
    encoders = Encoders(load_vqvae(root / block.vqvae / "x"), load_vqvae(root / block.adapt / "source_vq", "adapt"),
                        load_vqvae(root / block.vqvae / "y"))
    data = gather(cfg, root)
    resim = data.tuples.resim is not None
    if block.generator == "typ_resim" and not resim:
        raise TypError("params.yaml", "selftrain.generator", "typ unless stage2.resim is true (no re-simulated "
                       "tuples to train typ_resim on)", block.generator)
    variants = variants_to_run(block, resim=resim)
    metrics: dict = {"variants": [v.name for v in variants], "source_tuples": len(data.tuples),
                     "pseudo_references": len(data.references.x_e), "dummy_ego_tuples": len(data.dummy)}
    chosen = resim_variant(block) if block.generator == "typ_resim" else variant_of(block)
    for seed in stage1.replica_seeds(cfg.stage1.seed, cfg.stage1.replicas):
        base_pipe = base_pipeline(cfg, root, seed, encoders.target_x, encoders.y, data.stats)
        stage2_dir = stage1.replica_dir(root / block.stage2, seed)
        for v in variants:
            base = stage2.load_adapter(stage2_dir / stage2.ADAPTERS[v.conditions]) if v.discriminator else None
            adapter, example = trainings.run(f"train-{v.name}-seed{seed}", lambda: enhance(
                v, cfg, data, encoders, base_pipe, base, seed=seed, out=out, log_fn=log_fn))
            stage2.save_adapter(adapter, stage1.replica_dir(out, seed) / v.name)
            if v == chosen:
                base_pipe.with_adapter(adapter).save_pretrained(generator_dir(out, seed))
                if log_model is not None and seed == cfg.stage1.seed:
                    log_model("selftrain-adapter", adapter, example)
    return metrics
