"""Stage ``stage2`` (TYP Eq. 5–7): ground P(x|y) on the ego's view with a T2I-Adapter.

F_AD (:class:`models.adapter.ZeroAdapter`) maps the standardised x^f_e' = E_src(x_e') to one
feature map per UNet encoder level; they are added to the frozen stage-1 UNet's encoder
features at every denoising step (Eq. 6). Only F_AD learns, on source (simulated CAV) tuples
encoded with the adapted source encoder (stage ``adapt``). At inference on the target domain,
x_e' is encoded with the target encoder E_tgt (TYP §3.4).

Beyond the paper, ``conditions = 2`` gives the adapter the re-simulated reference view
(:mod:`typ.resim`: the ego cloud as surfels, ray-cast from the reference pose with the
reference sensor's beams) beside x_e': geometry-consistent where the ego saw, so the
diffusion only has to learn the sensor's pattern and what the ego did not see.

Tuples are used under symmetries of the grid (``augment``: 1 = as they are, 2 = with their
mirror images, 8 = every rotation and mirror): each symmetry is applied to x_r, y_r, x_e' and
the re-simulated view alike, all in the reference frame. One adapter is trained per stage-1
replica (same seed). Output: ``<out>/seed_<s>/`` (safetensors + config) and resumable
``<out>/checkpoints/``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np
import torch

from models.adapter import ZeroAdapter
from models.ldm import LatentDiffusion
from models.schedules import alphas_cumprod, betas
from tasks.pairs import Pair
from tasks.scene_stage import StageResult
from tasks.stage1 import train_views
from tasks.training import (EMA, Trainings, batch_rng, diffusion_loss, grad_norm, learning_rate, noised_batch,
                            run_checkpoint_dir, run_loop, seed_everything, set_learning_rate, steps_for)
from tasks.voxel_data import apply_dihedral
from typ import distributed
from typ.artifacts import load_module, save_module
from typ.config import as_dict
from typ.distributed import threaded_map
from typ.errors import TypError
from typ.io import hash_obj
from typ.resim import EGO_CAR_LWH, resimulated_points
from typ.voxel import Grid, voxelize
from typ.registry import declare

STAGE = "stage2"
#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare("stage2", data=("data/sim/source/train", "artifacts/vqvae", "artifacts/adapt/source_vq",
                                      "artifacts/stage1"),
                      params=("stage1", "voxelize"), outs=("artifacts/stage2",), loss_curves=True)
#: symmetries used for ``augment`` = 1, 2, 8 (see :func:`tasks.voxel_data.apply_dihedral`)
AUGMENTS = {1: (0,), 2: (0, 4), 8: tuple(range(8))}


@dataclass
class Tuples:
    """Dense (N, ·, H, W) grids of N (x_r, y_r, x_e'[, re-simulated]) tuples, {0, 1} as bool (one
    byte a voxel: 1.3 MB a grid at 256 x 256 x 20) or float32; :func:`encode` takes either."""

    x_r: np.ndarray
    y_r: np.ndarray
    x_e: np.ndarray
    resim: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.x_r)


def resimulated_view(ego_points: np.ndarray, spec, grid: Grid, ego_car_lwh=EGO_CAR_LWH) -> np.ndarray:
    """(C, H, W) bool: :func:`resimulated_points` voxelized on ``grid``."""
    return voxelize(resimulated_points(ego_points, spec, ego_car_lwh), grid).transpose(2, 0, 1)


def resimulated_views(ego_clouds: Iterable[np.ndarray], spec, grid: Grid, ego_car_lwh=EGO_CAR_LWH, *,
                      workers: int | None = None) -> Iterator[np.ndarray]:
    """:func:`resimulated_view` of each cloud, in order, on :func:`threaded_map`."""
    return threaded_map(lambda cloud: resimulated_view(cloud, spec, grid, ego_car_lwh), ego_clouds, workers=workers)


def collect(pairs: Iterable[Pair], *, grid: Grid, resim_spec=None, ego_car_lwh=EGO_CAR_LWH,
            max_pairs: int | None = None) -> Tuples:
    """The dense grids of ``pairs`` (streamed: no point cloud is kept beyond the re-simulation's
    window), with the re-simulated view when ``resim_spec`` (the reference sensor's
    :class:`typ.sim.sensor.SensorSpec`) is given."""
    rows: dict[str, list[np.ndarray]] = {"x_r": [], "y_r": [], "x_e": [], "resim": []}

    def ego_clouds() -> Iterator[np.ndarray]:
        for i, p in enumerate(pairs):
            if max_pairs is not None and i >= max_pairs:
                break
            rows["x_r"].append(p.x_r)
            rows["y_r"].append(p.y_r)
            rows["x_e"].append(p.x_e)
            yield p.ego_points

    if resim_spec is not None:
        rows["resim"] = list(resimulated_views(ego_clouds(), resim_spec, grid, ego_car_lwh))
    else:
        for _ in ego_clouds():
            pass
    if not rows["x_r"]:
        raise TypError("stage2", "pairs", "at least one (ego, reference) pair", 0)
    stack = {k: np.stack(v).astype(bool) for k, v in rows.items() if v}
    return Tuples(stack["x_r"], stack["y_r"], stack["x_e"], stack.get("resim"))


@dataclass
class Latents:
    """Standardised latents of :class:`Tuples` (rows: symmetry-major), ready for Eq. 7."""

    z0: torch.Tensor     # (M, c_x, h, w) x_r^f, standardised by the stage-1 model
    cond: torch.Tensor   # (M, c_y, h, w) y_r^f, standardised
    ego: torch.Tensor    # (M, conditions·c_x, h, w) the adapter's input: x_e'^f [, re-simulated^f]

    def __len__(self) -> int:
        return len(self.z0)


@torch.no_grad()
def encode(tuples: Tuples, x_encoder, y_encoder, ldm: LatentDiffusion, *, augment: int = 1,
           conditions: int = 1, batch_size: int = 16) -> Latents:
    """E(x_r), E_y(y_r), E(x_e') [, E(re-simulated)] under the ``augment`` symmetries, standardised
    with the stage-1 model's statistics (x_e' and the re-simulated view as x). Encoded on the
    runtime device, returned on the CPU."""
    if conditions == 2 and tuples.resim is None:
        raise TypError("stage2", "conditions", "re-simulated views for conditions = 2", "none collected")
    out: dict[str, list[torch.Tensor]] = {"z0": [], "cond": [], "ego": []}
    with distributed.on_device(x_encoder, y_encoder, ldm) as dev:
        for k in AUGMENTS[augment]:
            for start in range(0, len(tuples), batch_size):
                sl = slice(start, start + batch_size)
                grid = {name: torch.from_numpy(np.ascontiguousarray(apply_dihedral(getattr(tuples, name)[sl], k)))
                        .to(dev).float() for name in ("x_r", "y_r", "x_e", "resim") if getattr(tuples, name) is not None}
                out["z0"].append(ldm.normalize(x_encoder.encode_pre_quant(grid["x_r"])).cpu())
                out["cond"].append(ldm.normalize_cond(y_encoder.encode_pre_quant(grid["y_r"])).cpu())
                ego = [ldm.normalize(x_encoder.encode_pre_quant(grid["x_e"]))]
                if conditions == 2:
                    ego.append(ldm.normalize(x_encoder.encode_pre_quant(grid["resim"])))
                out["ego"].append(torch.cat(ego, dim=1).cpu())
    return Latents(*(torch.cat(out[k]) for k in ("z0", "cond", "ego")))


def build_adapter(ldm: LatentDiffusion, *, res_blocks: int, seed: int, conditions: int = 1) -> ZeroAdapter:
    """Feature widths follow the UNet's levels, so residual i matches encoder level i; the initial
    weights are drawn from ``seed`` alone (the global torch state is left as it was)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return ZeroAdapter(latent_channels=ldm.config["latent_channels"],
                           channels=tuple(ldm.config["block_out_channels"]), num_res_blocks=res_blocks,
                           conditions=conditions)


