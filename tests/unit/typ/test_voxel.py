"""typ.voxel against an independent per-point reference, on edge cases and real frames."""
from __future__ import annotations

import bisect
import math
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from typ import geometry
from typ.errors import TypError
from typ.voxel import PAPER_GRID, TINY_GRID, Grid, box_map, points_to_reference, voxel_centers, voxelize
from repo_paths import SHARED_DATA

DATA = SHARED_DATA
REAL_FRAMES = {  # name: (relative path, floats per point)
    "kitti_000000": ("kitti_object_vis/training/velodyne/000000.bin", 4),
    "kitti_000001": ("kitti_object_vis/training/velodyne/000001.bin", 4),
    "nuscenes": ("nuscenes_mmdet3d_demo/n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin", 5),
    "waymo_0000000": ("waymo_mmdet3d_testdata/kitti_format/velodyne/0000000.bin", 6),
    "waymo_1000000": ("waymo_mmdet3d_testdata/kitti_format/velodyne/1000000.bin", 6),
}
UNIT = Grid((0.0, 10.0), (0.0, 10.0), (-1.0, 1.0), (10, 10, 1))  # 1 m cells, centres at i + 0.5


def load_frame(name: str) -> np.ndarray:
    rel, width = REAL_FRAMES[name]
    path = DATA / rel
    if not path.is_file():
        pytest.skip(f"real frame not available: {path}")
    return np.fromfile(path, dtype=np.float32).reshape(-1, width)


def reference_voxelize(points, grid: Grid) -> np.ndarray:
    """One point at a time: bin i along an axis iff lo <= p < hi and e_i <= p < e_{i+1}, e_i = lo + i*size."""
    out = np.zeros(grid.shape, dtype=bool)
    ranges = (grid.x_range, grid.y_range, grid.z_range)
    edges = []
    for (lo, hi), n in zip(ranges, grid.shape):
        size = (hi - lo) / n
        edges.append([lo + i * size for i in range(n + 1)])
    for row in np.asarray(points)[:, :3].tolist():
        index = []
        for p, (lo, hi), e in zip(row, ranges, edges):
            if not (lo <= p < hi):
                break
            i = bisect.bisect_right(e, p) - 1  # last edge <= p
            if not (0 <= i < len(e) - 1 and e[i] <= p < e[i + 1]):
                break
            index.append(i)
        else:
            out[tuple(index)] = True
    return out


# --- Grid ---------------------------------------------------------------------------------

def test_grid_paper_values_and_round_trip():
    assert PAPER_GRID.shape == (512, 512, 20)
    np.testing.assert_array_equal(PAPER_GRID.voxel_size, [0.2, 0.2, 0.2])
    assert Grid.from_dict(PAPER_GRID.to_dict()) == PAPER_GRID
    assert PAPER_GRID.digest() == "d72f8a8b37958d28"  # stable across runs and versions
    assert PAPER_GRID.digest() == Grid((-51.2, 51.2), (-51.2, 51.2), (-3, 1), (512, 512, 20)).digest()
    assert PAPER_GRID.digest() != TINY_GRID.digest()
    assert len(PAPER_GRID.edges(2)) == 21 and PAPER_GRID.centers(0)[0] == pytest.approx(-51.1)


@pytest.mark.parametrize("kwargs, field", [
    (dict(x_range=(1.0, 1.0)), "x_range"),
    (dict(y_range=(2.0, -2.0)), "y_range"),
    (dict(z_range=(float("nan"), 1.0)), "z_range"),
    (dict(x_range=(0.0, float("inf"))), "x_range"),
    (dict(x_range=(0.0,)), "x_range"),
    (dict(shape=(4, 0, 2)), "shape"),
    (dict(shape=(4, 4)), "shape"),
    (dict(shape=(4, 4, 2.5)), "shape"),
    (dict(shape=(4, True, 2)), "shape"),
    (dict(x_range=(1e12, 1e12 + 1.0), shape=(1000, 4, 4)), "x_range"),
])
def test_grid_rejects_bad_fields(kwargs, field):
    args = dict(x_range=(-1.0, 1.0), y_range=(-1.0, 1.0), z_range=(-1.0, 1.0), shape=(4, 4, 4)) | kwargs
    with pytest.raises(TypError) as exc:
        Grid(**args)
    assert exc.value.field == field


def test_grid_from_dict_rejects_unknown_keys():
    with pytest.raises(TypError, match="grid"):
        Grid.from_dict(PAPER_GRID.to_dict() | {"voxel": 1}, where="params.yaml")


