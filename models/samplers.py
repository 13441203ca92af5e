"""Samplers: diffusers schedulers built on our β, and one generic reverse-diffusion loop.

``make_scheduler(kind, betas)`` returns a stock diffusers scheduler (DDIM, DDPM,
DPM-Solver++ or UniPC) whose training schedule is exactly ``betas``. ``sample`` drives any
of them with a plain callable ``eps_model(x_t, t, cond, adapter_features) -> ε̂`` so that
neither side knows about the other (diffusers' model/scheduler split). TYP samples with
DDIM for 200 steps ("Inference of generation and post-processing").

Conditioning that does not change across steps — y^f and the adapter features
F_c = F_AD(x^f_{e'}) of TYP Eq. 5 — is computed once by the caller and passed in;
the loop only hands it on.
"""
from __future__ import annotations

import inspect
import math
import numbers
from typing import Any, Callable

import numpy as np
import torch
import diffusers
from diffusers.schedulers.scheduling_utils import SchedulerMixin

from typ.errors import TypError
from typ.registry import SAMPLERS

__all__ = ["SCHEDULERS", "EpsModel", "make_scheduler", "sample"]

WHERE = "sampler"

EpsModel = Callable[[torch.Tensor, torch.Tensor, Any, Any], torch.Tensor]
"""eps_model(x_t (B, ...), t (B,) int64, cond, adapter_features) -> ε̂ shaped like x_t."""

#: the diffusers scheduler class and latent options of every sampler of :data:`typ.registry.SAMPLERS`
SCHEDULERS: dict[str, tuple[type[SchedulerMixin], dict[str, Any]]] = {
    name: (getattr(diffusers, spec.scheduler), dict(spec.latent)) for name, spec in SAMPLERS.items()}
PREDICTION_TYPES = ("epsilon", "sample", "v_prediction")
FLOAT_DTYPES = (torch.float32, torch.float16, torch.bfloat16, torch.float64)


def _check_betas(betas: object, num_train_timesteps: int | None) -> np.ndarray:
    try:
        if isinstance(betas, torch.Tensor):
            betas = betas.double().cpu().numpy()
        b = np.asarray(betas, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypError(WHERE, "betas", "a 1-D array of numbers β_1..β_T", type(betas).__name__) from None
    if b.ndim != 1 or b.size == 0:
        raise TypError(WHERE, "betas", "a non-empty 1-D array of β_1..β_T", b.shape)
    if not np.all(np.isfinite(b)):
        raise TypError(WHERE, "betas", "finite values (no NaN/Inf)", b[~np.isfinite(b)][:5])
    if not np.all((b > 0.0) & (b < 1.0)):
        raise TypError(WHERE, "betas", "values in (0, 1)", b[~((b > 0.0) & (b < 1.0))][:5])
    if num_train_timesteps is not None and num_train_timesteps != b.size:
        # diffusers would silently index past or short of trained_betas
        raise TypError(WHERE, "betas", f"length num_train_timesteps = {num_train_timesteps}", b.size)
    # diffusers keeps ᾱ in float32: once it rounds to 0, x̂_0 divides by √ᾱ = 0 and every
    # sample turns NaN, which would surface only after the whole sampling loop
    abar_last = np.prod(1.0 - b.astype(np.float32), dtype=np.float32)
    if not abar_last > 0.0:
        raise TypError(WHERE, "betas", "a schedule whose ᾱ_T = ∏(1 - β) stays > 0 in float32 "
                       "(diffusers' precision)", f"ᾱ_T = {np.prod(1.0 - b):.3g}")
    return b


def make_scheduler(
    kind: str,
    betas: np.ndarray | torch.Tensor,
    *,
    prediction_type: str = "epsilon",
    num_train_timesteps: int | None = None,
    timestep_spacing: str = "trailing",
    **options: Any,
) -> SchedulerMixin:
    """A diffusers scheduler of ``kind`` ("ddim", "ddpm", "dpmsolver++", "unipc") on ``betas``.

    betas: β_1..β_T, shape (T,), finite, in (0, 1); the scheduler gets ``trained_betas=betas``
    and ``num_train_timesteps=T``. num_train_timesteps: if given, must equal T (checked here,
    since diffusers does not). timestep_spacing: "trailing" (default) so the first step is at
    t = T-1, where the loop's N(0, I) start is the forward marginal. options: further keyword
    arguments of the diffusers class (e.g. ``solver_order``, ``set_alpha_to_one``).
    """
    if kind not in SCHEDULERS:
        raise TypError(WHERE, "kind", f"one of {sorted(SCHEDULERS)}", kind)
    if num_train_timesteps is not None and (
        not isinstance(num_train_timesteps, numbers.Integral) or isinstance(num_train_timesteps, bool)
    ):
        raise TypError(WHERE, "num_train_timesteps", "an integer", num_train_timesteps)
    b = _check_betas(betas, num_train_timesteps)
    if prediction_type not in PREDICTION_TYPES:
        raise TypError(WHERE, "prediction_type", f"one of {list(PREDICTION_TYPES)}", prediction_type)
    if timestep_spacing not in ("leading", "trailing", "linspace"):
        raise TypError(WHERE, "timestep_spacing", "one of ['leading', 'linspace', 'trailing']", timestep_spacing)
    cls, defaults = SCHEDULERS[kind]
    accepted = set(inspect.signature(cls.__init__).parameters) - {"self", "trained_betas", "num_train_timesteps"}
    accepted -= {"beta_start", "beta_end", "beta_schedule"}  # superseded by trained_betas
    for key in options:
        if key not in accepted:
            raise TypError(WHERE, f"{kind}.{key}", f"a keyword argument of {cls.__name__}", key)
    config = {
        **defaults,
        **options,
        "trained_betas": b,
        "num_train_timesteps": int(b.size),
        "prediction_type": prediction_type,
        "timestep_spacing": timestep_spacing,
    }
    return cls(**config)


def _positive_int(value: object) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool) and value >= 1


