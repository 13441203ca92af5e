"""Same seed and params, two separate runs -> byte-identical outputs and identical metrics.

Two throwaway projects run the stages through the CLI, each in its own process with a
different ``PYTHONHASHSEED`` (so iteration over sets of strings differs): the session's
uninterrupted run of tests/test_crash_safety.py (simulate, voxelize, vqvae)
and one more here. Their output trees must match byte for byte and their metrics JSON once the
timing fields are dropped. Training is compared through the saved weights: torch.save archives
carry a per-save id, so their bytes differ by design.
"""
from __future__ import annotations

import json
import re

import pytest

from test_crash_safety import STAGES, make_project, reference, run_stages, services, tree  # noqa: F401

TIMING = re.compile(r"seconds|per_second")


def without_timing(metrics):
    if isinstance(metrics, dict):
        return {k: without_timing(v) for k, v in metrics.items() if not TIMING.search(k)}
    return metrics


@pytest.fixture(scope="module")
def two_runs(services, reference, tmp_path_factory):
    again = make_project(tmp_path_factory.mktemp("again"))
    run_stages(again, services, *STAGES, extra_env={"PYTHONHASHSEED": "2"})
    return reference, again


@pytest.mark.parametrize("folder", ["data/sim", "data/voxels"])
def test_outputs_are_byte_identical(two_runs, folder):
    a, b = (tree(root / folder) for root in two_runs)
    assert a, f"{folder} is empty"
    assert sorted(a) == sorted(b)
    assert [rel for rel in a if a[rel] != b[rel]] == []


@pytest.mark.parametrize("stage", ["simulate", "voxelize", "vqvae"])
def test_metrics_are_identical_but_for_timings(two_runs, stage):
    a, b = (json.loads((root / "metrics" / f"{stage}.json").read_text()) for root in two_runs)
    assert without_timing(a) == without_timing(b)
    assert without_timing(a) != {}


def test_trained_weights_are_identical(two_runs):
    import torch

    from tasks.artifacts import read_config, read_weights

    for kind in ("x", "y"):
        a, b = (root / "artifacts" / "vqvae" / kind for root in two_runs)
        assert read_config(a, "vqvae") == read_config(b, "vqvae")
        wa, wb = read_weights(a, "vqvae"), read_weights(b, "vqvae")
        assert wa.keys() == wb.keys() and (wa or kind == "y")   # y is pooled (no weights) in the tiny profile
        assert all(torch.equal(wa[k], wb[k]) for k in wa), kind
