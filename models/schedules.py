"""Noise schedules β_1..β_T for the diffusion forward process, selectable by name.

The eight schedules compared by Aghanouri & Olaverri-Monreal (LiDAR DDPM, §III-A):
constant, linear and quadratic (Ho et al. 2020), cosine² (Nichol & Dhariwal 2021),
sigmoid (Jabri et al. 2022), hyperbolic (Sohl-Dickstein et al. 2015), and the paper's
own time-dependent exponential (Eq. 1) and ramp (Eq. 2–3).

Conventions: ``betas(name, T)`` is a float64 array of shape ``(T,)``; entry ``k``
(0-based) is the paper's β_{k+1}, so ``alphas_cumprod(b)[k]`` is ᾱ_{k+1} = ∏_{i≤k+1} (1 - β_i).
Every schedule returns β in (0, 1), so ᾱ is strictly decreasing and positive (until it
underflows float64, which for the defaults needs T in the tens of thousands).

The LiDAR DDPM paper prints no numeric hyper-parameters (its Fig. 2 only marks them);
where a constant is open we take the one its cited source uses, and say so per schedule.
"""
from __future__ import annotations

import inspect
import math
import numbers
from typing import Callable

import numpy as np

from typ import registry
from typ.errors import TypError

__all__ = ["SCHEDULES", "alphas_cumprod", "betas"]

WHERE = "noise schedule"
MIN_BETA = 1e-8
MAX_BETA = 0.999


def _probability(name: str, field: str, value: object, *, upper_inclusive: bool = False) -> float:
    """``value`` as a float in (0, 1) (or (0, 1] with ``upper_inclusive``), else TypError."""
    ok = isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        value = float(value)
        ok = 0.0 < value and (value <= 1.0 if upper_inclusive else value < 1.0)
    if not ok:
        interval = "(0, 1]" if upper_inclusive else "(0, 1)"
        raise TypError(WHERE, f"{name}.{field}", f"a finite number in {interval}", value)
    return value


def _real(name: str, field: str, value: object) -> float:
    if not isinstance(value, numbers.Real) or isinstance(value, bool) or not math.isfinite(value):
        raise TypError(WHERE, f"{name}.{field}", "a finite number", value)
    return float(value)


def _from_alphas_cumprod(abar: np.ndarray, max_beta: float) -> np.ndarray:
    """β_t = 1 - ᾱ_t / ᾱ_{t-1} from ``abar`` = ᾱ_0..ᾱ_T (ᾱ_0 = 1), clipped to [MIN_BETA, max_beta].

    The upper clip is part of the defining recipe (Nichol & Dhariwal): ᾱ_T = 0 gives β_T = 1.
    The lower clip only guards the cancellation in 1 - ratio, where a tiny first β can round
    to 0 in float64 for very large T.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        b = 1.0 - abar[1:] / abar[:-1]
    b = np.where(np.isfinite(b), b, max_beta)
    return np.clip(b, MIN_BETA, max_beta)


def constant(num_steps: int, *, beta: float = 0.02) -> np.ndarray:
    """β_t = β for all t. Default 0.02: Ho et al.'s ``const`` schedule uses their β_end."""
    beta = _probability("constant", "beta", beta)
    return np.full(num_steps, beta, dtype=np.float64)


def linear(num_steps: int, *, beta_start: float = 1e-4, beta_end: float = 0.02) -> np.ndarray:
    """β_t = β_start + (β_end - β_start)(t-1)/(T-1), t = 1..T (Ho et al.; T = 1 gives β_start)."""
    beta_start = _probability("linear", "beta_start", beta_start)
    beta_end = _probability("linear", "beta_end", beta_end)
    return np.linspace(beta_start, beta_end, num_steps, dtype=np.float64)


def quadratic(num_steps: int, *, beta_start: float = 1e-4, beta_end: float = 0.02) -> np.ndarray:
    """β_t = (√β_start + (√β_end - √β_start)(t-1)/(T-1))², t = 1..T (Ho et al.'s ``quad``)."""
    beta_start = _probability("quadratic", "beta_start", beta_start)
    beta_end = _probability("quadratic", "beta_end", beta_end)
    return np.linspace(math.sqrt(beta_start), math.sqrt(beta_end), num_steps, dtype=np.float64) ** 2


