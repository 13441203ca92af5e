"""Stage-1 latent diffusion network ε_θ(x^f_t, y^f, t) of TYP Eq. 4, on diffusers' UNet2DConditionModel.

Conditioning on the box map is by concatenation: the UNet sees ``[x^f_t, y^f]`` (c_x + c_y
channels) and predicts ε for the c_x channels. It is built from ``UNet2DConditionModel``
(CrossAttnDownBlock2D ×(levels-1) + DownBlock2D) so that stage 2's T2I-Adapter residuals
(``down_intrablock_additional_residuals``) land on the same encoder; the cross-attention
layers get a constant 1-token ``encoder_hidden_states`` because the UNet requires one (TYP
has no text). Latents are standardised per channel with statistics of the training set,
kept as buffers so they travel with the weights.
"""
from __future__ import annotations

from typing import Any

import torch
from diffusers import UNet2DConditionModel
from torch import nn

from models.time_embedding import FourierTimeEmbedding


class LatentDiffusion(nn.Module):
    """ε-prediction UNet on standardised x^f, conditioned on y^f by concatenation."""

    def __init__(self, *, latent_channels: int, cond_channels: int, sample_size: int,
                 block_out_channels: tuple[int, ...] = (32, 64, 64, 64), layers_per_block: int = 1,
                 cross_attention_dim: int = 32, attention_head_dim: int = 8, norm_num_groups: int = 8,
                 time_embedding: str = "sinusoidal"):
        """latent_channels: c_x; cond_channels: c_y; sample_size: h (= w) of the latents;
        block_out_channels: UNet widths per level; time_embedding: ``sinusoidal`` (DDPM) or
        ``fourier`` (LiDAR DDPM Eq. 4)."""
        super().__init__()
        if time_embedding not in ("sinusoidal", "fourier"):
            raise ValueError(f"time_embedding must be 'sinusoidal' or 'fourier', got {time_embedding!r}")
        self.config = {"latent_channels": latent_channels, "cond_channels": cond_channels,
                       "sample_size": sample_size, "block_out_channels": list(block_out_channels),
                       "layers_per_block": layers_per_block, "cross_attention_dim": cross_attention_dim,
                       "attention_head_dim": attention_head_dim, "norm_num_groups": norm_num_groups,
                       "time_embedding": time_embedding}
        levels = len(block_out_channels)
        self.unet = UNet2DConditionModel(
            sample_size=sample_size, in_channels=latent_channels + cond_channels, out_channels=latent_channels,
            down_block_types=("CrossAttnDownBlock2D",) * (levels - 1) + ("DownBlock2D",),
            up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * (levels - 1),
            block_out_channels=tuple(block_out_channels), layers_per_block=layers_per_block,
            cross_attention_dim=cross_attention_dim, attention_head_dim=attention_head_dim,
            norm_num_groups=norm_num_groups)
        if time_embedding == "fourier":
            # same width as diffusers' sinusoidal projection, so time_embedding's MLP fits as is
            self.unet.time_proj = FourierTimeEmbedding(dim=block_out_channels[0])
        self.register_buffer("context", torch.zeros(1, 1, cross_attention_dim))
        self.register_buffer("latent_mean", torch.zeros(1, latent_channels, 1, 1))
        self.register_buffer("latent_std", torch.ones(1, latent_channels, 1, 1))
        self.register_buffer("cond_mean", torch.zeros(1, cond_channels, 1, 1))
        self.register_buffer("cond_std", torch.ones(1, cond_channels, 1, 1))

    @classmethod
    def from_config(cls, config: dict) -> "LatentDiffusion":
        return cls(**{**config, "block_out_channels": tuple(config["block_out_channels"])})

    def set_statistics(self, latents: torch.Tensor, cond: torch.Tensor) -> None:
        """Per-channel mean/std of training x^f (B, c_x, h, w) and y^f (B, c_y, h, w)."""
        dims = (0, 2, 3)
        self.latent_mean.copy_(latents.mean(dims, keepdim=True))
        self.latent_std.copy_(latents.std(dims, keepdim=True).clamp_min(1e-4))
        self.cond_mean.copy_(cond.mean(dims, keepdim=True))
        self.cond_std.copy_(cond.std(dims, keepdim=True).clamp_min(1e-4))

    def normalize(self, latents: torch.Tensor) -> torch.Tensor:
        return (latents - self.latent_mean) / self.latent_std

    def denormalize(self, z: torch.Tensor) -> torch.Tensor:
        return z * self.latent_std + self.latent_mean

    def normalize_cond(self, cond: torch.Tensor) -> torch.Tensor:
        return (cond - self.cond_mean) / self.cond_std

    def forward(self, z_t: torch.Tensor, t: torch.Tensor, cond: torch.Tensor,
                adapter_features: list[torch.Tensor] | None = None) -> torch.Tensor:
        """ε̂ for standardised z_t (B, c_x, h, w), timesteps t (B,), standardised y^f ``cond``.

        adapter_features: T2I-Adapter residuals, one per encoder level (stage 2); the UNet
        consumes the list, so callers pass a fresh list every call.
        """
        context = self.context.expand(z_t.shape[0], -1, -1).to(z_t.dtype)
        extra: dict[str, Any] = {}
        if adapter_features is not None:
            extra["down_intrablock_additional_residuals"] = list(adapter_features)
        return self.unet(torch.cat([z_t, cond.to(z_t.dtype)], dim=1), t, encoder_hidden_states=context,
                         **extra).sample
