"""Range and BEV images of typ.projection: round trips on real and simulated frames, bounds, bad input."""
import math
from pathlib import Path

import numpy as np
import pytest

from typ.errors import TypError
from typ.projection import (HDL32E, HDL64E, RangeLayout, bev_image, bev_to_points, from_unit, no_return_threshold,
                            range_image, range_pixels, range_to_points, to_unit)
from typ.sim import domain_spec, simulate_scenario
from typ.voxel import Grid
from repo_paths import SHARED_DATA

SHARED = SHARED_DATA
KITTI = SHARED / "kitti_object_vis"
NUSCENES = SHARED / "nuscenes_mmdet3d_demo"
BEV = Grid((-51.2, 51.2), (-51.2, 51.2), (-3.0, 7.0), (256, 256, 1))


@pytest.fixture(scope="module")
def sim_view():
    """One simulated target-domain scan (1 deg azimuth step: 360 columns) with its sensor."""
    scene = simulate_scenario(domain="target", seed=3, n_frames=1, n_agents=1, azimuth_step_deg=1.0)[0]
    return scene.ego, domain_spec("target", azimuth_step_deg=1.0).sensor


def real_frames():
    frames = []
    if KITTI.is_dir():
        from typ.formats import read_kitti_frame

        frames += [(f"kitti {i}", read_kitti_frame(KITTI, i).ego.points, HDL64E) for i in (0, 1)]
    if NUSCENES.is_dir():
        from typ.formats import read_nuscenes_frame

        bin_path = next(NUSCENES.glob("*.pcd.bin"))
        frames.append(("nuscenes", read_nuscenes_frame(bin_path, next(NUSCENES.glob("*info.json"))).ego.points,
                       HDL32E))
    return frames


def _kept_errors(points: np.ndarray, layout: RangeLayout):
    """Reconstruction error of every kept point, its bound, and the kept count."""
    px = range_pixels(points, layout)
    order = np.flatnonzero(px.winner)
    order = order[np.argsort(px.row[order] * layout.width + px.col[order])]
    back = range_to_points(range_image(points, layout), layout)
    err = np.linalg.norm(back.astype(np.float64) - points[order, :3].astype(np.float64), axis=1)
    return err, layout.error_bound(px.depth[order], px.row[order]), px


def test_simulated_scan_on_its_own_layout_comes_back_to_float32_rounding(sim_view):
    view, sensor = sim_view
    layout = RangeLayout.from_sensor(sensor)
    assert layout.shape == (64, 360)
    err, bound, px = _kept_errors(view.points, layout)
    # points lie on the sensor's rays, one return per ray: every point keeps a pixel of its own
    assert px.kept == px.inside == len(view.points)
    assert err.max() < 2e-5 and (err <= bound).all()


@pytest.mark.parametrize("bins", [90, 256, 1024])
def test_simulated_scan_within_the_bound_at_coarser_and_finer_azimuths(sim_view, bins):
    view, sensor = sim_view
    layout = RangeLayout.from_sensor(sensor, bins)
    err, bound, px = _kept_errors(view.points, layout)
    assert (err <= bound).all()
    if bins >= 360:  # finer than the 1 deg rays: every return keeps a pixel of its own
        assert px.kept == px.inside
    else:            # coarser: a pixel holds 360/bins rays of its beam and keeps one of their returns
        assert px.inside * bins / 360 <= px.kept <= layout.height * bins
    # the bound is tight enough to mean something: half an azimuth bin at 40 m is ~0.7 m at 90 bins
    assert err.max() <= 75.0 * (layout.half_gaps().max() + math.pi / bins)


@pytest.mark.skipif(not real_frames(), reason="../shared/data not present")
@pytest.mark.parametrize("name,points,layout", real_frames() or [("none", None, None)])
def test_real_frames_round_trip_within_the_stated_bound(name, points, layout):
    err, bound, px = _kept_errors(points, layout)
    assert (err <= bound).all(), (name, float((err / bound).max()))
    assert px.inside > 0.8 * len(points)  # the layouts cover these sensors' fields of view
    assert px.kept > 0.25 * px.inside     # the rest shared a pixel with a nearer point
    assert np.median(err) < 0.2           # most points sit close to their pixel's ray


@pytest.mark.skipif(not real_frames(), reason="../shared/data not present")
@pytest.mark.parametrize("name,points,layout", real_frames() or [("none", None, None)])
def test_images_of_real_frames_are_fixed_points_of_both_inverses(name, points, layout):
    img = range_image(points, layout)
    again = range_image(range_to_points(img, layout), layout)
    assert np.array_equal(again > 0, img > 0)
    np.testing.assert_allclose(again, img, rtol=1e-6)
    bev = bev_image(points, BEV)
    assert np.array_equal(bev_image(bev_to_points(bev, BEV), BEV), bev)


