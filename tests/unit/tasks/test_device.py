"""``runtime.device``: every op of a training step and of generation runs on the runtime device.

This machine has no GPU, so the plumbing is checked on PyTorch's ``meta`` device, which
behaves like CUDA for device checks: an op mixing a meta tensor with a non-scalar CPU tensor
raises "... is not on the expected device ...". With the runtime set to ``meta``, a tensor
left on the CPU by a training step or by the sampler fails the test; a step that runs through
to its optimizer updates passes. (Meta tensors hold no data: reading a scalar gives 1.0 here,
and moving a module back to the CPU at the end fails by design, after the step ran.)
tests/e2e/test_cuda.py trains every stage on a GPU where there is one.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from pipelines.typ import pipeline_typ as pipeline
from tasks import adapt, fusion_train, stage1, stage2, vqvae
from tasks.fusion_batch import Inputs
from tasks.training import state_of
from tasks.voxel_data import ViewSet
from typ import distributed
from typ.config import config_from_dict
from typ.voxel import Grid

GRID = Grid((-16.0, 16.0), (-16.0, 16.0), (-3.0, 1.0), (32, 32, 4))
UNET = {"block_out_channels": [8, 8], "norm_num_groups": 4, "cross_attention_dim": 8, "attention_head_dim": 4}
NO_DATA = "Cannot copy out of meta tensor"


class StepRan(Exception):
    """Raised by the stand-in loop once a whole training step ran."""


@pytest.fixture
def meta_runtime(monkeypatch):
    """The runtime device is ``meta``; scalars read from meta tensors are 1.0 / True."""
    import torch.fx.experimental._config as fx_config

    monkeypatch.setattr(distributed, "_runtime", distributed.Runtime(torch.device("meta"), "fp32"))
    for name, value in (("__float__", 1.0), ("item", 1.0), ("__bool__", True)):
        real = getattr(torch.Tensor, name)
        monkeypatch.setattr(torch.Tensor, name,
                            lambda self, _real=real, _value=value: _value if self.is_meta else _real(self))
    with fx_config.patch(meta_nonzero_assume_all_nonzero=True):  # nonzero() on meta: every element
        yield


def _one_step_loop(seen: list):
    """Stand-in for ``run_loop``: one step, record what it logged and where the params are, stop."""
    def loop(*, step_fn, state, **_):
        values = step_fn(0)
        seen.append((values, {t.device.type for t in get_state_tensors(state_of(state))}))
        raise StepRan
    return loop


def get_state_tensors(state):
    if isinstance(state, torch.Tensor):
        yield state
    elif isinstance(state, dict):
        for v in state.values():
            yield from get_state_tensors(v)
    elif isinstance(state, (list, tuple)):
        for v in state:
            yield from get_state_tensors(v)


def _ran_on_meta(call, module, monkeypatch) -> dict:
    """Run ``call()`` with ``module.run_loop`` replaced; the step must complete on ``meta``."""
    seen: list = []
    monkeypatch.setattr(module, "run_loop", _one_step_loop(seen))
    with pytest.raises(NotImplementedError, match=NO_DATA) as raised:
        call()
    # moving the modules back to the CPU is what failed, after the step had run
    assert _step_ran(raised.value)
    values, devices = seen[0]
    assert devices == {"meta"}, devices        # model and optimizer state lived on the device
    assert "loss" in values
    return values


def _step_ran(error: BaseException) -> bool:
    """StepRan is in ``error``'s context chain and nothing but failed moves off meta came after it."""
    chain = []
    while error is not None:
        chain.append(error)
        error = error.__context__
    assert isinstance(chain[-1], StepRan), chain
    assert all(isinstance(e, NotImplementedError) and NO_DATA in str(e) for e in chain[:-1]), chain
    return True


