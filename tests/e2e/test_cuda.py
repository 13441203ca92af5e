"""Every training stage and generation on CUDA: against the CPU in fp32, resumed, in bf16.

Skipped without CUDA (CI); ``bench/gpu.py`` runs this file on the GPU machine. With
``TYP_TEST_ACCELERATOR=cpu`` the CPU stands in for the GPU, so the file's code paths can be
run anywhere (every comparison is then exact).

Tolerances, fp32 on both devices (``typ.distributed.setup`` turns TF32 off on CUDA and asks for
deterministic kernels): the first step's loss, same weights and batch, within ``FIRST_LOSS_RTOL``
(only the order of float sums differs); every later loss within ``LOSS_RTOL``, and the trained
weights within ``WEIGHT_RTOL`` of the CPU's in relative L2 norm over all tensors (Adam normalises
each gradient, so a parameter whose gradient is rounding noise moves by ~lr whatever its sign: a
few such elements are allowed, a wrong op is not). A resumed run on CUDA matches the uninterrupted
one within ``RESUME_RTOL`` (0 where every kernel is deterministic). bf16: every loss finite and the
first within ``BF16_RTOL`` of fp32's.

Data that needs the simulator (open3d, which the GPU machine lacks) is synthetic here: random
voxel grids, latents, pixels and clouds (``bench/gpu_bundle.synthetic_cav_scenario``).
"""
from __future__ import annotations

import contextlib
import os

import numpy as np
import pytest
import torch

from bench_modules import load_bench
from pipelines.typ.pipeline_typ import PointStats, TYPPipeline
from tasks import adapt, ddpm, fusion_train, selftrain, ssc, stage1, stage2, vqvae
from tasks.fusion_batch import Inputs
from tasks.fusion_data import FusionDataset
from tasks.voxel_data import ViewSet
from typ import distributed
from typ.config import config_from_dict
from typ.voxel import Grid

ACCELERATOR = os.environ.get("TYP_TEST_ACCELERATOR", "cuda")
pytestmark = [pytest.mark.cuda,
              pytest.mark.skipif(ACCELERATOR == "cuda" and not torch.cuda.is_available(),
                                 reason="needs CUDA (TYP_TEST_ACCELERATOR=cpu runs it with the CPU standing in)")]

FIRST_LOSS_RTOL = 1e-4
LOSS_RTOL = 1e-2
WEIGHT_RTOL = 1e-3
RESUME_RTOL = 1e-5
BF16_RTOL = 5e-2

GRID = Grid((-16.0, 16.0), (-16.0, 16.0), (-3.0, 1.0), (32, 32, 4))
UNET = {"block_out_channels": [8, 8], "norm_num_groups": 4, "cross_attention_dim": 8, "attention_head_dim": 4}
AE = {"latent_channels": 3, "block_out_channels": [8, 8], "num_codes": 16, "norm_num_groups": 4, "epochs": 3,
      "quantizer": "vq"}
STEPS = 3


@contextlib.contextmanager
def runtime(device: str, precision: str = "fp32"):
    distributed.setup(device, precision)
    try:
        yield
    finally:
        distributed.setup("cpu", "fp32")


class Losses(list):
    """A log_fn recording each step's loss (the key ending in ``loss``, first found)."""

    def __call__(self, values: dict, step: int) -> None:
        self.append(next(v for k, v in values.items() if k == "loss" or k.endswith(".loss")))


def on_both(train, precision: str = "fp32") -> dict:
    """``train(losses, tag)`` -> a module, on the CPU (tag ``cpu``) and on the accelerator (tag
    ``accelerator``; the tag names the run's folder): {tag: (module, losses)}."""
    out = {}
    for tag, device in (("cpu", "cpu"), ("accelerator", ACCELERATOR)):
        losses = Losses()
        with runtime(device, precision):
            module = train(losses, tag)
        assert distributed.module_device(module).type == "cpu"   # handed back where it was
        out[tag] = (module, losses)
    return out