@dataclass(frozen=True)
class FitSettings:
    """How one adapter is trained (stage 2's recipe, or self-training's)."""

    seed: int
    lr: float
    epochs: int
    batch_size: int
    warmup_steps: int
    lr_schedule: str
    ema_decay: float
    checkpoint_every: int
    min_snr: float = 0.0


def fit_adapter(adapter: ZeroAdapter, ldm: LatentDiffusion, schedule: str, train_timesteps: int, data: Latents, *,
                name: str, settings: FitSettings, views: int, key_extra: dict, out: Path,
                log_fn: Callable[[dict, int], None]) -> ZeroAdapter:
    """Minimise Eq. 7 over ``adapter`` alone on ``data``, the UNet frozen; returns the EMA weights.

    views: distinct tuples behind ``data`` (an epoch is ``views / batch_size`` steps).
    Checkpoints go to ``<out>/checkpoints/<name>/<key>``, the key covering the data, the frozen
    UNet, the adapter's starting weights and ``key_extra`` (the config), so a resumed run
    continues exactly the run that was interrupted.
    """
    s = settings
    seed_everything(s.seed)
    ldm.eval().requires_grad_(False)
    total = steps_for(s.epochs, views, s.batch_size)
    key = hash_obj({"cfg": key_extra, "settings": s.__dict__, "n": len(data),
                    "data": float(data.z0.double().sum() + data.ego.double().sum() + data.cond.double().sum()),
                    "ldm": float(sum(p.double().sum() for p in ldm.parameters())),
                    "init": float(sum(p.detach().double().sum() for p in adapter.parameters()))})[:16]
    return _fit(adapter, lambda z_t, t, cond, ego: ldm(z_t, t, cond, adapter(ego)), data,
                schedule=schedule, train_timesteps=train_timesteps, prediction=ldm.config.get("prediction", "epsilon"),
                total=total, settings=s, name=name, key=key, out=out, log_fn=log_fn, frozen=(ldm,))


