"""typ.castview: the scene a cast reference view is cast from, and the cast itself."""
from __future__ import annotations

import dataclasses
from collections import Counter

import numpy as np
import pytest

from typ import castview
from typ.config import CastConfig
from typ.errors import TypError
from typ.geometry import box_corners
from typ.sensors import on_beam_fractions
from typ.sim.sensor import domain_spec
from typ.voxel import Grid

GRID = Grid((-25.6, 25.6), (-25.6, 25.6), (-2.95, 1.05), (64, 64, 8))   # 0.8 x 0.8 x 0.5 m, road at -2.2 m
SPEC = domain_spec("target").sensor                                      # mount height 2.2 m
IDEAL = dataclasses.replace(SPEC, dropout=0.0, range_noise_std=0.0)


def _edges(tris: np.ndarray) -> Counter:
    return Counter(tuple(sorted(e)) for t in tris for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])))


def _plane(rng, slope=0.02, n=4000, reach=20.0):
    xy = rng.uniform(-reach, reach, (n, 2))
    return np.column_stack([xy, -2.2 + slope * xy[:, 0]])


def test_ground_heights_follow_the_egos_road_and_carry_it_to_unseen_cells():
    rng = np.random.default_rng(0)
    road = _plane(rng)
    wall = np.column_stack([np.full(500, 5.0), rng.uniform(-3, 3, 500), rng.uniform(-2.2, 0.5, 500)])
    h = castview.ground_heights(np.concatenate([road, wall]), GRID, -2.2)
    x = GRID.centers(0)[:, None] * np.ones((1, 64))
    seen = (np.abs(x) < 19) & (np.abs(GRID.centers(1))[None] < 19)
    # the lowest return in a cell (or its neighbour's, for the few cells without one): within two
    # cells' rise of the plane at its centre, the wall ignored
    assert np.abs(h[seen] - (-2.2 + 0.02 * x[seen])).max() < 2 * 0.02 * 0.8
    assert np.median(np.abs(h[seen] - (-2.2 + 0.02 * x[seen]))) < 0.01
    # beyond the ego's reach the nearest seen cell's height (monotone in x, flat past the edge)
    assert h[-1, 32] == pytest.approx(h[-8, 32], abs=0.02) and h[-1, 32] > h[0, 32]
    assert np.array_equal(castview.ground_heights(wall[:0], GRID, -2.2), np.full((64, 64), -2.2))


def test_free_space_holds_the_voxels_a_ray_crossed_and_not_its_return():
    free = castview.free_space(np.array([[10.0, 0.4, -1.5]]), [0.0, 0.4, -1.5], GRID)
    k, i, j = np.nonzero(free)
    assert set(k) == {2} and set(j) == {32}                       # z -1.5 -> layer 2, y 0.4 -> column 32
    assert i.min() == 32 and i.max() == 43                        # x 0 .. 9.5: the hit's own voxel (x 9.6-10.4) is not
    assert not free[:, :32].any() and not free[:, 44:].any()      # nothing behind the sensor or the return


def test_generated_solids_are_a_joined_road_and_one_box_per_run():
    occ = np.zeros((8, 64, 64), bool)
    occ[1, 10:12, 20] = True              # two road cells side by side
    occ[2:4, 40, 40] = True               # a run of two voxels on the road
    occ[6, 40, 40] = True                 # and a floating one above it
    heights = np.full((64, 64), -2.2)
    heights[11, 20] = -2.0
    verts, tris = castview.generated_solids(occ, np.ones((64, 64), bool), heights, GRID, -2.2)
    assert tris.shape == (2 * 2 + 2 * 12, 3) and tris.max() < len(verts)
    road = verts[:8].reshape(2, 4, 3)
    shared = [tuple(np.round(v, 4)) for v in road[0]] + [tuple(np.round(v, 4)) for v in road[1]]
    assert sum(c == 2 for c in Counter(p[:2] for p in shared).values()) == 2          # one edge shared ...
    assert len({p for p in shared}) == 6                                             # ... at one height
    boxes = verts[8:].reshape(2, 8, 3)
    lo, hi = boxes.min(axis=1), boxes.max(axis=1)
    ze = GRID.edges(2)
    assert lo[0, 2] == pytest.approx(-2.2) and hi[0, 2] == pytest.approx(ze[4])      # from the road to the run's top
    assert lo[1, 2] == pytest.approx(ze[6]) and hi[1, 2] == pytest.approx(ze[7])     # a floating voxel alone
    assert hi[0, 0] - lo[0, 0] == pytest.approx(0.8)
    for n in range(2):                                                                # closed: each edge twice
        assert set(_edges(tris[4 + 12 * n:16 + 12 * n]).values()) == {2}
    with pytest.raises(TypError):
        castview.generated_solids(occ[:4], np.ones((64, 64), bool), heights, GRID, -2.2)