def assert_same_training(result: dict) -> None:
    (cpu, cpu_losses), (acc, acc_losses) = result["cpu"], result["accelerator"]
    assert len(cpu_losses) == len(acc_losses) >= 2
    assert acc_losses[0] == pytest.approx(cpu_losses[0], rel=FIRST_LOSS_RTOL)
    assert acc_losses == pytest.approx(cpu_losses, rel=LOSS_RTOL)
    a, b = _flat(cpu), _flat(acc)
    assert torch.isfinite(b).all()
    assert float(torch.linalg.vector_norm(b - a) / torch.linalg.vector_norm(a)) < WEIGHT_RTOL


def _flat(module: torch.nn.Module) -> torch.Tensor:
    return torch.cat([t.detach().double().reshape(-1) for t in module.state_dict().values() if t.is_floating_point()])


def _views(seed: int, n: int = 4) -> ViewSet:
    rng = np.random.default_rng(seed)
    records = [(np.argwhere(rng.random(GRID.shape) < 0.1), np.argwhere(rng.random(GRID.shape[:2]) < 0.05))
               for _ in range(n)]
    return ViewSet(GRID, [("s", str(i), "000000") for i in range(n)], records)


def _latents(n: int = 4, size: int = 8):
    gen = torch.Generator().manual_seed(1)
    return tuple(torch.randn(n, c, size, size, generator=gen) for c in (4, 3, 4))


def _vq_cfg(**ae):
    return config_from_dict({"vqvae": {"batch_size": 2, "x": {**AE, **ae}, "y": AE}}).vqvae


def _vq(kind: str = "x", channels: int = 4, **ae):
    torch.manual_seed(0)
    return vqvae.build(kind, getattr(_vq_cfg(**ae), kind), channels)


def _ldm(latent: int = 4, cond: int = 3, size: int = 8):
    cfg = config_from_dict({"stage1": {"unet": UNET}})
    torch.manual_seed(0)
    ldm = stage1.build(cfg.stage1, latent, cond, size)
    x, y, _ = _latents(size=size)
    ldm.set_statistics(x[:, :latent], y[:, :cond])
    return ldm


# ------------------------------------------------------------------ each stage against the CPU


def test_vqvae_matches_cpu(tmp_path):
    cfg, views = _vq_cfg(), _views(0, n=2)
    assert_same_training(on_both(lambda log, dev: vqvae.train_one("x", cfg, views, out=tmp_path / dev, log_fn=log)))


def test_stage1_matches_cpu(tmp_path):
    cfg = config_from_dict({"stage1": {"unet": UNET, "epochs": STEPS, "batch_size": 2}}).stage1
    x, y, _ = _latents()
    assert_same_training(on_both(lambda log, dev: stage1.train(cfg, x, y, seed=0, views=2, out=tmp_path / dev,
                                                               log_fn=log)))


def test_adapt_matches_cpu(tmp_path):
    cfg = config_from_dict({"adapt": {"epochs": STEPS, "batch_size": 2, "disc_width": 8}}).adapt
    source, target = _views(1, n=2), _views(2, n=2)

    def train(log, dev):
        source_vq, disc = adapt.train(cfg, _vq(), source, target, out=tmp_path / dev, log_fn=log)
        return torch.nn.ModuleList([source_vq, disc])

    assert_same_training(on_both(train))


def _fit_settings(**kw):
    cfg = config_from_dict({"stage2": {"epochs": STEPS, "batch_size": 2, **kw}})
    return stage2.settings_of(cfg.stage2, seed=0, min_snr=0.0)


def test_stage2_matches_cpu(tmp_path):
    ldm = _ldm()

    def train(log, dev):
        adapter = stage2.build_adapter(ldm, res_blocks=1, seed=0)
        return stage2.fit_adapter(adapter, ldm, "linear", 1000, stage2.Latents(*_latents()), name="adapter",
                                  settings=_fit_settings(), views=2, key_extra={}, out=tmp_path / dev, log_fn=log)

    assert_same_training(on_both(train))


@pytest.fixture(scope="module")
def cav_root(tmp_path_factory):
    gpu_bundle = load_bench("gpu_bundle")
    root = tmp_path_factory.mktemp("cav") / "train"
    gpu_bundle.synthetic_cav_scenario(root, seed=3, agents=2, frames=2, points=4000)
    return root