def cosine(num_steps: int, *, s: float = 0.008, max_beta: float = MAX_BETA) -> np.ndarray:
    """Squared cosine (Nichol & Dhariwal Eq. 17): ᾱ_t = f(t)/f(0), f(t) = cos²(((t/T + s)/(1 + s))·π/2).

    β_t = min(1 - ᾱ_t/ᾱ_{t-1}, max_beta) with s = 0.008 and max_beta = 0.999 as in the paper;
    the clip is needed because f(T) = 0 makes β_T = 1.
    """
    s = _real("cosine", "s", s)
    if s < 0.0:
        raise TypError(WHERE, "cosine.s", "an offset >= 0", s)
    max_beta = _probability("cosine", "max_beta", max_beta)
    t = np.arange(num_steps + 1, dtype=np.float64) / num_steps
    f = np.cos((t + s) / (1.0 + s) * math.pi / 2.0) ** 2
    return _from_alphas_cumprod(f / f[0], max_beta)


def sigmoid(
    num_steps: int, *, start: float = -3.0, end: float = 3.0, tau: float = 1.0, max_beta: float = MAX_BETA
) -> np.ndarray:
    """Sigmoid ᾱ of Jabri et al. (RIN, ``sigmoid_schedule``), discretised like cosine².

    γ(u) = (σ(end/τ) - σ((u·(end - start) + start)/τ)) / (σ(end/τ) - σ(start/τ)), u ∈ [0, 1];
    ᾱ_t = γ(t/T), β_t = min(1 - ᾱ_t/ᾱ_{t-1}, max_beta). Defaults start = -3, end = 3, τ = 1
    (RIN's function defaults); γ(1) = 0 makes β_T = 1, hence the clip at 0.999.
    """
    start = _real("sigmoid", "start", start)
    end = _real("sigmoid", "end", end)
    tau = _real("sigmoid", "tau", tau)
    if not end > start:
        raise TypError(WHERE, "sigmoid.end", f"a number > start ({start})", end)
    if not tau > 0.0:
        raise TypError(WHERE, "sigmoid.tau", "a number > 0", tau)
    max_beta = _probability("sigmoid", "max_beta", max_beta)

    def sig(x: np.ndarray | float) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-np.asarray(x, dtype=np.float64)))

    u = np.arange(num_steps + 1, dtype=np.float64) / num_steps
    v_start, v_end = sig(start / tau), sig(end / tau)
    gamma = (v_end - sig((u * (end - start) + start) / tau)) / (v_end - v_start)
    return _from_alphas_cumprod(gamma, max_beta)


def hyperbolic(num_steps: int, *, max_beta: float = MAX_BETA) -> np.ndarray:
    """β_t = 1/(T - t + 1), t = 1..T (Sohl-Dickstein et al.; Ho et al.'s ``jsd``): ᾱ_t = (T - t)/T.

    Signal strength falls linearly; the formula's β_T = 1 is clipped to max_beta = 0.999 so
    that ᾱ_T = 0.001/T stays positive.
    """
    max_beta = _probability("hyperbolic", "max_beta", max_beta)
    b = 1.0 / np.arange(num_steps, 0, -1, dtype=np.float64)
    return np.minimum(b, max_beta)


def time_dependent(num_steps: int, *, beta_start: float = 1e-4, beta_end: float = 0.02) -> np.ndarray:
    """Time-dependent exponential (LiDAR DDPM Eq. 1): β_t = β_start·(β_end/β_start)^timing.

    timing = (t-1)/(T-1) rises linearly over [0, 1] (T = 1 gives timing 0, β = β_start), so
    β runs geometrically from β_start to β_end. The paper prints no endpoints; we use Ho et
    al.'s 1e-4 and 0.02 (ᾱ_T ≈ 0.023 at T = 1000, so x_T is not quite N(0, I)).
    """
    beta_start = _probability("time_dependent", "beta_start", beta_start)
    beta_end = _probability("time_dependent", "beta_end", beta_end)
    timing = np.linspace(0.0, 1.0, num_steps, dtype=np.float64)
    return beta_start * (beta_end / beta_start) ** timing


