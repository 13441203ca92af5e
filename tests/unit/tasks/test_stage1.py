"""Stage 1's training maths (Eq. 4): the forward process, the loss in each parameterisation,
the learning-rate curve and the EMA of the weights."""
import math

import numpy as np
import pytest
import torch

from models.schedules import alphas_cumprod, betas
from tasks.training import EMA, diffusion_loss, forward_process, learning_rate, noised_batch


@pytest.fixture(scope="module")
def abar():
    return torch.from_numpy(alphas_cumprod(betas("linear", 1000))).float()


def test_forward_process_is_sqrt_abar_z0_plus_sqrt_one_minus_abar_eps(abar):
    g = torch.Generator().manual_seed(0)
    z0, eps = torch.randn(5, 3, 4, 4, generator=g), torch.randn(5, 3, 4, 4, generator=g)
    t = torch.tensor([0, 1, 250, 700, 999])
    z_t = forward_process(z0, t, eps, abar)
    for i, ti in enumerate(t.tolist()):
        a = abar[ti]
        assert torch.equal(z_t[i], a.sqrt() * z0[i] + (1 - a).sqrt() * eps[i])


def test_noised_batch_is_the_forward_process_of_its_own_draws(abar):
    z0 = torch.randn(7, 2, 4, 4)
    index, t, eps, z_t = noised_batch(np.random.default_rng(3), z0, abar, 4)
    assert torch.equal(z_t, forward_process(z0[index], t, eps, abar))
    again = noised_batch(np.random.default_rng(3), z0, abar, 4)   # a pure function of the generator
    assert all(torch.equal(a, b) for a, b in zip((index, t, eps, z_t), again))


def test_a_zero_output_model_has_loss_mean_eps_squared(abar):
    g = torch.Generator().manual_seed(1)
    eps, z0 = torch.randn(6, 3, 4, 4, generator=g), torch.randn(6, 3, 4, 4, generator=g)
    t = torch.tensor([3, 100, 400, 600, 800, 999])
    loss = diffusion_loss(torch.zeros_like(eps), eps, z0, t, abar, prediction="epsilon", min_snr=0)
    assert float(loss) == pytest.approx(float((eps ** 2).mean()), rel=1e-6)
    # z_0-prediction regresses on z_0, not on ε
    loss = diffusion_loss(torch.zeros_like(eps), eps, z0, t, abar, prediction="sample", min_snr=0)
    assert float(loss) == pytest.approx(float((z0 ** 2).mean()), rel=1e-6)


def test_the_three_parameterisations_agree_on_the_perfect_prediction(abar):
    g = torch.Generator().manual_seed(2)
    eps, z0 = torch.randn(4, 2, 3, 3, generator=g), torch.randn(4, 2, 3, 3, generator=g)
    t = torch.tensor([10, 300, 600, 990])
    a = abar[t].view(-1, 1, 1, 1)
    perfect = {"epsilon": eps, "sample": z0, "v_prediction": a.sqrt() * eps - (1 - a).sqrt() * z0}
    for prediction, output in perfect.items():
        for min_snr in (0.0, 5.0):
            assert float(diffusion_loss(output, eps, z0, t, abar, prediction=prediction, min_snr=min_snr)) < 1e-10


def test_min_snr_weights_in_epsilon_terms(abar):
    """An error δ on ẑ_0 is an error δ·√ᾱ/√(1-ᾱ) on ε̂; Min-SNR-γ weighs the ε error by min(SNR, γ)/SNR,
    so the z_0 loss weight is min(SNR, γ)."""
    t = torch.tensor([50, 900])
    snr = abar[t] / (1 - abar[t])
    z0, eps = torch.zeros(2, 1, 1, 1), torch.zeros(2, 1, 1, 1)
    delta = torch.ones(2, 1, 1, 1)
    got = diffusion_loss(z0 + delta, eps, z0, t, abar, prediction="sample", min_snr=5.0)
    assert float(got) == pytest.approx(float(torch.clamp(snr, max=5.0).mean()), rel=1e-5)


def test_learning_rate_warms_up_then_decays_to_a_tenth():
    lrs = [learning_rate(1.0, s, 100, warmup=10, schedule="cosine", floor=0.1) for s in range(100)]
    assert lrs[0] == pytest.approx(0.1) and lrs[9] == pytest.approx(1.0)
    assert all(a >= b for a, b in zip(lrs[10:], lrs[11:]))
    assert learning_rate(1.0, 100, 100, warmup=10, schedule="cosine", floor=0.1) == pytest.approx(0.1)
    assert learning_rate(1.0, 55, 100, warmup=10, schedule="constant", floor=0.1) == 1.0
    assert learning_rate(2.0, 55, 100, warmup=10, schedule="cosine", floor=0.1) == pytest.approx(
        2.0 * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 0.5))))


def test_learning_rate_without_warm_up_or_floor_is_torchs_cosine_annealing():
    """The SSC networks' schedule: torch's CosineAnnealingLR (T_max = the run), to the last bits
    of its recursive form."""
    p = torch.nn.Parameter(torch.zeros(1))
    opt = torch.optim.Adam([p], lr=0.002)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=150)
    for step in range(150):
        assert learning_rate(0.002, step, 150) == pytest.approx(opt.param_groups[0]["lr"], rel=1e-12, abs=1e-18)
        opt.step()
        sched.step()
    assert learning_rate(0.002, 150, 150) == pytest.approx(0.0, abs=1e-18)


def test_ema_tracks_the_weights_and_copies_buffers():
    net = torch.nn.BatchNorm1d(2)
    ema = EMA(net, decay=0.9)
    with torch.no_grad():
        net.weight.fill_(2.0)
        net.running_mean.fill_(3.0)
    ema.update(net)
    assert torch.allclose(ema.shadow.weight, torch.full((2,), 0.9 * 1.0 + 0.1 * 2.0))
    assert torch.equal(ema.shadow.running_mean, net.running_mean)
    assert not ema.shadow.weight.requires_grad
