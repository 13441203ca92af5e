"""F_AD of TYP Eq. 5–6: a T2I-Adapter whose residuals start at exactly zero.

diffusers' ``T2IAdapter`` (full adapter, ``downscale_factor=1``) maps the conditioning latent
to one feature map per UNet encoder level ([h, h/2, h/4, h/8] at the UNet's widths), which the
frozen UNet adds to its encoder features (``down_intrablock_additional_residuals``). Its
blocks end in residual connections, so a fresh adapter already emits features of the input's
scale and perturbs the frozen stage-1 model from the first step. As ControlNet does with its
"zero convolutions", every level's output here passes a 1x1 convolution initialised to zero:
at step 0 the adapted model *is* stage 1, and the gradient still reaches the adapter through
the zero convolutions' weights (d out / d W = features, which are not zero).

``in_channels`` is c_x for x^f_e' alone (TYP) or 2 c_x for x^f_e' beside the re-simulated
view's latent (typ's re-simulation-conditioned variant: ``conditions = 2``).
"""
from __future__ import annotations

import torch
from diffusers import ConfigMixin, ModelMixin, T2IAdapter
from diffusers.configuration_utils import register_to_config
from torch import nn


class ZeroAdapter(ModelMixin, ConfigMixin):
    """T2I-Adapter + zero-initialised 1x1 output convolutions; returns one map per UNet level."""

    config_name = "config.json"   # diffusers' save_pretrained / from_pretrained

    @register_to_config
    def __init__(self, *, latent_channels: int, channels: tuple[int, ...], num_res_blocks: int = 1, conditions: int = 1):
        """latent_channels: c_x; channels: the UNet's block widths (one residual per level);
        num_res_blocks: residual blocks per adapter level; conditions: latents stacked as input."""
        super().__init__()
        self.adapter = T2IAdapter(in_channels=latent_channels * conditions, channels=list(channels),
                                  num_res_blocks=num_res_blocks, downscale_factor=1, adapter_type="full_adapter")
        self.zero = nn.ModuleList(nn.Conv2d(c, c, kernel_size=1) for c in channels)
        for conv in self.zero:
            nn.init.zeros_(conv.weight)
            nn.init.zeros_(conv.bias)

    def forward(self, condition: torch.Tensor) -> list[torch.Tensor]:
        """F_c = F_AD(condition): (B, conditions·c_x, h, w) -> [(B, channels[i], h/2^i, w/2^i)]."""
        return [zero(f) for zero, f in zip(self.zero, self.adapter(condition))]
