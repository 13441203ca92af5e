"""PointPillars detection loss, OpenCOOD's ``opencood/loss/point_pillar_loss.py`` (code ours).

- classification: sigmoid focal loss (α 0.25, γ 2) on every anchor; as in OpenCOOD, every
  anchor that is not positive counts as a negative (``neg_equal_one`` is not used), and the
  weights are divided by the number of positives of the sample.
- regression: weighted smooth-L1 (β 1/9) on the 7 residuals of the positives, with the yaw
  compared through ``sin(a - b) = sin a cos b - cos a sin b`` (``add_sin_difference``), so a
  box and its 180°-flip cost the same; the direction classifier resolves the flip.
- direction: softmax cross-entropy over the bins on positives (OpenCOOD v2 / HEAL ``dir_loss``).
Each term is summed over anchors and divided by the batch size, then weighted
(OpenCOOD's ``cls_weight`` 1, ``reg`` 2; HEAL's ``dir_weight`` 0.2).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def sigmoid_focal_loss(logits: torch.Tensor, target: torch.Tensor, *, alpha: float = 0.25,
                       gamma: float = 2.0) -> torch.Tensor:
    """Element-wise ``-α_t (1 - p_t)^γ log p_t`` on logits (no reduction)."""
    p = torch.sigmoid(logits)
    alpha_t = target * alpha + (1 - target) * (1 - alpha)
    pt = target * (1 - p) + (1 - target) * p                 # 1 - p_t: the modulating base
    return alpha_t * pt.pow(gamma) * F.binary_cross_entropy_with_logits(logits, target, reduction="none")


def smooth_l1(diff: torch.Tensor, beta: float) -> torch.Tensor:
    """``0.5 x² / β`` for ``|x| < β``, ``|x| - 0.5 β`` otherwise (β < 1e-5: plain L1)."""
    n = diff.abs()
    if beta < 1e-5:
        return n
    return torch.where(n < beta, 0.5 * n ** 2 / beta, n - 0.5 * beta)


class DetectionLoss(nn.Module):
    """Focal classification + smooth-L1 box regression + direction classification."""

    def __init__(self, *, cls_weight: float = 1.0, reg_weight: float = 2.0, dir_weight: float = 0.2,
                 alpha: float = 0.25, gamma: float = 2.0, beta: float = 1.0 / 9.0):
        """cls_weight / reg_weight / dir_weight: term weights; alpha, gamma: focal loss;
        beta: smooth-L1 change point."""
        super().__init__()
        self.cls_weight, self.reg_weight, self.dir_weight = cls_weight, reg_weight, dir_weight
        self.alpha, self.gamma, self.beta = alpha, gamma, beta

    def forward(self, output: dict[str, torch.Tensor], labels: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Head output {``psm`` (B, A, H, W), ``rm`` (B, 7A, H, W)[, ``dm`` (B, bins*A, H, W)]} and the
        stacked labels of ``AnchorBoxCoder.assign_batch`` -> {``total_loss``, ``cls_loss``, ``reg_loss``,
        ``dir_loss``} scalars."""
        psm, rm = output["psm"], output["rm"]
        b = psm.shape[0]
        pos = labels["pos_equal_one"].reshape(b, -1).to(psm.dtype)             # (B, H*W*A)
        norm = pos.sum(1, keepdim=True).clamp(min=1.0)
        cls_logits = psm.permute(0, 2, 3, 1).reshape(b, -1)
        cls = sigmoid_focal_loss(cls_logits, pos, alpha=self.alpha, gamma=self.gamma) / norm
        cls_loss = cls.sum() / b

        pred = rm.permute(0, 2, 3, 1).reshape(b, -1, 7)
        target = labels["targets"].reshape(b, -1, 7).to(pred.dtype)
        p_yaw, t_yaw = pred[..., 6:], target[..., 6:]
        pred = torch.cat([pred[..., :6], torch.sin(p_yaw) * torch.cos(t_yaw)], -1)
        target = torch.cat([target[..., :6], torch.cos(p_yaw) * torch.sin(t_yaw)], -1)
        reg = smooth_l1(pred - target, self.beta) * (pos / norm)[..., None]
        reg_loss = reg.sum() / b

        dir_loss = psm.new_zeros(())
        if "dm" in output and "dir_targets" in labels:
            bins = output["dm"].shape[1] // psm.shape[1]
            dir_logits = output["dm"].permute(0, 2, 3, 1).reshape(b, -1, bins)
            ce = F.cross_entropy(dir_logits.reshape(-1, bins), labels["dir_targets"].reshape(-1).long(),
                                 reduction="none").view(b, -1)
            dir_loss = (ce * pos / norm).sum() / b
        total = self.cls_weight * cls_loss + self.reg_weight * reg_loss + self.dir_weight * dir_loss
        return {"total_loss": total, "cls_loss": cls_loss, "reg_loss": reg_loss, "dir_loss": dir_loss}
