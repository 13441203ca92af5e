"""bench/generator_probe.py: the z_0 estimate it scores every kind of network by."""
from __future__ import annotations

import pytest
import torch

from bench_modules import load_bench


@pytest.fixture(scope="module")
def probe():
    return load_bench("generator_probe")


@pytest.mark.parametrize("a", [0.9, 0.3, 0.02])
def test_z0_estimate_inverts_each_prediction_kind(probe, a):
    g = torch.Generator().manual_seed(0)
    z0, eps = torch.randn(2, 8, 4, 4, generator=g), torch.randn(2, 8, 4, 4, generator=g)
    a = torch.tensor(a)
    z_t = a.sqrt() * z0 + (1 - a).sqrt() * eps
    exact = {"sample": z0, "epsilon": eps, "v_prediction": a.sqrt() * eps - (1 - a).sqrt() * z0}
    for kind, output in exact.items():
        torch.testing.assert_close(probe.z0_of(kind, z_t, output, a), z0, atol=1e-4, rtol=1e-4)
    # a wrong output is scored as wrong: ε mistaken for z_0 is off by the noise
    assert float(((probe.z0_of("sample", z_t, eps, a) - z0) ** 2).mean()) > 0.5

