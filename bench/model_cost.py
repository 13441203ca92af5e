"""bench/pipeline.py's model sections: the paper profile's training and denoising steps on this CPU
(extrapolated to TYP §4.5's dataset sizes) and the fusion methods' inference time per frame."""
from __future__ import annotations

import statistics
import sys
import time

from bench.pipeline_report import N_GEN, N_TRAIN, WARMUP_S


def call_seconds(fn, *, repeats: int, min_calls: int = 1) -> float:
    """Median wall seconds of ``fn()`` over ``max(repeats, min_calls)`` calls after a warm-up call;
    a first call slower than WARMUP_S counts as one of them (its warm-up share is small)."""
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    times = [first] if first > WARMUP_S else []
    while len(times) < max(repeats, min_calls):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_paper(steps: int) -> dict:
    """Seconds per training step (batch 1) and per generation component of the paper profile's models."""
    import numpy as np
    import torch
    import torch.nn.functional as F

    from models.samplers import make_scheduler, sample
    from models.schedules import alphas_cumprod, betas
    from tasks import stage1, stage2, vqvae
    from tasks.training import noised_batch
    from typ.config import config_from_dict

    cfg = config_from_dict({"profile": "paper"})
    H, W, C = cfg.voxelize.grid.shape
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    rows: list[dict] = []

    def add(name: str, what: str, modules: list, fn, *, training: bool, **extra) -> None:
        seconds = call_seconds(fn, repeats=steps, min_calls=2 if training else 1)
        params = sum(p.numel() for m in modules for p in m.parameters()) / 1e6
        rows.append({"name": name, "what": what, "params_m": params, "seconds": seconds, **extra})
        print(f"  paper {name}: {seconds:.3f} s", file=sys.stderr)

    def train_step(model_fn, opt):
        def step():
            loss = model_fn()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        return step

    occupancy = (torch.rand(1, C, H, W) < 0.04).float()     # about the tiny data's 3.7 % occupied voxels
    boxes = (torch.rand(1, 1, H, W) < 0.01).float()
    vq = {}
    for kind, x in (("y", boxes), ("x", occupancy)):
        ae = getattr(cfg.vqvae, kind)
        model = vqvae.build(kind, ae, C).train()
        opt = torch.optim.Adam(model.parameters(), lr=cfg.vqvae.lr)
        add(f"VQ-VAE {kind}", f"train step, input {tuple(x.shape[1:])}", [model],
            train_step(lambda model=model, x=x, g=ae.gamma: model.loss(x, gamma=g)[0], opt), training=True,
            epochs=ae.epochs, n=N_TRAIN)
        vq[kind] = model.eval()

    with torch.no_grad():
        x_lat, y_lat = vq["x"].encode_pre_quant(occupancy), vq["y"].encode_pre_quant(boxes)
    s1 = cfg.stage1
    ldm = stage1.build(s1, x_lat.shape[1], y_lat.shape[1], x_lat.shape[-1]).train()
    ldm.set_statistics(torch.randn(4, *x_lat.shape[1:]), torch.randn(4, *y_lat.shape[1:]))
    abar = torch.from_numpy(alphas_cumprod(betas(s1.schedule, s1.train_timesteps))).float()
    z0, c, ce = torch.randn(1, *x_lat.shape[1:]), torch.randn(1, *y_lat.shape[1:]), torch.randn(1, *x_lat.shape[1:])

    def eps_loss(adapter=None):
        index, t, eps, z_t = noised_batch(rng, z0, abar, 1)
        features = list(adapter(ce[index])) if adapter is not None else None
        return F.mse_loss(ldm(z_t, t, c[index], features), eps)

    add("stage-1 UNet", f"train step, x^f {tuple(x_lat.shape[1:])}, y^f {tuple(y_lat.shape[1:])}", [ldm],
        train_step(eps_loss, torch.optim.AdamW(ldm.parameters(), lr=s1.lr)), training=True, epochs=s1.epochs,
        n=N_TRAIN)
    ldm.eval().requires_grad_(False)
    adapter = stage2.build_adapter(ldm, res_blocks=cfg.stage2.adapter_res_blocks, seed=0).train()
    add("stage-2 adapter", "train step of F_AD, UNet frozen", [adapter],
        train_step(lambda: eps_loss(adapter), torch.optim.AdamW(adapter.parameters(), lr=cfg.stage2.lr)),
        training=True, epochs=cfg.stage2.epochs, n=N_TRAIN, assumed=True)
    rows.append({**rows[-1], "name": "self-training adapter", "epochs": cfg.selftrain.epochs})
    adapter.eval()

    with torch.no_grad():
        features = stage2.adapter_features(adapter, ldm, x_lat)
        scheduler = make_scheduler("ddim", betas(s1.schedule, s1.train_timesteps))
        gen = torch.Generator().manual_seed(0)
        add("E_x encode", "x_e' -> x^f_e'", [vq["x"].net.encoder, vq["x"].net.quant_conv],
            lambda: vq["x"].encode_pre_quant(occupancy), training=False)
        add("E_y encode", "y_r -> y^f_r", [vq["y"].net.encoder, vq["y"].net.quant_conv],
            lambda: vq["y"].encode_pre_quant(boxes), training=False)
        add("F_AD features", "once per sample", [adapter], lambda: stage2.adapter_features(adapter, ldm, x_lat),
            training=False)
        add("denoising step", "UNet forward with adapter features + DDIM step", [ldm],
            lambda: sample(ldm, scheduler, shape=tuple(x_lat.shape), num_steps=1, generator=gen,
                           cond=ldm.normalize_cond(y_lat), adapter_features=features), training=False)
        add("G_x decode", f"x^f -> logits {(1, C, H, W)}", [vq["x"].net.post_quant_conv, vq["x"].net.decoder],
            lambda: vq["x"].decode_latents(x_lat), training=False)
    return {"steps": steps, "sample_steps": cfg.generate.sample_steps, "n_gen": N_GEN,
            "pseudo_references": cfg.selftrain.pseudo_references, "rows": rows}


