"""The town's geometry as solids: what each mesh part encloses, for volumetric ground truth.

The ray caster only needs surfaces; semantic occupancy needs to know what is *inside* them.
So :func:`typ.sim.town.build_town` records every static object also as a solid, in world
coordinates (metres, z up, ground at z = 0), with its :data:`typ.scene.SEMANTIC_CODE`:

- ``boxes`` (K, 6) float64 axis-aligned ``[x0, y0, z0, x1, y1, z1]``: buildings, sidewalks,
  light arms, sign plates, and the ground surfaces (roads, open land) as slabs
  :data:`SURFACE_DEPTH` m deep under z = 0, since a surface has no volume of its own;
- ``cylinders`` (C, 5) float64 vertical ``[x, y, z0, z1, radius]``: poles and tree trunks;
- ``ellipsoids`` (E, 6) float64 axis-aligned ``[cx, cy, cz, rx, ry, rz]``: tree canopies.

Tree trunks are recorded split at the canopy's lowest point: the part below as ``pole``, the
part inside the canopy as ``vegetation`` (V2VSSC's height split of trees into trunk and canopy).
Vehicles move, so they are not here: their solids are their boxes (:meth:`typ.sim.Traffic.boxes`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: depth (m) of the slab that stands for a ground surface (road, open land) under its top face
SURFACE_DEPTH = 0.2


@dataclass(frozen=True)
class Solids:
    """Static solids of a town, world frame; each kind with a (n,) uint8 semantic code array."""

    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    box_code: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    cylinders: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))
    cylinder_code: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    ellipsoids: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))
    ellipsoid_code: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))


class SolidsBuilder:
    """Accumulates solids like :class:`typ.sim.mesh.MeshBuilder` accumulates their surfaces."""

    def __init__(self) -> None:
        self._parts: dict[str, list[np.ndarray]] = {"boxes": [], "cylinders": [], "ellipsoids": []}
        self._codes: dict[str, list[np.ndarray]] = {"boxes": [], "cylinders": [], "ellipsoids": []}

    def _add(self, kind: str, rows: np.ndarray, code: int) -> None:
        self._parts[kind].append(rows)
        self._codes[kind].append(np.full(len(rows), code, dtype=np.uint8))

    def boxes(self, lo, hi, code: int) -> None:
        """K axis-aligned boxes from corners ``lo``, ``hi`` (K, 3)."""
        lo, hi = (np.asarray(a, dtype=np.float64).reshape(-1, 3) for a in (lo, hi))
        self._add("boxes", np.c_[lo, hi], code)

    def surfaces(self, x0, x1, y0, y1, z, code: int) -> None:
        """K horizontal rectangles at height ``z`` (args (K,) or scalars), as slabs SURFACE_DEPTH deep."""
        x0, x1, y0, y1, z = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, dtype=np.float64))
                                                 for a in (x0, x1, y0, y1, z)))
        self.boxes(np.c_[x0, y0, z - SURFACE_DEPTH], np.c_[x1, y1, z], code)

    def cylinders(self, xy, z0, z1, radius, code: int) -> None:
        """K vertical cylinders (``xy`` (K, 2); ``z0``, ``z1``, ``radius`` (K,) or scalars)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        z0, z1, radius = (np.broadcast_to(np.asarray(a, dtype=np.float64), len(xy)) for a in (z0, z1, radius))
        self._add("cylinders", np.c_[xy, z0, z1, radius], code)

    def ellipsoids(self, centre, radii, code: int) -> None:
        """K axis-aligned ellipsoids (``centre``, ``radii`` (K, 3))."""
        centre, radii = (np.asarray(a, dtype=np.float64).reshape(-1, 3) for a in (centre, radii))
        self._add("ellipsoids", np.c_[centre, radii], code)

    def build(self) -> Solids:
        width = {"boxes": 6, "cylinders": 5, "ellipsoids": 6}
        arrays = {kind: np.concatenate(parts) if parts else np.zeros((0, width[kind]))
                  for kind, parts in self._parts.items()}
        return Solids(boxes=arrays["boxes"], box_code=_cat(self._codes["boxes"]),
                      cylinders=arrays["cylinders"], cylinder_code=_cat(self._codes["cylinders"]),
                      ellipsoids=arrays["ellipsoids"], ellipsoid_code=_cat(self._codes["ellipsoids"]))


def _cat(codes: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(codes) if codes else np.zeros(0, np.uint8)