@pytest.mark.skipif(not KITTI.is_dir(), reason="../shared/data not present")
def test_bev_keeps_the_top_of_every_column_of_a_real_frame():
    from typ.formats import read_kitti_frame

    points = read_kitti_frame(KITTI, 0).ego.points
    _check_bev_bound(points)


def test_bev_bound_on_a_simulated_frame(sim_view):
    _check_bev_bound(sim_view[0].points)


def _check_bev_bound(points):
    img = bev_image(points, BEV)
    back = bev_to_points(img, BEV).astype(np.float64)
    size = BEV.voxel_size
    inside = np.all((points[:, :3] >= BEV.lower) & (points[:, :3] < BEV.upper), axis=1)
    p = points[inside, :3].astype(np.float64)
    # cells by their definition, [e_i, e_(i+1)) on typ.voxel's float64 edges
    i = np.searchsorted(BEV.edges(0), p[:, 0], side="right") - 1
    j = np.searchsorted(BEV.edges(1), p[:, 1], side="right") - 1
    bi = np.searchsorted(BEV.edges(0), back[:, 0], side="right") - 1
    bj = np.searchsorted(BEV.edges(1), back[:, 1], side="right") - 1
    cell = {(int(a), int(b)): q for a, b, q in zip(bi, bj, back)}
    assert len(cell) == len(back) == int(img[0].sum())
    highest = {}
    for k, (a, b) in enumerate(zip(i, j)):
        q = cell[(int(a), int(b))]
        assert abs(q[0] - p[k, 0]) <= size[0] / 2 + 1e-6 and abs(q[1] - p[k, 1]) <= size[1] / 2 + 1e-6
        assert q[2] >= p[k, 2] - 1e-6
        highest[(int(a), int(b))] = max(highest.get((int(a), int(b)), -np.inf), p[k, 2])
    for key, z in highest.items():
        assert abs(cell[key][2] - z) <= 1e-6 * max(1.0, abs(z))  # the top point's height, to float32


@pytest.mark.parametrize("bad", [np.array([[1.0, np.nan, 0.0, 0.5]], np.float32),
                                 np.array([[np.inf, 1.0, 0.0]], np.float64)])
def test_nan_points_are_named(bad):
    for fn, layout in ((range_image, HDL64E), (bev_image, BEV)):
        with pytest.raises(TypError, match="points: expected finite x, y, z"):
            fn(bad, layout)


def test_an_empty_cloud_is_named():
    for fn, layout in ((range_image, HDL64E), (bev_image, BEV)):
        with pytest.raises(TypError, match="points: expected at least one point, got 'an empty cloud"):
            fn(np.zeros((0, 4), np.float32), layout)


def test_an_image_whose_height_is_not_the_beam_count_is_named():
    img = np.zeros((63, HDL64E.width), np.float32)
    with pytest.raises(TypError, match="beam layout mismatch"):
        range_to_points(img, HDL64E)
    with pytest.raises(TypError, match="beam layout mismatch"):
        to_unit(np.zeros((32, 1024), np.float32), HDL64E)
    with pytest.raises(TypError, match="shape"):
        range_to_points(np.zeros((64, 512), np.float32), HDL64E)


def test_bad_layouts_and_grids_are_named():
    with pytest.raises(TypError, match="elevations_deg"):
        RangeLayout((2.0, 1.0), 512, 100.0)
    with pytest.raises(TypError, match="azimuth_bins"):
        RangeLayout((0.0, 1.0), 2, 100.0)
    with pytest.raises(TypError, match="min_range"):
        RangeLayout((0.0, 1.0), 64, 100.0, 0.0)
    with pytest.raises(TypError, match="grid"):
        bev_image(np.ones((3, 3), np.float32), Grid((-1, 1), (-1, 1), (-1, 1), (4, 4, 2)))
    with pytest.raises(TypError, match="image"):
        range_to_points(np.full(HDL64E.shape, np.nan, np.float32), HDL64E)


def test_points_outside_the_layout_are_dropped_not_folded_in():
    layout = RangeLayout((-10.0, -5.0, 0.0), 8, 50.0, 1.0)
    pts = np.array([[10, 0, 10 * math.tan(math.radians(-5)), 0],   # on the middle beam
                    [10, 0, 10 * math.tan(math.radians(30)), 0],   # far above the top beam
                    [0.5, 0, 0, 0],                                # closer than min_range
                    [60, 0, 0, 0]], np.float32)                    # beyond max_range
    px = range_pixels(pts, layout)
    assert px.row.tolist() == [1, -1, -1, -1] and px.kept == 1
    assert px.col[0] == 4  # azimuth 0 is bin W/2 (bins start at -pi)