def _fit(trained: torch.nn.Module, predict: Callable, data: Latents, *, schedule: str, train_timesteps: int,
         prediction: str, total: int, settings: FitSettings, name: str, key: str, out: Path,
         log_fn: Callable[[dict, int], None], frozen: tuple = ()) -> torch.nn.Module:
    """Minimise Eq. 7 over ``trained``'s parameters; ``predict(z_t, t, y^f, ego^f)`` is the UNet's
    output with the adapter's features. Returns the EMA weights; resumes from
    ``<out>/checkpoints/<name>/<key>``."""
    s = settings
    ema = EMA(trained, s.ema_decay)
    abar = torch.from_numpy(alphas_cumprod(betas(schedule, train_timesteps))).float()
    opt = torch.optim.AdamW(trained.parameters(), lr=s.lr, weight_decay=0.0)

    def step_fn(step: int) -> dict[str, float]:
        lr = learning_rate(s.lr, step, total, warmup=s.warmup_steps, schedule=s.lr_schedule, floor=0.1)
        set_learning_rate(opt, lr)
        index, t, eps, z_t = noised_batch(batch_rng(s.seed, step), data.z0, abar, s.batch_size)
        t, eps, z_t, cond, ego, z0 = distributed.local_batch(t, eps, z_t, data.cond[index], data.ego[index],
                                                             data.z0[index])
        dev = distributed.device()
        trained.train()
        loss = diffusion_loss(predict(z_t.to(dev), t.to(dev), cond.to(dev), ego.to(dev)), eps.to(dev), z0.to(dev), t,
                              abar, prediction=prediction, min_snr=s.min_snr)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        ema.update(trained)
        return {"loss": float(loss.detach()), "grad_norm": grad_norm(trained.parameters()), "lr": lr}

    with distributed.on_device(trained, ema.shadow, *frozen):
        run_loop(name=name, total_steps=total, step_fn=step_fn,
                 state={"model": trained, "ema": ema.shadow, "opt": opt},
                 checkpoint_dir=run_checkpoint_dir(out / "checkpoints" / name, key), curve=out / "loss" / f"{name}.csv",
                 checkpoint_every=s.checkpoint_every,
                 log_fn=lambda values, step: log_fn({f"{name}.{k}": v for k, v in values.items()}, step))
    return ema.shadow.eval()


@torch.no_grad()
def adapter_features(adapter: ZeroAdapter, ldm: LatentDiffusion, condition_latents: torch.Tensor) -> list[torch.Tensor]:
    """F_c = F_AD(x^f_e' [, re-simulated^f]) (Eq. 5) from pre-quantization latents (B, k·c_x, h, w),
    computed once per sample and reused at every step."""
    c = ldm.config["latent_channels"]
    parts = [ldm.normalize(condition_latents[:, i:i + c]) for i in range(0, condition_latents.shape[1], c)]
    return adapter(torch.cat(parts, dim=1))


def save_adapter(adapter: ZeroAdapter, folder: Path, **extra) -> None:
    save_module(folder, adapter, adapter.config, **extra)


def load_adapter(folder: Path, stage: str = STAGE) -> ZeroAdapter:
    """An adapter saved by :func:`save_adapter`; a missing or damaged one names ``stage``."""
    return load_module(folder, ZeroAdapter.from_config, stage)[0]


