"""Noise schedules (models/schedules.py) and time embeddings (models/time_embedding.py).

Hand values are computed here from each defining formula, independently of the module.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from models.schedules import SCHEDULES, alphas_cumprod, betas
from models.time_embedding import FourierTimeEmbedding, SinusoidalTimeEmbedding
from typ.errors import TypError

NAMES = sorted(SCHEDULES)


def test_registry_holds_the_eight_schedules():
    assert set(SCHEDULES) == {
        "constant", "linear", "quadratic", "cosine", "sigmoid", "hyperbolic", "time_dependent", "ramp",
    }


# --- hand values -------------------------------------------------------------------------

def test_constant():
    np.testing.assert_array_equal(betas("constant", 5), [0.02] * 5)
    np.testing.assert_array_equal(betas("constant", 3, beta=0.1), [0.1] * 3)


def test_linear_endpoints_and_midpoint():
    b = betas("linear", 1000)
    assert b[0] == pytest.approx(1e-4, abs=1e-15)
    assert b[-1] == pytest.approx(0.02, abs=1e-15)
    b = betas("linear", 11, beta_start=0.001, beta_end=0.011)
    assert b[5] == pytest.approx(0.006, rel=1e-12)  # β_6 = 0.001 + 0.01·5/10


def test_quadratic():
    b = betas("quadratic", 5, beta_start=0.01, beta_end=0.09)
    # √β runs 0.1, 0.15, 0.2, 0.25, 0.3
    np.testing.assert_allclose(b, [0.01, 0.0225, 0.04, 0.0625, 0.09], rtol=1e-12)


def test_cosine_alphas_cumprod_at_half():
    T, s = 1000, 0.008
    abar = alphas_cumprod(betas("cosine", T))

    def f(t):
        return math.cos((t / T + s) / (1 + s) * math.pi / 2) ** 2

    assert abar[T // 2 - 1] == pytest.approx(f(T / 2) / f(0), rel=1e-10)  # ᾱ_{T/2}
    assert abar[0] == pytest.approx(f(1) / f(0), rel=1e-10)
    assert betas("cosine", T)[-1] == 0.999  # f(T) = 0 -> β_T = 1, clipped


def test_sigmoid_alphas_cumprod():
    T = 1000
    abar = alphas_cumprod(betas("sigmoid", T))
    # γ(1/2) = (σ(3) - σ(0)) / (σ(3) - σ(-3)) = 1/2 by the symmetry of σ
    assert abar[T // 2 - 1] == pytest.approx(0.5, rel=1e-10)
    sig = lambda x: 1 / (1 + math.exp(-x))  # noqa: E731
    gamma = lambda u: (sig(3) - sig(6 * u - 3)) / (sig(3) - sig(-3))  # noqa: E731
    assert abar[249] == pytest.approx(gamma(0.25), rel=1e-10)
    abar = alphas_cumprod(betas("sigmoid", 4, start=-1.0, end=2.0, tau=0.5))
    gamma = lambda u: (sig(4) - sig((3 * u - 1) / 0.5)) / (sig(4) - sig(-2))  # noqa: E731
    assert abar[1] == pytest.approx(gamma(0.5), rel=1e-10)


def test_hyperbolic():
    b = betas("hyperbolic", 10)
    np.testing.assert_allclose(b[:9], [1 / (10 - t + 1) for t in range(1, 10)], rtol=1e-12)
    assert b[-1] == 0.999
    abar = alphas_cumprod(b)
    np.testing.assert_allclose(abar[:9], [(10 - t) / 10 for t in range(1, 10)], rtol=1e-12)  # ᾱ_t = (T-t)/T


def test_time_dependent_eq1():
    b = betas("time_dependent", 5)
    # β = 1e-4 · 200^timing, timing = 0, 1/4, 1/2, 3/4, 1
    assert b[0] == pytest.approx(1e-4, rel=1e-12)
    assert b[2] == pytest.approx(1e-4 * math.sqrt(200), rel=1e-12)
    assert b[3] == pytest.approx(1e-4 * 200 ** 0.75, rel=1e-12)
    assert b[4] == pytest.approx(0.02, rel=1e-12)
    b = betas("time_dependent", 3, beta_start=0.001, beta_end=0.1)
    np.testing.assert_allclose(b, [0.001, 0.01, 0.1], rtol=1e-12)


def test_ramp_eq2_eq3():
    T, n = 40, 10
    b = betas("ramp", T, beta_start=0.001, beta_end=0.04, n=n)
    lin = lambda j: 0.001 + (0.04 - 0.001) / (T - 1) * j  # noqa: E731  (Eq. 2)
    np.testing.assert_allclose(b[0:10], [lin(10)] * 10, rtol=1e-12)  # constant part, ramp 0
    np.testing.assert_allclose(b[10:20], [lin(j) for j in range(10, 20)], rtol=1e-12)  # linear part
    np.testing.assert_allclose(b[20:30], [lin(30)] * 10, rtol=1e-12)  # constant part, ramp 1
    np.testing.assert_allclose(b[30:40], [lin(j) for j in range(30, 40)], rtol=1e-12)
    assert b[-1] == pytest.approx(0.04, rel=1e-12)
    # partial last ramp (2n does not divide T): reference index capped at T-1
    b = betas("ramp", 25, n=10)
    assert b[20] == b[24] == pytest.approx(0.02, rel=1e-12)


# --- properties --------------------------------------------------------------------------

def _check_valid(b: np.ndarray, T: int) -> None:
    assert b.dtype == np.float64 and b.shape == (T,)
    assert np.all(np.isfinite(b)) and np.all(b > 0) and np.all(b < 1)
    abar = alphas_cumprod(b)
    assert np.all(np.isfinite(abar)) and np.all(abar > 0)
    assert np.all(np.diff(abar) < 0) and abar[0] < 1


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("T", [1, 2, 1000])
def test_valid_at_edges(name, T):
    _check_valid(betas(name, T), T)


@pytest.mark.parametrize("name", NAMES)
@settings(max_examples=40, deadline=None)
@given(T=st.integers(min_value=1, max_value=2000))
def test_valid_for_any_T(name, T):
    _check_valid(betas(name, T), T)


# --- validation --------------------------------------------------------------------------

def test_unknown_name_lists_valid_names():
    with pytest.raises(TypError) as err:
        betas("cosine2", 10)
    assert all(name in str(err.value) for name in NAMES)


@pytest.mark.parametrize("T", [0, -3, 1.5, True, "10", None])
def test_bad_num_steps(T):
    with pytest.raises(TypError, match="num_steps"):
        betas("linear", T)


@pytest.mark.parametrize(
    "name, kwargs, field",
    [
        ("linear", {"beta_max": 0.02}, "linear.beta_max"),
        ("hyperbolic", {"s": 0.1}, "hyperbolic.s"),
        ("linear", {"beta_start": 0.0}, "linear.beta_start"),
        ("quadratic", {"beta_end": 1.0}, "quadratic.beta_end"),
        ("constant", {"beta": float("nan")}, "constant.beta"),
        ("time_dependent", {"beta_start": -1e-4}, "time_dependent.beta_start"),
        ("ramp", {"beta_end": "0.02"}, "ramp.beta_end"),
        ("ramp", {"n": 0}, "ramp.n"),
        ("ramp", {"n": 2.5}, "ramp.n"),
        ("cosine", {"s": -0.1}, "cosine.s"),
        ("cosine", {"max_beta": 1.5}, "cosine.max_beta"),
        ("sigmoid", {"tau": 0.0}, "sigmoid.tau"),
        ("sigmoid", {"start": 3.0, "end": -3.0}, "sigmoid.end"),
    ],
)
def test_bad_kwargs(name, kwargs, field):
    with pytest.raises(TypError) as err:
        betas(name, 10, **kwargs)
    assert err.value.field == field


@pytest.mark.parametrize("bad", [[0.1, float("nan")], [0.1, 1.0], [0.0, 0.1], [[0.1]], []])
def test_alphas_cumprod_rejects_bad_betas(bad):
    with pytest.raises(TypError):
        alphas_cumprod(np.array(bad))


# --- time embeddings ---------------------------------------------------------------------

def test_sinusoidal_at_zero_and_by_hand():
    emb = SinusoidalTimeEmbedding(dim=8)(torch.tensor([0, 1]))
    assert emb.shape == (2, 8) and emb.dtype == torch.float32
    torch.testing.assert_close(emb[0], torch.tensor([0.0] * 4 + [1.0] * 4))  # sin 0 | cos 0
    # h = 4, shift 1: ω_i = 10000^(-i/3) = 1, 10^(-4/3), 10^(-8/3), 1e-4
    w = [10000 ** (-i / 3) for i in range(4)]
    hand = [math.sin(x) for x in w] + [math.cos(x) for x in w]
    torch.testing.assert_close(emb[1], torch.tensor(hand), rtol=1e-6, atol=1e-7)
    flipped = SinusoidalTimeEmbedding(dim=8, flip_sin_to_cos=True)(torch.tensor([1]))
    torch.testing.assert_close(flipped[0], torch.tensor(hand[4:] + hand[:4]), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("flip, shift", [(False, 1.0), (True, 0.0), (True, 1.0)])
def test_sinusoidal_matches_diffusers(flip, shift):
    from diffusers.models.embeddings import get_timestep_embedding

    t = torch.tensor([0, 3, 17, 250, 999])
    ours = SinusoidalTimeEmbedding(dim=64, flip_sin_to_cos=flip, downscale_freq_shift=shift)(t)
    theirs = get_timestep_embedding(t, 64, flip_sin_to_cos=flip, downscale_freq_shift=shift)
    torch.testing.assert_close(ours, theirs)


def test_fourier_eq4_by_hand():
    d, N, t = 4, 2, 3.0
    emb = FourierTimeEmbedding(dim=d, harmonics=N)(torch.tensor([0, 3]))
    assert emb.shape == (2, 4)
    torch.testing.assert_close(emb[0], torch.tensor([0.0, 0.0, 1.5, 1.5]))  # cos series: 1 + 1/2
    for i in range(d // 2):
        theta = t / 10000 ** (2 * i / d)  # ω_0 = 1, ω_1 = 1/100
        sin_series = math.sin(theta) + math.sin(2 * theta) / 2
        cos_series = math.cos(theta) + math.cos(2 * theta) / 2
        assert emb[1, i].item() == pytest.approx(sin_series, abs=1e-6)
        assert emb[1, d // 2 + i].item() == pytest.approx(cos_series, abs=1e-6)
        eq4 = sum((math.sin(n * theta) + math.cos(n * theta)) / n for n in range(1, N + 1))
        assert (emb[1, i] + emb[1, d // 2 + i]).item() == pytest.approx(eq4, abs=1e-6)


def test_fourier_with_one_harmonic_is_sinusoidal():
    t = torch.tensor([0, 5, 123, 999])
    torch.testing.assert_close(
        FourierTimeEmbedding(dim=32, harmonics=1)(t),
        SinusoidalTimeEmbedding(dim=32, downscale_freq_shift=0.0)(t),
    )


@pytest.mark.parametrize("cls", [SinusoidalTimeEmbedding, FourierTimeEmbedding])
def test_embedding_validation(cls):
    with pytest.raises(TypError, match="dim"):
        cls(dim=7)
    with pytest.raises(TypError, match="timesteps"):
        cls(dim=8)(torch.tensor(3))
    with pytest.raises(TypeError):
        cls(8)  # keyword-only
    with pytest.raises(TypError, match="harmonics"):
        FourierTimeEmbedding(dim=8, harmonics=0)
