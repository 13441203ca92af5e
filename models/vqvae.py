"""VQ-VAEs for BEV occupancy x and box maps y (TYP §3.2, Eq. 1–3).

E and G are diffusers' ``VQModel`` encoder / decoder (with its ``quant_conv`` and
``post_quant_conv``); Q is chosen by ``quantizer``:
- ``"ema"`` (default): vector-quantize-pytorch's ``VectorQuantize`` — codebook updated by an
  exponential moving average of the vectors assigned to each code (VQ-VAE-2, van den Oord et
  al. 2017 App. A.1) instead of the ``||sg[E(x)] - x^z||²`` gradient term, initialised by
  k-means on the first batch, and codes unused for a while (EMA cluster size below
  ``dead_code_threshold``) restarted on vectors of the current batch. The commitment term
  ``||sg[x^z] - E(x)||²`` keeps weight 1 as in Eq. 1. This is the fix for codebook collapse:
  with the plain gradient codebook the tiny x VQ-VAE used 7 % of 1024 codes, with EMA + restarts
  all of them (``reports/vqvae_ablation.md``).
- ``"vq"``: diffusers' ``VectorQuantizer`` with Eq. 1 as written (codebook and commitment terms,
  both weight 1; diffusers hard-codes 0.25 for the second, set to 1 here).

The reconstruction term is the focal loss of Eq. 2 on binary occupancy. Eq. 3 sums it over
the M voxels while the codebook terms are squared norms over the latent's h·w·c elements; the
loss here is Eq. 1 divided by h·w·c, i.e. ``mean_voxels(FL) · M/(h·w·c) + mean_latent(...)``,
so the two terms keep the paper's relative weight and the learning rate does not depend on
the grid size.

``encode_pre_quant`` / ``quantize`` / ``decode_logits`` expose E, Q and G separately, which
the adaptation stage needs (E_src, G_src trained against a frozen, shared Q_tgt; Eq. 8–10).

Shapes: x is (B, C, H, W) float in {0, 1} (height channels first, as torch wants; the voxel
grid's (H, W, C) is permuted by the caller); x^f is (B, c, H/f, W/f) with f = 2^(levels-1).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from diffusers import VQModel
from torch import nn

from models.losses import focal_loss

QUANTIZERS = ("ema", "vq")


@dataclass
class VQOutput:
    logits: torch.Tensor          # (B, C, H, W) decoder output, before the sigmoid
    latents: torch.Tensor         # (B, c, h, w) x^f = E(x), before quantization
    quantized: torch.Tensor       # (B, c, h, w) x^z = Q(x^f) with a straight-through gradient
    codebook_loss: torch.Tensor   # commitment (+ codebook term for "vq"), mean over latent elements
    indices: torch.Tensor         # (B, h, w) code index per cell


class BEVVQVAE(nn.Module):
    """One VQ-VAE (E, Q, G) for binary BEV grids with ``in_channels`` height channels."""

    def __init__(self, *, in_channels: int, latent_channels: int, block_out_channels: tuple[int, ...] = (16, 32, 64),
                 num_codes: int = 1024, layers_per_block: int = 1, norm_num_groups: int = 8,
                 quantizer: str = "ema", ema_decay: float = 0.9, dead_code_threshold: float = 1.0):
        """in_channels: C (height channels, or 1 for y); latent_channels: c_x or c_y;
        block_out_channels: one entry per level, ``len - 1`` downsamplings by 2;
        num_codes: codebook size; norm_num_groups must divide every block width;
        quantizer: ``"ema"`` or ``"vq"`` (module doc); ema_decay: the EMA codebook's decay;
        dead_code_threshold: EMA cluster size under which a code is restarted (``"ema"`` only)."""
        super().__init__()
        if quantizer not in QUANTIZERS:
            raise ValueError(f"quantizer must be one of {QUANTIZERS}, got {quantizer!r}")
        self.config = {"in_channels": in_channels, "latent_channels": latent_channels,
                       "block_out_channels": list(block_out_channels), "num_codes": num_codes,
                       "layers_per_block": layers_per_block, "norm_num_groups": norm_num_groups,
                       "quantizer": quantizer, "ema_decay": ema_decay, "dead_code_threshold": dead_code_threshold}
        levels = len(block_out_channels)
        self.net = VQModel(in_channels=in_channels, out_channels=in_channels,
                           down_block_types=("DownEncoderBlock2D",) * levels,
                           up_block_types=("UpDecoderBlock2D",) * levels,
                           block_out_channels=tuple(block_out_channels), layers_per_block=layers_per_block,
                           latent_channels=latent_channels, num_vq_embeddings=num_codes,
                           norm_num_groups=norm_num_groups, vq_embed_dim=latent_channels,
                           mid_block_add_attention=False)
        if quantizer == "ema":
            from vector_quantize_pytorch import VectorQuantize

            del self.net.quantize  # Q is ours
            self.quantizer = VectorQuantize(dim=latent_channels, codebook_size=num_codes, decay=ema_decay,
                                            commitment_weight=1.0, kmeans_init=True, kmeans_iters=10,
                                            threshold_ema_dead_code=dead_code_threshold, accept_image_fmap=True,
                                            channel_last=False, sync_codebook=False, sync_kmeans=False)
        else:
            self.net.quantize.beta = 1.0  # Eq. 1: codebook and commitment terms weigh the same
            self.quantizer = self.net.quantize
        self.downsample = 2 ** (levels - 1)
        self.codebook_frozen = False

    @classmethod
    def from_config(cls, config: dict) -> "BEVVQVAE":
        """Rebuild from :attr:`config` (weights are loaded separately with ``load_state_dict``)."""
        return cls(**{**config, "block_out_channels": tuple(config["block_out_channels"])})

    @property
    def codebook(self) -> torch.Tensor:
        """(num_codes, c) the code vectors."""
        if self.config["quantizer"] == "ema":
            return self.quantizer.codebook
        return self.quantizer.embedding.weight

    def freeze_codebook(self) -> None:
        """Keep Q as it is (the shared, frozen Q_tgt of Eq. 9): no EMA update, no restart, no gradient."""
        self.codebook_frozen = True
        if self.config["quantizer"] == "ema":  # no k-means initialisation either: the codes are final
            self.quantizer._codebook.initted.fill_(True)
        for p in self.quantizer.parameters():
            p.requires_grad_(False)

    def encode_pre_quant(self, x: torch.Tensor) -> torch.Tensor:
        """E: (B, C, H, W) -> x^f (B, c, h, w)."""
        return self.net.quant_conv(self.net.encoder(x))

    def quantize(self, latents: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Q: nearest code per cell; returns (x^z with straight-through grad, codebook loss, indices (B, h, w))."""
        if self.config["quantizer"] == "ema":
            z_q, idx, loss = self.quantizer(latents.float(), freeze_codebook=self.codebook_frozen)
            loss = loss.sum() if loss.numel() else loss  # (1,) in training, scalar 0 in eval
            return z_q.to(latents.dtype), loss.reshape(()), idx.reshape(latents.shape[0], *latents.shape[2:])
        z_q, loss, (_, _, idx) = self.quantizer(latents)
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
        """Eq. 1 with the focal reconstruction term (Eq. 2–3), divided by the latent size (module doc)."""
        out = self(x)
        rec = reconstruction_loss(out.logits, x, out.latents, gamma=gamma)
        total = rec + out.codebook_loss
        return total, out, {"loss": float(total.detach()), "rec": float(rec.detach()),
                            "codebook": float(out.codebook_loss.detach())}


