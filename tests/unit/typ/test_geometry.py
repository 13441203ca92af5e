"""Hand-worked cases for typ.geometry (OpenCOOD's x_to_world / x1_to_x2 / create_bbx conventions).

Expected matrices are derived on paper from OpenCOOD's x_to_world entries
(m00 = cp cy, m01 = cy sp sr - sy cr, m02 = -cy sp cr - sy sr, m10 = sy cp,
m11 = sy sp sr + cy cr, m12 = -sy sp cr + cy sr, m20 = sp, m21 = -cp sr, m22 = cp cr).
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from typ import geometry as g
from typ.errors import TypError

C30, S30 = np.cos(np.radians(30)), np.sin(np.radians(30))


def rz(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def ry(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rx(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def test_pose_to_matrix_pure_yaw_90():
    m = g.pose_to_matrix([1.0, 2.0, 3.0, 0.0, 90.0, 0.0])
    # cy = 0, sy = 1, cr = cp = 1: m00 = 0, m01 = -1, m10 = 1, m11 = 0
    expected = np.array([[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1.0]])
    np.testing.assert_allclose(m, expected, atol=1e-15)
    assert m.dtype == np.float64


def test_pose_to_matrix_pure_pitch_30():
    m = g.pose_to_matrix([0, 0, 0, 0, 0, 30.0])
    # cy = cr = 1: m00 = cp, m02 = -sp, m20 = sp, m22 = cp -> the nose (x) tilts up
    expected = np.array([[C30, 0, -S30], [0, 1, 0], [S30, 0, C30]])
    np.testing.assert_allclose(m[:3, :3], expected, atol=1e-15)
    np.testing.assert_allclose(m[:3, :3] @ [1, 0, 0], [C30, 0, S30], atol=1e-15)


def test_pose_to_matrix_pure_roll_30():
    m = g.pose_to_matrix([0, 0, 0, 30.0, 0, 0])
    # cy = cp = 1: m11 = cr, m12 = sr, m21 = -sr, m22 = cr
    expected = np.array([[1, 0, 0], [0, C30, S30], [0, -S30, C30]])
    np.testing.assert_allclose(m[:3, :3], expected, atol=1e-15)


def test_pose_to_matrix_is_rz_ry_minus_pitch_rx_minus_roll():
    roll, yaw, pitch = 12.0, -137.0, 7.5
    m = g.pose_to_matrix([4, 5, 6, roll, yaw, pitch])
    np.testing.assert_allclose(m[:3, :3], rz(yaw) @ ry(-pitch) @ rx(-roll), atol=1e-14)
    np.testing.assert_allclose(m[:3, 3], [4, 5, 6])
    np.testing.assert_allclose(m[3], [0, 0, 0, 1])


def test_pose_to_matrix_rejects_bad_input():
    with pytest.raises(TypError, match="pose"):
        g.pose_to_matrix([0, 0, 0, 0, 0])
    with pytest.raises(TypError, match="finite"):
        g.pose_to_matrix([0, 0, np.nan, 0, 0, 0])


angles = st.floats(-179.0, 179.0)
poses = st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(-50, 50),
                  angles, angles, st.floats(-89.0, 89.0))


@settings(max_examples=60, deadline=None)
@given(poses)
def test_matrix_to_pose_round_trip(pose):
    m = g.pose_to_matrix(pose)
    back = g.matrix_to_pose(m)
    np.testing.assert_allclose(back[:3], pose[:3], atol=1e-9)
    np.testing.assert_allclose(g.wrap_angle(np.radians(back[3:] - np.array(pose[3:]))), 0, atol=1e-8)
    np.testing.assert_allclose(g.pose_to_matrix(back), m, atol=1e-12)
    np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0)


def test_invert_is_exact_inverse():
    m = g.pose_to_matrix([3, -4, 1, 5, 60, -10])
    np.testing.assert_allclose(g.invert(m) @ m, np.eye(4), atol=1e-14)


def test_relative_transform_hand_case():
    a = [0, 0, 0, 0, 0, 0]
    b = [10, 0, 0, 0, 90, 0]  # at (10, 0, 0), facing world +y
    t = g.relative_transform(a, b)
    # world point (10, 5, 1) is 5 m straight ahead of b and 1 m up
    np.testing.assert_allclose(g.transform_points(t, [[10, 5, 1]]), [[5, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(g.relative_transform(b, b), np.eye(4), atol=1e-14)


@settings(max_examples=30, deadline=None)
@given(poses, poses, poses)
def test_relative_transform_chains(a, b, c):
    ab, bc, ac = g.relative_transform(a, b), g.relative_transform(b, c), g.relative_transform(a, c)
    np.testing.assert_allclose(bc @ ab, ac, atol=1e-9)
    # matrices and 6-vectors are interchangeable
    np.testing.assert_allclose(g.relative_transform(g.pose_to_matrix(a), b), ab, atol=1e-12)


def test_box_corners_hand_worked():
    corners = g.box_corners([1, 2, 3, 4, 2, 1, np.pi / 2])
    # half sizes (2, 1, 0.5); a quarter turn maps local (x, y) to (-y, x); then + centre
    expected = np.array([[2, 4, 2.5], [0, 4, 2.5], [0, 0, 2.5], [2, 0, 2.5],
                         [2, 4, 3.5], [0, 4, 3.5], [0, 0, 3.5], [2, 0, 3.5]])
    assert corners.shape == (1, 8, 3)
    np.testing.assert_allclose(corners[0], expected, atol=1e-12)


def test_box_corners_order_matches_create_bbx():
    e = np.array([2.0, 1.0, 0.75])  # OpenCOOD extent = half sizes
    create_bbx = np.array([[e[0], -e[1], -e[2]], [e[0], e[1], -e[2]], [-e[0], e[1], -e[2]], [-e[0], -e[1], -e[2]],
                           [e[0], -e[1], e[2]], [e[0], e[1], e[2]], [-e[0], e[1], e[2]], [-e[0], -e[1], e[2]]])
    np.testing.assert_allclose(g.box_corners([0, 0, 0, *(2 * e), 0])[0], create_bbx)


def test_transform_boxes_matches_transformed_corners():
    boxes = np.array([[5, -2, 0.5, 4.2, 1.8, 1.5, 0.3], [-12, 7, 1.0, 2.0, 1.0, 2.0, -2.9]])
    m = g.pose_to_matrix([100, -50, 2, 0, 123, 0])
    moved = g.transform_boxes(m, boxes)
    corners = g.box_corners(boxes)
    expected = g.transform_points(m, corners.reshape(-1, 3)).reshape(corners.shape)
    np.testing.assert_allclose(g.box_corners(moved), expected, atol=1e-9)
    np.testing.assert_allclose(moved[:, 3:6], boxes[:, 3:6])
    assert g.transform_boxes(m, np.zeros((0, 7))).shape == (0, 7)


def test_transform_boxes_yaw_wraps():
    moved = g.transform_boxes(g.pose_to_matrix([0, 0, 0, 0, 90, 0]), [[0, 0, 0, 1, 1, 1, 3.0]])
    assert moved[0, 6] == pytest.approx(3.0 + np.pi / 2 - 2 * np.pi)


def test_wrap_angle():
    got = g.wrap_angle([np.pi, -np.pi, 1.5 * np.pi, -1.5 * np.pi, 2 * np.pi, 0.0, 0.5])
    np.testing.assert_allclose(got, [-np.pi, -np.pi, -np.pi / 2, np.pi / 2, 0, 0, 0.5], atol=1e-12)
    assert ((got >= -np.pi) & (got < np.pi)).all()


def test_points_in_boxes():
    # 4 m long box turned a quarter: it spans |x| <= 1, |y| <= 2, |z| <= 1
    box = [0, 0, 0, 4, 2, 2, np.pi / 2]
    pts = np.array([[0, 1.9, 0], [1.9, 0, 0], [1, 2, 1], [0, 0, 1.01], [-0.9, -1.9, -0.9]])
    inside = g.points_in_boxes(pts, box)
    assert inside.shape == (5, 1)
    assert inside[:, 0].tolist() == [True, False, True, False, True]
    two = g.points_in_boxes(pts, [box, [10, 10, 10, 1, 1, 1, 0]])
    assert two.shape == (5, 2) and not two[:, 1].any()


def _points_in_boxes_every_pair(points, boxes) -> np.ndarray:
    """The exact test on every (point, box) pair: the reference the pruned search must equal."""
    pts, b = np.asarray(points, float)[:, :3], np.asarray(boxes, float).reshape(-1, 7)
    d = pts[:, None, :] - b[None, :, :3]
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    lx, ly = d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c
    half = b[:, 3:6] / 2.0
    return (np.abs(lx) <= half[:, 0]) & (np.abs(ly) <= half[:, 1]) & (np.abs(d[..., 2]) <= half[:, 2])


@pytest.mark.parametrize("seed", range(5))
def test_points_in_boxes_equals_the_test_of_every_pair_corners_and_faces_included(seed):
    from typ.geometry import box_corners, points_in_boxes

    rng = np.random.default_rng(seed)
    boxes = np.column_stack([rng.uniform(-30, 30, (40, 2)), rng.uniform(-1, 1, 40), rng.uniform(0.5, 8, 40),
                             rng.uniform(0.5, 3, 40), rng.uniform(1, 3, 40), rng.uniform(-np.pi, np.pi, 40)])
    boxes[:5, 6] = [0.0, np.pi / 2, -np.pi, np.pi / 4, 1e-12]  # axis-aligned and diagonal boxes
    corners = box_corners(boxes).reshape(-1, 3)  # on the boundary: inside or not by round-off alone
    faces = (box_corners(boxes)[:, :4] + box_corners(boxes)[:, 4:]).reshape(-1, 3) / 2
    points = np.concatenate([rng.uniform([-35, -35, -2], [35, 35, 2], (20_000, 3)), corners, faces,
                             corners + rng.normal(0, 1e-9, corners.shape)])
    inside = points_in_boxes(points, boxes)
    np.testing.assert_array_equal(inside, _points_in_boxes_every_pair(points, boxes))
    assert inside.any(axis=0).all()  # every box holds points (a search that missed them would pass the rest)
    assert points_in_boxes(points[:0], boxes).shape == (0, 40) and points_in_boxes(points, boxes[:0]).shape == (len(points), 0)
