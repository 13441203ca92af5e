"""Stage ``ddpm``: the LiDAR DDPM system (Aghanouri & Olaverri-Monreal) on the target domain.

A pixel-space U-Net DDPM (:class:`models.pixel_ddpm.PixelDiffusion`) is trained on range images
and BEV images (:mod:`typ.projection`) of the simulated target domain's scans, once per Table I
configuration (schedule x time embedding) and training seed, and sampled with each configured
sampler; generated images go back to points, which are what every metric compares.

- Scans: every agent's view of the ``train`` / ``test`` scenarios (``ego_only`` keeps the
  first agent only); each carries the simulator's per-point semantic labels. Scans and their
  image representations live in :mod:`tasks.ddpm_data`.
- Training (Ho et al.): E_{t, ε} ||target - f_θ(√ᾱ_t x_0 + √(1 - ᾱ_t) ε, t)||² with the target
  ε (``prediction: epsilon``, the paper's) or v = √ᾱ_t ε - √(1 - ᾱ_t) x_0 (``v_prediction``,
  Salimans & Ho: the same minimiser, with more weight where x_0 is hard to read from x_t), AdamW,
  mirrored copies of every image (y -> -y), batches a pure function of (seed, step)
  (:func:`tasks.training.run_loop`: resumable, a NaN loss stops with the last good checkpoint).
  Weights: ``<out>/models/<network>/seed_<k>/`` as :mod:`typ.artifacts` writes them (the config with the
  run key: a model whose key matches is loaded, not retrained).
- Sampling: :func:`models.samplers.sample` with a stock diffusers scheduler on the model's
  own β and ``prediction_type``; the generated set of a (model, sampler, steps) is cached under ``<out>/samples/``.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

import models.pixel_ddpm
import models.samplers
import models.schedules
import models.time_embedding
import typ.artifacts
from models.pixel_ddpm import PixelDiffusion
from models.samplers import make_scheduler, sample
from models.schedules import alphas_cumprod, betas
from tasks.ddpm_data import (BevRepresentation, RangeRepresentation, Representation, Scan, data_key,  # noqa: F401
                             load_scans, pixel_set, representations, unlabelled)
from tasks.scene_stage import StageResult
from tasks.training import (Trainings, batch_rng, grad_norm, noised_batch, prediction_target, run_checkpoint_dir,
                            run_loop, seed_everything)
from typ import distributed
from typ.artifacts import load_if_key, save_module
from typ.config import DdpmConfig, DdpmRunConfig, as_dict
from typ.io import atomic_path, code_digest, hash_obj, seed_dir
from typ.registry import SAMPLERS, TARGET_VOXELS, declare

STAGE = "ddpm"
LOG = logging.getLogger(__name__)
#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare("ddpm", data=("data/sim/target/train", "data/sim/target/test", f"{TARGET_VOXELS}test",
                                    "artifacts/vqvae", "artifacts/stage1"),
                      params=("stage1",), outs=("artifacts/ddpm",), reports=("reports/ddpm.md",),
                      images=("reports/ddpm_pareto.png", "reports/ddpm_samples.png"), loss_curves=True)
#: the code a trained model / a generated set depends on: part of their cache keys (typ.artifacts:
#: the saved folder's layout, so that a folder in an older layout is retrained, not misread)
_MODEL_CODE = code_digest(models.pixel_ddpm, models.time_embedding, models.schedules, typ.artifacts)
_SAMPLER_CODE = code_digest(models.samplers)
#: samples drawn per reverse-process call (bounds memory at paper scale)
SAMPLE_BATCH = 32
#: Pixels live in [-1, 1], so every sampler clips its x̂_0 estimate there at each step (Ho et al.
#: clip; diffusers' default for pixel models, which typ's latent samplers switch off). Without
#: it an undertrained ε̂ at t near T, divided by √ᾱ_T ~ 0.006, throws the first estimates far
#: outside the image range and the chain never recovers. Dynamic thresholding with a maximum of 1
#: is the same clip for the multistep solvers (:attr:`typ.registry.SamplerSpec.pixel`).
PIXEL_CLIP = {name: spec.pixel for name, spec in SAMPLERS.items()}


# ---------------------------------------------------------------- models


def network_name(run: DdpmRunConfig, prediction: str) -> str:
    """The network a configuration trains, shared by configurations that train the same (``-v``
    marks a v-prediction model, so that it does not take an ε model's folder)."""
    tag = {"epsilon": "", "v_prediction": "-v"}[prediction]
    return f"{run.representation}-{run.schedule}-{run.embedding}{tag}"


def model_name(run: DdpmRunConfig, seed: int, prediction: str) -> str:
    """MLflow / metrics name of one trained model: its network and seed."""
    return f"{network_name(run, prediction)}-seed{seed}"


def model_folder(out: Path, run: DdpmRunConfig, seed: int, prediction: str) -> Path:
    """``<out>/models/<network>/seed_<k>``: where one trained model is saved."""
    return seed_dir(Path(out) / "models" / network_name(run, prediction), seed)


def build(cfg: DdpmConfig, run: DdpmRunConfig, rep: Representation) -> PixelDiffusion:
    c, h, w = rep.shape
    u = cfg.unet
    return PixelDiffusion(channels=c, height=h, width=w, patch=rep.patch, block_out_channels=u.block_out_channels,
                          layers_per_block=u.layers_per_block, norm_num_groups=u.norm_num_groups, dropout=u.dropout,
                          time_embedding=run.embedding, harmonics=u.harmonics, coordinates=u.coordinates)


def model_key(cfg: DdpmConfig, run: DdpmRunConfig, rep: Representation, seed: int, data: list) -> str:
    recipe = {"unet": as_dict(cfg.unet), "T": cfg.train_timesteps, "steps": cfg.steps, "batch": cfg.batch_size,
              "lr": cfg.lr, "schedule": run.schedule, "embedding": run.embedding, "rep": rep.describe(),
              "seed": seed, "data": data, "code": _MODEL_CODE}
    if cfg.prediction != "epsilon":  # epsilon models keep the keys they were trained under
        recipe["prediction"] = cfg.prediction
    return hash_obj(recipe)[:16]


@dataclass
class TrainedModel:
    name: str
    key: str
    model: PixelDiffusion
    schedule: str
    train_timesteps: int
    seconds_training: float
    trained: bool
    prediction: str = "epsilon"  #: what the model outputs: the sampler's prediction_type


def train_model(cfg: DdpmConfig, run: DdpmRunConfig, rep: Representation, seed: int, pixels: torch.Tensor,
                data: list, *, out: Path, log_fn: Callable[[dict, int], None]) -> TrainedModel:
    """Train one model (or load it, when ``<out>/models/<name>`` holds the same run key).

    pixels: (N, C, H, W) training images in [-1, 1] (mirrored copies included).
    """
    name = model_name(run, seed, cfg.prediction)
    key = model_key(cfg, run, rep, seed, data)
    folder = model_folder(out, run, seed, cfg.prediction)
    found = load_if_key(folder, PixelDiffusion.from_config, STAGE, key)
    if found is not None:
        model, saved = found
        return TrainedModel(name, key, model, saved["schedule"], saved["train_timesteps"],
                            saved["seconds_training"], trained=False, prediction=saved.get("prediction", "epsilon"))
    seed_everything(seed)
    model = build(cfg, run, rep)
    abar = torch.from_numpy(alphas_cumprod(betas(run.schedule, cfg.train_timesteps))).float()
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr)

    def step_fn(step: int) -> dict[str, float]:
        rng = batch_rng(seed, step)
        index, t, eps, x_t = noised_batch(rng, pixels, abar, cfg.batch_size)
        # dropout draws from torch's global generator: seed it per step, so a resumed run drops
        # the same units an uninterrupted one would have
        torch.manual_seed(int(rng.integers(2 ** 62)))
        x0, t, eps, x_t = distributed.local_batch(pixels[index], t, eps, x_t)
        model.train()
        loss = F.mse_loss(model(x_t, t), prediction_target(cfg.prediction, eps, x0, abar[t.cpu()].to(x0.device)))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return {"loss": float(loss.detach()), "grad_norm": grad_norm(model.parameters())}

    checkpoints = run_checkpoint_dir(seed_dir(out / "checkpoints" / network_name(run, cfg.prediction), seed), key)
    t0 = time.perf_counter()
    with distributed.on_device(model):
        run_loop(name=f"ddpm {name}", total_steps=cfg.steps, step_fn=step_fn,
                 state={"model": model, "opt": opt},
                 checkpoint_dir=checkpoints, curve=out / "loss" / f"{name}.csv",
                 checkpoint_every=cfg.checkpoint_every,
                 log_fn=lambda v, step: log_fn({f"ddpm.{name}.{k}": val for k, val in v.items()}, step))
    seconds = round(time.perf_counter() - t0, 3)
    if distributed.is_main():
        save_module(folder, model, model.config, key=key, schedule=run.schedule, train_timesteps=cfg.train_timesteps,
                    prediction=cfg.prediction, representation=rep.describe(), seconds_training=seconds)
    return TrainedModel(name, key, model.eval(), run.schedule, cfg.train_timesteps, seconds, trained=True,
                        prediction=cfg.prediction)


