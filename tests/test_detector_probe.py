"""bench/detector_probe.py: the fusion-block overrides its variants are trained with."""
from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import pytest

from typ.config import config_from_dict

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def probe():
    spec = importlib.util.spec_from_file_location("detector_probe", ROOT / "bench" / "detector_probe.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_overrides_reach_nested_blocks_and_leave_the_rest(probe):
    fusion = config_from_dict({}).fusion
    changed = probe.override(fusion, {"warm_start_steps": 900, "v2xvit": {"depth": 3},
                                      "detector": {"num_filters": [32, 64]}})
    assert changed.warm_start_steps == 900 and changed.v2xvit.depth == 3
    assert changed.detector.num_filters == (32, 64) and isinstance(changed.detector.num_filters, tuple)
    # every other field, at every level, is the profile's
    assert dataclasses.replace(changed, warm_start_steps=fusion.warm_start_steps, v2xvit=fusion.v2xvit,
                               detector=fusion.detector) == fusion
    assert dataclasses.replace(changed.v2xvit, depth=fusion.v2xvit.depth) == fusion.v2xvit
    assert changed.detector.pillar_channels == fusion.detector.pillar_channels
    with pytest.raises(AttributeError):
        probe.override(fusion, {"no_such_key": 1})
