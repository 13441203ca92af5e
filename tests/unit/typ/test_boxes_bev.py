"""Rotated BEV IoU and NMS (typ.boxes_bev) against hand-worked areas and a raster estimate."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from typ.boxes_bev import bev_corners, nms_bev, rotated_iou_bev, standup_iou_bev
from typ.errors import TypError
from typ.geometry import points_in_boxes


def car(x=0.0, y=0.0, yaw=0.0, l=4.0, w=2.0):
    return [x, y, 0.0, l, w, 1.5, yaw]


def iou1(a, b) -> float:
    return float(rotated_iou_bev([a], [b])[0, 0])


def test_bev_corners_opencood_order_ccw():
    c = bev_corners([car(10.0, 5.0)])
    # bottom face (+l,-w), (+l,+w), (-l,+w), (-l,-w) around the centre
    np.testing.assert_allclose(c[0], [[12, 4], [12, 6], [8, 6], [8, 4]])
    x, y = c[0, :, 0], c[0, :, 1]
    assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) == pytest.approx(8.0)  # CCW: +l*w
    assert bev_corners(np.zeros((0, 7))).shape == (0, 4, 2)


def test_identity_symmetry_disjoint_and_shapes():
    a = car(3.0, -2.0, 0.7)
    assert iou1(a, a) == pytest.approx(1.0, abs=1e-12)
    assert iou1(a, car(30.0)) == 0.0
    # shared edge only (x in [-2, 2] vs [2, 6]): zero area, not a spurious edge contribution
    assert iou1(car(0.0), car(4.0)) == pytest.approx(0.0, abs=1e-12)
    rng = np.random.default_rng(1)
    a = np.column_stack([rng.uniform(-2, 2, (5, 2)), np.zeros(5), rng.uniform(1, 5, (5, 3)),
                         rng.uniform(-np.pi, np.pi, 5)])
    b = a[::-1] + [0.5, -0.3, 0, 0, 0, 0, 0.4]
    m = rotated_iou_bev(a, b)
    assert m.shape == (5, 5) and m.dtype == np.float64
    np.testing.assert_allclose(m, rotated_iou_bev(b, a).T, atol=1e-12)
    assert rotated_iou_bev(np.zeros((0, 7)), b).shape == (0, 5)


def test_shift_along_length():
    # 4 x 2 boxes shifted by 1 m along x: inter = 3 * 2 = 6, union = 8 + 8 - 6 = 10
    assert iou1(car(), car(1.0)) == pytest.approx(0.6)


def test_rotated_90_degrees_vs_itself():
    # l x w box vs itself turned 90 deg: overlap is the w x w square in the middle,
    # IoU = w^2 / (2 l w - w^2) = w / (2 l - w) = 2 / 6 for 4 x 2
    assert iou1(car(), car(yaw=np.pi / 2)) == pytest.approx(1.0 / 3.0, abs=1e-12)


def test_unit_square_rotated_45_degrees():
    # the overlap is a regular octagon: 1 - 4 corner triangles with legs 1 - 1/sqrt2,
    # area 2 sqrt2 - 2; union = 2 - (2 sqrt2 - 2) = 4 - 2 sqrt2, IoU = 1 / sqrt2
    sq = car(l=1.0, w=1.0)
    assert iou1(sq, car(l=1.0, w=1.0, yaw=np.pi / 4)) == pytest.approx(2 ** -0.5, abs=1e-12)


def test_zero_area_box_has_zero_iou_and_bad_input_raises():
    assert iou1(car(l=0.0), car(l=0.0)) == 0.0
    with pytest.raises(TypError):
        rotated_iou_bev(np.zeros((2, 6)), np.zeros((1, 7)))
    with pytest.raises(TypError):
        rotated_iou_bev([car(x=np.nan)], [car()])
    with pytest.raises(TypError):
        rotated_iou_bev([car(l=-1.0)], [car()])


def raster_iou(a, b, n=300) -> float:
    corners = bev_corners(np.array([a, b])).reshape(-1, 2)
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    xs = lo[0] + (np.arange(n) + 0.5) * (hi[0] - lo[0]) / n
    ys = lo[1] + (np.arange(n) + 0.5) * (hi[1] - lo[1]) / n
    gx, gy = np.meshgrid(xs, ys)
    pts = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    inside = points_in_boxes(pts, np.array([a, b]))
    both = np.count_nonzero(inside.all(axis=1))
    return both / np.count_nonzero(inside.any(axis=1))


box_st = st.tuples(st.floats(-2, 2), st.floats(-2, 2), st.floats(0.5, 6), st.floats(0.5, 3),
                   st.floats(-np.pi, np.pi)).map(lambda t: car(t[0], t[1], t[4], t[2], t[3]))


@settings(max_examples=40, deadline=None)
@given(box_st, box_st)
def test_rotated_iou_matches_raster_estimate(a, b):
    exact = iou1(a, b)
    assert exact == pytest.approx(iou1(b, a), abs=1e-12)
    assert 0.0 <= exact <= 1.0
    assert exact == pytest.approx(raster_iou(a, b), abs=0.01)


def test_standup_iou_opencood_plus_one_convention():
    # standup rects [-2,-1,2,1] and [-1,-1,3,1]; with bbox_overlaps' +1:
    # iw = 2 - (-1) + 1 = 4, ih = 1 - (-1) + 1 = 3, inter 12; areas 5 * 3 = 15 each -> 12 / 18
    m = standup_iou_bev([car()], [car(1.0), car(yaw=np.pi / 2), car(50.0)])
    assert m.dtype == np.float32
    # turned 90 deg: rects [-2,-1,2,1] vs [-1,-2,1,2]: inter (2+1)*(2+1) = 9, union 15 + 15 - 9
    np.testing.assert_allclose(m[0], [12 / 18, 9 / 21, 0.0], rtol=1e-6)


def test_nms_three_overlapping_boxes():
    # A (0.9) at x=0, B (0.8) at x=0.5, C (0.7) at x=3; 4 x 2 boxes shifted along x by dx
    # have IoU (4 - dx) / (4 + dx): A-B 3.5/4.5 = 0.778, A-C 1/7 = 0.143, B-C 1.5/6.5 = 0.231
    boxes = np.array([car(3.0), car(0.0), car(0.5)])  # C, A, B
    scores = np.array([0.7, 0.9, 0.8])
    np.testing.assert_array_equal(nms_bev(boxes, scores, 0.5), [1, 0])  # A kept, B gone, C kept
    np.testing.assert_array_equal(nms_bev(boxes, scores, 0.1), [1])  # C also > 0.1 with A
    np.testing.assert_array_equal(nms_bev(boxes, scores, 0.8), [1, 2, 0])  # nothing above 0.8
    # the cap keeps only the best max_candidates boxes, as OpenCOOD's top = 1000
    np.testing.assert_array_equal(nms_bev(boxes, scores, 0.5, max_candidates=1), [1])


def test_nms_ties_and_edge_cases():
    # equal scores: lower index ranks first; IoU exactly 1 > 0.5 suppresses the copy
    np.testing.assert_array_equal(nms_bev([car(), car()], [0.5, 0.5], 0.5), [0])
    # suppression is strict: IoU (0.6) equal to the threshold keeps both
    thr = iou1(car(), car(1.0))
    np.testing.assert_array_equal(nms_bev([car(), car(1.0)], [0.9, 0.8], thr), [0, 1])
    assert nms_bev(np.zeros((0, 7)), np.zeros(0), 0.5).shape == (0,)
    with pytest.raises(TypError):
        nms_bev([car()], [0.1, 0.2], 0.5)
