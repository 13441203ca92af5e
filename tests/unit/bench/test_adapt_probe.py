"""bench/adapt_probe.py: its overrides, the weighted adversarial term and the gap it reports."""
from __future__ import annotations

import pytest
import torch

from bench_modules import ROOT, load_bench
from typ.errors import TypError


@pytest.fixture(scope="module")
def probe():
    return load_bench("adapt_probe")


def test_overrides_are_checked_by_the_config_and_the_weight_is_split_off(probe):
    block, weight = probe.variant(ROOT, '{"epochs": 7, "adv_weight": 2.5}')
    assert (block.epochs, weight) == (7, 2.5)
    default, one = probe.variant(ROOT, "{}")
    assert one == 1.0 and default.epochs != 7 and default.lr == block.lr
    with pytest.raises(TypError, match="adapt.no_such_key"):
        probe.variant(ROOT, '{"no_such_key": 1}')
    with pytest.raises(TypError, match="adapt.epochs"):
        probe.variant(ROOT, '{"epochs": 0}')
    with pytest.raises(ValueError, match="adv_weight"):
        probe.variant(ROOT, '{"adv_weight": 0}')


def test_the_weighted_generator_term_is_the_hinge_term_times_the_weight(probe):
    logits = torch.tensor([[-1.5, 0.25], [2.0, 4.0]])
    assert float(probe.weighted_g_loss(1.0)(logits)) == pytest.approx(-1.1875)   # Eq. 10: -E[D(E_src(x))]
    assert float(probe.weighted_g_loss(4.0)(logits)) == pytest.approx(-4.75)


def test_the_gap_closed_runs_from_no_adaptation_to_the_vqvae_floor(probe):
    assert probe.gap_closed(0.4, 0.3, 0.2) == pytest.approx(0.5)
    assert probe.gap_closed(0.4, 0.4, 0.2) == 0.0 and probe.gap_closed(0.4, 0.2, 0.2) == pytest.approx(1.0)
    assert probe.gap_closed(0.4, 0.45, 0.2) < 0   # worse than no adaptation
