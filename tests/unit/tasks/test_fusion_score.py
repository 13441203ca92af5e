"""AP cells with bootstrap intervals over test scenarios and training seeds (tasks/fusion_score.py)."""
from __future__ import annotations

import numpy as np
import pytest

from tasks.fusion_score import ap_cell, paired_difference
from typ.metrics import ap_by_range, frame_matches


def _car(x: float) -> list[float]:
    return [x, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]


def _matches(preds, gts):
    return {"ap50": frame_matches(preds, gts, 0.5), "ap70": frame_matches(preds, gts, 0.7)}


GTS = [np.array([_car(10.0), _car(35.0)]), np.array([_car(60.0)]), np.array([_car(20.0)]), np.array([_car(40.0)])]
SCENES = ["a", "a", "b", "b"]


def test_perfect_predictions_score_one_with_a_point_interval():
    perfect = [(g, np.full(len(g), 0.9)) for g in GTS]
    cell = ap_cell([_matches(perfect, GTS)] * 3, SCENES, n_boot=100)
    for key in ("ap50", "ap70"):
        for band in ("overall", "0-30", "30-50", "50-100"):
            assert cell[key][band] == {"value": 1.0, "low": 1.0, "high": 1.0}
    assert cell["per_seed"] == [1.0, 1.0, 1.0]


def test_value_is_the_mean_over_seeds_and_the_interval_spans_scenes_and_seeds():
    hit = [(g, np.full(len(g), 0.9)) for g in GTS]
    miss_b = [hit[0], hit[1], (np.zeros((0, 7)), np.zeros(0)), (np.zeros((0, 7)), np.zeros(0))]
    seeds = [_matches(hit, GTS), _matches(miss_b, GTS)]
    cell = ap_cell(seeds, SCENES, n_boot=400, seed=1)
    ap_miss = ap_by_range(miss_b, GTS)["overall"]                         # 3 of 5 cars, all at precision 1
    assert ap_miss == pytest.approx(0.6)
    assert cell["ap50"]["overall"]["value"] == pytest.approx((1.0 + 0.6) / 2)
    assert cell["per_seed"] == [1.0, 0.6]
    lo, hi = cell["ap50"]["overall"]["low"], cell["ap50"]["overall"]["high"]
    assert lo < 0.8 < hi and lo >= 0.0 and hi == 1.0                      # a replicate of seed 0 only is 1
    assert cell["ap50"]["50-100"]["value"] == 1.0                        # scene a's car at 60 m: always found
    # a band without vehicles has no number (and no interval), not 0
    no_far = [g[np.abs(g[:, 0]) < 50] for g in GTS]
    cell = ap_cell([_matches([(g, np.full(len(g), 0.9)) for g in no_far], no_far)], SCENES, n_boot=50)
    assert cell["ap50"]["50-100"] is None


def test_global_sort_ranks_all_frames_by_score_where_frame_order_does_not():
    """Frame 0: a false positive at 0.3 (its car missed); frame 1: its car at 0.9. Frame order
    ranks the 0.3 first: precision 0 then 0.5 at recall 0.5, AP 0.5 * 0.5 = 0.25; ranked by score
    the hit comes first: precision 1 at recall 0.5, AP 0.5."""
    gts = [np.array([_car(10.0)]), np.array([_car(20.0)])]
    preds = [(np.array([_car(30.0)]), np.array([0.3])), (gts[1], np.array([0.9]))]
    cell = ap_cell([_matches(preds, gts)], ["a", "a"], n_boot=20, global_sort=True)
    assert cell["ap50"]["overall"]["value"] == pytest.approx(0.25)
    assert cell["ap50_global"] == {"overall": {"value": 0.5, "low": 0.5, "high": 0.5}}
    assert set(cell["ap70_global"]) == {"overall"}
    assert "ap50_global" not in ap_cell([_matches(preds, gts)], ["a", "a"], n_boot=20)


def test_paired_difference_is_the_difference_of_the_seeds_aps_and_zero_against_itself():
    hit = [(g, np.full(len(g), 0.9)) for g in GTS]
    miss_b = [hit[0], hit[1], (np.zeros((0, 7)), np.zeros(0)), (np.zeros((0, 7)), np.zeros(0))]
    a, b = [_matches(hit, GTS)] * 2, [_matches(hit, GTS), _matches(miss_b, GTS)]
    d = paired_difference(a, b, SCENES, n_boot=300, seed=2)
    assert d["value"] == pytest.approx(((1.0 - 1.0) + (1.0 - 0.6)) / 2)
    assert 0.0 <= d["low"] <= d["value"] <= d["high"] <= 1.0
    assert paired_difference(b, b, SCENES, n_boot=50) == {"value": 0.0, "low": 0.0, "high": 0.0}
    # every replicate holds scene a (all found by both) or scene b (missed by seed 1 of b only)
    far = paired_difference(a, b, SCENES, n_boot=50, band="50-100")
    assert far == {"value": 0.0, "low": 0.0, "high": 0.0}      # the only far car is scene a's
    with pytest.raises(ValueError, match="paired seeds"):
        paired_difference(a, b[:1], SCENES, n_boot=10)