# ---------------------------------------------------------------- sampling


@dataclass
class Generated:
    """One generated set: (n, C, H, W) float32 pixels and the sampling wall time per sample."""

    pixels: np.ndarray
    seconds_per_sample: float


def generate(trained: TrainedModel, sampler: str, steps: int, n: int, seed: int, *, out: Path) -> Generated:
    """``n`` samples of ``trained`` with ``sampler`` at ``steps`` steps, x_T from ``seed``.

    Cached under ``<out>/samples/`` by (model key, sampler, steps, n, seed) with the time it took,
    so a resumed sweep skips finished sets. Time: wall clock of the reverse process, per sample.
    """
    key = hash_obj({"model": trained.key, "sampler": sampler, "steps": steps, "n": n, "seed": seed,
                    "options": PIXEL_CLIP[sampler], "code": _SAMPLER_CODE})[:16]
    path = out / "samples" / f"{trained.name}-{sampler}-{steps}-{key}.npz"
    if path.exists():
        with np.load(path) as cached:
            return Generated(cached["pixels"], float(cached["seconds_per_sample"]))
    scheduler = make_scheduler(sampler, betas(trained.schedule, trained.train_timesteps),
                               prediction_type=trained.prediction, **PIXEL_CLIP[sampler])
    generator = torch.Generator().manual_seed(seed)
    parts, t0 = [], time.perf_counter()
    shape = tuple(trained.model.config[k] for k in ("channels", "height", "width"))
    with distributed.on_device(trained.model) as device:  # x_T is drawn on the CPU whatever the device
        for start in range(0, n, SAMPLE_BATCH):
            m = min(SAMPLE_BATCH, n - start)
            parts.append(sample(trained.model, scheduler, shape=(m, *shape), num_steps=steps, generator=generator,
                                device=device).cpu().numpy())
    seconds = (time.perf_counter() - t0) / n
    pixels = np.concatenate(parts).astype(np.float32)
    if not distributed.is_main():  # under torchrun every rank samples the same; rank 0 keeps it
        return Generated(pixels, seconds)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, pixels=pixels, seconds_per_sample=seconds)
    return Generated(pixels, seconds)


