"""float64 SE(3) helpers with OpenCOOD's conventions.

Frames: right-handed as OpenCOOD treats them; x forward, y left, z up in a sensor
frame. A *pose* is OPV2V/CARLA's ``[x, y, z, roll, yaw, pitch]`` (metres, degrees)
of a frame in world coordinates; ``pose_to_matrix(pose)`` is the 4x4 that maps
points from that frame into the world (OpenCOOD ``x_to_world``).
A *box* is ``[x, y, z, l, w, h, yaw]``: centre (metres), sizes along the box's own
x (length), y (width), z (height), and yaw (radians) about +z, counter-clockwise
from +x. Corner order follows OpenCOOD's ``boxes_to_corners_3d``/``create_bbx``:
the bottom face first, ``(+l,-w), (+l,+w), (-l,+w), (-l,-w)``, then the same for the top.
All arithmetic is float64; cast to float32 only after moving into a local frame.
"""
from __future__ import annotations

import numpy as np

from typ.errors import TypError


def _as_f64(a, shape_tail: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.shape[len(arr.shape) - len(shape_tail):] != shape_tail:
        raise TypError(None, name, f"array with trailing shape {shape_tail}", arr.shape)
    if not np.isfinite(arr).all():
        raise TypError(None, name, "finite values (no NaN/Inf)", "non-finite entries")
    return arr


def pose_to_matrix(pose) -> np.ndarray:
    """``[x, y, z, roll, yaw, pitch]`` (m, deg) -> (4, 4) float64 frame-to-world (OpenCOOD ``x_to_world``).

    Rotation is ``Rz(yaw) @ Ry(-pitch) @ Rx(-roll)`` written out exactly as OpenCOOD does,
    so that matrices match theirs entry for entry (CARLA's left-handed angles).
    """
    x, y, z, roll, yaw, pitch = _as_f64(pose, (6,), "pose")
    cy, sy = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    cr, sr = np.cos(np.radians(roll)), np.sin(np.radians(roll))
    cp, sp = np.cos(np.radians(pitch)), np.sin(np.radians(pitch))
    m = np.eye(4)
    m[0, 3], m[1, 3], m[2, 3] = x, y, z
    m[0, 0] = cp * cy
    m[0, 1] = cy * sp * sr - sy * cr
    m[0, 2] = -cy * sp * cr - sy * sr
    m[1, 0] = sy * cp
    m[1, 1] = sy * sp * sr + cy * cr
    m[1, 2] = -sy * sp * cr + cy * sr
    m[2, 0] = sp
    m[2, 1] = -cp * sr
    m[2, 2] = cp * cr
    return m


def matrix_to_pose(matrix) -> np.ndarray:
    """Inverse of :func:`pose_to_matrix`: (4, 4) -> ``[x, y, z, roll, yaw, pitch]`` (m, deg).

    Pitch is taken in [-90, 90] degrees; roll and yaw in (-180, 180].
    """
    m = _as_f64(matrix, (4, 4), "matrix")
    pitch = np.degrees(np.arcsin(np.clip(m[2, 0], -1.0, 1.0)))
    roll = np.degrees(np.arctan2(-m[2, 1], m[2, 2]))
    yaw = np.degrees(np.arctan2(m[1, 0], m[0, 0]))
    return np.array([m[0, 3], m[1, 3], m[2, 3], roll, yaw, pitch], dtype=np.float64)


def invert(matrix) -> np.ndarray:
    """Exact inverse of a rigid (4, 4) transform: ``[R t]^-1 = [R^T, -R^T t]``."""
    m = _as_f64(matrix, (4, 4), "matrix")
    out = np.eye(4)
    r = m[:3, :3]
    out[:3, :3] = r.T
    out[:3, 3] = -r.T @ m[:3, 3]
    return out


def relative_transform(pose_from, pose_to) -> np.ndarray:
    """(4, 4) mapping points in frame ``pose_from`` into frame ``pose_to`` (OpenCOOD ``x1_to_x2``).

    Accepts poses as 6-vectors or as (4, 4) frame-to-world matrices.
    """
    a = _pose_or_matrix(pose_from, "pose_from")
    b = _pose_or_matrix(pose_to, "pose_to")
    return invert(b) @ a


def _pose_or_matrix(p, name: str) -> np.ndarray:
    arr = np.asarray(p, dtype=np.float64)
    if arr.shape == (6,):
        return pose_to_matrix(arr)
    return _as_f64(arr, (4, 4), name)


def transform_points(matrix, points) -> np.ndarray:
    """Apply (4, 4) ``matrix`` to ``points`` (N, >=3); extra columns are kept; float64 out."""
    m = _as_f64(matrix, (4, 4), "matrix")
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise TypError(None, "points", "array of shape (N, >=3)", pts.shape)
    out = pts.copy()
    out[:, :3] = pts[:, :3] @ m[:3, :3].T + m[:3, 3]
    return out


def wrap_angle(angle):
    """Wrap radians into [-pi, pi)."""
    a = np.asarray(angle, dtype=np.float64)
    return (a + np.pi) % (2.0 * np.pi) - np.pi


_CORNER_SIGNS = np.array(
    [[1, -1, -1], [1, 1, -1], [-1, 1, -1], [-1, -1, -1],
     [1, -1, 1], [1, 1, 1], [-1, 1, 1], [-1, -1, 1]], dtype=np.float64) / 2.0


def box_corners(boxes) -> np.ndarray:
    """``(K, 7)`` boxes -> ``(K, 8, 3)`` corners in OpenCOOD's order (see module doc)."""
    b = _as_f64(boxes, (7,), "boxes").reshape(-1, 7)
    local = _CORNER_SIGNS[None, :, :] * b[:, None, 3:6]
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    rot = np.zeros((len(b), 3, 3))
    rot[:, 0, 0], rot[:, 0, 1] = c, -s
    rot[:, 1, 0], rot[:, 1, 1] = s, c
    rot[:, 2, 2] = 1.0
    return np.einsum("kij,kcj->kci", rot, local) + b[:, None, :3]


def transform_boxes(matrix, boxes) -> np.ndarray:
    """Move ``(K, 7)`` boxes by a rigid (4, 4) transform.

    The centre is transformed exactly; the yaw gains the rotation of the box's heading
    vector projected on the xy-plane (boxes stay upright, as in OpenCOOD's BEV boxes).
    """
    m = _as_f64(matrix, (4, 4), "matrix")
    b = _as_f64(boxes, (7,), "boxes").reshape(-1, 7).copy()
    if len(b) == 0:
        return b
    b[:, :3] = b[:, :3] @ m[:3, :3].T + m[:3, 3]
    heading = np.stack([np.cos(b[:, 6]), np.sin(b[:, 6]), np.zeros(len(b))], axis=1) @ m[:3, :3].T
    b[:, 6] = wrap_angle(np.arctan2(heading[:, 1], heading[:, 0]))
    return b


def points_in_boxes(points, boxes) -> np.ndarray:
    """(N, K) bool: point n lies inside box k (closed box, upright, in the same frame).

    Each box tests only the points whose x lies within its planar reach (half its xy diagonal,
    plus a margin for round-off) of its centre, found by binary search in the points sorted by x;
    those get the exact test. 50 k points against 30 boxes: 77 ms testing every pair, 16 ms this
    way (2-core AMD EPYC); the answer is the same bit for bit (the same arithmetic on every point
    that can be inside; tests/unit/typ/test_geometry.py checks it against the test of every pair)."""
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    b = _as_f64(boxes, (7,), "boxes").reshape(-1, 7)
    out = np.zeros((len(pts), len(b)), dtype=bool)
    if len(pts) == 0 or len(b) == 0:
        return out
    order = np.argsort(pts[:, 0], kind="stable")
    xs = pts[order, 0]
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    half = b[:, 3:6] / 2.0
    reach = np.hypot(half[:, 0], half[:, 1]) * (1 + 1e-9) + 1e-9
    lo = np.searchsorted(xs, b[:, 0] - reach, side="left")
    hi = np.searchsorted(xs, b[:, 0] + reach, side="right")
    for k in range(len(b)):
        index = order[lo[k]:hi[k]]
        d = pts[index] - b[k, :3]
        lx = d[:, 0] * c[k] + d[:, 1] * s[k]
        ly = -d[:, 0] * s[k] + d[:, 1] * c[k]
        out[index, k] = (np.abs(lx) <= half[k, 0]) & (np.abs(ly) <= half[k, 1]) & (np.abs(d[:, 2]) <= half[k, 2])
    return out
