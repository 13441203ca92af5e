"""VQ-VAEs for BEV occupancy x and box maps y (TYP §3.2, Eq. 1–3), built on diffusers' VQModel.

We use diffusers' ``VQModel`` (encoder, ``quant_conv``, ``VectorQuantizer``, ``post_quant_conv``,
decoder) as it is; what it lacks is written here:
- Eq. 1 weighs the codebook and commitment terms equally: the quantizer's ``beta`` is set to 1
  (diffusers hard-codes 0.25).
- The reconstruction term is the focal loss of Eq. 2 on binary occupancy, not MSE on pixels,
  so the decoder output is read as logits.
- ``encode_pre_quant`` / ``quantize`` / ``decode_logits`` expose E, Q and G separately, which the
  adaptation stage needs (E_src, G_src trained against a frozen, shared Q_tgt; Eq. 8–10).

Shapes: x is (B, C, H, W) float in {0, 1} (height channels first, as torch wants; the
voxel grid's (H, W, C) is permuted by the caller); x^f is (B, c_x, H/f, W/f) with f = 2^(levels-1).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from diffusers import VQModel
from torch import nn

from models.losses import focal_loss


@dataclass
class VQOutput:
    logits: torch.Tensor          # (B, C, H, W) decoder output, before the sigmoid
    latents: torch.Tensor         # (B, c, h, w) x^f = E(x), before quantization
    quantized: torch.Tensor       # (B, c, h, w) x^z = Q(x^f) with straight-through gradient
    codebook_loss: torch.Tensor   # ||sg[E(x)] - x^z||² + ||sg[x^z] - E(x)||² (Eq. 1, weights 1)
    indices: torch.Tensor         # (B, h, w) code index per cell


class BEVVQVAE(nn.Module):
    """One VQ-VAE (E, Q, G) for binary BEV grids with ``in_channels`` height channels."""

    def __init__(self, *, in_channels: int, latent_channels: int, block_out_channels: tuple[int, ...] = (32, 64, 64, 64),
                 num_codes: int = 512, layers_per_block: int = 1, norm_num_groups: int = 8):
        """in_channels: C (height channels, or 1 for y); latent_channels: c_x or c_y;
        block_out_channels: one entry per level, ``len - 1`` downsamplings by 2;
        num_codes: codebook size; norm_num_groups must divide every block width."""
        super().__init__()
        self.config = {"in_channels": in_channels, "latent_channels": latent_channels,
                       "block_out_channels": list(block_out_channels), "num_codes": num_codes,
                       "layers_per_block": layers_per_block, "norm_num_groups": norm_num_groups}
        levels = len(block_out_channels)
        self.net = VQModel(in_channels=in_channels, out_channels=in_channels,
                           down_block_types=("DownEncoderBlock2D",) * levels,
                           up_block_types=("UpDecoderBlock2D",) * levels,
                           block_out_channels=tuple(block_out_channels), layers_per_block=layers_per_block,
                           latent_channels=latent_channels, num_vq_embeddings=num_codes,
                           norm_num_groups=norm_num_groups, vq_embed_dim=latent_channels,
                           mid_block_add_attention=False)
        self.net.quantize.beta = 1.0  # Eq. 1: codebook and commitment terms weigh the same
        self.downsample = 2 ** (levels - 1)

    @classmethod
    def from_config(cls, config: dict) -> "BEVVQVAE":
        """Rebuild from :attr:`config` (weights are loaded separately with ``load_state_dict``)."""
        return cls(**{**config, "block_out_channels": tuple(config["block_out_channels"])})

    def encode_pre_quant(self, x: torch.Tensor) -> torch.Tensor:
        """E: (B, C, H, W) -> x^f (B, c, h, w)."""
        return self.net.quant_conv(self.net.encoder(x))

    def quantize(self, latents: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Q: nearest code per cell; returns (x^z with straight-through grad, codebook loss, indices)."""
        z_q, loss, (_, _, idx) = self.net.quantize(latents)
        return z_q, loss, idx.reshape(latents.shape[0], *latents.shape[2:])

    def decode_logits(self, quantized: torch.Tensor) -> torch.Tensor:
        """G: x^z (B, c, h, w) -> logits (B, C, H, W)."""
        return self.net.decoder(self.net.post_quant_conv(quantized))

    def decode_latents(self, latents: torch.Tensor) -> torch.Tensor:
        """G∘Q on latents produced by the diffusion model: logits (B, C, H, W)."""
        return self.decode_logits(self.quantize(latents)[0])

    def forward(self, x: torch.Tensor) -> VQOutput:
        latents = self.encode_pre_quant(x)
        quantized, codebook_loss, indices = self.quantize(latents)
        return VQOutput(self.decode_logits(quantized), latents, quantized, codebook_loss, indices)

    def loss(self, x: torch.Tensor, *, gamma: float) -> tuple[torch.Tensor, VQOutput, dict[str, float]]:
        """Eq. 1 with the focal reconstruction term (Eq. 2–3, mean over voxels)."""
        out = self(x)
        rec = focal_loss(out.logits, x, gamma=gamma)
        total = rec + out.codebook_loss
        return total, out, {"loss": float(total.detach()), "rec": float(rec.detach()),
                            "codebook": float(out.codebook_loss.detach())}
