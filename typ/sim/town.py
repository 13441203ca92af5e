"""Procedural towns: a jittered grid of roads with kerbs, buildings, trees, poles and parked cars.

World frame: metres, z up, flat ground at z = 0, town centred on the origin. Roads are
axis-aligned: ``road_x`` are the centre lines of the roads running along y, ``road_y``
those running along x. Each road has ``lanes_per_direction`` lanes each way plus a parking
strip on both sides; traffic keeps right. Sidewalks (ground class) are raised by
``kerb_height``; everything outside the carriageways is ground at z = 0.
The static mesh is built once per scenario; parked cars are returned as vehicles (they get
boxes and ids) and meshed with the moving ones, see :mod:`typ.sim.vehicles`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from typ.scene import SEMANTIC_CODE
from typ.sim import mesh
from typ.sim.solids import Solids, SolidsBuilder
from typ.sim.vehicles import sample_labels, sample_paint, sample_sizes


@dataclass(frozen=True, kw_only=True)
class TownStyle:
    """How a domain's towns look; ranges are ``(low, high)`` for uniform draws."""

    n_roads: tuple[int, int] = (2, 3)              #: roads per direction
    block_size: tuple[float, float] = (70.0, 100.0)  #: spacing of parallel road centre lines (m)
    lane_width: float = 3.5
    lanes_per_direction: int = 2
    parking_width: float = 2.5                     #: parking strip along each kerb (m)
    sidewalk_width: float = 3.0
    kerb_height: float = 0.15
    margin: float = 60.0                           #: town extent beyond the outermost roads (m)
    building_density: float = 0.7                  #: probability that a lot holds a building
    building_height: tuple[float, float] = (6.0, 30.0)
    building_setback: tuple[float, float] = (2.0, 5.0)  #: gap sidewalk -> facade (m)
    building_depth: tuple[float, float] = (10.0, 25.0)
    lot_width: tuple[float, float] = (10.0, 30.0)
    tree_density: float = 4.0                      #: street trees per 100 m of sidewalk
    yard_trees: float = 0.5                        #: extra trees per 1000 m^2 of block interior
    pole_spacing: float = 30.0                     #: street lights along each sidewalk (m)
    parked_density: float = 0.3                    #: fraction of parking slots taken
    parked_class_probs: tuple[float, float, float] = (0.8, 0.15, 0.05)  #: car, van, truck

    @property
    def road_half_width(self) -> float:
        """Centre line to kerb (m): lanes plus the parking strip."""
        return self.lanes_per_direction * self.lane_width + self.parking_width

    @property
    def lane_offsets(self) -> np.ndarray:
        """(lanes,) lateral offsets of the lane centres from the road centre line, inner first."""
        return (np.arange(self.lanes_per_direction) + 0.5) * self.lane_width


@dataclass
class Town:
    """A static town: road layout, the static triangle mesh, and parked vehicles.

    vertices (V, 3) float32 world; triangles (T, 3) uint32; tri_class (T,) uint8 semantic
    codes; tri_reflectivity (T,) float32 in (0, 1). Parked vehicles: parked_xy (P, 2),
    parked_yaw (P,) rad, parked_sizes (P, 3) ``(l, w, h)``, parked_labels, parked_paint (P,).
    extent = (x0, x1, y0, y1) of the built area. solids: the same static objects as solids
    (:mod:`typ.sim.solids`), for volumetric ground truth.
    """

    style: TownStyle
    road_x: np.ndarray
    road_y: np.ndarray
    extent: tuple[float, float, float, float]
    vertices: np.ndarray
    triangles: np.ndarray
    tri_class: np.ndarray
    tri_reflectivity: np.ndarray
    parked_xy: np.ndarray
    parked_yaw: np.ndarray
    parked_sizes: np.ndarray
    parked_labels: tuple[str, ...]
    parked_paint: np.ndarray
    solids: Solids = Solids()