def test_the_nearest_point_wins_a_pixel_and_carries_its_value():
    layout = RangeLayout((-1.0, 0.0, 1.0), 16, 100.0, 1.0)
    pts = np.array([[20, 0, 0, 0], [10, 0.01, 0, 0], [30, 0, 0, 0]], np.float32)
    depth, labels = range_image(pts, layout, values=np.array([1, 2, 3], np.uint8), fill=255)
    assert depth[1, 8] == pytest.approx(10.0, rel=1e-5) and labels[1, 8] == 2
    assert (labels == 255).sum() == labels.size - 1


def test_model_pixels_round_trip_for_canonical_images(sim_view):
    view, sensor = sim_view
    layout = RangeLayout.from_sensor(sensor, 256)
    img = range_image(view.points, layout)
    np.testing.assert_allclose(from_unit(to_unit(img, layout), layout), img, rtol=1e-5, atol=1e-4)
    bev = bev_image(view.points, BEV)
    back = from_unit(to_unit(bev, BEV), BEV)
    assert np.array_equal(back[0], bev[0])
    np.testing.assert_allclose(back[1], bev[1], atol=1e-5)
    # model output outside [-1, 1] or below min_range is made canonical
    noisy = from_unit(np.full((1, *layout.shape), -0.999, np.float32), layout)
    assert (noisy == 0).all()
    assert from_unit(np.full((1, *layout.shape), 3.0, np.float32), layout).max() < layout.max_range


def test_log_depth_pixels_are_hand_worked_values():
    layout = RangeLayout((-1.0, 0.0, 1.0), 4, 255.0, 1.0)  # log2(255 + 1) = 8
    img = np.zeros(layout.shape, np.float32)
    img[0, :] = [1.0, 3.0, 7.0, 15.0]   # log2(d + 1) = 1, 2, 3, 4
    img[1, 0] = 254.0
    px = to_unit(img, layout, depth="log")[0]
    np.testing.assert_allclose(px[0], [2 * k / 8 - 1 for k in (1, 2, 3, 4)], atol=1e-6)
    assert px[1, 0] == pytest.approx(2 * math.log2(255) / 8 - 1, abs=1e-6)
    assert (px[1, 1:] == -1).all() and (px[2] == -1).all()  # no return stays -1
    # the same depths, linearly: 2 d / 255 - 1
    np.testing.assert_allclose(to_unit(img, layout)[0, 0], 2 * img[0] / 255 - 1, atol=1e-6)


@pytest.mark.parametrize("depth", ["linear", "log"])
def test_both_depth_encodings_round_trip_canonical_images(sim_view, depth):
    view, sensor = sim_view
    layout = RangeLayout.from_sensor(sensor, 256)
    img = range_image(view.points, layout)
    img[0, 0] = layout.min_range  # the edges of the kept range survive too
    img[0, 1] = np.nextafter(np.float32(layout.max_range), np.float32(0))
    px = to_unit(img, layout, depth=depth)
    assert px.min() >= -1 and px.max() <= 1
    back = from_unit(px, layout, depth=depth)
    assert np.array_equal(back > 0, img > 0)
    np.testing.assert_allclose(back, img, rtol=2e-6, atol=1e-5)
    # the log scale spends more of [-1, 1] on near returns: the median return sits higher
    if depth == "log":
        lin = to_unit(img, layout)
        assert np.median(px[img[None] > 0]) > np.median(lin[img[None] > 0]) + 0.3


def test_log_depth_reads_no_return_below_the_threshold_and_clamps_above_it():
    layout = RangeLayout((-1.0, 0.0, 1.0), 4, 75.0, 0.5)
    vmin = 2 * math.log2(1.5) / math.log2(76) - 1                  # pixel of min_range, -0.68
    thr = no_return_threshold(layout, "log")
    assert thr == pytest.approx((vmin - 1) / 2)
    px = np.full((1, *layout.shape), -1.0, np.float32)
    px[0, 0, :] = [thr - 0.01, thr + 0.01, vmin, 5.0]
    d = from_unit(px, layout, depth="log")
    assert d[0, 0] == 0 and d[0, 1] == pytest.approx(0.5) and d[0, 2] == pytest.approx(0.5, rel=1e-5)
    assert d[0, 3] == np.nextafter(np.float32(75.0), np.float32(0))  # clipped to 1, below max_range
    assert (d[1:] == 0).all()
    # linear keeps its threshold at the pixel of min_range
    assert no_return_threshold(layout) == pytest.approx(2 * 0.5 / 75 - 1, abs=2e-6)


def test_unknown_or_misplaced_depth_encodings_are_named():
    with pytest.raises(TypError, match="depth"):
        to_unit(np.zeros(HDL64E.shape, np.float32), HDL64E, depth="sqrt")
    with pytest.raises(TypError, match="depth"):
        from_unit(np.zeros((1, *HDL64E.shape), np.float32), HDL64E, depth="sqrt")
    with pytest.raises(TypError, match="BEV"):
        to_unit(np.zeros((2, 4, 4), np.float32), BEV, depth="log")
