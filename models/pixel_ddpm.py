"""The LiDAR DDPM network (Aghanouri & Olaverri-Monreal §III, §IV-2): a lightweight pixel-space
U-Net ε_θ(x_t, t) on a LiDAR image (range image or BEV image, see :mod:`typ.projection`).

diffusers' ``UNet2DModel`` of plain ResNet blocks (no attention: the paper's point is a small,
cheap backbone), dropout 0.1 as in §IV-2, and either time embedding of §III-B: the sinusoidal
one (diffusers' own projection) or the Fourier series of Eq. 4
(:class:`models.time_embedding.FourierTimeEmbedding`, same width, so the learnable MLP that
lifts it is unchanged).

``patch = (ph, pw)`` folds each ph×pw block of pixels into channels before the U-Net and
unfolds the output again (a lossless space-to-depth reshape, as pixel-space models such as
simple diffusion do to trade resolution for width): the network still predicts ε for every
pixel, at a fraction of the cost on a CPU. ``(1, 1)`` is the plain pixel U-Net.
"""
from __future__ import annotations

import torch
from diffusers import ConfigMixin, ModelMixin, UNet2DModel
from diffusers.configuration_utils import register_to_config
from torch import nn

from models.time_embedding import FourierTimeEmbedding

EMBEDDINGS = ("sinusoidal", "fourier")


def fold(x: torch.Tensor, ph: int, pw: int) -> torch.Tensor:
    """(B, C, H, W) -> (B, C·ph·pw, H/ph, W/pw): each ph×pw block becomes channels."""
    b, c, h, w = x.shape
    return x.view(b, c, h // ph, ph, w // pw, pw).permute(0, 1, 3, 5, 2, 4).reshape(b, c * ph * pw, h // ph, w // pw)


def unfold(x: torch.Tensor, ph: int, pw: int) -> torch.Tensor:
    """Inverse of :func:`fold`."""
    b, cp, h, w = x.shape
    c = cp // (ph * pw)
    return x.view(b, c, ph, pw, h, w).permute(0, 1, 4, 2, 5, 3).reshape(b, c, h * ph, w * pw)


class PixelDiffusion(ModelMixin, ConfigMixin):
    """ε-prediction U-Net on (B, channels, height, width) images in [-1, 1]."""

    config_name = "config.json"   # diffusers' save_pretrained / from_pretrained

    @register_to_config
    def __init__(self, *, channels: int, height: int, width: int, patch: tuple[int, int] = (1, 1),
                 block_out_channels: tuple[int, ...] = (32, 64, 64), layers_per_block: int = 1,
                 norm_num_groups: int = 8, dropout: float = 0.1, time_embedding: str = "sinusoidal",
                 harmonics: int = 4, coordinates: bool = False):
        """channels, height, width: the image; patch: space-to-depth block (must divide the image,
        and the folded size must be divisible by 2^(levels-1)); block_out_channels: U-Net widths per
        level; dropout: in every ResNet block (0.1 in the paper); time_embedding: ``sinusoidal`` or
        ``fourier`` (Eq. 4 with ``harmonics`` = N); coordinates: append two fixed channels, the
        pixel's row and column scaled to [-1, 1] (beam elevation and azimuth in a range image, x and y
        in a BEV image), so the convolutions know where in the image they are."""
        super().__init__()
        if time_embedding not in EMBEDDINGS:
            raise ValueError(f"time_embedding must be one of {EMBEDDINGS}, got {time_embedding!r}")
        ph, pw = patch
        levels = len(block_out_channels)
        factor = 2 ** (levels - 1)
        if height % ph or width % pw or (height // ph) % factor or (width // pw) % factor:
            raise ValueError(f"image {height}x{width} with patch {ph}x{pw} does not fold into a size "
                             f"divisible by {factor} (= 2^(levels - 1))")
        self.patch = (ph, pw)
        extra = 2 if coordinates else 0
        rows = torch.linspace(-1.0, 1.0, height).view(1, 1, height, 1).expand(1, 1, height, width)
        cols = torch.linspace(-1.0, 1.0, width).view(1, 1, 1, width).expand(1, 1, height, width)
        self.register_buffer("coords", torch.cat([rows, cols], dim=1)[:, :extra].contiguous(), persistent=False)
        folded = channels * ph * pw
        self.unet = UNet2DModel(
            sample_size=(height // ph, width // pw), in_channels=(channels + extra) * ph * pw, out_channels=folded,
            down_block_types=("DownBlock2D",) * levels, up_block_types=("UpBlock2D",) * levels,
            block_out_channels=tuple(block_out_channels), layers_per_block=layers_per_block,
            norm_num_groups=norm_num_groups, dropout=dropout)
        if time_embedding == "fourier":
            self.unet.time_proj = FourierTimeEmbedding(dim=block_out_channels[0], harmonics=harmonics)

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, cond=None, adapter_features=None) -> torch.Tensor:
        """ε̂ for x_t (B, C, H, W) at timesteps t (B,). ``cond`` and ``adapter_features`` are
        accepted (and must be None) so that :func:`models.samplers.sample` can drive the model."""
        if cond is not None or adapter_features is not None:
            raise ValueError("the LiDAR DDPM is unconditional: cond and adapter_features must be None")
        ph, pw = self.patch
        if self.coords.shape[1]:
            x_t = torch.cat([x_t, self.coords.expand(x_t.shape[0], -1, -1, -1).to(x_t.dtype)], dim=1)
        return unfold(self.unet(fold(x_t, ph, pw), t).sample, ph, pw)