def _road_lines(n_range: tuple[int, int], spacing: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    n = int(rng.integers(n_range[0], n_range[1] + 1))
    lines = np.concatenate([[0.0], np.cumsum(rng.uniform(*spacing, n - 1))])
    return lines - lines.mean()


def _quads(x0, x1, y0, y1, z) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal rectangles at height z (all args (K,) or scalars): 4 vertices, 2 triangles each."""
    x0, x1, y0, y1, z = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (x0, x1, y0, y1, z)))
    verts = np.stack([np.c_[x0, y0, z], np.c_[x1, y0, z], np.c_[x1, y1, z], np.c_[x0, y1, z]], axis=1)
    return mesh._stack(verts, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64))


def _cells(lines: np.ndarray, hw: float, lo: float, hi: float) -> list[tuple[float, float, bool, bool]]:
    """Intervals between carriageways along one axis: (start, end, road_at_start, road_at_end)."""
    edges = [lo] + [v for c in lines for v in (c - hw, c + hw)] + [hi]
    return [(edges[2 * i], edges[2 * i + 1], i > 0, i < len(lines)) for i in range(len(lines) + 1)]


def build_town(style: TownStyle, rng: np.random.Generator) -> Town:
    """Build one town from ``style`` using only ``rng`` (same generator state -> same town)."""
    hw, sw = style.road_half_width, style.sidewalk_width
    road_x = _road_lines(style.n_roads, style.block_size, rng)
    road_y = _road_lines(style.n_roads, style.block_size, rng)
    ext = (road_x[0] - style.margin, road_x[-1] + style.margin, road_y[0] - style.margin, road_y[-1] + style.margin)
    b = mesh.MeshBuilder()
    s = SolidsBuilder()
    ground, road = SEMANTIC_CODE["ground"], SEMANTIC_CODE["road"]

    # Roads along y span the town; roads along x stop at the crossings, so no two surfaces
    # overlap coplanar (which one a ray hits there would be up to the BVH).
    b.add(_quads(road_x - hw, road_x + hw, ext[2], ext[3], 0.0), road, rng.uniform(0.07, 0.14, len(road_x)))
    s.surfaces(road_x - hw, road_x + hw, ext[2], ext[3], 0.0, road)
    x_cells = _cells(road_x, hw, ext[0], ext[1])
    for cy in road_y:
        b.add(_quads([c[0] for c in x_cells], [c[1] for c in x_cells], cy - hw, cy + hw, 0.0), road, rng.uniform(0.07, 0.14))
        s.surfaces([c[0] for c in x_cells], [c[1] for c in x_cells], cy - hw, cy + hw, 0.0, road)
    # Open land around the town, as a frame so it never overlaps the roads.
    far = 150.0
    frame = ([ext[0] - far, ext[1], ext[0], ext[0]], [ext[0], ext[1] + far, ext[1], ext[1]],
             [ext[2] - far, ext[2] - far, ext[2] - far, ext[3]], [ext[3] + far, ext[3] + far, ext[2], ext[3] + far], 0.0)
    b.add(_quads(*frame), ground, 0.3)
    s.surfaces(*frame, ground)

    buildings: list[np.ndarray] = []   # rows [x0, y0, x1, y1, height]
    sidewalks: list[list[float]] = []  # rows [x0, y0, x1, y1]
    street: list[tuple] = []           # (x0, y0, x1, y1, inward normal) of sidewalk strips, for trees/poles
    for cx0, cx1, road_l, road_r in x_cells:
        for cy0, cy1, road_b, road_t in _cells(road_y, hw, ext[2], ext[3]):
            b.add(_quads(cx0, cx1, cy0, cy1, 0.0), ground, rng.uniform(0.25, 0.45))
            s.surfaces(cx0, cx1, cy0, cy1, 0.0, ground)
            edges = []  # (road?, strip rect, inward normal)
            edges.append((road_b, [cx0, cy0, cx1, cy0 + sw], (0.0, 1.0)))
            edges.append((road_t, [cx0, cy1 - sw, cx1, cy1], (0.0, -1.0)))
            # Side strips stop where the bottom/top strips run, so strips never overlap.
            sy0, sy1 = cy0 + (sw if road_b else 0.0), cy1 - (sw if road_t else 0.0)
            edges.append((road_l, [cx0, sy0, cx0 + sw, sy1], (1.0, 0.0)))
            edges.append((road_r, [cx1 - sw, sy0, cx1, sy1], (-1.0, 0.0)))
            for is_road, rect, normal in edges:
                if is_road:
                    sidewalks.append(rect)
                    street.append((*rect, normal))
            buildings += _place_buildings(style, rng, (cx0, cx1, cy0, cy1), (road_b, road_t, road_l, road_r))

    sw_arr = np.array(sidewalks)
    sw_lo, sw_hi = np.c_[sw_arr[:, :2], np.zeros(len(sw_arr))], np.c_[sw_arr[:, 2:], np.full(len(sw_arr), style.kerb_height)]
    b.add(mesh.boxes_axis_aligned(sw_lo, sw_hi), ground, rng.uniform(0.35, 0.55, len(sw_arr)))
    s.boxes(sw_lo, sw_hi, ground)
    bld = np.array(buildings).reshape(-1, 5)
    _add_buildings(b, s, bld, rng)
    _add_street_furniture(b, s, style, rng, street, bld, (road_x, road_y), ext)
    verts, tris, cls, refl = b.build()
    parked = _place_parked(style, rng, road_x, road_y, ext)
    return Town(style, road_x, road_y, ext, verts, tris, cls, refl, *parked, solids=s.build())


def _place_buildings(style: TownStyle, rng: np.random.Generator, cell, road_edges) -> list[np.ndarray]:
    """Buildings along the road-facing edges of one block: rows [x0, y0, x1, y1, height]."""
    cx0, cx1, cy0, cy1 = cell
    road_b, road_t, road_l, road_r = road_edges
    inset = style.sidewalk_width + style.building_setback[0]
    x0, x1 = cx0 + (inset if road_l else 5.0), cx1 - (inset if road_r else 5.0)
    y0, y1 = cy0 + (inset if road_b else 5.0), cy1 - (inset if road_t else 5.0)
    dcap_y = min(style.building_depth[1], (y1 - y0) / 2.0 - 1.0)
    dcap_x = min(style.building_depth[1], (x1 - x0) / 2.0 - 1.0)
    if dcap_x < 4.0 or dcap_y < 4.0:
        return []
    out: list[np.ndarray] = []
    # (road?, along-edge range, edge coordinate, inward sign, axis along the edge, depth cap).
    # Bottom and top rows go first; a side-row building that would touch one is skipped.
    runs = [(road_b, (x0, x1), y0, 1.0, 0, dcap_y), (road_t, (x0, x1), y1, -1.0, 0, dcap_y),
            (road_l, (y0, y1), x0, 1.0, 1, dcap_x), (road_r, (y0, y1), x1, -1.0, 1, dcap_x)]
    for is_road, (u0, u1), edge, sign, axis, dcap in runs:
        if not is_road:
            continue
        u = u0
        while u1 - u > style.lot_width[0]:
            lot = min(rng.uniform(*style.lot_width), u1 - u)
            gap = rng.uniform(1.0, 4.0)
            depth = min(rng.uniform(*style.building_depth), dcap)
            back = rng.uniform(0.0, style.building_setback[1] - style.building_setback[0])
            height = rng.uniform(*style.building_height)
            if rng.random() < style.building_density and lot - gap > 4.0:
                start, end = u + gap / 2, u + lot - gap / 2
                e0 = edge + sign * back
                e1 = e0 + sign * max(depth - back, 4.0)
                lo_e, hi_e = min(e0, e1), max(e0, e1)
                rect = np.array([start, lo_e, end, hi_e] if axis == 0 else [lo_e, start, hi_e, end])
                if not out or not _rects_touch(rect, np.array(out)[:, :4], pad=2.0):
                    out.append(np.r_[rect, height])
            u += lot
    return out


def _rects_touch(rect: np.ndarray, rects: np.ndarray, pad: float) -> bool:
    """True if ``rect`` [x0, y0, x1, y1] comes within ``pad`` of any of ``rects`` (K, 4)."""
    return bool(((rect[0] < rects[:, 2] + pad) & (rect[2] > rects[:, 0] - pad)
                 & (rect[1] < rects[:, 3] + pad) & (rect[3] > rects[:, 1] - pad)).any())


def _add_buildings(b: mesh.MeshBuilder, s: SolidsBuilder, bld: np.ndarray, rng: np.random.Generator) -> None:
    """Boxes for buildings; a third get a set-back upper storey so roofs aren't all flat slabs."""
    if len(bld) == 0:
        return
    code = SEMANTIC_CODE["building"]
    refl = rng.uniform(0.2, 0.6, len(bld))
    b.add(mesh.boxes_axis_aligned(np.c_[bld[:, :2], np.zeros(len(bld))], np.c_[bld[:, 2:4], bld[:, 4]]), code, refl)
    s.boxes(np.c_[bld[:, :2], np.zeros(len(bld))], np.c_[bld[:, 2:4], bld[:, 4]], code)
    top = rng.random(len(bld)) < 0.35
    inset = rng.uniform(1.5, 3.5, len(bld))
    size = bld[:, 2:4] - bld[:, :2]
    top &= (size > 2 * inset[:, None] + 3.0).all(axis=1)
    t = bld[top]
    if len(t):
        i = inset[top][:, None]
        extra = rng.uniform(3.0, 8.0, len(t))
        b.add(mesh.boxes_axis_aligned(np.c_[t[:, :2] + i, t[:, 4]], np.c_[t[:, 2:4] - i, t[:, 4] + extra]), code, refl[top])
        s.boxes(np.c_[t[:, :2] + i, t[:, 4]], np.c_[t[:, 2:4] - i, t[:, 4] + extra], code)


def _add_street_furniture(b: mesh.MeshBuilder, s: SolidsBuilder, style: TownStyle, rng: np.random.Generator,
                          street: list[tuple], bld: np.ndarray, roads, ext) -> None:
    """Street trees and lights on every road-facing sidewalk, signs near corners, yard trees."""
    tree_xy, light_xy, light_dir, sign_xy, sign_half = [], [], [], [], []
    for x0, y0, x1, y1, (nx, ny) in street:
        along_x = nx == 0.0
        u0, u1 = (x0, x1) if along_x else (y0, y1)
        # Kerb line: the strip's road-side edge; "inward" points away from the road.
        kerb = (y0 if ny > 0 else y1) if along_x else (x0 if nx > 0 else x1)
        inward = ny if along_x else nx

        def at(u, off):
            u = np.asarray(u)
            c = np.full(len(u), kerb + inward * off)
            return np.c_[u, c] if along_x else np.c_[c, u]

        length = u1 - u0
        n_trees = rng.poisson(style.tree_density * length / 100.0)
        tree_xy.append(at(rng.uniform(u0 + 3.0, u1 - 3.0, n_trees), 0.65 * style.sidewalk_width))
        n_lights = int(length // style.pole_spacing)
        lights = u0 + (np.arange(n_lights) + 0.5) * length / max(n_lights, 1) + rng.uniform(-2, 2, n_lights)
        light_xy.append(at(lights, 0.4))
        light_dir.append(np.tile([-nx, -ny], (n_lights, 1)))
        corners = np.array([u0 + 1.0, u1 - 1.0])[rng.random(2) < 0.5]
        sign_xy.append(at(corners, 0.3))
        # Sign plates face the traffic: thin along the road, 0.7 m across it.
        sign_half.append(np.tile([0.03, 0.35] if along_x else [0.35, 0.03], (len(corners), 1)))
    # Yard trees inside blocks, kept off the buildings.
    area = (ext[1] - ext[0]) * (ext[3] - ext[2])
    n_yard = rng.poisson(style.yard_trees * area / 1000.0)
    yard = np.c_[rng.uniform(ext[0], ext[1], n_yard), rng.uniform(ext[2], ext[3], n_yard)]
    clear = style.road_half_width + style.sidewalk_width + 3.0
    off_street = ((np.abs(yard[:, None, 0] - roads[0][None]) > clear).all(axis=1)
                  & (np.abs(yard[:, None, 1] - roads[1][None]) > clear).all(axis=1))
    yard = yard[off_street & ~_in_rects(yard, bld[:, :4], pad=4.0)]
    trees = np.concatenate(tree_xy + [yard])
    _add_trees(b, s, trees, style, rng)
    lights, ldir = np.concatenate(light_xy), np.concatenate(light_dir)
    signs, half = np.concatenate(sign_xy), np.concatenate(sign_half)
    pole = SEMANTIC_CODE["pole"]
    h = rng.uniform(6.0, 9.0, len(lights))
    b.add(mesh.cylinders(lights, np.zeros(len(lights)), h, np.full(len(lights), 0.11)), pole, 0.5)
    s.cylinders(lights, 0.0, h, 0.11, pole)
    arm = rng.uniform(1.5, 2.8, len(lights))[:, None]
    tip = lights + ldir * arm
    lo = np.c_[np.minimum(lights, tip) - 0.06, h - 0.15]
    hi = np.c_[np.maximum(lights, tip) + 0.06, h]
    b.add(mesh.boxes_axis_aligned(lo, hi), pole, 0.55)
    s.boxes(lo, hi, pole)
    b.add(mesh.cylinders(signs, np.zeros(len(signs)), np.full(len(signs), 2.6), np.full(len(signs), 0.04)), pole, 0.5)
    s.cylinders(signs, 0.0, 2.6, 0.04, pole)
    plate = (np.c_[signs - half, np.full(len(signs), 2.0)], np.c_[signs + half, np.full(len(signs), 2.7)])
    b.add(mesh.boxes_axis_aligned(*plate), pole, 0.9)
    s.boxes(*plate, pole)


def _in_rects(xy: np.ndarray, rects: np.ndarray, pad: float) -> np.ndarray:
    """(N,) bool: point inside any of ``rects`` (K, 4) [x0, y0, x1, y1] grown by ``pad``."""
    if len(rects) == 0 or len(xy) == 0:
        return np.zeros(len(xy), dtype=bool)
    inside = ((xy[:, None, 0] >= rects[None, :, 0] - pad) & (xy[:, None, 0] <= rects[None, :, 2] + pad)
              & (xy[:, None, 1] >= rects[None, :, 1] - pad) & (xy[:, None, 1] <= rects[None, :, 3] + pad))
    return inside.any(axis=1)


def _add_trees(b: mesh.MeshBuilder, s: SolidsBuilder, xy: np.ndarray, style: TownStyle, rng: np.random.Generator) -> None:
    """Trees: a trunk into an ellipsoid canopy. The mesh is all vegetation (what a LiDAR's labels
    say); the solids split the trunk at the canopy's lowest point into pole below and vegetation
    above, V2VSSC's height split of trees."""
    n = len(xy)
    veg = SEMANTIC_CODE["vegetation"]
    trunk_h = rng.uniform(1.8, 3.5, n)
    radius_xy = rng.uniform(1.5, 3.2, n)
    radius_z = radius_xy * rng.uniform(0.9, 1.4, n)
    trunk_top, trunk_r = trunk_h + 0.5 * radius_z, rng.uniform(0.12, 0.28, n)
    centre, radii = np.c_[xy, trunk_h + 0.8 * radius_z], np.c_[radius_xy, radius_xy, radius_z]
    b.add(mesh.cylinders(xy, np.zeros(n), trunk_top, trunk_r, n=6), veg, 0.3)
    b.add(mesh.ellipsoids(centre, radii), veg, rng.uniform(0.4, 0.65, n))
    canopy_bottom = centre[:, 2] - radius_z
    s.cylinders(xy, 0.0, canopy_bottom, trunk_r, SEMANTIC_CODE["pole"])
    s.cylinders(xy, canopy_bottom, trunk_top, trunk_r, veg)
    s.ellipsoids(centre, radii, veg)


def _place_parked(style: TownStyle, rng: np.random.Generator, road_x: np.ndarray, road_y: np.ndarray, ext):
    """Parked vehicles in the parking strips, away from intersections, facing the traffic on their side."""
    hw = style.road_half_width
    lateral = hw - style.parking_width / 2.0
    xy, yaw, sizes = [], [], []
    labels: list[str] = []
    # (centre line, crossing lines, span, axis along road)
    for centres, crossing, span, axis in ((road_x, road_y, (ext[2], ext[3]), 1), (road_y, road_x, (ext[0], ext[1]), 0)):
        for c in centres:
            for side in (-1.0, 1.0):
                # Keep right: on a road along y the +x side drives towards +y; along x the -y side drives +x.
                heading = (np.pi / 2 if side > 0 else -np.pi / 2) if axis == 1 else (0.0 if side < 0 else np.pi)
                u = span[0] + 5.0
                while u < span[1] - 12.0:
                    label = sample_labels(1, style.parked_class_probs, rng)[0]
                    size = sample_sizes((label,), rng)[0]
                    gap = rng.uniform(1.0, 3.0)
                    centre_u = u + size[0] / 2.0
                    near_cross = np.abs(crossing - centre_u).min() < hw + 6.0 + size[0] / 2.0
                    if not near_cross and rng.random() < style.parked_density:
                        lat = c + side * (lateral + rng.uniform(-0.15, 0.1))
                        xy.append([centre_u, lat] if axis == 0 else [lat, centre_u])
                        yaw.append(heading + np.radians(rng.uniform(-2.0, 2.0)))
                        sizes.append(size)
                        labels.append(label)
                    u += size[0] + gap
    n = len(xy)
    return (np.array(xy).reshape(n, 2), np.array(yaw).reshape(n), np.array(sizes).reshape(n, 3),
            tuple(labels), sample_paint(n, rng))