def reconstruction_loss(logits: torch.Tensor, x: torch.Tensor, latents: torch.Tensor, *, gamma: float) -> torch.Tensor:
    """Eq. 3's L_rec in Eq. 1's units (module doc): the focal loss (Eq. 2) summed over the M voxels
    of a view and divided by the h·w·c elements of its latent ``latents`` (B, c, h, w), over which
    the codebook terms are means. Eq. 9 (adaptation) takes the same term."""
    return focal_loss(logits, x, gamma=gamma) * (x[0].numel() / latents[0].numel())


class PooledBoxMap(nn.Module):
    """y^f without a learned encoder: the box map averaged over each latent cell.

    y (B, 1, H, W) in {0, 1} -> y^f (B, 1, H/f, W/f), the share of each f x f block that lies
    inside some box. A departure from TYP, which encodes y with a VQ-VAE: the map is binary
    and smooth at the latent's scale, so pooling keeps every box's position, extent and
    heading to within a cell exactly, where the tiny y VQ-VAE reconstructed it at IoU 0.38–0.45.
    Same interface as :class:`BEVVQVAE`'s encoder (``encode_pre_quant``).
    """

    def __init__(self, *, downsample: int):
        super().__init__()
        if downsample < 1:
            raise ValueError(f"downsample must be >= 1, got {downsample}")
        self.config = {"kind": "pool", "downsample": downsample}
        self.downsample = downsample

    @classmethod
    def from_config(cls, config: dict) -> "PooledBoxMap":
        return cls(downsample=config["downsample"])

    def encode_pre_quant(self, y: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.avg_pool2d(y, self.downsample)


def build_from_config(config: dict) -> BEVVQVAE | PooledBoxMap:
    """The encoder a saved config describes: a VQ-VAE, or the pooled box map (``kind: pool``)."""
    return PooledBoxMap.from_config(config) if config.get("kind") == "pool" else BEVVQVAE.from_config(config)
