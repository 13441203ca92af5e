"""ap_by_range / pr_curves on hand-worked cases (OpenCOOD / V2V4Real evaluation conventions).

AP by hand, as OpenCOOD's voc_ap: mrec = [0, rec..., 1], mpre = [0, prec..., 0] made
non-increasing from the right, AP = sum over recall steps of (mrec[i] - mrec[i-1]) * mpre[i].
All boxes are 4 x 2 cars; two of them shifted by dx along x have BEV IoU (4 - dx) / (4 + dx).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from typ.errors import TypError
from typ.metrics import PRCurve, ap_by_range, pr_curves


def car(x=10.0, y=0.0, yaw=0.0, z=0.0):
    return [x, y, z, 4.0, 2.0, 1.5, yaw]


def pred(*pairs):
    """pred((box, score), ...) -> (boxes (N, 7), scores (N,))."""
    return np.array([b for b, _ in pairs]), np.array([s for _, s in pairs])


def test_one_perfect_detection():
    # rec [1], prec [1] -> mrec [0, 1, 1], mpre [1, 1, 0]: AP = 1 * 1
    ap = ap_by_range([pred((car(), 0.9))], [np.array([car()])])
    assert list(ap) == ["overall", "0-30", "30-50", "50-100"]
    assert ap["overall"] == 1.0 and ap["0-30"] == 1.0
    assert math.isnan(ap["30-50"]) and math.isnan(ap["50-100"])  # no gt there


def test_false_positive_ranked_above_true_positive():
    # ranking [FP 0.9, TP 0.8], 1 gt: rec [0, 1], prec [0, 1/2]
    # mrec [0, 0, 1, 1], mpre [0, 0, .5, 0] -> [.5, .5, .5, 0]; recall steps at i = 2 only:
    # AP = (1 - 0) * 0.5 = 0.5
    c = pr_curves([pred((car(20.0), 0.9), (car(), 0.8))], [np.array([car()])])["overall"]
    assert isinstance(c, PRCurve) and c.ap == pytest.approx(0.5) and c.num_gt == 1
    np.testing.assert_allclose(c.recall, [0, 1])
    np.testing.assert_allclose(c.precision, [0, 0.5])
    np.testing.assert_allclose(c.mrec, [0, 0, 1, 1])
    np.testing.assert_allclose(c.mpre, [0.5, 0.5, 0.5, 0])
    np.testing.assert_array_equal(c.tp, [False, True])


def test_false_positive_between_two_true_positives():
    # ranking [TP .9, FP .8, TP .7], 2 gts: rec [.5, .5, 1], prec [1, .5, 2/3]
    # mpre envelope at the recall steps i = 1 (0 -> .5) and i = 3 (.5 -> 1): 1 and 2/3
    # AP = .5 * 1 + .5 * 2/3 = 5/6
    gts = [np.array([car(), car(y=5.0)])]
    preds = [pred((car(), 0.9), (car(20.0), 0.8), (car(y=5.0), 0.7))]
    assert ap_by_range(preds, gts)["overall"] == pytest.approx(5 / 6)


def test_frame_order_versus_global_sort():
    # frame 1: gt at 10 m, one FP (score .4); frame 2: gt at 10 m, one exact TP (score .9); 2 gts.
    # frame order [FP, TP]: rec [0, .5], prec [0, .5]; mrec [0, 0, .5, 1], mpre [.5, .5, .5, 0]
    #   AP = (.5 - 0) * .5 + (1 - .5) * 0 = 0.25
    # global sort [TP, FP]: rec [.5, .5], prec [1, .5]; mrec [0, .5, .5, 1], mpre [1, 1, .5, 0]
    #   AP = .5 * 1 + .5 * 0 = 0.5
    preds = [pred((car(20.0), 0.4)), pred((car(), 0.9))]
    gts = [np.array([car()]), np.array([car()])]
    assert ap_by_range(preds, gts)["overall"] == pytest.approx(0.25)
    assert ap_by_range(preds, gts, global_sort=True)["overall"] == pytest.approx(0.5)
    c = pr_curves(preds, gts, global_sort=True)["overall"]
    np.testing.assert_allclose(c.scores, [0.9, 0.4])


def test_within_frame_ranking_is_by_score_not_input_order():
    # same as the FP-above-TP case with the input order reversed: still [FP .9, TP .8] -> 0.5
    preds = [pred((car(), 0.8), (car(20.0), 0.9))]
    assert ap_by_range(preds, [np.array([car()])])["overall"] == pytest.approx(0.5)


def test_duplicate_detection_is_false_positive():
    # 2 gts; [TP .9 on g1, duplicate .8 on g1 -> FP (g1 taken), TP .7 on g2] = 5/6 as above
    gts = [np.array([car(), car(y=5.0)])]
    preds = [pred((car(), 0.9), (car(), 0.8), (car(y=5.0), 0.7))]
    c = pr_curves(preds, gts)["overall"]
    np.testing.assert_array_equal(c.tp, [True, False, True])
    assert c.ap == pytest.approx(5 / 6)
    assert ap_by_range([pred((car(), 0.9), (car(), 0.8))], [np.array([car()])])["overall"] == 1.0


def test_duplicate_takes_next_free_gt_when_it_overlaps_enough():
    # OpenCOOD matches against the *remaining* gts: gts at x = 10 and 10.5, two detections at
    # 10.25 (IoU 3.75 / 4.25 = .88 with both); the first takes one gt, the second the other.
    # (VOC would make the second an FP because its best gt is taken.) [TP, TP] -> AP 1.
    gts = [np.array([car(10.0), car(10.5)])]
    preds = [pred((car(10.25), 0.9), (car(10.25), 0.8))]
    assert ap_by_range(preds, gts)["overall"] == 1.0


@pytest.mark.parametrize("thr, dx, is_tp", [
    (0.5, 1.30, True),   # IoU 2.70 / 5.30 = 0.5094
    (0.5, 1.37, False),  # IoU 2.63 / 5.37 = 0.4898
    (0.7, 0.70, True),   # IoU 3.30 / 4.70 = 0.7021
    (0.7, 0.72, False),  # IoU 3.28 / 4.72 = 0.6949
])
def test_iou_just_over_and_under_threshold(thr, dx, is_tp):
    ap = ap_by_range([pred((car(10.0 + dx), 0.9))], [np.array([car()])], iou_thr=thr)
    assert ap["overall"] == (1.0 if is_tp else 0.0)


def test_range_bands_planar_centre_distance():
    # centre (24, 32) is 40 m away in the plane (z = 5 ignored): only 30-50 and overall
    box = car(24.0, 32.0, yaw=0.3, z=5.0)
    ap = ap_by_range([pred((box, 0.9))], [np.array([box])])
    assert ap["overall"] == 1.0 and ap["30-50"] == 1.0
    assert math.isnan(ap["0-30"]) and math.isnan(ap["50-100"])
    c = pr_curves([pred((box, 0.9))], [np.array([box])])
    assert [c[k].num_gt for k in c] == [1, 0, 1, 0]


def test_band_bounds_are_strict():
    # a car at exactly 30 m is in neither 0-30 nor 30-50 (V2V4Real: left < d < right)
    ap = ap_by_range([pred((car(30.0), 0.9))], [np.array([car(30.0)])])
    assert ap["overall"] == 1.0 and math.isnan(ap["0-30"]) and math.isnan(ap["30-50"])


def test_predictions_are_filtered_by_band_too():
    # det at 29 m, gt at 31 m: IoU 2 / 6 = 1/3 >= 0.3 -> TP overall (AP 1); in 0-30 the det is
    # an FP with no gt (NaN); in 30-50 the gt has no det (AP 0)
    ap = ap_by_range([pred((car(29.0), 0.9))], [np.array([car(31.0)])], iou_thr=0.3)
    assert ap["overall"] == 1.0 and ap["30-50"] == 0.0 and math.isnan(ap["0-30"])


def test_none_predictions():
    # frame 1 has no prediction but one gt, frame 2 one exact TP: rec [.5], prec [1]
    # mrec [0, .5, 1], mpre [1, 1, 0] -> AP = .5 * 1 + .5 * 0 = 0.5
    gts = [np.array([car()]), np.array([car()])]
    assert ap_by_range([None, pred((car(), 0.9))], gts)["overall"] == pytest.approx(0.5)
    empty = (np.zeros((0, 7)), np.zeros(0))
    assert ap_by_range([empty, pred((car(), 0.9))], gts)["overall"] == pytest.approx(0.5)
    # nothing predicted anywhere: mrec [0, 1], mpre [0, 0] -> AP 0 (as OpenCOOD)
    ap = ap_by_range([None, None], gts)
    assert ap["overall"] == 0.0 and ap["0-30"] == 0.0 and math.isnan(ap["30-50"])


def test_zero_gts_gives_nan():
    ap = ap_by_range([pred((car(), 0.9))], [np.zeros((0, 7))])
    assert all(math.isnan(v) for v in ap.values())
    assert math.isnan(ap_by_range([], [])["overall"])


def test_custom_ranges_and_bad_input():
    ap = ap_by_range([pred((car(), 0.9))], [np.array([car()])], ranges=((0, 12.5),))
    assert ap == {"overall": 1.0, "0-12.5": 1.0}
    with pytest.raises(TypError):
        ap_by_range([None], [])
    with pytest.raises(TypError):
        ap_by_range([(np.zeros((1, 6)), np.zeros(1))], [np.zeros((0, 7))])
    with pytest.raises(TypError):
        ap_by_range([(np.array([car()]), np.zeros(2))], [np.zeros((0, 7))])
    with pytest.raises(TypError):
        ap_by_range([None], [np.zeros((0, 7))], iou_thr=0.0)
    with pytest.raises(TypError):
        ap_by_range([None], [np.zeros((0, 7))], ranges=((30, 0),))


def test_ap_of_frames_pools_any_choice_and_order_of_frames():
    """Matching once per frame, then AP over chosen frames, is AP on those frames alone."""
    from typ.metrics import ap_of_frames, frame_matches

    rng = np.random.default_rng(0)
    gts = [np.array([car(x) for x in rng.uniform(5, 80, k)]) for k in (2, 3, 1, 4)]
    preds = [pred(*[(car(b[0] + rng.normal(0, 0.4)), s) for b, s in zip(g, rng.random(len(g)))],
                  (car(40.0, 20.0), 0.95)) for g in gts]
    m = frame_matches(preds, gts, iou_thr=0.5)
    for frames in ([0, 1, 2, 3], [2, 0], [3, 3, 1], [1]):
        expected = ap_by_range([preds[i] for i in frames], [gts[i] for i in frames], iou_thr=0.5)
        for band in m.bands:
            got = ap_of_frames(m, band, frames)
            assert (math.isnan(got) and math.isnan(expected[band])) or got == pytest.approx(expected[band]), band
    assert list(m.num_gt["overall"]) == [2, 3, 1, 4]
