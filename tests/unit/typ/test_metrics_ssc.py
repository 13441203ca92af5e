"""ssc_iou on hand-worked cases (SSCNet / SemanticKITTI / MonoScene conventions, V2VSSC's cIoU).

Classes (V2VSSC): 0 empty, 1 road, 2 car, 3 terrain, 4 building, 5 vegetation, 6 pole.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from typ.errors import TypError
from typ.metrics import SSC_CLASSES, ssc_iou

N = len(SSC_CLASSES)  # 7


def test_identical_maps_with_every_class_score_one():
    gt = np.array([0, 1, 2, 3, 4, 5, 6, 6, 0])
    r = ssc_iou(gt.copy(), gt, N)
    assert r["iou"] == 1.0 and r["precision"] == 1.0 and r["recall"] == 1.0
    assert r["iou_per_class"].tolist() == [1.0] * 6
    assert r["miou"] == 1.0 and r["ciou"] == 1.0


def test_class_absent_from_both_counts_as_zero_in_miou():
    # Identical maps holding only road and car: road, car IoU 1; the 4 absent classes 0 (SemanticKITTI,
    # MonoScene), so mIoU = 2/6 while geometric IoU and cIoU are 1.
    gt = np.array([0, 1, 1, 2])
    r = ssc_iou(gt.copy(), gt, N)
    assert r["iou"] == 1.0 and r["ciou"] == 1.0
    assert r["iou_per_class"].tolist() == [1.0, 1.0, 0.0, 0.0, 0.0, 0.0]
    assert r["miou"] == pytest.approx(2 / 6)


def test_disjoint_maps_score_zero():
    gt = np.array([1, 2, 3, 0, 0, 0])
    pred = np.array([0, 0, 0, 1, 2, 3])
    r = ssc_iou(pred, gt, N)
    assert r["iou"] == 0.0 and r["precision"] == 0.0 and r["recall"] == 0.0
    assert r["miou"] == 0.0 and r["ciou"] == 0.0


def test_one_class_swapped_by_hand():
    gt = np.array([1, 1, 2, 2, 3, 0, 0, 0])
    pred = np.array([1, 1, 2, 3, 2, 0, 0, 4])
    r = ssc_iou(pred, gt, N)
    # occupied: truth {0..4} (5), prediction {0..4, 7} (6), TP 5, FP 1, FN 0
    assert r["iou"] == pytest.approx(5 / 6)
    assert r["precision"] == pytest.approx(5 / 6) and r["recall"] == 1.0
    # road 2/2; car gt {2,3} pred {2,4}: 1/3; terrain gt {4} pred {3}: 0/2; building pred {7} only: 0/1
    assert r["iou_per_class"] == pytest.approx([1.0, 1 / 3, 0.0, 0.0, 0.0, 0.0])
    assert r["miou"] == pytest.approx((1 + 1 / 3) / 6)
    assert r["ciou"] == pytest.approx((1 + 1 / 3) / 2)
    assert r["confusion"][2, 3] == 1 and r["confusion"][3, 2] == 1 and r["confusion"][0, 4] == 1
    assert r["confusion"].sum() == 8


def test_ignore_and_mask_leave_voxels_out_of_every_count():
    gt = np.array([1, 255, 2, 2, 0])
    pred = np.array([1, 4, 2, 0, 3])
    mask = np.array([True, True, True, True, False])
    r = ssc_iou(pred, gt, N, mask=mask)
    # kept: voxels 0, 2, 3. occupied truth {0,2,3}, pred {0,2}: TP 2, FN 1, FP 0
    assert r["iou"] == pytest.approx(2 / 3) and r["precision"] == 1.0 and r["recall"] == pytest.approx(2 / 3)
    assert r["iou_per_class"] == pytest.approx([1.0, 0.5, 0.0, 0.0, 0.0, 0.0])  # the building FP was ignored
    assert r["confusion"].sum() == 3
    # a different ignore value
    r2 = ssc_iou(np.array([1, 1]), np.array([1, 7]), 7, ignore=7)
    assert r2["iou"] == 1.0 and r2["confusion"].sum() == 1


def test_counts_are_pooled_over_frames_and_list_equals_stack():
    a_gt, a_pred = np.array([1, 1, 1, 1]), np.array([1, 1, 1, 1])
    b_gt, b_pred = np.array([1, 0, 0, 0]), np.array([0, 1, 0, 0])
    r = ssc_iou([a_pred, b_pred], [a_gt, b_gt], N)
    # road pooled: TP 4, truth 5, pred 5 -> 4 / 6 (the per-frame mean would be (1 + 0) / 2)
    assert r["iou_per_class"][0] == pytest.approx(4 / 6) and r["iou"] == pytest.approx(4 / 6)
    s = ssc_iou(np.stack([a_pred, b_pred]), np.stack([a_gt, b_gt]), N)
    assert s["iou"] == r["iou"] and np.array_equal(s["confusion"], r["confusion"])
    # frames of different shapes are fine in a list
    r3 = ssc_iou([a_pred, np.array([[1, 0], [0, 0]])], [a_gt, np.array([[1, 0], [0, 2]])], N)
    assert r3["confusion"].sum() == 8 and r3["recall"] == pytest.approx(5 / 6)


def test_3d_grid_and_ciou_undefined_for_other_class_sets():
    gt = np.zeros((4, 4, 2), dtype=np.uint8)
    gt[0, :, 0] = 1
    pred = gt.copy()
    pred[0, 0, 0] = 0
    r = ssc_iou(pred, gt, 3)
    assert r["iou"] == pytest.approx(3 / 4) and r["iou_per_class"] == pytest.approx([3 / 4, 0.0])
    assert math.isnan(r["ciou"])


def test_empty_everywhere_gives_nan_geometry_and_zero_miou():
    z = np.zeros(5, dtype=np.int64)
    r = ssc_iou(z, z, N)
    assert math.isnan(r["iou"]) and math.isnan(r["precision"]) and r["miou"] == 0.0


@pytest.mark.parametrize("pred,gt,kw,field", [
    (np.zeros(3, int), np.zeros(4, int), {}, "pred"),
    (np.array([0, 9]), np.array([0, 1]), {}, "pred"),
    (np.array([0, 1]), np.array([0, 7]), {}, "gt"),
    (np.zeros(3, bool), np.zeros(3, int), {}, "pred"),
    (np.zeros(3, float), np.zeros(3, int), {}, "pred"),
    ([np.zeros(3, int)], [np.zeros(3, int)] * 2, {}, "pred"),
    (np.zeros(3, int), np.zeros(3, int), {"mask": np.ones(3, int)}, "mask"),
    (np.zeros(3, int), np.zeros(3, int), {"n_classes": 1}, "n_classes"),
])
def test_bad_input_is_a_named_typerror(pred, gt, kw, field):
    kw = {"n_classes": N, **kw}
    n = kw.pop("n_classes")
    with pytest.raises(TypError) as e:
        ssc_iou(pred, gt, n, **kw)
    assert e.value.field == field and e.value.where == "ssc_iou"


def test_ssc_scores_of_a_pooled_matrix_equal_ssc_iou_and_a_bad_matrix_is_named():
    from typ.metrics.ssc import ssc_scores

    rng = np.random.default_rng(3)
    pred, gt = rng.integers(0, 7, (2, 8, 8, 4)), rng.integers(0, 7, (2, 8, 8, 4))
    whole = ssc_iou(pred, gt, 7)
    split = ssc_scores(ssc_iou(pred[:1], gt[:1], 7)["confusion"] + ssc_iou(pred[1:], gt[1:], 7)["confusion"])
    for key in ("iou", "miou", "ciou", "precision", "recall"):
        assert split[key] == whole[key]
    with pytest.raises(TypError, match="confusion"):
        ssc_scores(np.zeros((7, 6)))