FUSION = {"detector": {"lidar_range": [-51.2, -25.6, -3.0, 51.2, 25.6, 1.0], "voxel_size": 0.8,
                       "max_points_per_pillar": 8, "max_pillars": 4000, "pillar_channels": 8,
                       "num_filters": [8, 16], "num_upsample_filters": [8, 8]},
          "v2xvit": {"dim": 8, "heads": 1, "dim_head": 8, "window_sizes": [4], "window_heads": [1],
                     "window_dim_heads": [8], "mlp_dim": 8, "dropout": 0.0},
          "batch_size": 2, "augment": {"flip": True, "rotation_deg": 10.0, "scale": [0.95, 1.05]}}


@pytest.mark.parametrize("method", ["late", "early", "attfuse", "v2xvit"])
def test_fusion_matches_cpu(tmp_path, cav_root, method):
    cfg = config_from_dict({"fusion": FUSION}).fusion
    data = FusionDataset(cav_root, lidar_range=cfg.detector.lidar_range, comm_range=cfg.comm_range, seed=cfg.seed)
    inputs = Inputs(list(data), cfg)

    def train(log, dev):
        # logged every LOG_EVERY steps and at the last: steps 0 and 2
        return fusion_train.train(method, cfg, inputs, steps=STEPS, out=tmp_path / dev, name=method, log_fn=log).model

    assert_same_training(on_both(train))


SSC = {"network": {"layer_nums": [1, 1, 1], "num_filters": [8, 8, 8], "num_upsample_filters": [8, 8, 8],
                   "pillar_channels": 8, "head_hidden": 8, "max_pillars": 16384},
       "v2xvit": {"dim": 8, "depth": 1, "heads": 2, "dim_head": 4, "window_sizes": [4, 8], "window_heads": [1, 1],
                  "window_dim_heads": [4, 4], "mlp_dim": 8, "dropout": 0.0, "shrink_stride": 2}}


@pytest.mark.parametrize("method", ["single", "attfuse"])
def test_ssc_matches_cpu(cav_root, method):
    block = config_from_dict({"ssc": SSC}).ssc
    data = ssc.TrainingSet.read(ssc.ssc_dataset(cav_root))
    weights = ssc.class_weights(data.class_counts(), eps=block.class_weight_eps)
    kw = ssc.model_kwargs(block)
    single, _ = ssc.train_single(data, steps=STEPS, seed=0, lr=5e-3, model_kw=kw, weights=weights)

    def train(log, dev):
        if method == "single":
            module, losses = ssc.train_single(data, steps=STEPS, seed=0, lr=5e-3, model_kw=kw, weights=weights)
        else:
            module, losses = ssc.train_fused(method, data, single, steps=STEPS, seed=0, lr=5e-3, weights=weights,
                                             options=ssc.network_options(block, method))
        log.extend(losses)
        return module

    assert_same_training(on_both(train))


DDPM = {"range_image": {"azimuth_bins": 64, "patch": [4, 4]},
        "unet": {"block_out_channels": [8, 16], "norm_num_groups": 8, "dropout": 0.0},
        "steps": STEPS, "checkpoint_every": 2, "batch_size": 2}


def _ddpm():
    cfg = config_from_dict({"profile": "tiny", "ddpm": DDPM}).ddpm
    run = cfg.configs[0]
    rep = ddpm.representations(cfg)[run.representation]
    pixels = torch.rand(4, *rep.shape, generator=torch.Generator().manual_seed(0)) * 2 - 1
    return cfg, run, rep, pixels


def test_ddpm_matches_cpu(tmp_path):
    cfg, run, rep, pixels = _ddpm()
    assert_same_training(on_both(lambda log, dev: ddpm.train_model(cfg, run, rep, 0, pixels, ["synthetic"],
                                                                    out=tmp_path / dev, log_fn=log).model))


