"""Probe the trained generator of `make run` (artifacts/) on held-out target pairs, and retrain
stage 1 or the stage-2 adapter with other settings beside it (the ablations of reports/generation_ablation.md).

    python bench/generator_probe.py [--split val] [--stage1 '{"min_snr": 0.0}' ...] [--adapter '{"epochs": 30}' ...]
        [--scales 1,2,4,8]

For every model it prints:
- the held-out z_0 error: the mean squared error of the UNet's z_0 estimate on the split's
  reference latents (target encoder, standardised) noised to t = 0.1 T ... 0.9 T with one fixed
  ε, against the per-cell mean of the training latents as a predictor (a model above that
  line at high noise has learned less than the average scene, and its samples start from it);
- the sample scores of :mod:`tasks.genscore` (IoU, seen / unseen, above ground, object hit
  rate) of the stage's own sampler on every (ego, reference) pair of the split, and (stage 1)
  the sample-to-sample IoU of two noise seeds; the adapters' samples (trained and retrained) at each of
  ``--scales`` (their residuals times the scale, ``selftrain.adapter_scale``). The z_0 errors are
  the adapters' as trained (scale 1).
Retrained models go to /tmp/generator_probe/ (their checkpoints resume); the committed
artifacts are not touched. The numbers quoted in reports/generation_ablation.md come from here.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.schedules import alphas_cumprod, betas  # noqa: E402
from pipelines.typ.pipeline_typ import TYPPipeline  # noqa: E402
from tasks import evaluate_generation as gen, genscore, stage1, stage2  # noqa: E402
from pipelines.typ.pipeline_typ import generator_dir  # noqa: E402
from tasks.selftrain import base_pipeline  # noqa: E402
from tasks.voxel_data import load_views  # noqa: E402
from tasks.vqvae import load_model as load_vqvae  # noqa: E402
from typ.config import load_config  # noqa: E402
from typ.sim.sensor import domain_spec  # noqa: E402

LEVELS = (0.1, 0.3, 0.5, 0.7, 0.9)
KEYS = ("iou", "iou_seen", "iou_unseen", "iou_above_ground", "object_hit_rate")
OUT = Path("/tmp/generator_probe")


def encode(encoder, grids: np.ndarray) -> torch.Tensor:
    with torch.no_grad():
        return torch.cat([encoder.encode_pre_quant(torch.from_numpy(grids[i:i + 16].astype(np.float32)))
                          for i in range(0, len(grids), 16)])


def z0_of(prediction: str, z_t: torch.Tensor, output: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """The network's z_0 estimate from its output of kind ``prediction``."""
    if prediction == "sample":
        return output
    if prediction == "epsilon":
        return (z_t - (1 - a).sqrt() * output) / a.sqrt()
    return a.sqrt() * z_t - (1 - a).sqrt() * output  # v


@torch.no_grad()
def z0_errors(ldm, schedule: str, steps: int, z0: torch.Tensor, cond: torch.Tensor, eps: torch.Tensor,
              ego: torch.Tensor | None = None, adapter=None) -> list[float]:
    """ego: the adapter's pre-quantization input latents (x_e' [, re-simulated]), unstandardised."""
    abar = torch.from_numpy(alphas_cumprod(betas(schedule, steps))).float()
    z0, c = ldm.normalize(z0), ldm.normalize_cond(cond)
    feats = stage2.adapter_features(adapter, ldm, ego) if adapter is not None else None
    out = []
    for level in LEVELS:
        t = int(level * steps)
        a = abar[t]
        z_t = a.sqrt() * z0 + (1 - a).sqrt() * eps
        pred = z0_of(ldm.config["prediction"], z_t, ldm(z_t, torch.full((len(z0),), t), c, feats), a)
        out.append(float(((pred - z0) ** 2).mean()))
    return out