def _views(seed: int, n: int = 4) -> ViewSet:
    rng = np.random.default_rng(seed)
    records = [(np.argwhere(rng.random(GRID.shape) < 0.1), np.argwhere(rng.random(GRID.shape[:2]) < 0.05))
               for _ in range(n)]
    return ViewSet(GRID, [("s", str(i), "000000") for i in range(n)], records)


def _vq_cfg():
    # dead-code restarts draw a data-dependent number of samples, which meta tensors cannot
    # hold: the check runs without them (they are index ops on tensors already on the device)
    ae = {"latent_channels": 3, "block_out_channels": [8, 8], "num_codes": 16, "norm_num_groups": 4, "epochs": 1,
          "dead_code_threshold": 0.0}
    return config_from_dict({"vqvae": {"batch_size": 2, "x": ae, "y": ae}}).vqvae


def _vq(kind: str, channels: int):
    torch.manual_seed(0)
    return vqvae.build(kind, getattr(_vq_cfg(), kind), channels)


def test_vqvae_step_runs_on_the_runtime_device(meta_runtime, monkeypatch, tmp_path):
    _ran_on_meta(lambda: vqvae.train_one("x", _vq_cfg(), _views(0), out=tmp_path, log_fn=lambda v, s: None),
                 vqvae, monkeypatch)


def test_adapt_step_runs_on_the_runtime_device(meta_runtime, monkeypatch, tmp_path):
    cfg = config_from_dict({"adapt": {"epochs": 1, "batch_size": 2, "disc_width": 8}}).adapt
    values = _ran_on_meta(lambda: adapt.train(cfg, _vq("x", 4), _views(1), _views(2), out=tmp_path,
                                              log_fn=lambda v, s: None), adapt, monkeypatch)
    assert {"rec", "adv", "commit", "disc_loss"} <= set(values)


def _latents(n: int = 4):
    gen = torch.Generator().manual_seed(1)
    return tuple(torch.randn(n, c, 8, 8, generator=gen) for c in (4, 3, 4))


def test_stage1_step_runs_on_the_runtime_device(meta_runtime, monkeypatch, tmp_path):
    cfg = config_from_dict({"stage1": {"unet": UNET, "epochs": 1, "batch_size": 2}}).stage1
    x, y, _ = _latents()
    _ran_on_meta(lambda: stage1.train(cfg, x, y, seed=0, views=len(x), out=tmp_path, log_fn=lambda v, s: None),
                 stage1, monkeypatch)


def test_stage2_step_runs_on_the_runtime_device(meta_runtime, monkeypatch, tmp_path):
    cfg = config_from_dict({"stage1": {"unet": UNET}, "stage2": {"epochs": 1, "batch_size": 2}})
    torch.manual_seed(0)
    ldm = stage1.build(cfg.stage1, 4, 3, 8)
    ldm.set_statistics(_latents()[0], _latents()[1])
    adapter = stage2.build_adapter(ldm, res_blocks=1, seed=0)
    settings = stage2.settings_of(cfg.stage2, seed=0, min_snr=5.0)
    _ran_on_meta(lambda: stage2.fit_adapter(adapter, ldm, "linear", 1000, stage2.Latents(*_latents()), name="adapter",
                                            settings=settings, views=4, key_extra={}, out=tmp_path,
                                            log_fn=lambda v, s: None), stage2, monkeypatch)


@pytest.fixture(scope="module")
def fusion_inputs(tmp_path_factory):
    from tasks.fusion_data import FusionDataset
    from typ.formats.opv2v import write_scene
    from typ.sim import simulate_scenario

    root = tmp_path_factory.mktemp("device_fusion")
    for scene in simulate_scenario(domain="real_cav", seed=3, n_frames=2, n_agents=2, scenario="real_cav_0003"):
        write_scene(scene, root)
    cfg = config_from_dict({"fusion": {
        "detector": {"lidar_range": [-51.2, -25.6, -3.0, 51.2, 25.6, 1.0], "voxel_size": 0.8,
                     "max_points_per_pillar": 8, "max_pillars": 4000, "pillar_channels": 8,
                     "num_filters": [8, 16], "num_upsample_filters": [8, 8]},
        "v2xvit": {"dim": 8, "heads": 1, "dim_head": 8, "window_sizes": [4], "window_heads": [1],
                   "window_dim_heads": [8], "mlp_dim": 8},
        "batch_size": 2}}).fusion
    data = FusionDataset(root, lidar_range=cfg.detector.lidar_range, comm_range=cfg.comm_range, seed=cfg.seed)
    return cfg, Inputs(list(data), cfg)


