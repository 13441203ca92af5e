"""Every training stage resumed after a kill ends at the model the uninterrupted run trains.

A kill is a ``log_fn`` that raises after ``KILL_AT`` steps (the checkpoint of step
``CHECKPOINT_EVERY`` is on disk then, the steps after it are lost); the second call, with the
same arguments and output folder, resumes from that checkpoint. The result must equal, tensor
by tensor, the model a run that was never interrupted trains in another folder: same batches
(drawn from the step number), same optimizer and EMA state, same codebook buffers.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from tasks import adapt, stage1, stage2, vqvae
from tasks.voxel_data import ViewSet
from typ.config import config_from_dict
from typ.voxel import Grid

GRID = Grid((-16.0, 16.0), (-16.0, 16.0), (-0.75, 3.25), (32, 32, 4))
UNET = {"block_out_channels": [8, 8], "norm_num_groups": 4, "cross_attention_dim": 8, "attention_head_dim": 4}
CHECKPOINT_EVERY, KILL_AT = 2, 3   # steps 0-1 checkpointed, step 2 lost, total 6


class Killed(Exception):
    pass


def _killer(at: int = KILL_AT):
    seen = []

    def log_fn(values, step):
        seen.append(step)
        if len(seen) == at:
            raise Killed
    return log_fn, seen


def _resumed_equals_uninterrupted(train, tmp_path) -> tuple[list, list]:
    """(states of the resumed and the uninterrupted run), after checking the resume happened."""
    log_fn, seen = _killer()
    with pytest.raises(Killed):
        train(tmp_path / "killed", log_fn)
    resumed_steps = []
    resumed = train(tmp_path / "killed", lambda v, s: resumed_steps.append(s))
    whole = train(tmp_path / "whole", lambda v, s: None)
    assert seen == list(range(KILL_AT)) and resumed_steps[0] == CHECKPOINT_EVERY  # resumed, not restarted
    for r, w in zip(resumed if isinstance(resumed, tuple) else (resumed,), whole if isinstance(whole, tuple) else (whole,)):
        a, b = r.state_dict(), w.state_dict()
        assert a.keys() == b.keys()
        for k in a:
            torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    return resumed, whole


def _views(seed: int, density: float, n: int = 4) -> ViewSet:
    rng = np.random.default_rng(seed)
    records = [(np.argwhere(rng.random(GRID.shape) < density), np.argwhere(rng.random(GRID.shape[:2]) < 0.02))
               for _ in range(n)]
    return ViewSet(GRID, [("s", str(i), "000000") for i in range(n)], records)


@pytest.mark.parametrize("dead_code_threshold", [1.0, 1e6])
def test_vqvae_resumes_to_the_uninterrupted_model(tmp_path, dead_code_threshold):
    """At 1e6 every code is restarted on every step from vectors the quantizer draws with torch's
    global generator: the resumed run matches only if the checkpoint restores that generator
    (a kill in `make run`'s vqvae ended 1.5 away from the uninterrupted weights without it)."""
    ae = {"latent_channels": 3, "block_out_channels": [8, 8], "num_codes": 16, "norm_num_groups": 4, "epochs": 3,
          "dead_code_threshold": dead_code_threshold}
    cfg = config_from_dict({"vqvae": {"batch_size": 2, "checkpoint_every": CHECKPOINT_EVERY, "x": ae,
                                      "y": {"block_out_channels": [8, 8]}}}).vqvae
    views = _views(0, 0.1)
    _resumed_equals_uninterrupted(lambda out, log: vqvae.train_one("x", cfg, views, out=out, log_fn=log), tmp_path)


def test_adapt_resumes_to_the_uninterrupted_encoder_and_discriminator(tmp_path):
    torch.manual_seed(0)
    from models.vqvae import BEVVQVAE

    target = BEVVQVAE(in_channels=4, latent_channels=3, block_out_channels=(8, 8), num_codes=16, norm_num_groups=4)
    target.eval()
    with torch.no_grad():
        target.train()(torch.from_numpy(_views(9, 0.1).occupancy([0, 1])))  # k-means: a trained codebook
    target.eval()
    cfg = config_from_dict({"adapt": {"epochs": 3, "batch_size": 2, "checkpoint_every": CHECKPOINT_EVERY,
                                      "disc_width": 8}}).adapt
    src, tgt = _views(1, 0.15), _views(2, 0.05)
    _resumed_equals_uninterrupted(lambda out, log: adapt.train(cfg, target, src, tgt, out=out, log_fn=log), tmp_path)


def _latents(n: int = 4):
    gen = torch.Generator().manual_seed(1)
    return tuple(torch.randn(n, c, 8, 8, generator=gen) for c in (4, 3, 4))


def test_stage1_resumes_to_the_uninterrupted_ema_model(tmp_path):
    cfg = config_from_dict({"stage1": {"unet": UNET, "epochs": 3, "batch_size": 2, "warmup_steps": 2,
                                       "checkpoint_every": CHECKPOINT_EVERY, "prediction": "sample",
                                       "min_snr": 5.0}}).stage1
    x, y, _ = _latents()
    _resumed_equals_uninterrupted(
        lambda out, log: stage1.train(cfg, x, y, seed=0, views=len(x), out=out, log_fn=log), tmp_path)


@pytest.mark.parametrize("one_stage", [False, True])
def test_adapters_resume_to_the_uninterrupted_model(tmp_path, one_stage):
    """Stage 2 and self-training (fit_adapter), and Table 5's joint model (the same loop)."""
    cfg = config_from_dict({"stage1": {"unet": UNET},
                            "stage2": {"epochs": 3, "batch_size": 2, "warmup_steps": 2,
                                       "checkpoint_every": CHECKPOINT_EVERY}})
    torch.manual_seed(0)
    ldm = stage1.build(cfg.stage1, 4, 3, 8)
    x, y, e = _latents()
    ldm.set_statistics(x, y)
    data = stage2.Latents(x, y, e)
    settings = stage2.settings_of(cfg.stage2, seed=0, min_snr=5.0)

    def fit(out, log):
        adapter = stage2.build_adapter(ldm, res_blocks=1, seed=0)
        if one_stage:
            import copy

            joint = stage2.JointModel(copy.deepcopy(ldm), adapter)
            return stage2._fit_joint(joint, "linear", 1000, data, steps=6, settings=settings, name="joint", out=out,
                                     log_fn=log)
        return stage2.fit_adapter(adapter, ldm, "linear", 1000, data, name="adapter", settings=settings, views=4,
                                  key_extra={}, out=out, log_fn=log)

    _resumed_equals_uninterrupted(fit, tmp_path)


class _KilledAt(list):
    """The views of an SSC training set that raise :class:`Killed` at the ``at``-th read: a kill in
    the middle of a step, after the checkpoint of step ``CHECKPOINT_EVERY``."""

    def __init__(self, items, at: int):
        super().__init__(items)
        self.reads, self.at = 0, at

    def __getitem__(self, k):
        self.reads += 1
        if self.reads == self.at:
            raise Killed
        return super().__getitem__(k)


def test_ssc_networks_resume_to_the_uninterrupted_model(tmp_path):
    """The SSC stage's networks train on the shared loop: killed in step 2, resumed from the
    checkpoint of step 2, they end at the uninterrupted run's weights and losses."""
    from tasks import ssc as S
    from typ.ssc import SSC_GRID

    rng = np.random.default_rng(0)
    views = []
    for _ in range(3):
        cloud = np.concatenate([rng.uniform([-40, -40, -2.5], [40, 40, 3.0], (3000, 3)), rng.random((3000, 1))], 1)
        views.append((cloud.astype(np.float32), rng.integers(0, S.N_CLASSES, SSC_GRID.shape).astype(np.uint8)))
    kw = dict(layer_nums=(1, 1, 1), num_filters=(8, 8, 8), num_upsample_filters=(8, 8, 8), pillar_channels=8, head_hidden=8,
              max_pillars=4096)
    weights = np.linspace(0.5, 2.0, S.N_CLASSES)

    def train(folder, killed_at=None):
        data = S.TrainingSet(_KilledAt(views, killed_at or 10**9), [], [], "k", [True] * 3)
        return S.train_single(data, steps=6, seed=1, lr=5e-3, model_kw=kw, weights=weights, checkpoints=folder,
                              checkpoint_every=CHECKPOINT_EVERY)

    with pytest.raises(Killed):
        train(tmp_path / "killed", killed_at=KILL_AT)
    from tasks.training import checkpoints
    assert [s for s, _ in checkpoints(tmp_path / "killed")] == [CHECKPOINT_EVERY]
    resumed, resumed_losses = train(tmp_path / "killed")
    whole, whole_losses = train(tmp_path / "whole")
    assert len(whole_losses) == 6 and resumed_losses == whole_losses
    a, b = resumed.state_dict(), whole.state_dict()
    assert a.keys() == b.keys()
    for k in a:
        torch.testing.assert_close(a[k], b[k], rtol=0, atol=0, msg=k)
    assert [s for s, _ in checkpoints(tmp_path / "whole")] == [4, 6]   # the last two kept
