"""bench/detector_probe.py: the fusion-block overrides its variants are trained with."""
from __future__ import annotations

import dataclasses

import pytest

from bench_modules import load_bench
from typ.errors import TypError


@pytest.fixture(scope="module")
def probe():
    return load_bench("detector_probe")


def test_overrides_reach_nested_blocks_and_leave_the_rest(probe, tmp_path):
    (tmp_path / "params.yaml").write_text("profile: tiny\nfusion: {steps: 1500}\n")
    fusion = probe.fusion_block(tmp_path, {})
    assert fusion.steps == 1500  # the workspace's own params.yaml is read
    changed = probe.fusion_block(tmp_path, {"warm_start_steps": 900, "v2xvit": {"depth": 3},
                                            "detector": {"num_filters": [32, 64]}})
    assert changed.warm_start_steps == 900 and changed.v2xvit.depth == 3
    assert changed.detector.num_filters == (32, 64) and isinstance(changed.detector.num_filters, tuple)
    # every other field, at every level, is the workspace's
    assert dataclasses.replace(changed, warm_start_steps=fusion.warm_start_steps, v2xvit=fusion.v2xvit,
                               detector=fusion.detector) == fusion
    assert dataclasses.replace(changed.v2xvit, depth=fusion.v2xvit.depth) == fusion.v2xvit
    assert changed.detector.pillar_channels == fusion.detector.pillar_channels
    with pytest.raises(TypError, match="fusion.no_such_key"):
        probe.fusion_block(tmp_path, {"no_such_key": 1})