# --- voxelize -----------------------------------------------------------------------------

@pytest.mark.parametrize("grid", [TINY_GRID, Grid((-3.3, 7.1), (-2.0, 2.9), (-1.7, 0.4), (13, 7, 5))])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_random_clouds_match_reference(grid, dtype):
    rng = np.random.default_rng(7)
    margin = 0.1 * (grid.upper - grid.lower)
    pts = rng.uniform(grid.lower - margin, grid.upper + margin, size=(4000, 3)).astype(dtype)
    pts = np.concatenate([pts, pts[:50]])  # duplicates
    np.testing.assert_array_equal(voxelize(pts, grid), reference_voxelize(pts, grid))


@pytest.mark.parametrize("grid", [PAPER_GRID, TINY_GRID, Grid((-40.0, 70.4), (-40.0, 40.0), (-3.0, 1.0), (550, 400, 40))])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_points_on_every_edge(grid, dtype):
    """Each edge e_i = lo + i*size along each axis: lower edges included, the range's top excluded."""
    for axis in range(3):
        edges = grid.edges(axis).astype(dtype)
        pts = np.tile(grid.centers(0)[[0]], (len(edges), 3))
        pts[:, 1], pts[:, 2] = grid.centers(1)[0], grid.centers(2)[0]
        pts[:, axis] = edges
        pts = pts.astype(dtype)
        got = voxelize(pts, grid)
        np.testing.assert_array_equal(got, reference_voxelize(pts, grid))
        if dtype == np.float64:  # exact edges: one voxel per bin, none for e_n == hi
            assert got.sum() == grid.shape[axis]


def test_just_inside_and_outside():
    g = Grid((-51.2, 51.2), (-51.2, 51.2), (-3.0, 1.0), (512, 512, 20))
    c = g.centers(1)[3], g.centers(2)[4]
    xs = {
        np.nextafter(-51.2, -np.inf): None,   # just below the range
        -51.2: 0,                             # lower edge of the range: included
        np.nextafter(51.2, -np.inf): 511,     # just below the top: last bin
        51.2: None,                           # top of the range: excluded
    }
    e = g.edges(0)
    for i in (1, 100, 255, 256, 257, 400):
        xs[np.nextafter(e[i], -np.inf)] = i - 1
        xs[e[i]] = i
        xs[np.nextafter(e[i], np.inf)] = i
    for x, expected in xs.items():
        occ = voxelize(np.array([[x, c[0], c[1]]]), g)
        if expected is None:
            assert not occ.any(), x
        else:
            assert occ[expected, 3, 4] and occ.sum() == 1, (x, expected, np.argwhere(occ))


def test_duplicates_empty_and_extra_columns():
    pts = np.array([[1.2, 3.4, 0.1, 0.5]] * 1000, dtype=np.float32)
    occ = voxelize(pts, UNIT)
    assert occ.sum() == 1 and occ[1, 3, 0]
    assert not voxelize(np.zeros((0, 4), np.float32), UNIT).any()
    assert voxelize(np.zeros((0, 3)), PAPER_GRID).shape == (512, 512, 20)
    pts[0, 3] = np.nan  # intensity is not looked at
    assert voxelize(pts, UNIT).sum() == 1


def test_non_contiguous_inputs():
    rng = np.random.default_rng(3)
    pts = rng.uniform(-60, 60, size=(3000, 5)).astype(np.float32)
    expected = reference_voxelize(pts, TINY_GRID)
    np.testing.assert_array_equal(voxelize(pts[:, :3], TINY_GRID), expected)
    np.testing.assert_array_equal(voxelize(np.asfortranarray(pts), TINY_GRID), expected)
    np.testing.assert_array_equal(voxelize(pts[::-1], TINY_GRID), expected)


def test_non_finite_rows_rejected_with_count():
    pts = np.zeros((10, 4), dtype=np.float32)
    pts[2, 0], pts[5, 2], pts[7, 1], pts[7, 2] = np.nan, np.inf, -np.inf, np.nan
    with pytest.raises(TypError) as exc:
        voxelize(pts, UNIT)
    assert exc.value.field == "points" and "3 rows" in str(exc.value)


@pytest.mark.parametrize("bad", [np.zeros((5, 2)), np.zeros(6), np.zeros((4, 3), dtype=np.int32), [[1, 2, 3]]])
def test_bad_point_arrays_rejected(bad):
    with pytest.raises(TypError) as exc:
        voxelize(bad, UNIT)
    assert exc.value.field == "points"