def _pipeline(sampler: str, steps: int) -> TYPPipeline:
    x_vq = _vq(latent_channels=4)
    y = vqvae.PooledBoxMap(downsample=2)
    ldm = _ldm(latent=4, cond=1, size=16)
    return TYPPipeline(x_vq, y, ldm, stage2.build_adapter(ldm, res_blocks=1, seed=0), GRID, "linear", 1000,
                       sampler, steps, {"low": 0.5, "high": 0.5, "noise_std": 0.0})


@pytest.mark.parametrize("sampler,steps", [("dpmsolver++", 4), ("ddim", 8)])
def test_generation_matches_cpu(sampler, steps):
    pipe = _pipeline(sampler, steps)
    views = _views(4, n=2)
    x_e, y_r = views.occupancy([0, 1]), views.box_maps([0, 1])
    logits = {}
    for device in ("cpu", ACCELERATOR):
        with runtime(device):
            logits[device] = pipe.logits(x_e, y_r, seed=5)
    assert logits[ACCELERATOR].device.type == "cpu" and logits["cpu"].shape == (2, 4, 32, 32)
    torch.testing.assert_close(logits[ACCELERATOR], logits["cpu"], rtol=1e-3, atol=1e-3)


def test_selftrain_enhances_on_the_accelerator(tmp_path):
    """One TYP variant's self-training (pseudo references sampled, then the adapter fitted) on the device."""
    cfg = config_from_dict({"stage1": {"unet": UNET}, "stage2": {"batch_size": 2, "augment": 1},
                            "selftrain": {"epochs": 1, "batch_size": 2}})
    pipe = _pipeline("dpmsolver++", 2)
    views = _views(6, n=2)
    x, y = views.occupancy([0, 1]) > 0.5, views.box_maps([0, 1]) > 0.5
    data = selftrain.Inputs(stage2.Tuples(x, y, x[::-1].copy()), selftrain.References(x, y),
                            selftrain.dummy_ego_tuples(views), PointStats.single())
    encoders = selftrain.Encoders(pipe.x_vqvae, _vq(latent_channels=4), pipe.box_encoder)
    base = pipe.adapter
    losses = Losses()
    with runtime(ACCELERATOR):
        adapter, example = selftrain.enhance(selftrain.TABLE4[-1], cfg, data, encoders, pipe.with_adapter(None), base,
                                             seed=0, out=tmp_path, log_fn=losses)
    assert distributed.module_device(adapter).type == "cpu" and example.shape[0] == 2
    assert len(losses) == 3 and np.isfinite(losses).all()   # 2 source + 2 pseudo + 2 dummy views, batch 2
    assert torch.isfinite(_flat(adapter)).all() and not torch.equal(_flat(adapter), _flat(base))


# ------------------------------------------------------------------ resume, bf16, flags


class Stop(Exception):
    pass


def _stop_at(step: int, losses: Losses):
    def log(values, s):
        if s == step:
            raise Stop
        losses(values, s)
    return log


@pytest.mark.parametrize("stage", ["stage1", "vqvae_ema"])
def test_resume_on_the_accelerator_equals_the_uninterrupted_run(tmp_path, stage):
    """Killed after the checkpoint of step 2 and run again, training ends where one run ends (the
    EMA quantizer's k-means and dead-code restarts draw from the device's generator, which the
    checkpoint keeps)."""
    if stage == "stage1":
        cfg = config_from_dict({"stage1": {"unet": UNET, "epochs": 5, "batch_size": 2, "checkpoint_every": 2}}).stage1
        x, y, _ = _latents()

        def train(out, log):
            return stage1.train(cfg, x, y, seed=0, views=2, out=out, log_fn=log)
    else:
        ae = {**AE, "quantizer": "ema", "epochs": 5, "dead_code_threshold": 2.0}
        cfg = config_from_dict({"vqvae": {"batch_size": 2, "checkpoint_every": 2, "x": ae, "y": AE}}).vqvae
        views = _views(7, n=2)

        def train(out, log):
            return vqvae.train_one("x", cfg, views, out=out, log_fn=log)

    whole, first, second = Losses(), Losses(), Losses()

    def stop_at_3(values, step):
        if step == 3:   # before step 3's checkpoint: the run resumes from step 2's
            raise Stop
        first(values, step)

    with runtime(ACCELERATOR):
        uninterrupted = train(tmp_path / "whole", whole)
        with pytest.raises(Stop):
            train(tmp_path / "resumed", stop_at_3)
        resumed = train(tmp_path / "resumed", second)
    assert len(whole) == 5 and len(first) == 3 and len(second) == 3
    assert second == pytest.approx(whole[2:], rel=RESUME_RTOL)
    a, b = _flat(uninterrupted), _flat(resumed)
    assert float(torch.linalg.vector_norm(b - a) / torch.linalg.vector_norm(a)) <= RESUME_RTOL


