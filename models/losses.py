"""Losses of TYP: the focal reconstruction loss (Eq. 2–3), the commitment term (Eq. 1, 9) and the
hinge GAN losses (Eq. 8, 10).

Everything works on logits, in float32 or wider, so that saturated scores stay finite:
``log(x̂) = -softplus(-z)`` and ``log(1 - x̂) = -softplus(z)`` never evaluate ``log(0)``.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F


def focal_loss(logits: torch.Tensor, target: torch.Tensor, *, gamma: float = 2.0,
               reduction: str = "mean") -> torch.Tensor:
    """Eq. 2: ``-(1 - x̂)^γ log x̂`` where x = 1, ``-x̂^γ log(1 - x̂)`` where x = 0, x̂ = sigmoid(logits).

    logits, target: same shape; target in {0, 1}. ``gamma = 0`` is exactly binary cross-entropy.
    reduction: ``"sum"`` is Eq. 3 as written (sum over the M voxels); ``"mean"`` divides that
    by the number of voxels so the learning rate does not depend on the grid size; ``"none"``.
    """
    if gamma < 0:
        raise ValueError(f"focal_loss: gamma must be >= 0, got {gamma}")
    logits = logits.float()
    target = target.to(logits.dtype)
    # -log x̂ = softplus(-z), -log(1 - x̂) = softplus(z); the modulating factors are taken in
    # log space, (1 - x̂)^γ = exp(-γ softplus(z)), so their gradient stays finite when x̂
    # rounds to 0 or 1 (a plain pow(0, γ<1) has an infinite derivative).
    nll_pos, nll_neg = F.softplus(-logits), F.softplus(logits)
    if gamma == 0:
        loss = target * nll_pos + (1 - target) * nll_neg
    else:
        loss = target * torch.exp(-gamma * nll_neg) * nll_pos + (1 - target) * torch.exp(-gamma * nll_pos) * nll_neg
    if reduction == "mean":
        return loss.mean()
    if reduction == "sum":
        return loss.sum()
    if reduction == "none":
        return loss
    raise ValueError(f"focal_loss: reduction must be 'mean', 'sum' or 'none', got {reduction!r}")


def hinge_d_loss(real_scores: torch.Tensor, fake_scores: torch.Tensor) -> torch.Tensor:
    """Eq. 8: ``E[max(0, 1 - D(real))] + E[max(0, 1 + D(fake))]`` (real = target, fake = source)."""
    return F.relu(1.0 - real_scores).mean() + F.relu(1.0 + fake_scores).mean()


def hinge_g_loss(fake_scores: torch.Tensor) -> torch.Tensor:
    """Eq. 10: ``L_src = -E[D(E_src(x))]``, the generator side of the hinge GAN."""
    return -fake_scores.mean()


def commitment_loss(latents: torch.Tensor, quantized: torch.Tensor) -> torch.Tensor:
    """Eq. 1's and Eq. 9's ``||sg[x^z] - E(x)||²``, mean over the latent elements: it pulls the
    encoder's x^f = ``latents`` towards its code x^z = ``quantized`` and gives the code no gradient
    (``quantized`` may carry a straight-through gradient to ``latents``: it is cut here too)."""
    return F.mse_loss(latents, quantized.detach())