def settings_of(block, seed: int, min_snr: float) -> FitSettings:
    """The training recipe of a stage2 / selftrain config block, for the replica ``seed``; the loss
    weighting is stage 1's (``min_snr``), the UNet's output being what stage 1 trained it to give."""
    return FitSettings(seed=seed, lr=block.lr, epochs=block.epochs, batch_size=block.batch_size,
                       warmup_steps=block.warmup_steps, lr_schedule=block.lr_schedule, ema_decay=block.ema_decay,
                       checkpoint_every=block.checkpoint_every, min_snr=min_snr)


#: adapter folder names under ``<out>/seed_<s>/``, by number of conditions
ADAPTERS = {1: "adapter", 2: "adapter_resim"}


def source_tuples(cfg, root: Path, *, resim: bool) -> Tuples:
    """Stage 2's training tuples: every ordered pair of the source split, with re-simulated views."""
    from tasks.pairs import iter_pairs
    from typ.sim.sensor import DOMAINS, domain_spec

    block = cfg.stage2
    grid = cfg.voxelize.sensor_grid(block.source_domain)
    spec = None
    if resim:
        if block.source_domain not in DOMAINS:
            raise TypError("params.yaml", "stage2.resim", f"a simulated source domain (one of {sorted(DOMAINS)}) whose "
                           "sensor the re-simulation casts with", block.source_domain)
        spec = domain_spec(block.source_domain, azimuth_step_deg=cfg.simulate.azimuth_step_deg).sensor
    pairs = iter_pairs(root / block.sim / block.source_domain / block.source_split, grid)
    return collect(pairs, grid=grid, resim_spec=spec, max_pairs=block.max_pairs or None)


def run(cfg, root: Path, *, run, trainings: Trainings = Trainings()) -> StageResult:
    """The stage: adapters for every stage-1 replica (and the one-stage model when asked), each
    training reported to ``trainings`` as ``train-<adapter>-seed<k>`` / ``train-one-stage-seed<k>``;
    losses and the first replica's adapter go to ``run`` (a :class:`typ.tracking.StageRun`)."""
    from tasks import stage1
    from tasks.vqvae import load_model as load_vqvae

    block = cfg.stage2
    out = root / block.out
    log_fn = run.metrics
    source_x = load_vqvae(root / block.adapt / "source_vq", "adapt")
    y_encoder = load_vqvae(root / block.vqvae / "y")
    tuples = source_tuples(cfg, root, resim=block.resim)
    save_tuples(tuples, out)
    metrics: dict = {"train_pairs": len(tuples), "augment": block.augment}
    for seed in stage1.replica_seeds(cfg.stage1.seed, cfg.stage1.replicas):
        ldm, saved = stage1.load_model(stage1.replica_dir(root / block.stage1, seed))
        for conditions in ((1, 2) if block.resim else (1,)):
            data = encode(tuples, source_x, y_encoder, ldm, augment=block.augment, conditions=conditions)
            adapter = build_adapter(ldm, res_blocks=block.adapter_res_blocks, seed=seed, conditions=conditions)
            name = ADAPTERS[conditions]
            fitted = trainings.run(f"train-{name}-seed{seed}", lambda: fit_adapter(
                adapter, ldm, saved["schedule"], saved["train_timesteps"], data, name=f"stage2.seed_{seed}.{name}",
                settings=settings_of(block, seed, cfg.stage1.min_snr), views=len(tuples), key_extra=as_dict(block),
                out=out, log_fn=log_fn))
            save_adapter(fitted, stage1.replica_dir(out, seed) / name)
            if seed == cfg.stage1.seed and conditions == 1:
                run.log_model("stage2-adapter", fitted, data.ego[:2])  # F_AD(x^f_e') -> one map per UNet level
        if block.one_stage:
            trainings.run(f"train-one-stage-seed{seed}", lambda: fit_one_stage(
                cfg, root, tuples, source_x, y_encoder, seed=seed, out=out, log_fn=log_fn))
    return StageResult(metrics)


def one_stage_steps(cfg, root: Path, source_tuples_n: int) -> tuple[int, int]:
    """(stage-1 steps, stage-2 steps) of the two-stage recipe, whose sum the one-stage model trains."""
    target = train_views(cfg.stage1, root)
    return (steps_for(cfg.stage1.epochs, len(target), cfg.stage1.batch_size),
            steps_for(cfg.stage2.epochs, source_tuples_n, cfg.stage2.batch_size))


class JointModel(torch.nn.Module):
    """UNet and adapter trained as one (TYP Table 5's one-stage baseline)."""

    def __init__(self, unet: LatentDiffusion, adapter: ZeroAdapter):
        super().__init__()
        self.unet, self.adapter = unet, adapter


