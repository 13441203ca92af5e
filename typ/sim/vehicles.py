"""Vehicle classes: realistic size distributions, paint reflectivity, and a two-box mesh.

Sizes ``(l, w, h)`` are metres along the vehicle's x (forward), y (left), z (up). A vehicle
stands on flat ground (z = 0); its box is ``[x, y, h/2, l, w, h, yaw]`` in the world and its
mesh lies exactly inside that box, so points that hit it fall inside the labelled box.
"""
from __future__ import annotations

import numpy as np

from typ.sim.mesh import boxes_oriented

VEHICLE_CLASSES: tuple[str, ...] = ("car", "van", "truck")

# (mean, std) of length, width, height; normal draws are clipped at 2.5 std.
# Trucks' lengths are uniform in [8, 11] m instead (rigid trucks to short semis).
_SIZE_STATS = {
    "car": ((4.5, 0.4), (1.85, 0.1), (1.5, 0.1)),
    "van": ((5.2, 0.3), (2.0, 0.08), (2.1, 0.12)),
    "truck": ((9.5, 0.0), (2.5, 0.05), (3.2, 0.15)),
}

# Two boxes per class as fractions of (l, w, h) in the box frame (x from -0.5 to 0.5 of l,
# y symmetric, z from 0 at the ground to 1 at the roof): [x0, x1, half-width, z0, z1].
# The first is the body (cars, vans) or cargo box (trucks), the second the cabin / tractor,
# so vehicles aren't plain bricks and the ground shows under the body.
_PARTS = {
    "car": ((-0.5, 0.5, 0.5, 0.13, 0.58), (-0.32, 0.18, 0.44, 0.58, 1.0)),
    "van": ((-0.5, 0.5, 0.5, 0.10, 0.45), (-0.5, 0.30, 0.48, 0.45, 1.0)),
    "truck": ((-0.5, 0.27, 0.5, 0.28, 1.0), (0.30, 0.5, 0.48, 0.10, 0.85)),
}

# Paint reflectivity: black, dark, mid (red/blue), silver, white, drawn with these weights.
_PAINTS = np.array([0.04, 0.12, 0.3, 0.5, 0.8])
_PAINT_WEIGHTS = np.array([0.2, 0.2, 0.2, 0.2, 0.2])

#: Triangles per vehicle in :func:`vehicle_mesh` (two boxes of 12).
TRIS_PER_VEHICLE = 24


def sample_sizes(labels: list[str] | tuple[str, ...], rng: np.random.Generator) -> np.ndarray:
    """(K, 3) float64 ``(l, w, h)`` for vehicles of the given class names."""
    out = np.empty((len(labels), 3))
    z = np.clip(rng.standard_normal((len(labels), 3)), -2.5, 2.5)
    u = rng.uniform(8.0, 11.0, len(labels))
    for k, label in enumerate(labels):
        stats = _SIZE_STATS[label]
        out[k] = [m + s * z[k, i] for i, (m, s) in enumerate(stats)]
        if label == "truck":
            out[k, 0] = u[k]
    return out


def sample_labels(n: int, probs: tuple[float, float, float], rng: np.random.Generator) -> tuple[str, ...]:
    """n class names drawn with probabilities ``probs`` for (car, van, truck)."""
    p = np.asarray(probs, dtype=np.float64)
    idx = rng.choice(len(VEHICLE_CLASSES), size=n, p=p / p.sum())
    return tuple(VEHICLE_CLASSES[i] for i in idx)


def sample_paint(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n,) float32 paint reflectivity in (0, 1): dark cars return less light."""
    base = rng.choice(_PAINTS, size=n, p=_PAINT_WEIGHTS)
    return np.clip(base * rng.uniform(0.85, 1.15, n), 0.02, 0.95).astype(np.float32)


def vehicle_boxes(xy: np.ndarray, yaw: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """(K, 7) world boxes ``[x, y, h/2, l, w, h, yaw]`` for vehicles at ``xy`` (K, 2), ``yaw`` (K,) rad."""
    return np.c_[xy, sizes[:, 2] / 2.0, sizes, yaw]


def vehicle_mesh(boxes: np.ndarray, labels: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Two-box meshes of K vehicles from world ``boxes`` (K, 7): vertices (16K, 3), triangles (24K, 3);
    triangles ``[24k, 24k+24)`` belong to vehicle k."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    parts = np.array([_PARTS[label] for label in labels]).reshape(-1, 2, 5)  # (K, 2, 5)
    size = boxes[:, None, 3:6]
    lo = np.stack([parts[..., 0] * size[..., 0], -parts[..., 2] * size[..., 1], parts[..., 3] * size[..., 2]], -1)
    hi = np.stack([parts[..., 1] * size[..., 0], parts[..., 2] * size[..., 1], parts[..., 4] * size[..., 2]], -1)
    xy = np.repeat(boxes[:, :2], 2, axis=0)
    yaw = np.repeat(boxes[:, 6], 2)
    return boxes_oriented(lo.reshape(-1, 3), hi.reshape(-1, 3), xy, yaw)
