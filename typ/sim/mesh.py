"""Triangle-mesh primitives for the procedural town, built for many objects at once.

Every builder takes K objects as arrays and returns ``(vertices (K*v, 3) float64,
triangles (K*t, 3) int64)`` in world coordinates (metres, z up), with the triangles of
object k stored contiguously as rows ``[k*t, (k+1)*t)`` so a triangle's object is
``row // t``. Winding is not consistent: the ray caster only uses ``|cos|`` of normals.
:class:`MeshBuilder` stacks parts and keeps a per-triangle class and reflectivity.
"""
from __future__ import annotations

import numpy as np

# Unit cube corners, bottom face then top, and its 12 triangles.
_CUBE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                  [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float64)
_CUBE_TRIS = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7],
                       [0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5],
                       [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]], dtype=np.int64)


def _stack(verts: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, v, 3) per-object vertices + (t, 3) template triangles -> flat arrays with offsets."""
    k, v = verts.shape[:2]
    offs = (np.arange(k, dtype=np.int64) * v)[:, None, None]
    return verts.reshape(-1, 3), (tris[None] + offs).reshape(-1, 3)


def boxes_axis_aligned(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """K axis-aligned boxes from corners ``lo``/``hi`` (K, 3); 8 vertices, 12 triangles each."""
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    verts = lo[:, None, :] + _CUBE[None] * (hi - lo)[:, None, :]
    return _stack(verts, _CUBE_TRIS)


def boxes_oriented(local_lo: np.ndarray, local_hi: np.ndarray, xy: np.ndarray, yaw: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray]:
    """K boxes given in an object frame (``local_lo/hi`` (K, 3)), rotated by ``yaw`` (K,) rad
    about z and moved to ``xy`` (K, 2) on the ground; 8 vertices, 12 triangles each."""
    lo = np.asarray(local_lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(local_hi, dtype=np.float64).reshape(-1, 3)
    local = lo[:, None, :] + _CUBE[None] * (hi - lo)[:, None, :]
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    verts = np.empty_like(local)
    verts[..., 0] = c * local[..., 0] - s * local[..., 1] + xy[:, None, 0]
    verts[..., 1] = s * local[..., 0] + c * local[..., 1] + xy[:, None, 1]
    verts[..., 2] = local[..., 2]
    return _stack(verts, _CUBE_TRIS)


def _cylinder_template(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit cylinder (radius 1, z in [0, 1]) with n sides and a top cap: 2n+1 vertices, 3n triangles."""
    a = 2.0 * np.pi * np.arange(n) / n
    ring = np.stack([np.cos(a), np.sin(a)], axis=1)
    verts = np.concatenate([np.c_[ring, np.zeros(n)], np.c_[ring, np.ones(n)], [[0.0, 0.0, 1.0]]])
    i = np.arange(n)
    j = (i + 1) % n
    side = np.concatenate([np.stack([i, j, n + j], 1), np.stack([i, n + j, n + i], 1)])
    cap = np.stack([n + i, n + j, np.full(n, 2 * n)], 1)
    return verts, np.concatenate([side, cap]).astype(np.int64)


def cylinders(xy: np.ndarray, z0: np.ndarray, z1: np.ndarray, radius: np.ndarray, n: int = 8
              ) -> tuple[np.ndarray, np.ndarray]:
    """K vertical cylinders (centre ``xy`` (K, 2), from ``z0`` to ``z1``, ``radius``, all (K,))."""
    tv, tt = _cylinder_template(n)
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    verts = np.empty((len(xy), len(tv), 3))
    verts[..., :2] = xy[:, None, :] + tv[None, :, :2] * np.asarray(radius)[:, None, None]
    verts[..., 2] = np.asarray(z0)[:, None] + tv[None, :, 2] * (np.asarray(z1) - np.asarray(z0))[:, None]
    return _stack(verts, tt)


def _icosphere() -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere subdivided once: 42 vertices, 80 triangles."""
    p = (1.0 + 5 ** 0.5) / 2.0
    v = [[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0], [0, -1, p], [0, 1, p],
         [0, -1, -p], [0, 1, -p], [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]]
    f = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
         [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
         [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    verts = [np.array(x, dtype=np.float64) / np.linalg.norm(x) for x in v]
    mid: dict[tuple[int, int], int] = {}

    def midpoint(a: int, b: int) -> int:
        key = (min(a, b), max(a, b))
        if key not in mid:
            m = verts[a] + verts[b]
            verts.append(m / np.linalg.norm(m))
            mid[key] = len(verts) - 1
        return mid[key]

    faces = []
    for a, b, c in f:
        ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
        faces += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
    return np.array(verts), np.array(faces, dtype=np.int64)


_ICO_V, _ICO_T = _icosphere()


def ellipsoids(centre: np.ndarray, radii: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """K axis-aligned ellipsoids (``centre`` (K, 3), ``radii`` (K, 3)); 42 vertices, 80 triangles each."""
    centre = np.asarray(centre, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1, 3)
    verts = centre[:, None, :] + _ICO_V[None] * radii[:, None, :]
    return _stack(verts, _ICO_T)


class MeshBuilder:
    """Accumulates mesh parts, each with one semantic code and a per-object reflectivity."""

    def __init__(self) -> None:
        self._verts: list[np.ndarray] = []
        self._tris: list[np.ndarray] = []
        self._cls: list[np.ndarray] = []
        self._refl: list[np.ndarray] = []
        self._n = 0

    def add(self, part: tuple[np.ndarray, np.ndarray], code: int, reflectivity: np.ndarray | float) -> None:
        """Add ``part`` = (vertices, triangles); ``reflectivity`` is a scalar or one value per
        object (the part's triangles are split evenly among its objects, as the builders emit them)."""
        verts, tris = part
        if len(tris) == 0:
            return
        refl = np.atleast_1d(np.asarray(reflectivity, dtype=np.float32))
        self._verts.append(verts)
        self._tris.append(tris + self._n)
        self._cls.append(np.full(len(tris), code, dtype=np.uint8))
        self._refl.append(np.repeat(refl, len(tris) // len(refl)))
        self._n += len(verts)

    def build(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """-> vertices (V, 3) float32, triangles (T, 3) uint32, class (T,) uint8, reflectivity (T,) float32."""
        return (np.concatenate(self._verts).astype(np.float32),
                np.concatenate(self._tris).astype(np.uint32),
                np.concatenate(self._cls),
                np.concatenate(self._refl).astype(np.float32))
