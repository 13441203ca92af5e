"""Stage-1 latent diffusion network ε_θ(x^f_t, y^f, t) of TYP Eq. 4, on diffusers' UNet2DConditionModel.

Conditioning on the box map is by concatenation: the UNet sees ``[x^f_t, y^f]`` (c_x + c_y
channels), plus with ``coordinates`` three fixed channels (x, y and the distance from the
sensor at the grid's centre, scaled to [-1, 1] / [0, 1.4]), and predicts ε for the c_x
channels. A convolutional UNet cannot tell where it is on the grid; a LiDAR's scan pattern
(its rings, its density falling with range) is a function of exactly that, so the model gets
it as input, as R2DM conditions its range-image UNet on the beam angles. It is built from ``UNet2DConditionModel``
(CrossAttnDownBlock2D ×(levels-1) + DownBlock2D) so that stage 2's T2I-Adapter residuals
(``down_intrablock_additional_residuals``) land on the same encoder; the cross-attention
layers get a constant 1-token ``encoder_hidden_states`` because the UNet requires one (TYP
has no text). With ``self_attention=False`` the transformer blocks attend to that token only
(``only_cross_attention``): the blocks stay where the adapter residuals land, without the
quadratic cost of self-attention over every latent cell (2x faster training at 32x32). Attention to
one key token gives that token a softmax weight of exactly 1, so every latent cell receives the same
``to_out(to_v(context))``: :class:`OneTokenAttnProcessor` computes it once per sample instead of
once per cell (the same forward output, bit for bit here; 1.3x faster training steps at the tiny
size, ``bench/attention.py``). Latents are standardised per channel with statistics of the
training set, kept as buffers so they travel with the weights.
"""
from __future__ import annotations

from typing import Any

import torch
from diffusers import ConfigMixin, ModelMixin, UNet2DConditionModel
from diffusers.configuration_utils import register_to_config
from diffusers.models.attention_processor import Attention, AttnProcessor2_0
from torch import nn

from models.time_embedding import FourierTimeEmbedding


class LatentDiffusion(ModelMixin, ConfigMixin):
    """ε-prediction UNet on standardised x^f, conditioned on y^f by concatenation."""

    config_name = "config.json"   # diffusers' save_pretrained / from_pretrained

    @register_to_config
    def __init__(self, *, latent_channels: int, cond_channels: int, sample_size: int,
                 block_out_channels: tuple[int, ...] = (32, 64, 64, 64), layers_per_block: int = 1,
                 cross_attention_dim: int = 32, attention_head_dim: int = 8, norm_num_groups: int = 8,
                 time_embedding: str = "sinusoidal", self_attention: bool = True, coordinates: bool = False,
                 prediction: str = "epsilon"):
        """latent_channels: c_x; cond_channels: c_y; sample_size: h (= w) of the latents;
        block_out_channels: UNet widths per level; time_embedding: ``sinusoidal`` (DDPM) or
        ``fourier`` (LiDAR DDPM Eq. 4); self_attention: keep the transformer blocks' self-attention;
        coordinates: add the three coordinate channels to the input (module doc); prediction: what
        the network outputs, ``epsilon`` (Eq. 4), ``sample`` (z_0) or ``v_prediction``, diffusers' names
        (a sampler must be built with the same ``prediction_type``)."""
        super().__init__()
        if prediction not in ("epsilon", "sample", "v_prediction"):
            raise ValueError(f"prediction must be 'epsilon', 'sample' or 'v_prediction', got {prediction!r}")
        if time_embedding not in ("sinusoidal", "fourier"):
            raise ValueError(f"time_embedding must be 'sinusoidal' or 'fourier', got {time_embedding!r}")
        levels = len(block_out_channels)
        extra_channels = 3 if coordinates else 0
        self.unet = UNet2DConditionModel(
            sample_size=sample_size, in_channels=latent_channels + cond_channels + extra_channels,
            out_channels=latent_channels, only_cross_attention=not self_attention,
            down_block_types=("CrossAttnDownBlock2D",) * (levels - 1) + ("DownBlock2D",),
            up_block_types=("UpBlock2D",) + ("CrossAttnUpBlock2D",) * (levels - 1),
            block_out_channels=tuple(block_out_channels), layers_per_block=layers_per_block,
            cross_attention_dim=cross_attention_dim, attention_head_dim=attention_head_dim,
            norm_num_groups=norm_num_groups)
        self.unet.set_attn_processor(OneTokenAttnProcessor())
        if time_embedding == "fourier":
            # same width as diffusers' sinusoidal projection, so time_embedding's MLP fits as is
            self.unet.time_proj = FourierTimeEmbedding(dim=block_out_channels[0])
        self.register_buffer("context", torch.zeros(1, 1, cross_attention_dim))
        self.register_buffer("coords", coordinate_channels(sample_size) if coordinates else torch.zeros(1, 0, 1, 1),
                             persistent=False)
        self.register_buffer("latent_mean", torch.zeros(1, latent_channels, 1, 1))
        self.register_buffer("latent_std", torch.ones(1, latent_channels, 1, 1))
        self.register_buffer("cond_mean", torch.zeros(1, cond_channels, 1, 1))
        self.register_buffer("cond_std", torch.ones(1, cond_channels, 1, 1))

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
        """ε̂ (or ẑ_0 / v̂, see ``prediction``) for standardised z_t (B, c_x, h, w), timesteps t (B,),
        standardised y^f ``cond``.

        adapter_features: T2I-Adapter residuals, one per encoder level (stage 2); the UNet
        consumes the list, so callers pass a fresh list every call.
        """
        context = self.context.expand(z_t.shape[0], -1, -1).to(z_t.dtype)
        extra: dict[str, Any] = {}
        if adapter_features is not None:
            extra["down_intrablock_additional_residuals"] = list(adapter_features)
        inputs = [z_t, cond.to(z_t.dtype)]
        if self.config["coordinates"]:
            inputs.append(self.coords.to(z_t.dtype).expand(z_t.shape[0], -1, -1, -1))
        return self.unet(torch.cat(inputs, dim=1), t, encoder_hidden_states=context, **extra).sample