def full_noise(rep: Representation, n: int, seed: int) -> np.ndarray:
    """(n, C, H, W) pixels of pure N(0, I) noise: the paper's "Full noise" row."""
    return np.random.default_rng(seed).standard_normal((n, *rep.shape)).astype(np.float32)


def reference_sets(cfg: DdpmConfig, rep: Representation, own: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The reference rows' sets, sized like a model row's: (full-noise sets, real-train sets).

    k = the most seeds any configuration trains; each set holds ``eval_samples`` images. Noise
    set i is drawn from seed ``cfg.seed + i``; the real sets are disjoint draws (without
    replacement, seeded by ``cfg.seed``) from ``own``, the training images (N, C, H, W), or as
    many whole sets as N allows (at least one, of min(N, eval_samples) images).
    """
    k = max(len(seeds_of(cfg, run)) for run in cfg.configs)
    n = cfg.eval_samples
    noise = [full_noise(rep, n, cfg.seed + i) for i in range(k)]
    order = np.random.default_rng(cfg.seed).permutation(len(own))
    whole = max(1, min(k, len(own) // n))
    real = [own[np.sort(order[i * n:(i + 1) * n])] for i in range(whole)]
    return noise, real


def clouds(rep: Representation, pixels: np.ndarray) -> list[np.ndarray]:
    """Generated (n, C, H, W) pixels -> n point clouds."""
    return [rep.points(p) for p in pixels]


def sample_rows(cfg: DdpmConfig) -> list[tuple[DdpmRunConfig, str, int]]:
    """(configuration, sampler, steps) of every Table II row, in params order."""
    return [(run, sampler, steps) for run in cfg.configs for sampler, steps in (run.samplers or cfg.samplers)]


def seeds_of(cfg: DdpmConfig, run: DdpmRunConfig) -> tuple[int, ...]:
    return run.seeds or cfg.seeds


def sampling_seed(cfg: DdpmConfig, model_seed: int) -> int:
    """x_T of every set of one model comes from one seed: rows of one model differ by sampler only."""
    return int(np.random.SeedSequence([cfg.seed, model_seed, 7]).generate_state(1)[0])


# ---------------------------------------------------------------- Table II


def _row(route: str, rep: str, label: str, **fields) -> dict:
    return {"route": route, "representation": rep, "config": label, "schedule": "", "embedding": "",
            "sampler": "", "steps": 0, "seconds_per_sample": 0.0, "iou": None, **fields}


def table(cfg: DdpmConfig, reps: dict[str, Representation], train: list[Scan], test: list[Scan], nets, *,
          out: Path, log_fn: Callable[[dict, int], None],
          trainings: Trainings = Trainings()) -> tuple[list[dict], dict[str, TrainedModel], dict]:
    """Train every model the configurations need (each reported to ``trainings`` as
    ``train-<model name>``), sample every (configuration, sampler) row for every seed, and score it
    against the held-out scans passed through the same representation.

    Per representation two reference rows come first: ``full noise`` (N(0, I) pixels decoded,
    the paper's ceiling) and ``real train views`` (training scans through the representation:
    as close as the data itself is to the held-out set). Each reference row is scored exactly
    like a model row: as many sets as the most-seeded configuration has seeds, each of
    ``eval_samples`` clouds (:func:`reference_sets`), since the set-level JSD and Fréchet
    distances depend on the set size. Returns (rows, trained models by name, example pixels
    by row label for the gallery).
    """
    from tasks.ddpm_metrics import score, set_stats

    used = list(dict.fromkeys(run.representation for run in cfg.configs))
    real, training, rows, examples = {}, {}, [], {}
    for name in used:
        rep = reps[name]
        real[name] = set_stats([rep.points(rep.pixels(s.points)) for s in test], nets)
        training[name] = pixel_set(rep, train, mirror=True)
        examples[f"{name} real"] = pixel_set(rep, test[:2]).numpy()
        noise, own = reference_sets(cfg, rep, training[name][:len(train)].numpy())
        for label, sets in (("full noise", noise), ("real train views", own)):
            rows.append(_row("reference", name, label, seeds=list(range(len(sets))),
                             **score(real[name], [set_stats(clouds(rep, x), nets) for x in sets],
                                     n_boot=cfg.bootstrap, seed=cfg.seed)))
    trained: dict[str, TrainedModel] = {}
    data = data_key(train)
    for run, sampler, steps in sample_rows(cfg):
        rep = reps[run.representation]
        stats, seconds = [], []
        for seed in seeds_of(cfg, run):
            name = model_name(run, seed, cfg.prediction)
            if name not in trained:
                trained[name] = trainings.run(f"train-{name}", lambda: train_model(
                    cfg, run, rep, seed, training[run.representation], data, out=out, log_fn=log_fn))
            made = generate(trained[name], sampler, steps, cfg.eval_samples, sampling_seed(cfg, seed), out=out)
            stats.append(set_stats(clouds(rep, made.pixels), nets))
            seconds.append(made.seconds_per_sample)
            examples.setdefault(f"{run.representation} {run.name} {sampler}-{steps}", made.pixels[:2])
        rows.append(_row("pixel", run.representation, run.name, schedule=run.schedule, embedding=run.embedding,
                         sampler=sampler, steps=steps, seconds_per_sample=float(np.mean(seconds)),
                         seeds=list(seeds_of(cfg, run)),
                         **score(real[run.representation], stats, n_boot=cfg.bootstrap, seed=cfg.seed)))
    return rows, trained, examples


def latent_sampler(cfg, root: Path, views) -> tuple[Callable[[str, int], np.ndarray], dict]:
    """The one place that knows how TYP's generator is loaded and called (adapt it here when the
    generator's API changes): stage 1 with its VQ-VAEs and tuned post-processing, conditioned on
    ``views``' own box maps. Returns (sample(sampler, steps) -> (N, C, H, W) bool occupancy,
    {"schedule", "embedding"} of the model)."""
    from models.postprocess import postprocess
    from tasks import stage1
    from tasks.vqvae import load_model as load_vqvae

    latent = cfg.ddpm.latent
    model, saved = stage1.load_model(stage1.replica_dir(root / latent.stage1, cfg.stage1.seed))
    x_vq, y_vq = (load_vqvae(root / latent.vqvae / k) for k in ("x", "y"))
    _, y_lat = stage1.encode_views(x_vq, y_vq, views)
    thresholds = saved["postprocess"]

    def sample_occupancy(sampler: str, steps: int) -> np.ndarray:
        sampling = stage1.sampling_config(cfg.stage1, saved, sampler, steps)
        seed = cfg.ddpm.seed
        logits = stage1.sample_logits(model, x_vq, y_lat, cfg=sampling, generator=torch.Generator().manual_seed(seed))
        return postprocess(logits, low=thresholds["low"], high=thresholds["high"], noise_std=thresholds["noise_std"],
                           generator=torch.Generator().manual_seed(seed)).numpy()

    return sample_occupancy, {"schedule": saved["schedule"], "embedding": model.config["time_embedding"]}


#: Left out of the latent route's rows: typ's range network cannot tell voxel-centre clouds
#: apart. Against the true views' voxel centres, random occupancy at the truth's own rate scores
#: FRID 0.02 and a z-shuffled truth 0.05, where full noise scores 1.39 on the range route (tiny
#: profile, 16 views); its features' spread is as blind. FPVD separates the same cases (0.79,
#: 0.40).
BLIND_ON_VOXELS = ("frid", "spread")


def random_occupancy(truth: np.ndarray, seed: int) -> np.ndarray:
    """The latent route's ceiling row: each view's voxels occupied independently at that view's
    own occupancy rate (truth: (N, ...) bool), from ``seed``."""
    rate = truth.reshape(len(truth), -1).mean(1).reshape(-1, *([1] * (truth.ndim - 1)))
    return np.random.default_rng(seed).random(truth.shape) < rate


def latent_route(cfg, root: Path, nets) -> list[dict]:
    """TYP's latent route on the same held-out views: its generator (:func:`latent_sampler`)
    sampled with each ``ddpm.latent.samplers`` entry for the first ``latent.views`` test views,
    conditioned on their own box maps; scored against the true views' voxel centres (its
    representation), with voxel IoU to the truth, beside a ``random occupancy`` reference row
    (:func:`random_occupancy`). FRID and spread are None (:data:`BLIND_ON_VOXELS`). One trained
    model: the intervals cover the sample spread only. ``cfg``: the whole :class:`typ.config.Config`.
    """
    from tasks.ddpm_metrics import score, set_stats
    from tasks.voxel_data import load_views
    from typ.metrics import occupancy_iou
    from typ.voxel import voxel_centers

    block, latent = cfg.ddpm, cfg.ddpm.latent
    views = load_views(root / latent.voxels, dataset=block.domain, split=block.test_split, ego_only=False)
    views = views.head(latent.views)
    x_true, _ = views.batch(np.arange(len(views)))
    truth = x_true.numpy() > 0.5
    sample_occupancy, model = latent_sampler(cfg, root, views)

    def centres(occupancy: np.ndarray) -> list[np.ndarray]:
        return [voxel_centers(o.transpose(1, 2, 0), views.grid).astype(np.float32) for o in occupancy]

    real = set_stats(centres(truth), nets)

    def scores(occupancy: np.ndarray) -> dict:
        out = score(real, [set_stats(centres(occupancy), nets)], n_boot=block.bootstrap, seed=block.seed)
        return {**out, **dict.fromkeys(BLIND_ON_VOXELS)}

    rows = [_row("reference", "voxel", "random occupancy", seeds=[0],
                 **scores(random_occupancy(truth, block.seed)))]
    for sampler, steps in latent.samplers:
        t0 = time.perf_counter()
        occupancy = sample_occupancy(sampler, steps)
        seconds = (time.perf_counter() - t0) / len(views)
        rows.append(_row("latent", "voxel", "TYP stage 1", **model, sampler=sampler, steps=steps,
                         seconds_per_sample=seconds, seeds=[0], iou=float(occupancy_iou(occupancy, truth)["iou"]),
                         **scores(occupancy)))
    return rows


DESCRIPTION = (
    "Aghanouri & Olaverri-Monreal's LiDAR DDPM rebuilt in typ: a lightweight pixel-space U-Net DDPM "
    "(`models/pixel_ddpm.py`, {prediction}, dropout 0.1, AdamW) on the equirectangular range image "
    "(the target sensor's beams x azimuth bins, depth encoded to [-1, 1] {depth}) and on the BEV image "
    "(occupancy + height of the highest point per cell), trained on the simulated target domain. "
    "Rows are Table I configurations (schedule x time embedding; the paper's dataset column is the one "
    "simulated target domain here, so its I = H and K = J) sampled with the samplers listed; every "
    "sampler clips x̂_0 to the image range at each step.")
#: DESCRIPTION's words for each ``ddpm.range_image.depth``
DEPTH_WORDS = {"linear": "linearly", "log": "on R2DM's log scale, log2(d + 1) / log2(max_range + 1)"}
#: DESCRIPTION's words for each ``ddpm.prediction``
PREDICTION_WORDS = {"epsilon": "ε-prediction", "v_prediction": "v-prediction, v = √ᾱ ε - √(1 - ᾱ) x_0"}


def round_trips(reps: dict[str, Representation], scans: list[Scan]) -> dict:
    """:meth:`Representation.round_trip` of every representation, with its image size."""
    return {name: {"layout": "x".join(map(str, rep.shape[1:])), **rep.round_trip(scans)}
            for name, rep in reps.items()}


def context(cfg: DdpmConfig, train: list[Scan], test: list[Scan]) -> dict:
    """What the report says about the data and the estimator."""
    return {"description": DESCRIPTION.format(depth=DEPTH_WORDS[cfg.range_image.depth],
                                                  prediction=PREDICTION_WORDS[cfg.prediction]),
            "train_scans": len(train), "test_scans": len(test),
            "train_split": cfg.train_split, "test_split": cfg.test_split, "ego_only": cfg.ego_only,
            "eval_samples": cfg.eval_samples, "bootstrap": cfg.bootstrap, "threads": torch.get_num_threads()}


def model_summary(trained: dict[str, TrainedModel]) -> dict:
    return {tm.name: {"seconds_training": tm.seconds_training, "trained_now": tm.trained,
                      "parameters": sum(p.numel() for p in tm.model.parameters())} for tm in trained.values()}


def run(cfg, root: Path, *, run, trainings: Trainings = Trainings()) -> StageResult:
    """The stage (:mod:`flows.generic`): the FRID / FPVD feature networks, every Table II row
    (each network a task of ``trainings``), TYP's latent route side by side, the report; every
    network logged as an MLflow model of ``run``. Data it cannot train on (no labelled scans): the
    metrics and the report say why, and nothing is trained."""
    from tasks import ddpm_report
    from tasks.lidar_features import train_feature_nets

    root = Path(root)
    block = cfg.ddpm
    out = root / block.out
    reps = representations(block, cfg.source)
    train, test = (trainings.step(f"scans-{split}", lambda split=split: load_scans(
        root / block.input, domain=block.domain, split=split, ego_only=block.ego_only))
        for split in (block.train_split, block.test_split))
    counts = {"train_scans": len(train), "test_scans": len(test)}
    reason = unlabelled([*train, *test], f"{block.domain}/{block.train_split} and {block.test_split}")
    if reason is not None:
        LOG.warning("ddpm: not run: %s", reason)
        out.mkdir(parents=True, exist_ok=True)
        return StageResult({"skipped": reason, **counts}, artifacts=ddpm_report.write_skipped(root / block.reports,
                                                                                                 reason))
    t0 = time.perf_counter()
    nets, feature_scores = trainings.step("feature-nets", lambda: train_feature_nets(
        block.features, block.seed, reps["range"].layout, train, test, out=out, log_fn=run.metrics))
    run.log_model("ddpm-frid-net", nets.range_net, torch.zeros(1, 1, *reps["range"].layout.shape))
    run.log_model("ddpm-fpvd-net", nets.voxel_net, torch.zeros(1, nets.grid.shape[2], *nets.grid.shape[:2]))
    rows, trained, examples = table(block, reps, train, test, nets, out=out, log_fn=run.metrics, trainings=trainings)
    for tm in trained.values():
        c = tm.model.config
        run.log_model(f"ddpm-{tm.name}", tm.model, {"x_t": torch.zeros(1, c["channels"], c["height"], c["width"]),
                                                    "t": torch.tensor([0])})
    if block.latent.samplers:
        rows += trainings.step("latent-route", lambda: latent_route(cfg, root, nets))
    round_trips_ = round_trips(reps, test)
    paths = ddpm_report.write_all(root / block.reports, rows, examples, round_trips=round_trips_,
                                  feature_scores=feature_scores, context=context(block, train, test)) \
        if distributed.is_main() else []
    metrics = ddpm_report.metrics_of(rows, round_trips_, feature_scores, model_summary(trained),
                                     {**counts, "seconds_total": round(time.perf_counter() - t0, 3)})
    return StageResult(metrics, artifacts=paths)