def synthetic_cloud(rng, n: int) -> "np.ndarray":
    """(n, 4) float32 64-beam-like scan: ground rings thinning with range, 35 % obstacle hits within 60 m."""
    import numpy as np

    elev = np.radians(rng.choice(np.linspace(-24.9, 2.0, 64), n))
    az = rng.uniform(-np.pi, np.pi, n)
    r = np.where(elev < 0, 1.73 / np.tan(-np.minimum(elev, -1e-3)), 120.0)
    r = np.where(rng.random(n) < 0.35, np.minimum(r, rng.uniform(3.0, 60.0, n)), np.minimum(r, 120.0))
    xyz = np.stack([r * np.cos(elev) * np.cos(az), r * np.cos(elev) * np.sin(az), r * np.sin(elev) - 0.2], 1)
    return np.column_stack([xyz, rng.random(n)]).astype(np.float32)


def fusion_frame(rng, *, agents: int, points: int):
    """One FusionSample of ``agents`` random clouds, the others within 30 m of the ego, no labels."""
    import numpy as np

    from tasks.fusion_data import FusionSample
    from typ.geometry import pose_to_matrix

    poses = [np.eye(4)] + [pose_to_matrix([*rng.uniform(-30, 30, 2), 0.0, 0.0, rng.uniform(-180, 180), 0.0])
                           for _ in range(agents - 1)]
    transforms = np.stack(poses)
    empty = np.zeros((0, 7))
    return FusionSample("bench", "000000", tuple(str(i) for i in range(agents)),
                        tuple(synthetic_cloud(rng, points) for _ in range(agents)), transforms, transforms,
                        np.zeros(agents, np.int64), empty, np.zeros(0, np.int64), tuple(empty for _ in range(agents)))


def time_fusion(cfg, *, agents: int, points: int, repeats: int, seed: int = 0) -> dict:
    """method -> {'frame_s', 'network_s'} for one frame, methods taking turns call by call."""
    import numpy as np
    import torch

    from models.fusion import METHODS
    from tasks.fusion_batch import Inputs
    from tasks.fusion_score import predict
    from tasks.fusion_train import Trained, box_coder, build_model

    sample = fusion_frame(np.random.default_rng(seed), agents=agents, points=points)
    trained, batches = {}, {}
    for method in cfg.methods:
        torch.manual_seed(seed)
        model = build_model(METHODS[method].network, cfg).eval()
        trained[method] = Trained(METHODS[method].network, model, box_coder(cfg, model), key="bench",
                                  steps=0).as_method(method)
        batches[method] = Inputs([sample], cfg).batch(method, [0])
    calls = {}
    for method in cfg.methods:
        calls[(method, "frame_s")] = lambda m=method: predict(trained[m], Inputs([sample], cfg), cfg, batch_size=1)
        calls[(method, "network_s")] = lambda m=method: batches[m].run(trained[m].model)
    times: dict = {k: [] for k in calls}
    with torch.no_grad():
        for rep in range(repeats + 1):      # the first round warms up, and counts for calls over WARMUP_S
            for key, fn in calls.items():
                if len(times[key]) == repeats:
                    continue
                t0 = time.perf_counter()
                fn()
                seconds = time.perf_counter() - t0
                if rep or seconds > WARMUP_S:
                    times[key].append(seconds)
    out: dict = {m: {} for m in cfg.methods}
    for (method, what), t in times.items():
        out[method][what] = statistics.median(t)
    return out


def bench_fusion(*, agents: int, points: int, repeats: int) -> dict:
    from typ.config import config_from_dict

    profiles = {}
    for profile in ("tiny", "paper"):
        cfg = config_from_dict({"profile": profile}).fusion
        d = cfg.detector
        nx, ny = (round((d.lidar_range[k + 3] - d.lidar_range[k]) / d.voxel_size) for k in (0, 1))
        detector = f"{d.voxel_size} m pillars, {nx}×{ny}, filters {list(d.num_filters)}"
        print(f"fusion: {profile} profile ({detector})", file=sys.stderr)
        profiles[profile] = {"detector": detector,
                             "methods": time_fusion(cfg, agents=agents, points=points, repeats=repeats)}
    return {"agents": agents, "points": points, "repeats": repeats, "profiles": profiles}