def _fresh(features: Any) -> Any:
    """A new container holding the same tensors: diffusers' UNet pops from
    ``down_intrablock_additional_residuals``, so each step must get its own list."""
    if isinstance(features, (list, tuple)):
        return list(features)
    if isinstance(features, dict):
        return dict(features)
    return features


@torch.no_grad()
def sample(
    eps_model: EpsModel,
    scheduler: SchedulerMixin,
    *,
    shape: tuple[int, ...],
    num_steps: int,
    generator: torch.Generator | None,
    cond: Any = None,
    adapter_features: Any = None,
    dtype: torch.dtype = torch.float32,
    device: str | torch.device = "cpu",
    eta: float = 0.0,
) -> torch.Tensor:
    """Run the reverse process from x_T ~ N(0, I) and return x_0 of ``shape`` in ``dtype``.

    eps_model: returns the scheduler's ``prediction_type`` (ε̂ by default) for (x_t, t (B,)).
    shape: (B, C, ...) — the batch is sampled at once. num_steps: sampler steps (<= T).
    generator: seeds x_T (drawn in float32, then cast, so every dtype starts from the same
    noise) and the stochastic steps of DDPM / DDIM with eta > 0. cond, adapter_features:
    passed to ``eps_model`` unchanged every step (a list/tuple/dict of adapter features is
    passed as a fresh container each step). dtype: what ``eps_model`` is given and what is
    returned; between steps x_t stays in float32 (float64 if asked), the scheduler's
    arithmetic being cheap next to the model. eta: DDIM's η (0 = deterministic); DDIM only.
    Raises FloatingPointError if the result holds NaN or Inf.
    """
    name = type(scheduler).__name__
    if not isinstance(scheduler, SchedulerMixin) or not hasattr(scheduler, "step"):
        raise TypError(WHERE, "scheduler", "a diffusers scheduler from make_scheduler", name)
    if not callable(eps_model):
        raise TypError(WHERE, "eps_model", "a callable eps_model(x_t, t, cond, adapter_features)", eps_model)
    shape = tuple(shape)
    if len(shape) < 2 or not all(_positive_int(s) for s in shape):
        # diffusers' DDPM and UniPC steps index a channel axis
        raise TypError(WHERE, "shape", "a tuple of >= 2 positive integers (B, C, ...)", shape)
    train_steps = int(scheduler.config.num_train_timesteps)
    if not _positive_int(num_steps) or num_steps > train_steps:
        raise TypError(WHERE, "num_steps", f"an integer in [1, {train_steps}]", num_steps)
    if dtype not in FLOAT_DTYPES:
        raise TypError(WHERE, "dtype", f"one of {[str(d) for d in FLOAT_DTYPES]}", dtype)
    step_params = inspect.signature(scheduler.step).parameters
    if not (isinstance(eta, numbers.Real) and math.isfinite(eta) and eta >= 0.0):
        raise TypError(WHERE, "eta", "a finite number >= 0", eta)
    if eta != 0.0 and "eta" not in step_params:
        raise TypError(WHERE, "eta", f"0 for {name} (η applies to DDIM only)", eta)

    extra: dict[str, Any] = {}
    if "eta" in step_params:
        extra["eta"] = float(eta)
    if "generator" in step_params:
        extra["generator"] = generator

    # the schedule stays on the CPU (diffusers keeps its sigmas there too): reading a step's t
    # needs no device sync, and only x_t and the model's inputs live on ``device``
    scheduler.set_timesteps(int(num_steps))
    # x_t is carried in float32 whatever the model's dtype: in bfloat16 (8-bit mantissa) the
    # small per-step updates round away and the sample drifts (DDPM, 1000 steps: mean -0.13).
    state_dtype = torch.float64 if dtype == torch.float64 else torch.float32
    noise_device = generator.device if generator is not None else device
    x = torch.randn(shape, generator=generator, dtype=torch.float32, device=noise_device)
    x = (x * scheduler.init_noise_sigma).to(device=device, dtype=state_dtype)
    batch = shape[0]
    for t in scheduler.timesteps:
        t_batch = torch.full((batch,), int(t), dtype=torch.long, device=device)
        model_input = scheduler.scale_model_input(x, t).to(dtype)
        eps = eps_model(model_input, t_batch, cond, _fresh(adapter_features))
        if not isinstance(eps, torch.Tensor) or eps.shape != x.shape:
            got = getattr(eps, "shape", eps)
            raise TypError(WHERE, "eps_model output", f"a tensor of shape {tuple(x.shape)}", got)
        x = scheduler.step(eps.to(state_dtype), t, x, **extra).prev_sample

    x = x.to(dtype)
    finite = torch.isfinite(x)
    if not bool(finite.all()):
        bad = int((~finite).sum())
        raise FloatingPointError(
            f"{name} sampling with {num_steps} steps in {dtype} produced {bad} non-finite values "
            f"(NaN/Inf) out of {x.numel()}; try float32, fewer steps or a checked schedule"
        )
    return x