def scores(pipe: TYPPipeline, data, spread: bool) -> str:
    occ, points, _ = gen.sample_method(pipe, data, 0)
    summary = genscore.summarize([gen.score_method(data, occ, points)], data.scenes,
                                 [s["histogram"] for s in data.truth_stats], [s["centres"] for s in data.truth_stats],
                                 n_boot=200)
    text = " ".join(f"{k} {summary[k].value:.3f}" for k in KEYS)
    if spread:
        other, _, _ = gen.sample_method(pipe, data, 7919)
        text += f" spread {genscore.pairwise_iou(occ, other):.3f}"
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", default="val", help="held-out target split of data/sim scored")
    ap.add_argument("--stage1", action="append", default=[], help="JSON overrides of stage1 (unet: a dict)")
    ap.add_argument("--adapter", action="append", default=[], help="JSON overrides of stage2 (conditions: 1 or 2)")
    ap.add_argument("--scales", type=lambda text: [float(v) for v in text.split(",")], default=[],
                    help="adapter scales to sample the trained adapters with, e.g. 1,2,4,8 (default: selftrain's)")
    args = ap.parse_args()
    cfg, root = load_config("params.yaml"), Path(".")
    grid = cfg.voxelize.sensor_grid("target")
    spec = domain_spec("target", azimuth_step_deg=cfg.simulate.azimuth_step_deg).sensor
    x_vq, y_vq = load_vqvae(root / cfg.stage1.vqvae / "x"), load_vqvae(root / cfg.stage1.vqvae / "y")
    stats = TYPPipeline.from_pretrained(generator_dir(root / cfg.selftrain.out, cfg.stage1.seed)).point_stats
    data = gen.build_eval_set(root / cfg.simulate.out / "target" / args.split, grid, spec)
    print(f"{len(data)} pairs from {len(set(data.scenes))} {args.split} scenes", flush=True)
    z0, cond = encode(x_vq, data.x_r), encode(y_vq, data.y_r)
    ego = {1: encode(x_vq, data.x_e)}
    ego[2] = torch.cat([ego[1], encode(x_vq, data.resim)], 1)
    eps = torch.randn(z0.shape, generator=torch.Generator().manual_seed(0))
    base = base_pipeline(cfg, root, cfg.stage1.seed, x_vq, y_vq, stats)
    ldm = base.unet
    train = stage1.train_views(cfg.stage1, root)
    latents, train_cond = stage1.encode_views(x_vq, y_vq, train, dihedral=True)
    mean = float(((ldm.normalize(z0) - ldm.normalize(latents).mean(0, keepdim=True)) ** 2).mean())
    fmt = lambda errs: " ".join(f"{e:.3f}" for e in errs)  # noqa: E731
    print(f"z_0 error at t/T = {LEVELS}; per-cell training mean as predictor: {mean:.3f}")
    print(f"stage 1 (artifacts): z_0 error {fmt(z0_errors(ldm, base.schedule, base.train_timesteps, z0, cond, eps))}")
    print(f"  samples: {scores(base, data, spread=True)}", flush=True)

    def adapter_samples(adapter) -> None:
        """The scores of ``adapter``'s samples at each of ``--scales`` (default: selftrain's)."""
        for scale in args.scales or [base.adapter_scale]:
            pipe = dataclasses.replace(base.with_adapter(adapter), adapter_scale=scale)
            print(f"  samples, adapter scale {scale:g}: {scores(pipe, data, spread=False)}", flush=True)

    folder = stage1.replica_dir(root / cfg.selftrain.out, cfg.stage1.seed)
    for name, conditions in (("disc_st_dummy", 1), ("typ_resim", 2)):
        if (folder / name / "config.json").is_file():
            adapter = stage2.load_adapter(folder / name, "selftrain")
            errs = z0_errors(ldm, base.schedule, base.train_timesteps, z0, cond, eps, ego[conditions], adapter)
            print(f"selftrain {name}: z_0 error {fmt(errs)}")
            adapter_samples(adapter)
    for text in args.stage1:
        over = json.loads(text)
        block = dataclasses.replace(cfg.stage1, **{k: v for k, v in over.items() if k != "unet"}, checkpoint_every=10 ** 9)
        if "unet" in over:
            block = dataclasses.replace(block, unet=dataclasses.replace(block.unet, **over["unet"]))
        views, z, c = train, latents, train_cond
        if block.ego_only != cfg.stage1.ego_only:
            views = stage1.train_views(block, root)
            z, c = stage1.encode_views(x_vq, y_vq, views, dihedral=True)
        t0 = time.perf_counter()
        model = stage1.train(block, z, c, seed=cfg.stage1.seed, views=len(views),
                             out=OUT / "stage1" / text.replace(" ", ""), log_fn=lambda values, step: None)
        val = load_views(root / cfg.stage1.input, dataset=cfg.stage1.dataset, split=cfg.stage1.val_split)
        val = val.head(cfg.stage1.eval_views)
        truth, _ = val.batch(np.arange(len(val)))
        _, val_cond = stage1.encode_views(x_vq, y_vq, val)
        logits = stage1.sample_logits(model, x_vq, val_cond, cfg=block, generator=torch.Generator().manual_seed(1))
        pipe = dataclasses.replace(base, unet=model, schedule=block.schedule, train_timesteps=block.train_timesteps,
                                   thresholds=stage1.tune_thresholds(logits, truth, block, cfg.stage1.seed))
        print(f"stage 1 {text} ({time.perf_counter() - t0:.0f} s): "
              f"z_0 error {fmt(z0_errors(model, block.schedule, block.train_timesteps, z0, cond, eps))}")
        print(f"  samples: {scores(pipe, data, spread=True)}", flush=True)
    if args.adapter:
        tuples = stage2.load_tuples(root / cfg.stage2.out)
        source_x = load_vqvae(root / cfg.stage2.adapt / "source_vq", "adapt")
    for text in args.adapter:
        over = json.loads(text)
        conditions = over.pop("conditions", 1)
        block = dataclasses.replace(cfg.stage2, **over)
        latents2 = stage2.encode(tuples, source_x, y_vq, ldm, augment=block.augment, conditions=conditions)
        adapter = stage2.build_adapter(ldm, res_blocks=block.adapter_res_blocks, seed=cfg.stage1.seed,
                                       conditions=conditions)
        settings = dataclasses.replace(stage2.settings_of(block, cfg.stage1.seed, cfg.stage1.min_snr),
                                       checkpoint_every=10 ** 9)
        t0 = time.perf_counter()
        fitted = stage2.fit_adapter(adapter, ldm, base.schedule, base.train_timesteps, latents2, name="probe",
                                    settings=settings, views=len(tuples), key_extra={}, out=OUT / "adapter" / text.replace(" ", ""),
                                    log_fn=lambda values, step: None)
        errs = z0_errors(ldm, base.schedule, base.train_timesteps, z0, cond, eps, ego[conditions], fitted)
        print(f"adapter {text} ({time.perf_counter() - t0:.0f} s): z_0 error {fmt(errs)}")
        adapter_samples(fitted)


if __name__ == "__main__":
    main()
