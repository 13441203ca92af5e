"""Fixed (parameter-free) time-step embeddings: (B,) timesteps -> (B, dim) float32.

Two choices from LiDAR DDPM §III-B: the sinusoidal embedding (Vaswani et al., in the
DDPM/diffusers form) and the Fourier-series embedding of its Eq. 4. Like diffusers'
``Timesteps``, these modules hold no weights; the learnable MLP that lifts the embedding
("transformed into higher dimensions using learnable linear layers") belongs to the network.
"""
from __future__ import annotations

import math

import torch
from torch import nn

from typ.errors import TypError

__all__ = ["FourierTimeEmbedding", "SinusoidalTimeEmbedding"]

WHERE = "time embedding"


def _check_dim(dim: object) -> int:
    if not isinstance(dim, int) or isinstance(dim, bool) or dim < 2 or dim % 2:
        raise TypError(WHERE, "dim", "an even integer >= 2", dim)
    return dim


def _check_timesteps(timesteps: torch.Tensor) -> torch.Tensor:
    if not isinstance(timesteps, torch.Tensor) or timesteps.ndim != 1:
        raise TypError(WHERE, "timesteps", "a 1-D tensor of shape (B,)", getattr(timesteps, "shape", timesteps))
    return timesteps.to(torch.float32)


class SinusoidalTimeEmbedding(nn.Module):
    """Sinusoidal embedding, same values as ``diffusers.models.embeddings.get_timestep_embedding``.

    With h = dim/2 and frequencies ω_i = max_period^(-i/(h - downscale_freq_shift)), i = 0..h-1:
    emb = [sin(t·ω) | cos(t·ω)] (or [cos | sin] with ``flip_sin_to_cos``). The defaults
    (shift 1, sin first) are Ho et al.'s DDPM; diffusers' UNet2DModel uses shift 0 and flip.
    """

    def __init__(
        self,
        *,
        dim: int,
        max_period: float = 10000.0,
        flip_sin_to_cos: bool = False,
        downscale_freq_shift: float = 1.0,
    ) -> None:
        """dim: output width (even); max_period: longest wavelength / 2π; the rest as in diffusers."""
        super().__init__()
        self.dim = _check_dim(dim)
        half = dim // 2
        if not half - downscale_freq_shift > 0:
            raise TypError(WHERE, "dim", f"dim/2 > downscale_freq_shift ({downscale_freq_shift})", dim)
        if not max_period > 1.0:
            raise TypError(WHERE, "max_period", "a number > 1", max_period)
        self.flip_sin_to_cos = bool(flip_sin_to_cos)
        exponent = -math.log(max_period) * torch.arange(half, dtype=torch.float32) / (half - downscale_freq_shift)
        self.register_buffer("frequencies", torch.exp(exponent), persistent=False)

    def forward(self, timesteps: torch.Tensor) -> torch.Tensor:
        """timesteps (B,) int or float -> (B, dim) float32."""
        phase = _check_timesteps(timesteps)[:, None] * self.frequencies[None, :]
        sin, cos = torch.sin(phase), torch.cos(phase)
        return torch.cat([cos, sin] if self.flip_sin_to_cos else [sin, cos], dim=-1)


class FourierTimeEmbedding(nn.Module):
    """Fourier-series embedding of LiDAR DDPM Eq. 4.

    Eq. 4: TE(t, i) = Σ_{n=1..N} (1/n)·(sin(n·t·ω_i) + cos(n·t·ω_i)), ω_i = 10000^(-2i/d),
    i = 0..d/2-1 (wavelengths 2π .. 20000π, as the paper states). The paper has d/2 indices i
    for a d-wide embedding; we fill the d channels the way the sinusoidal embedding does, with
    the sine series S_i = Σ sin(n·t·ω_i)/n in channels [0, d/2) and the cosine series
    C_i = Σ cos(n·t·ω_i)/n in [d/2, d). Eq. 4 is then ``emb[:, i] + emb[:, d/2 + i]`` — a fixed
    linear map the following learnable layer can represent — and N = 1 is exactly the
    sinusoidal embedding with ``downscale_freq_shift=0``. The paper gives no N; we default to 4.
    """

    def __init__(self, *, dim: int, harmonics: int = 4, max_period: float = 10000.0) -> None:
        """dim: output width d (even); harmonics: N in Eq. 4; max_period: the 10000 in Eq. 4."""
        super().__init__()
        self.dim = _check_dim(dim)
        if not isinstance(harmonics, int) or isinstance(harmonics, bool) or harmonics < 1:
            raise TypError(WHERE, "harmonics", "an integer N >= 1", harmonics)
        if not max_period > 1.0:
            raise TypError(WHERE, "max_period", "a number > 1", max_period)
        self.harmonics = harmonics
        half = dim // 2
        exponent = -math.log(max_period) * 2.0 * torch.arange(half, dtype=torch.float32) / dim
        self.register_buffer("frequencies", torch.exp(exponent), persistent=False)
        n = torch.arange(1, harmonics + 1, dtype=torch.float32)
        self.register_buffer("orders", n, persistent=False)

    def forward(self, timesteps: torch.Tensor) -> torch.Tensor:
        """timesteps (B,) int or float -> (B, dim) float32: [S_0..S_{d/2-1} | C_0..C_{d/2-1}]."""
        phase = _check_timesteps(timesteps)[:, None] * self.frequencies[None, :]  # (B, d/2)
        harmonic = phase[:, :, None] * self.orders  # (B, d/2, N)
        weight = 1.0 / self.orders
        sin = (torch.sin(harmonic) * weight).sum(-1)
        cos = (torch.cos(harmonic) * weight).sum(-1)
        return torch.cat([sin, cos], dim=-1)
