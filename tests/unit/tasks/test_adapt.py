"""Adaptation stage (Eq. 8–10): frozen target parts, shared frozen codebook, divergence stop."""
import numpy as np
import pytest
import torch

from models.losses import focal_loss
from models.vqvae import BEVVQVAE
from tasks import adapt
from tasks.training import TrainingDiverged
from tasks.voxel_data import ViewSet
from typ.config import config_from_dict
from typ.voxel import Grid

GRID = Grid((-16.0, 16.0), (-16.0, 16.0), (-3.0, 1.0), (32, 32, 4))


def _views(seed, density):
    rng = np.random.default_rng(seed)
    records = []
    for _ in range(4):
        occ = np.argwhere(rng.random(GRID.shape) < density)
        records.append((occ, np.zeros((0, 2), dtype=np.intp)))
    return ViewSet(GRID, [("s", str(i), "000000") for i in range(4)], records)


def _target():
    torch.manual_seed(0)
    return BEVVQVAE(in_channels=4, latent_channels=3, block_out_channels=(8, 8, 8), num_codes=16, norm_num_groups=4)


def _cfg(**kw):
    return config_from_dict({"adapt": {"epochs": 1, "batch_size": 2, "checkpoint_every": 1, "disc_width": 8, **kw}}).adapt


def test_only_source_encoder_decoder_learn(tmp_path):
    target = _target()
    before_target = {k: v.clone() for k, v in target.state_dict().items()}
    source, disc = adapt.train(_cfg(), target, _views(1, 0.15), _views(2, 0.03), out=tmp_path,
                               log_fn=lambda values, step: None)
    for k, v in target.state_dict().items():  # E_tgt, Q_tgt, G_tgt frozen
        assert torch.equal(v, before_target[k]), k
    # the codebook is Q_tgt, shared and unchanged; encoder and decoder moved
    assert torch.equal(source.codebook, target.codebook)
    assert not torch.equal(source.net.encoder.conv_in.weight, target.net.encoder.conv_in.weight)
    assert not torch.equal(source.net.decoder.conv_out.weight, target.net.decoder.conv_out.weight)
    scores = adapt.translation_scores(source, target, _views(3, 0.15), _views(4, 0.03), n=4)
    assert np.isfinite(scores["jsd_r2dm"]) and 0 <= scores["rec_iou_source"] <= 1
    assert 0 <= adapt.discriminator_accuracy(disc, source, target, _views(3, 0.15), _views(4, 0.03), n=4) <= 1


def test_exploding_discriminator_stops_without_a_model(tmp_path):
    with pytest.raises(TrainingDiverged, match="discriminator loss .* > max_disc_loss"):
        adapt.train(_cfg(max_disc_loss=1e-6), _target(), _views(1, 0.15), _views(2, 0.03), out=tmp_path,
                    log_fn=lambda values, step: None)
    assert not (tmp_path / "source_vq").exists() and not (tmp_path / "discriminator").exists()


# ---------------------------------------------------------------- Eq. 8–10 as functions, on stubs
# Features separable by construction: E_tgt(x) = x + 1 and E_src(x) = x - 1 (learnable shifts, so
# a gradient that reaches an encoder shows), and D a linear critic of the features' mean.


class Shifted(torch.nn.Module):
    """A stand-in encoder: x^f = x + shift."""

    def __init__(self, shift: float):
        super().__init__()
        self.shift = torch.nn.Parameter(torch.tensor(shift))

    def encode_pre_quant(self, x):
        return x + self.shift


class Critic(torch.nn.Module):
    """A stub D: ``scale`` times (the features' mean - ``offset``), one score per map."""

    def __init__(self, scale: float, offset: float = 0.0):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.tensor(scale))
        self.offset = offset

    def forward(self, latents):
        return self.scale * (latents.mean(dim=(1, 2, 3)) - self.offset)


def _batches(target_value=1.0, source_value=-1.0):
    return torch.full((2, 4, 8, 8), target_value), torch.full((2, 4, 8, 8), source_value)


def test_discriminator_loss_takes_target_through_e_tgt_as_real_and_source_through_e_src_as_fake():
    x_tgt, x_src = _batches()  # E_tgt(x_tgt) = 2, E_src(x_src) = -2
    e_tgt, e_src = Shifted(1.0), Shifted(-1.0)
    # a critic scoring target +2 and source -2 is beyond both margins; its negation pays 1 + 2 on each side
    assert adapt.discriminator_loss(Critic(1.0), e_tgt, e_src, x_tgt, x_src).item() == 0.0
    assert adapt.discriminator_loss(Critic(-1.0), e_tgt, e_src, x_tgt, x_src).item() == pytest.approx(6.0)
    # the encoders swapped would score both sides 0 and pay 1 + 1
    # inside the margins (scores ±0.5) D learns to separate more: its gradient raises the scale;
    # the encoders are constants of L_D
    d = Critic(0.25)
    loss = adapt.discriminator_loss(d, e_tgt, e_src, x_tgt, x_src)
    assert loss.item() == pytest.approx(1.0)
    loss.backward()
    assert float(d.scale.grad) == pytest.approx(-4.0)  # d/ds [relu(1 - 2s) + relu(1 - 2s)]
    assert e_tgt.shift.grad is None and e_src.shift.grad is None