@pytest.mark.parametrize("method", ["early"])
def test_fusion_step_runs_on_the_runtime_device(meta_runtime, monkeypatch, tmp_path, fusion_inputs, method):
    cfg, inputs = fusion_inputs
    values = _ran_on_meta(lambda: fusion_train.train(method, cfg, inputs, steps=1, out=tmp_path, name=method),
                          fusion_train, monkeypatch)
    assert {"cls_loss", "reg_loss"} <= set(values)


def test_generation_samples_on_the_runtime_device(meta_runtime, monkeypatch):
    cfg = config_from_dict({"stage1": {"unet": UNET}})
    torch.manual_seed(0)
    x_vq, y_vq = _vq("x", 4), _vq("y", 1)
    ldm = stage1.build(cfg.stage1, 3, 3, 16)
    ldm.set_statistics(torch.randn(4, 3, 16, 16), torch.randn(4, 3, 16, 16))
    pipe = pipeline.TYPPipeline(x_vq, y_vq, ldm, stage2.build_adapter(ldm, res_blocks=1, seed=0), GRID, "linear",
                                1000, "ddim", 2, {"low": 0.5, "high": 0.5, "noise_std": 0.0})
    sampled: list = []

    def recording(model, scheduler, *, shape, cond, adapter_features, device, **kw):
        sampled.append((cond.device.type, {f.device.type for f in adapter_features}, torch.device(device).type,
                        {p.device.type for p in model.parameters()}))
        raise StepRan

    monkeypatch.setattr(pipeline, "sample", recording)
    occupancy = np.zeros((1, 4, 32, 32), np.float32)
    with pytest.raises(NotImplementedError, match=NO_DATA) as raised:
        pipe.logits(occupancy, occupancy[:, :1], seed=0)
    assert _step_ran(raised.value)
    assert sampled == [("meta", {"meta"}, "meta", {"meta"})]


class _Recorder(torch.nn.Linear):
    """Records where it is asked to go (and stays put)."""

    def __init__(self):
        super().__init__(2, 2)
        self.moves: list[str] = []

    def to(self, device):
        self.moves.append(torch.device(device).type)
        return self


def test_on_device_puts_modules_back_where_they_were(monkeypatch):
    monkeypatch.setattr(distributed, "_runtime", distributed.Runtime(torch.device("meta"), "fp32"))
    a, b = _Recorder(), _Recorder()
    with distributed.on_device(a, None, b) as dev:
        assert dev.type == "meta" and a.moves == b.moves == ["meta"]
    assert a.moves == b.moves == ["meta", "cpu"]
    with pytest.raises(RuntimeError, match="boom"), distributed.on_device(a):
        raise RuntimeError("boom")
    assert a.moves[-2:] == ["meta", "cpu"]          # back also when the block fails
    assert distributed.module_device(torch.nn.ReLU()).type == "cpu"


def test_local_batch_outside_torchrun_moves_tensors_and_keeps_arrays():
    index, flips = np.arange(5), np.ones(5, bool)
    t = torch.arange(5.0)
    got = distributed.local_batch(index, flips, t)
    assert got[0] is index and got[1] is flips and torch.equal(got[2], t)
    with pytest.raises(ValueError, match="one length"):
        distributed.local_batch(index, t[:4])