def ramp(num_steps: int, *, beta_start: float = 1e-4, beta_end: float = 0.02, n: int = 10) -> np.ndarray:
    """Ramp (LiDAR DDPM Eq. 2–3): repeated "flat then linear" segments of length n each.

    With the linear reference β^lin_j = β_start + (β_end - β_start)·j/(T-1), j = 0..T-1 (Eq. 2),
    ramp k (k = 0..L-1, L = T/(2n)) covers 0-based positions 2nk..2nk+2n-1: its constant part
    holds β^lin_{2nk+n} (the first value of its linear part) for n steps, then its linear part
    is β^lin_{2nk+n}, ..., β^lin_{2nk+2n-1}. For n = 10, k = 0 this is Eq. 3's β_10 repeated,
    then β_10..β_19 (Eq. 3 prints the offset as 10k where 2nk is needed to tile [0, T-1]).
    When 2n does not divide T, the last partial ramp's reference index is capped at T-1.
    n = 10 is the segment length Eq. 3 is written with; endpoints as in ``time_dependent``.
    """
    beta_start = _probability("ramp", "beta_start", beta_start)
    beta_end = _probability("ramp", "beta_end", beta_end)
    if not isinstance(n, numbers.Integral) or isinstance(n, bool) or n < 1:
        raise TypError(WHERE, "ramp.n", "an integer segment length >= 1", n)
    n = int(n)
    reference = np.linspace(beta_start, beta_end, num_steps, dtype=np.float64)
    position = np.arange(num_steps)
    linear_from = (position // (2 * n)) * (2 * n) + n
    index = np.minimum(np.maximum(position, linear_from), num_steps - 1)
    return reference[index]


#: config name -> β(T), one function of this module per entry of :data:`typ.registry.SCHEDULES`
SCHEDULES: dict[str, Callable[..., np.ndarray]] = {name: globals()[spec.function]
                                                  for name, spec in registry.SCHEDULES.items()}


def betas(name: str, num_steps: int, **kwargs: object) -> np.ndarray:
    """β_1..β_T of schedule ``name`` as float64 ``(T,)``; ``kwargs`` override its hyper-parameters."""
    if not isinstance(name, str) or name not in SCHEDULES:
        raise TypError(WHERE, "name", f"one of {sorted(SCHEDULES)}", name)
    if not isinstance(num_steps, numbers.Integral) or isinstance(num_steps, bool) or num_steps < 1:
        raise TypError(WHERE, "num_steps", "an integer T >= 1", num_steps)
    schedule = SCHEDULES[name]
    accepted = [p for p in inspect.signature(schedule).parameters if p != "num_steps"]
    for key in kwargs:
        if key not in accepted:
            expected = f"one of {accepted}" if accepted else "no hyper-parameters"
            raise TypError(WHERE, f"{name}.{key}", expected, key)
    out = schedule(int(num_steps), **kwargs)
    if out.shape != (num_steps,) or not np.all((out > 0.0) & (out < 1.0)):
        raise TypError(WHERE, name, "hyper-parameters giving every β in (0, 1)", kwargs)
    return out


def alphas_cumprod(betas: np.ndarray) -> np.ndarray:
    """ᾱ_t = ∏_{i<=t} (1 - β_i) as float64 ``(T,)`` for β of shape ``(T,)`` in (0, 1)."""
    b = np.asarray(betas, dtype=np.float64)
    if b.ndim != 1 or b.size == 0:
        raise TypError(WHERE, "betas", "a non-empty 1-D array", getattr(b, "shape", b))
    if not np.all(np.isfinite(b)) or not np.all((b > 0.0) & (b < 1.0)):
        raise TypError(WHERE, "betas", "finite values in (0, 1)", b[~((b > 0) & (b < 1))][:5])
    return np.cumprod(1.0 - b)
