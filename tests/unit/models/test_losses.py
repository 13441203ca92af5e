"""Focal loss (TYP Eq. 2–3) and hinge losses (Eq. 8, 10) against hand-computed values."""
import math

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings, strategies as st

from models.losses import focal_loss, hinge_d_loss, hinge_g_loss


def test_gamma_zero_is_exactly_bce():
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(2, 8, 16, 16, generator=g) * 5
    target = (torch.rand(2, 8, 16, 16, generator=g) < 0.1).float()
    assert torch.allclose(focal_loss(logits, target, gamma=0.0),
                          F.binary_cross_entropy_with_logits(logits, target), rtol=0, atol=1e-7)
    assert torch.allclose(focal_loss(logits, target, gamma=0.0, reduction="sum"),
                          F.binary_cross_entropy_with_logits(logits, target, reduction="sum"), rtol=1e-6)


def test_hand_computed_values():
    # x̂ = sigmoid(0) = 0.5: positive -> (0.5)^2 * ln 2, negative -> (0.5)^2 * ln 2
    val = focal_loss(torch.zeros(2), torch.tensor([1.0, 0.0]), gamma=2.0, reduction="none")
    assert torch.allclose(val, torch.full((2,), 0.25 * math.log(2)), atol=1e-7)
    # x̂ = sigmoid(ln 3) = 0.75 on a positive: (0.25)^1 * -ln 0.75
    val = focal_loss(torch.tensor([math.log(3.0)]), torch.tensor([1.0]), gamma=1.0, reduction="none")
    assert val.item() == pytest.approx(0.25 * -math.log(0.75), rel=1e-6)
    # on a negative: 0.75^1 * -ln 0.25
    val = focal_loss(torch.tensor([math.log(3.0)]), torch.tensor([0.0]), gamma=1.0, reduction="none")
    assert val.item() == pytest.approx(0.75 * -math.log(0.25), rel=1e-6)


@settings(max_examples=40, deadline=None)
@given(st.floats(-100, 100), st.sampled_from([0.0, 0.5, 2.0, 5.0]), st.sampled_from([0.0, 1.0]))
def test_finite_and_nonnegative_at_saturated_logits(z, gamma, y):
    logits = torch.tensor([z], requires_grad=True)
    loss = focal_loss(logits, torch.tensor([y]), gamma=gamma)
    loss.backward()
    assert torch.isfinite(loss) and loss.item() >= 0
    assert torch.isfinite(logits.grad).all()


def test_focal_down_weights_easy_examples():
    easy = torch.tensor([6.0])  # confident and right
    hard = torch.tensor([-1.0])  # wrong
    t = torch.tensor([1.0])
    ratio_bce = focal_loss(easy, t, gamma=0) / focal_loss(hard, t, gamma=0)
    ratio_focal = focal_loss(easy, t, gamma=2) / focal_loss(hard, t, gamma=2)
    assert ratio_focal < ratio_bce / 100


def test_hinge_losses():
    real = torch.tensor([2.0, 0.5, -1.0])
    fake = torch.tensor([-2.0, 0.0, 3.0])
    # relu(1 - real) = [0, 0.5, 2] mean 2.5/3; relu(1 + fake) = [0, 1, 4] mean 5/3
    assert hinge_d_loss(real, fake).item() == pytest.approx(2.5 / 3 + 5 / 3)
    assert hinge_g_loss(fake).item() == pytest.approx(-1 / 3)
    # saturation: far on the right side gives exactly zero loss for D
    assert hinge_d_loss(torch.full((4,), 1e6), torch.full((4,), -1e6)).item() == 0.0