def fit_one_stage(cfg, root: Path, tuples: Tuples, x_encoder, y_encoder, *, seed: int, out: Path,
                  log_fn: Callable[[dict, int], None]) -> JointModel:
    """TYP Table 5's one-stage model: UNet and adapter from scratch, together, on the source tuples
    alone, for as many steps as stage 1 and stage 2 take together (equal budget). Written to
    ``<out>/seed_<s>/one_stage/{unet,adapter}``."""
    from tasks import stage1

    s1, s2 = one_stage_steps(cfg, root, len(tuples))
    seed_everything(seed)
    with torch.no_grad(), distributed.on_device(x_encoder, y_encoder) as dev:
        x_lat = torch.cat([x_encoder.encode_pre_quant(torch.from_numpy(tuples.x_r[i:i + 16]).to(dev).float()).cpu()
                           for i in range(0, len(tuples), 16)])
        y_lat = torch.cat([y_encoder.encode_pre_quant(torch.from_numpy(tuples.y_r[i:i + 16]).to(dev).float()).cpu()
                           for i in range(0, len(tuples), 16)])
    unet = stage1.build(cfg.stage1, x_lat.shape[1], y_lat.shape[1], x_lat.shape[-1])
    unet.set_statistics(x_lat, y_lat)
    adapter = build_adapter(unet, res_blocks=cfg.stage2.adapter_res_blocks, seed=seed)
    data = encode(tuples, x_encoder, y_encoder, unet, augment=cfg.stage2.augment)
    joint = JointModel(unet, adapter)
    block = cfg.stage2
    settings = FitSettings(seed=seed, lr=block.lr, epochs=1, batch_size=block.batch_size,
                           warmup_steps=block.warmup_steps, lr_schedule=block.lr_schedule,
                           ema_decay=cfg.stage1.ema_decay, checkpoint_every=block.checkpoint_every,
                           min_snr=cfg.stage1.min_snr)
    fitted = _fit_joint(joint, cfg.stage1.schedule, cfg.stage1.train_timesteps, data, steps=s1 + s2,
                        settings=settings, name=f"stage2.seed_{seed}.one_stage", out=out, log_fn=log_fn)
    folder = stage1.replica_dir(out, seed) / "one_stage"
    save_module(folder / "unet", fitted.unet, fitted.unet.config, schedule=cfg.stage1.schedule,
                train_timesteps=cfg.stage1.train_timesteps)
    save_adapter(fitted.adapter, folder / "adapter")
    return fitted


def _fit_joint(joint: JointModel, schedule: str, train_timesteps: int, data: Latents, *, steps: int,
               settings: FitSettings, name: str, out: Path, log_fn) -> JointModel:
    key = hash_obj({"settings": settings.__dict__, "steps": steps, "n": len(data),
                    "data": float(data.z0.double().sum() + data.ego.double().sum())})[:16]
    return _fit(joint, lambda z_t, t, cond, ego: joint.unet(z_t, t, cond, joint.adapter(ego)), data,
                schedule=schedule, train_timesteps=train_timesteps,
                prediction=joint.unet.config.get("prediction", "epsilon"), total=steps, settings=settings, name=name,
                key=key, out=out, log_fn=log_fn)


TUPLES_FILE = "source_tuples.npz"


def save_tuples(tuples: Tuples, folder: Path) -> Path:
    """The training tuples as bit-packed grids (``<folder>/source_tuples.npz``), for self-training."""
    from typ.io import atomic_path

    arrays = {k: np.packbits(getattr(tuples, k) > 0.5, axis=-1) for k in ("x_r", "y_r", "x_e", "resim")
              if getattr(tuples, k) is not None}
    path = Path(folder) / TUPLES_FILE
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, width=np.int64(tuples.x_r.shape[-1]), **arrays)
    return path


def load_tuples(folder: Path) -> Tuples:
    """Tuples written by :func:`save_tuples` (a missing or damaged file names the stage2 stage)."""
    path = Path(folder) / TUPLES_FILE
    if not path.is_file():
        raise TypError(path, "file", "stage 2's training tuples (run the stage2 stage: dvc repro)", "missing")
    try:
        with np.load(path) as data:
            width = int(data["width"])
            grids = {k: np.unpackbits(data[k], axis=-1, count=width).astype(bool)
                     for k in ("x_r", "y_r", "x_e", "resim") if k in data.files}
    except (OSError, ValueError, KeyError) as exc:
        raise TypError(path, "file", "the tuples the stage2 stage writes", f"{type(exc).__name__}: {exc}") from None
    return Tuples(grids["x_r"], grids["y_r"], grids["x_e"], grids.get("resim"))