class Stop(Exception):
    pass


def _bf16_run(stage: str, tmp_path):
    """``train(losses, precision)`` of ``stage``'s few steps."""
    if stage == "vqvae":
        return lambda log, p: vqvae.train_one("x", _vq_cfg(), _views(0, n=2), out=tmp_path / p, log_fn=log)
    if stage == "stage1":
        cfg = config_from_dict({"stage1": {"unet": UNET, "epochs": STEPS, "batch_size": 2}}).stage1
        x, y, _ = _latents()
        return lambda log, p: stage1.train(cfg, x, y, seed=0, views=2, out=tmp_path / p, log_fn=log)
    if stage == "stage2":
        ldm = _ldm()
        return lambda log, p: stage2.fit_adapter(stage2.build_adapter(ldm, res_blocks=1, seed=0), ldm, "linear", 1000,
                                                 stage2.Latents(*_latents()), name="a", settings=_fit_settings(),
                                                 views=2, key_extra={}, out=tmp_path / p, log_fn=log)
    if stage == "adapt":
        cfg = config_from_dict({"adapt": {"epochs": STEPS, "batch_size": 2, "disc_width": 8}}).adapt
        return lambda log, p: adapt.train(cfg, _vq(), _views(1, n=2), _views(2, n=2), out=tmp_path / p, log_fn=log)
    cfg, run, rep, pixels = _ddpm()
    return lambda log, p: ddpm.train_model(cfg, run, rep, 0, pixels, ["synthetic"], out=tmp_path / p, log_fn=log)


@pytest.mark.parametrize("stage", ["vqvae", "stage1", "stage2", "adapt", "ddpm"])
def test_bf16_losses_are_finite_and_near_fp32(tmp_path, stage):
    train, losses = _bf16_run(stage, tmp_path), {}
    for precision in ("fp32", "bf16"):
        losses[precision] = Losses()
        with runtime(ACCELERATOR, precision):
            train(losses[precision], precision)
    assert len(losses["bf16"]) == len(losses["fp32"]) >= 2 and np.isfinite(losses["bf16"]).all()
    assert losses["bf16"][0] == pytest.approx(losses["fp32"][0], rel=BF16_RTOL)


@pytest.mark.skipif(ACCELERATOR != "cuda", reason="CUDA's generator")
def test_checkpoints_keep_the_cuda_generator():
    """What a resumed run restores (tasks.training.rng_state): the device's generator too, from
    which the EMA quantizer's k-means and dead-code restarts draw."""
    from tasks.training import rng_state, set_rng_state

    with runtime("cuda"):
        torch.cuda.manual_seed(3)
        state = rng_state()
        first = torch.rand(4, device="cuda")
        torch.cuda.manual_seed(4)
        set_rng_state(state)
        assert "cuda" in state and torch.equal(torch.rand(4, device="cuda"), first)


@pytest.mark.skipif(ACCELERATOR != "cuda", reason="CUDA's flags")
def test_setup_on_cuda_asks_for_reproducible_arithmetic():
    with runtime("cuda"):
        assert torch.are_deterministic_algorithms_enabled()
        assert not torch.backends.cudnn.allow_tf32 and not torch.backends.cuda.matmul.allow_tf32
        assert torch.backends.cudnn.deterministic and not torch.backends.cudnn.benchmark
        assert os.environ["CUBLAS_WORKSPACE_CONFIG"] in (":4096:8", ":16:8")
    distributed.reproducible_cuda(False)
    assert not torch.are_deterministic_algorithms_enabled() and torch.backends.cudnn.allow_tf32
