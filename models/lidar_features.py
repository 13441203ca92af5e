"""typ's own feature networks for FRID and FPVD (LiDM's perceptual LiDAR metrics).

LiDM computes FRID in the feature space of RangeNet++ (a range-image segmentation network)
and FPVD in that of a MinkowskiNet/SPVCNN (a point-voxel one), both trained on SemanticKITTI.
Neither can be used here, so typ trains small stand-ins of the same kind on the simulator's
per-point semantic labels: one segmentation network on range images (FRID), one on voxel
grids (FPVD). Their features — the bottleneck, averaged over the image — are what the Fréchet
distance compares. Numbers in these feature spaces compare runs *within typ only*.

One architecture serves both: an encoder-decoder CNN (stride-2 convolutions down, nearest
upsampling with skip connections up) that predicts ``out_channels`` logits per pixel. For the
voxel network the height channels are the input channels and the output holds
``classes × height`` logits, one class distribution per voxel.
"""
from __future__ import annotations

import torch
from diffusers import ConfigMixin, ModelMixin
from diffusers.configuration_utils import register_to_config
import torch.nn.functional as F
from torch import nn


def _block(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    groups = 4 if cout % 4 == 0 else 1
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1), nn.GroupNorm(groups, cout), nn.SiLU(),
                         nn.Conv2d(cout, cout, 3, padding=1), nn.GroupNorm(groups, cout), nn.SiLU())


class SegmentationFeatureNet(ModelMixin, ConfigMixin):
    """Per-pixel logits (B, out_channels, H, W); :meth:`features` gives (B, width·2^(levels-1))."""

    config_name = "config.json"   # diffusers' save_pretrained / from_pretrained

    @register_to_config
    def __init__(self, *, in_channels: int, out_channels: int, width: int = 8, levels: int = 3):
        """in_channels / out_channels: image channels in, logits out; width: channels of the first
        level, doubled at each of the ``levels - 1`` stride-2 steps (H and W must divide by 2^(levels-1))."""
        super().__init__()
        widths = [width * 2 ** i for i in range(levels)]
        self.down = nn.ModuleList([_block(in_channels, widths[0])] +
                                  [_block(widths[i - 1], widths[i], stride=2) for i in range(1, levels)])
        self.up = nn.ModuleList([_block(widths[i] + widths[i - 1], widths[i - 1]) for i in range(levels - 1, 0, -1)])
        self.head = nn.Conv2d(widths[0], out_channels, 1)

    @property
    def feature_dim(self) -> int:
        return self.config["width"] * 2 ** (self.config["levels"] - 1)

    def _encode(self, x: torch.Tensor) -> list[torch.Tensor]:
        skips = []
        for block in self.down:
            x = block(x)
            skips.append(x)
        return skips

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C, H, W) -> (B, feature_dim): the bottleneck averaged over the image."""
        return self._encode(x)[-1].mean(dim=(2, 3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = self._encode(x)
        y = skips[-1]
        for block, skip in zip(self.up, reversed(skips[:-1])):
            y = block(torch.cat([F.interpolate(y, size=skip.shape[-2:], mode="nearest"), skip], dim=1))
        return self.head(y)