def test_memory_is_bounded_by_the_output():
    pts = np.random.default_rng(0).uniform(-60, 60, size=(2_000_000, 3))
    voxelize(pts[:10], PAPER_GRID)  # compile outside the measurement
    tracemalloc.start()
    occ = voxelize(pts, PAPER_GRID)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < occ.nbytes + (1 << 20), peak  # no per-point temporaries (pts are 48 MB)


@pytest.mark.parametrize("name", list(REAL_FRAMES))
def test_real_frames_match_reference(name):
    pts = load_frame(name)
    # Waymo points are in the vehicle frame (origin on the ground), so its grid sits higher.
    grid = PAPER_GRID if not name.startswith("waymo") else Grid((-80.0, 80.0), (-80.0, 80.0), (0.0, 6.0), (320, 320, 30))
    occ = voxelize(pts, grid)
    np.testing.assert_array_equal(occ, reference_voxelize(pts, grid))
    assert occ.any()


# --- voxel_centers ------------------------------------------------------------------------

@st.composite
def grids_and_occupancy(draw):
    shape = tuple(draw(st.integers(1, 9)) for _ in range(3))
    ranges = []
    for _ in range(3):
        lo = draw(st.floats(-100.0, 100.0))
        ranges.append((lo, lo + draw(st.floats(0.05, 80.0))))
    grid = Grid(*ranges, shape)
    bits = draw(st.lists(st.booleans(), min_size=math.prod(shape), max_size=math.prod(shape)))
    return grid, np.array(bits, dtype=bool).reshape(shape)


@settings(max_examples=150, deadline=None)
@given(grids_and_occupancy())
def test_voxel_centers_round_trip(case):
    grid, occ = case
    centres = voxel_centers(occ, grid)
    assert centres.shape == (occ.sum(), 3) and centres.dtype == np.float64
    np.testing.assert_array_equal(voxelize(centres, grid), occ)


def test_voxel_centers_values_and_checks():
    occ = np.zeros(UNIT.shape, dtype=bool)
    occ[2, 7, 0] = True
    np.testing.assert_array_equal(voxel_centers(occ, UNIT), [[2.5, 7.5, 0.0]])
    with pytest.raises(TypError, match="occupancy"):
        voxel_centers(occ.astype(np.uint8), UNIT)
    with pytest.raises(TypError, match="occupancy"):
        voxel_centers(occ[:5], UNIT)


# --- box_map ------------------------------------------------------------------------------

def cells(*ij):
    out = np.zeros((10, 10, 1), dtype=bool)
    for i, j in ij:
        out[i, j, 0] = True
    return out


def test_box_map_axis_aligned():
    # x in [2, 5], y in [4, 6]: centres 2.5, 3.5, 4.5 and 4.5, 5.5
    got = box_map([[3.5, 5.0, 0.0, 3.0, 2.0, 1.5, 0.0]], UNIT)
    np.testing.assert_array_equal(got, cells(*[(i, j) for i in (2, 3, 4) for j in (4, 5)]))
    # edges exactly on centres 1.5 and 3.5: the rectangle is closed, so they count
    got = box_map([[2.5, 2.5, 0.0, 2.0, 2.0, 1.0, 0.0]], UNIT)
    np.testing.assert_array_equal(got, cells(*[(i, j) for i in (1, 2, 3) for j in (1, 2, 3)]))
    # yaw = 90 deg swaps length and width
    got = box_map([[3.5, 5.0, 0.0, 2.0, 3.0, 1.5, np.pi / 2]], UNIT)
    np.testing.assert_array_equal(got, cells(*[(i, j) for i in (2, 3, 4) for j in (4, 5)]))


def test_box_map_rotated_45_degrees():
    # a square of side 2*sqrt(2) turned 45 deg is the diamond |dx| + |dy| <= 2
    diamond = [(5 + a, 5 + b) for a in range(-2, 3) for b in range(-2, 3) if abs(a) + abs(b) <= 2]
    got = box_map([[5.5, 5.5, 0.0, 2 * math.sqrt(2), 2 * math.sqrt(2), 1.0, np.pi / 4]], UNIT)
    np.testing.assert_array_equal(got, cells(*diamond))
    assert got.sum() == 13
    # length 4*sqrt(2) along (1, 1), width sqrt(2): |dx + dy| <= 4 and |dy - dx| <= 1
    strip = [(0, 0), (1, 1), (2, 2), (-1, -1), (-2, -2), (0, 1), (1, 0), (1, 2), (2, 1),
             (-1, 0), (0, -1), (-1, -2), (-2, -1)]
    got = box_map([[5.5, 5.5, 0.0, 4 * math.sqrt(2), math.sqrt(2), 1.0, np.pi / 4]], UNIT)
    np.testing.assert_array_equal(got, cells(*[(5 + a, 5 + b) for a, b in strip]))