def test_discriminator_accuracy_is_one_for_a_perfect_critic_and_zero_for_its_negation():
    # target views denser than source ones, and the offset between them: only the right encoder on
    # the right views puts every view on its side (swapping either gives 0.5)
    x_tgt, x_src = _batches(0.5, 0.1)  # features 1.5 and -0.9; offset 1.3 sits between 1.5 and 0.1 + 1
    e_tgt, e_src = Shifted(1.0), Shifted(-1.0)
    assert adapt.batch_accuracy(Critic(1.0, 1.3), e_tgt, e_src, x_tgt, x_src) == 1.0
    assert adapt.batch_accuracy(Critic(-1.0, 1.3), e_tgt, e_src, x_tgt, x_src) == 0.0
    assert adapt.batch_accuracy(Critic(1.0, 1.3), e_tgt, e_src, x_src, x_tgt) == 0.5
    # the stage's figure on view sets: the first n views of each, source views through encoder_vq
    dense, sparse = _views(5, 0.5), _views(6, 0.1)
    assert adapt.discriminator_accuracy(Critic(1.0, 1.3), e_src, e_tgt, sparse, dense, n=3) == 1.0
    assert adapt.discriminator_accuracy(Critic(-1.0, 1.3), e_src, e_tgt, sparse, dense, n=3) == 0.0


def _source_vq():
    """E_src, G_src as the stage starts them, from a target whose codebook holds codes (k-means on a
    first batch): an all-zero codebook would quantize every cell to 0 and cut every gradient through Q."""
    target = _target()
    target(torch.rand(2, 4, 32, 32).round())
    return adapt.source_from_target(target)


def _source_views_batch():
    torch.manual_seed(1)
    return (torch.rand(2, 4, 32, 32) < 0.15).float()


def test_generator_loss_parts_are_eq9_and_eq10_on_the_source_batch():
    source, x = _source_vq(), _source_views_batch()
    d = Critic(3.0, 0.2)
    g = adapt.generator_loss(d, source, x, gamma=2.0)
    with torch.no_grad():
        f = source.encode_pre_quant(x)
        idx = torch.cdist(f.permute(0, 2, 3, 1).reshape(-1, 3), source.codebook).argmin(dim=1)
        code = source.codebook[idx].reshape(2, 8, 8, 3).permute(0, 3, 1, 2)
        logits = source.decode_logits(code)  # G_src(Q_tgt(E_src(x)))
    assert float(g.adv) == pytest.approx(-float(d(f).mean()), rel=1e-6)                 # Eq. 10
    assert float(g.commit) == pytest.approx(float(((f - code) ** 2).mean()), rel=1e-5)  # ||sg[x^z] - E_src(x)||²
    # L_rec as in Eq. 1 (models.vqvae): the focal loss summed over M voxels per h·w·c latent elements
    ratio = (4 * 32 * 32) / (3 * 8 * 8)
    assert float(g.rec) == pytest.approx(float(focal_loss(logits, x, gamma=2.0)) * ratio, rel=1e-4)
    assert float(g.total) == pytest.approx(float(g.rec + g.adv + g.commit), rel=1e-6)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_generator_steps_with_d_frozen_raise_ds_score_of_source_features(sign):
    """Eq. 10's sign: E_src, G_src descending L_vq move the source features to where D scores high
    (whichever way that is)."""
    source, x = _source_vq(), _source_views_batch()
    d = Critic(20.0 * sign).requires_grad_(False)
    trainable = [p for p in source.parameters() if p.requires_grad]
    opt = torch.optim.Adam(trainable, lr=1e-3)
    with torch.no_grad():
        before = float(d(source.encode_pre_quant(x)).mean())
    for _ in range(3):
        loss = adapt.generator_loss(d, source, x, gamma=2.0).total
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        after = float(d(source.encode_pre_quant(x)).mean())
    assert after > before + 0.3  # (it rises by about 0.6 either way)


def test_the_commitment_term_pulls_e_src_to_its_code_and_leaves_the_code_alone():
    source, x = _source_vq(), _source_views_batch()
    source.quantizer.requires_grad_(True)  # (frozen in the stage) a gradient that reached the code would show
    seen = {}

    def keep(module, inputs, output):
        output.retain_grad()
        seen["f"] = output

    source.net.quant_conv.register_forward_hook(keep)  # x^f = E_src(x)
    g = adapt.generator_loss(Critic(1.0), source, x, gamma=2.0)
    g.commit.backward()
    f = seen["f"].detach()
    idx = torch.cdist(f.permute(0, 2, 3, 1).reshape(-1, 3), source.codebook).argmin(dim=1)
    code = source.codebook.detach()[idx].reshape(2, 8, 8, 3).permute(0, 3, 1, 2)
    assert torch.allclose(seen["f"].grad, 2 * (f - code) / f.numel(), atol=1e-7)  # towards the code, weight 1
    assert float(seen["f"].grad.abs().sum()) > 0
    assert all(p.grad is None or not p.grad.any() for p in source.quantizer.parameters())
    assert all(p.grad is not None for p in source.net.encoder.parameters())  # it reaches E_src's weights
    assert all(p.grad is None for p in source.net.decoder.parameters())      # and nothing reaches G_src
