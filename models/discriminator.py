"""The feature discriminator D of TYP §3.4 (Eq. 8): 4 convolutional layers on x^f.

D scores a latent map x^f (B, c_x, h, w) as target-like (high) or source-like (low); the
hinge losses are in :mod:`models.losses`. Spectral normalisation keeps D 1-Lipschitz-ish,
the usual companion of the hinge GAN loss (Geometric GAN), so its scores do not explode
while E_src chases it.
"""
from __future__ import annotations

import torch
from diffusers import ConfigMixin, ModelMixin
from diffusers.configuration_utils import register_to_config
from torch import nn
from torch.nn.utils.parametrizations import spectral_norm


class LatentDiscriminator(ModelMixin, ConfigMixin):
    """Four 3×3 conv layers (the last to one channel), LeakyReLU between, one score per map."""

    config_name = "config.json"   # diffusers' save_pretrained / from_pretrained

    @register_to_config
    def __init__(self, *, in_channels: int, width: int = 64):
        """in_channels: c_x of the latents; width: channels of the hidden layers."""
        super().__init__()
        layers: list[nn.Module] = []
        chans = [in_channels, width, width * 2, width * 2]
        for i in range(3):
            layers += [spectral_norm(nn.Conv2d(chans[i], chans[i + 1], 3, stride=2 if i else 1, padding=1)),
                       nn.LeakyReLU(0.2)]
        layers.append(spectral_norm(nn.Conv2d(chans[3], 1, 3, padding=1)))
        self.net = nn.Sequential(*layers)

    def forward(self, latents: torch.Tensor) -> torch.Tensor:
        """(B, c_x, h, w) -> (B,) scores: the mean of the patch scores."""
        return self.net(latents).mean(dim=(1, 2, 3))