def coordinate_channels(size: int) -> torch.Tensor:
    """(1, 3, size, size): cell centres' x and y in [-1, 1] (rows along x, as the BEV grid's H)
    and their distance from the centre, the sensor."""
    c = (torch.arange(size, dtype=torch.float32) + 0.5) / size * 2 - 1
    x, y = torch.meshgrid(c, c, indexing="ij")
    return torch.stack([x, y, torch.sqrt(x ** 2 + y ** 2)])[None]


class OneTokenAttnProcessor(AttnProcessor2_0):
    """diffusers' attention, short-cut where the keys are one token (the LDM's constant context).

    softmax over one key is exactly 1, so ``softmax(q k^T / sqrt(d)) v`` is ``v`` for every query:
    the output is ``to_out(to_v(context))``, the same for every cell of a sample, whatever the
    queries. Only that one row is computed and broadcast; ``to_q``, ``to_k`` and the attention
    itself are skipped (their gradients are zero anyway). Anything else (self-attention, a mask, a spatial or
    group norm, a residual connection, 4-d input) runs diffusers' own :class:`AttnProcessor2_0`.
    """

    def __call__(self, attn: Attention, hidden_states: torch.Tensor, encoder_hidden_states: torch.Tensor | None = None,
                 attention_mask: torch.Tensor | None = None, temb: torch.Tensor | None = None, *args,
                 **kwargs) -> torch.Tensor:
        if (encoder_hidden_states is None or encoder_hidden_states.shape[1] != 1 or attention_mask is not None
                or hidden_states.ndim != 3 or attn.spatial_norm is not None or attn.group_norm is not None
                or attn.residual_connection):
            return super().__call__(attn, hidden_states, encoder_hidden_states, attention_mask, temb, *args, **kwargs)
        context = attn.norm_encoder_hidden_states(encoder_hidden_states) if attn.norm_cross else encoder_hidden_states
        out = attn.to_out[1](attn.to_out[0](attn.to_v(context))) / attn.rescale_output_factor
        return out.expand(-1, hidden_states.shape[1], -1)