def test_oriented_boxes_have_the_label_corners_and_are_closed():
    boxes = np.array([[3.0, -2.0, -1.4, 4.5, 1.9, 1.6, 0.7], [-8.0, 5.0, -1.0, 10.0, 2.5, 3.0, -2.0]])
    verts, tris = castview.oriented_boxes_mesh(boxes)
    for n, corners in enumerate(box_corners(boxes)):
        got = sorted(map(tuple, np.round(verts[8 * n:8 * n + 8], 6)))
        assert got == sorted(map(tuple, np.round(corners, 6)))
    assert set(_edges(tris).values()) == {2} and tris.shape == (24, 3)


def test_cast_is_one_scan_of_the_sensor_with_its_drop_and_noise():
    # a closed room around the sensor: every ray returns
    verts, tris = castview.boxes_mesh(np.array([[-30.0, -30.0, -2.2]]), np.array([[30.0, 30.0, 10.0]]))
    rays = SPEC.n_beams * SPEC.n_azimuths
    ideal = castview.cast(verts, tris, IDEAL, np.random.default_rng(0))
    assert len(ideal) == rays and on_beam_fractions(ideal, IDEAL, (0.05,))[0.05] == 1.0
    noisy = castview.cast(verts, tris, SPEC, np.random.default_rng(0))
    assert abs(1 - len(noisy) / rays - SPEC.dropout) < 0.01
    floor = noisy[(noisy[:, 2] < -2.0) & (np.abs(noisy[:, :2]).max(axis=1) < 29.0)]
    r_true = 2.2 / np.abs(floor[:, 2] / np.linalg.norm(floor[:, :3], axis=1))     # along the ray to z = -2.2
    err = np.linalg.norm(floor[:, :3], axis=1) - r_true
    assert abs(err.std() / SPEC.range_noise_std - 1) < 0.2                          # its noise, through elevation
    assert np.array_equal(noisy, castview.cast(verts, tris, SPEC, np.random.default_rng(0)))
    assert castview.cast(verts[:0], tris[:0], SPEC, np.random.default_rng(0)).shape == (0, 3)
    with pytest.raises(TypError):
        castview.cast(verts, tris, SPEC, 0)


def test_a_generated_wall_hides_what_the_ego_saw_behind_it():
    rng = np.random.default_rng(1)
    road = _plane(rng, slope=0.0, n=20000)
    behind = np.column_stack([np.full(3000, 15.0), rng.uniform(-4, 4, 3000), rng.uniform(-2.2, 0.8, 3000)])
    ego = np.concatenate([road, behind])
    seen = np.zeros((64, 64), bool)
    seen[48:] = True                       # the ego saw x >= 12.8 m only: the rest is generated
    occ = np.zeros((8, 64, 64), bool)
    occ[1] = True                          # generated road everywhere
    occ[2:6, 42, 24:40] = True             # and a generated wall at x 8.0-8.8 m, y -6.4 .. 6.4
    params = CastConfig(label_boxes=0.0, road="generated", carve=False)
    pts = castview.cast_view(ego, occ, GRID, IDEAL, rng, params=params, mask=seen)
    # the wall (0.05 m top) covers |y| < 6.4 m at 8 m: rays within 20 deg of ahead and below its top stop there
    ahead = (np.abs(np.arctan2(pts[:, 1], pts[:, 0])) < np.radians(20)) & (pts[:, 2] > -1.8) & (pts[:, 2] < 0.0)
    assert ahead.any() and np.all(pts[ahead, 0] < 9.0)
    open_view = castview.cast_view(ego, occ & (np.arange(8)[:, None, None] < 2), GRID, IDEAL, rng, params=params,
                                   mask=seen)
    assert np.any((open_view[:, 0] > 14.0) & (open_view[:, 2] > -1.8) & (open_view[:, 2] < 0.0))   # without it: seen


