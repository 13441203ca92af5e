"""A tiny TYPPipeline (untrained, a 32 x 32 x 8 grid): the generator's wiring in seconds."""
import numpy as np
import torch

from models.adapter import ZeroAdapter
from models.ldm import LatentDiffusion
from models.vqvae import BEVVQVAE, PooledBoxMap
from pipelines.typ.pipeline_typ import PointStats, TYPPipeline
from typ.voxel import Grid

TINY_GRID = Grid((-12.8, 12.8), (-12.8, 12.8), (-0.75, 3.25), (32, 32, 8))


def tiny_pipeline(adapter=True, conditions=1) -> TYPPipeline:
    torch.manual_seed(0)
    x_vq = BEVVQVAE(in_channels=8, latent_channels=4, block_out_channels=(8, 16), num_codes=32, norm_num_groups=4)
    x_vq(torch.rand(2, 8, 32, 32).round())  # initialise the EMA codebook
    unet = LatentDiffusion(latent_channels=4, cond_channels=1, sample_size=16, block_out_channels=(16, 16),
                           norm_num_groups=8, cross_attention_dim=8, self_attention=False, coordinates=True,
                           prediction="sample")
    ad = ZeroAdapter(latent_channels=4, channels=(16, 16), conditions=conditions) if adapter else None
    stats = PointStats((0.0, 10.0, 1e9), ((0.5, 0.5), (1.0,)), (tuple(np.linspace(0, 0.5, 21)), (0.2,) * 21))
    return TYPPipeline(x_vq.eval(), PooledBoxMap(downsample=2), unet.eval(), None if ad is None else ad.eval(), TINY_GRID,
                       "linear", 1000, "dpmsolver++", 3, {"low": 0.4, "high": 0.6, "noise_std": 1.0}, stats)