def test_box_map_clips_boxes_outside():
    got = box_map([[0.0, 0.0, 0.0, 3.0, 3.0, 1.0, 0.0]], UNIT)  # covers [-1.5, 1.5]^2
    np.testing.assert_array_equal(got, cells((0, 0), (0, 1), (1, 0), (1, 1)))
    assert not box_map([[100.0, -50.0, 0.0, 4.0, 2.0, 1.0, 0.3], [1e30, 0, 0, 1, 1, 1, 0]], UNIT).any()
    assert box_map([[5.0, 5.0, 0.0, 40.0, 40.0, 1.0, 0.7]], UNIT).all()
    assert not box_map(np.zeros((0, 7)), UNIT).any()


def reference_box_map(boxes, grid):
    """Cell centre inside the convex BEV corner polygon (cross products, one cell at a time)."""
    out = np.zeros((grid.shape[0], grid.shape[1], 1), dtype=bool)
    for corners in geometry.box_corners(boxes)[:, :4, :2]:
        for i, cx in enumerate(grid.centers(0)):
            for j, cy in enumerate(grid.centers(1)):
                sides = [(b[0] - a[0]) * (cy - a[1]) - (b[1] - a[1]) * (cx - a[0])
                         for a, b in zip(corners, np.roll(corners, -1, axis=0))]
                if all(s >= 0 for s in sides) or all(s <= 0 for s in sides):
                    out[i, j, 0] = True
    return out


def test_box_map_random_boxes_match_polygon_reference():
    rng = np.random.default_rng(11)
    grid = Grid((-8.0, 8.0), (-6.0, 10.0), (-1.0, 1.0), (32, 40, 1))
    boxes = np.column_stack([rng.uniform(-10, 12, 25), rng.uniform(-8, 12, 25), np.zeros(25),
                             rng.uniform(0.5, 6, 25), rng.uniform(0.5, 3, 25), np.ones(25),
                             rng.uniform(-np.pi, np.pi, 25)])
    np.testing.assert_array_equal(box_map(boxes, grid), reference_box_map(boxes, grid))


@pytest.mark.parametrize("bad", [np.zeros((2, 6)), [[0, 0, 0, 1, 1, 1, np.nan]], [[0, 0, 0, 0, 1, 1, 0]]])
def test_box_map_rejects_bad_boxes(bad):
    with pytest.raises(TypError) as exc:
        box_map(bad, UNIT)
    assert exc.value.field == "boxes"


# --- points_to_reference ------------------------------------------------------------------

def test_points_to_reference_by_hand():
    # reference 10 m ahead of the ego, turned 90 deg left: world (10, 1) is 1 m ahead of it
    pts = np.array([[10.0, 1.0, 0.5, 0.25]], dtype=np.float32)
    got = points_to_reference(pts, [0, 0, 0, 0, 0, 0], [10, 0, 0, 0, 90, 0])
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, [[1.0, 0.0, 0.5, 0.25]], atol=1e-6)


def test_points_to_reference_matches_matrices_and_moves_in_float64():
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(-50, 50, (500, 3)), rng.random(500)]).astype(np.float32)
    ego = [123456.7, -98765.4, 12.3, 1.5, 33.0, -2.0]  # far from the world origin
    ref = [123470.1, -98750.2, 11.9, -0.5, 121.0, 1.0]
    world = geometry.pose_to_matrix(ego)
    to_ref = np.linalg.inv(geometry.pose_to_matrix(ref))
    homog = np.column_stack([pts[:, :3].astype(np.float64), np.ones(len(pts))])
    expected = (to_ref @ world @ homog.T).T[:, :3]
    got = points_to_reference(pts, ego, ref)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got[:, 3], pts[:, 3])
    np.testing.assert_allclose(got[:, :3], expected.astype(np.float32), atol=1e-5)
    got64 = points_to_reference(pts.astype(np.float64), geometry.pose_to_matrix(ego), geometry.pose_to_matrix(ref))
    np.testing.assert_allclose(got64[:, :3], expected, atol=1e-9)
    with pytest.raises(TypError, match="points"):
        points_to_reference(pts[:, :2], ego, ref)