def test_carving_drops_generated_voxels_the_ego_saw_through():
    ego = np.array([[20.0, 0.0, -1.5], [20.0, 0.4, -1.5], [20.0, -0.4, -1.5]])
    occ = np.zeros((8, 64, 64), bool)
    occ[2, 44, 32] = True                  # x 9.6-10.4, on the ego's rays
    occ[2, 44, 20] = True                  # off them
    seen = np.zeros((64, 64), bool)
    params = CastConfig(label_boxes=0.0, road="generated", carve=True)
    v_carved, _ = castview.scene_model(ego, occ, GRID, IDEAL, params=params, ego_origin=[0.0, 0.0, -1.5], mask=seen)
    v_kept, _ = castview.scene_model(ego, occ, GRID, IDEAL, params=dataclasses.replace(params, carve=False), mask=seen)
    assert len(v_kept) - len(v_carved) == 8                       # one box fewer
    with pytest.raises(TypError) as err:
        castview.scene_model(ego, occ, GRID, IDEAL, params=params, mask=seen)
    assert err.value.field == "ego_origin"


def test_a_surface_inside_min_range_does_not_blind_the_sensor():
    room_v, room_t = castview.boxes_mesh(np.array([[-30.0, -30.0, -2.2]]), np.array([[30.0, 30.0, 10.0]]))
    # a 1 x 1 m plate 0.3 m in front of the sensor (a surfel of a bush it stands in)
    plate_v = np.array([[0.3, -0.5, -0.5], [0.3, 0.5, -0.5], [0.3, 0.5, 0.5], [0.3, -0.5, 0.5]])
    verts = np.concatenate([room_v, plate_v])
    tris = np.concatenate([room_t, np.array([[0, 1, 2], [0, 2, 3]]) + len(room_v)])
    pts = castview.cast(verts, tris, IDEAL, np.random.default_rng(0))
    assert len(pts) == IDEAL.n_beams * IDEAL.n_azimuths and np.linalg.norm(pts, axis=1).min() > IDEAL.min_range


def test_the_road_under_a_car_seen_only_by_its_roof_is_the_road_around_it():
    """The ego's returns in the 6 x 4 cells of a car 4.8 x 3.2 m are its roof only, 1.5 m over the
    road (the road under it hidden): those cells take the nearest road cell's height, not the
    roof's (which a 3-cell median would not remove either)."""
    rng = np.random.default_rng(2)
    road = _plane(rng, slope=0.0, n=20000)
    car = (road[:, 0] >= 8.0) & (road[:, 0] < 12.8) & (road[:, 1] >= -1.6) & (road[:, 1] < 1.6)
    roof = road[car] + [0.0, 0.0, 1.5]
    h = castview.ground_heights(np.concatenate([road[~car], roof]), GRID, -2.2)
    # the car's cells are rows 42..47 and columns 30..33 (their centres 8.4..12.4 m and -1.2..1.2 m)
    assert GRID.centers(0)[[42, 47]] == pytest.approx([8.4, 12.4])
    assert GRID.centers(1)[[30, 33]] == pytest.approx([-1.2, 1.2])
    np.testing.assert_array_equal(h, np.full((64, 64), -2.2))


def test_label_boxes_are_scaled_in_every_dimension_about_their_centre():
    """generate.cast.label_boxes = 0.8: a labelled car 4.5 x 2.0 x 1.6 m turned 30 deg is built as
    the box of the same centre and heading 3.6 x 1.6 x 1.28 m (its height too, not only its
    footprint): its 8 corners, as geometry.box_corners gives them, are the model's last 8 vertices."""
    ego = np.array([[20.0, 0.0, -1.5], [20.0, 0.4, -1.5], [20.0, -0.4, -1.5]])
    occ = np.zeros((8, 64, 64), bool)
    seen = np.zeros((64, 64), bool)
    car = np.array([12.0, -3.0, -1.4, 4.5, 2.0, 1.6, np.radians(30.0)])
    params = CastConfig(label_boxes=0.8, road="generated", carve=False)
    v_boxes, t_boxes = castview.scene_model(ego, occ, GRID, IDEAL, params=params, label_boxes=car[None], mask=seen)
    v_none, t_none = castview.scene_model(ego, occ, GRID, IDEAL, params=dataclasses.replace(params, label_boxes=0.0),
                                          mask=seen)
    assert len(v_boxes) - len(v_none) == 8 and len(t_boxes) - len(t_none) == 12
    want = box_corners(car * [1, 1, 1, 0.8, 0.8, 0.8, 1])[0]
    got = v_boxes[-8:].astype(np.float64)
    np.testing.assert_allclose(got[np.lexsort(got.T)], want[np.lexsort(want.T)], atol=1e-5)
    np.testing.assert_allclose(np.ptp(got[:, 2]), 1.6 * 0.8, atol=1e-5)
