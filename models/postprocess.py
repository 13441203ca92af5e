"""TYP §4.1 post-processing of decoded occupancy probabilities into a binary volume.

Two thresholds on the decoder's probability p = sigmoid(logit): below ``low`` a voxel is
dropped, above ``high`` it is kept, and in between it is decided by the sign of the logit
perturbed with Gaussian noise (a Gumbel-softmax-like relaxation with Gaussian noise, as the
paper describes). ``low = high`` is a plain threshold.
"""
from __future__ import annotations

import torch


def postprocess(logits: torch.Tensor, *, low: float, high: float, noise_std: float,
                generator: torch.Generator | None = None) -> torch.Tensor:
    """logits (..., ) -> bool occupancy of the same shape."""
    if not 0.0 <= low <= high <= 1.0:
        raise ValueError(f"postprocess: need 0 <= low <= high <= 1, got low={low}, high={high}")
    p = torch.sigmoid(logits.float())
    noise = torch.randn(logits.shape, generator=generator, dtype=torch.float32) * noise_std
    middle = (logits.float() + noise.to(logits.device)) > 0
    return (p > high) | ((p >= low) & (p <= high) & middle)
