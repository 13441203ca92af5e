"""typ.viz on hand-made clouds: pixels where the convention puts them, boxes on their corners,
range images against the sensor's own rays, error maps by hand, PNGs and the gallery."""
import math

import matplotlib.image as mpimg
import numpy as np
import pytest

from typ import viz
from typ.errors import TypError
from typ.geometry import box_corners
from typ.scene import SEMANTIC_CODE
from typ.sim.sensor import SensorSpec, domain_spec
from typ.voxel import Grid, voxelize

GRID = Grid((-20.0, 20.0), (-20.0, 20.0), (-3.0, 1.0), (10, 10, 4))   # 4 m cells, 1 m channels


def _pts(*xyz):
    return np.array([[*p, 0.0] for p in xyz], dtype=np.float32)


def _rgb(canvas, yx, ax):
    """Canvas RGB (0-255) at plot coordinates (y, x) of ``ax`` (matplotlib's display y is up)."""
    dx, dy = ax.transData.transform(yx)
    return canvas[int(canvas.shape[0] - dy), int(dx), :3].astype(int)


def _close(rgb, colour, tol=3):
    return np.all(np.abs(np.asarray(rgb) - np.round(np.asarray(colour) * 255)) <= tol)


def test_a_point_lands_on_the_pixel_of_the_convention_and_the_highest_point_wins():
    window = viz.Window((-20.0, 20.0), (-20.0, 20.0), 4.0)
    assert window.shape == (10, 10)
    # x = 6 m forward, y = -10 m (right): row floor((20 - 6) / 4) = 3, col floor((20 + 10) / 4) = 7
    image = viz.bev_points_image(_pts((6.0, -10.0, -2.0), (6.5, -9.0, 0.5), (-30.0, 0.0, 0.0)), window)
    lit = np.argwhere((image != viz.BACKGROUND).any(axis=2))
    assert lit.tolist() == [[3, 7]]  # one pixel; the point outside the window is dropped
    assert np.allclose(image[3, 7], viz._height_colours(np.array([0.5]), (-3.0, 1.0))[0])  # the higher point
    # pixel edges: (x_max - (row+1) res, x_max - row res] along x, same along y
    row, col, inside = window.pixels(np.array([[20.0, 20.0], [16.0, 16.0], [15.999, 15.999], [-20.0, 0.0]]))
    assert row.tolist()[:3] == [0, 1, 1] and col.tolist()[:3] == [0, 1, 1]
    assert inside.tolist() == [True, True, True, False]


def test_points_are_drawn_heading_up_with_y_to_the_left_on_the_rendered_canvas():
    window = viz.Window((-20.0, 20.0), (-20.0, 20.0), 4.0)
    pts = _pts((14.0, -2.0, -1.0), (-14.0, -2.0, -1.0), (-2.0, 14.0, -1.0), (-2.0, -14.0, -1.0))
    semantics = np.array([SEMANTIC_CODE[c] for c in ("vehicle", "vegetation", "pole", "building")], dtype=np.uint8)
    fig = viz.bev_figure(pts, window=window, semantics=semantics)
    canvas = viz.figure_array(fig)
    ax = fig.axes[0]
    centres = {}
    for name in ("vehicle", "vegetation", "pole", "building"):
        target = np.round(np.array(viz.CLASS_COLOURS[name]) * 255)
        hits = np.argwhere(np.all(np.abs(canvas[..., :3].astype(int) - target) <= 2, axis=2))
        hits = hits[hits[:, 0] > 40]  # not the legend's patches, top right
        assert len(hits) > 100, name  # a 4 m pixel is many screen pixels
        centres[name] = hits.mean(axis=0)
    assert centres["vehicle"][0] < centres["vegetation"][0]  # +x is up
    assert centres["pole"][1] < centres["building"][1]        # +y is left
    # and each lands where the axes put its pixel's centre: (x, y) = (14, -2) -> cell centre (14, -2)
    for name, (x, y) in (("vehicle", (14.0, -2.0)), ("pole", (-2.0, 14.0))):
        assert _close(_rgb(canvas, (y, x), ax), viz.CLASS_COLOURS[name])
    assert _close(_rgb(canvas, (-6.0, 14.0), ax), viz.BACKGROUND)  # the neighbouring pixel is empty


@pytest.mark.parametrize("yaw_deg", [0.0, 30.0, -110.0])
def test_a_box_is_drawn_through_its_corners_and_nowhere_else(yaw_deg):
    box = np.array([[5.0, -3.0, -1.0, 8.0, 4.0, 1.5, math.radians(yaw_deg)]])
    window = viz.Window((-20.0, 20.0), (-20.0, 20.0), 0.5)
    fig = viz.bev_figure(np.zeros((0, 4), np.float32), window=window, boxes=box)
    canvas = viz.figure_array(fig)
    ax = fig.axes[0]
    red = (canvas[..., 0] > 150) & (canvas[..., 1] < 110) & (canvas[..., 2] < 130)

    def near_red(x, y, radius=1):
        dx, dy = ax.transData.transform((y, x))
        r, c = int(round(canvas.shape[0] - dy)), int(round(dx))
        return red[r - radius:r + radius + 1, c - radius:c + radius + 1].any()

    corners = box_corners(box)[0, :4, :2]  # the bottom four: the BEV outline
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        for t in (0.0, 0.25, 0.5, 0.75):
            assert near_red(*(a + t * (b - a))), (k, t)
    # inside the box, away from the heading tick (centre -> front), nothing is drawn
    c, s = math.cos(box[0, 6]), math.sin(box[0, 6])
    for lx, ly in ((-2.0, 1.0), (-2.0, -1.0), (1.0, 1.2)):
        assert not near_red(5.0 + lx * c - ly * s, -3.0 + lx * s + ly * c, radius=2)
    # well outside the box no red pixel at all
    for x, y in ((-15.0, 15.0), (15.0, -15.0), (-10.0, -15.0)):
        assert not near_red(x, y, radius=4)


def test_an_occupancy_is_drawn_on_the_pixel_its_points_would_take():
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-19.9, 19.9, (40, 2)), rng.uniform(-2.9, 0.9, 40), np.zeros(40)].astype(np.float32)
    occ = voxelize(pts, GRID)
    from_grid = viz.bev_occupancy_image(occ, GRID)
    from_points = viz.bev_points_image(pts, viz.Window.of_grid(GRID))
    filled = (from_grid != viz.BACKGROUND).any(axis=2)
    assert np.array_equal(filled, (from_points != viz.BACKGROUND).any(axis=2))
    # the colour is the height of the highest occupied voxel's centre
    i, j = 7, 2
    occ2 = np.zeros(GRID.shape, bool)
    occ2[i, j, [0, 2]] = True
    image = viz.bev_occupancy_image(occ2, GRID)
    assert np.allclose(image[GRID.shape[0] - 1 - i, GRID.shape[1] - 1 - j],
                       viz._height_colours(np.array([GRID.centers(2)[2]]), GRID.z_range)[0])
    classes = np.full(GRID.shape, 255, np.uint8)
    classes[i, j, 2] = SEMANTIC_CODE["vegetation"]
    image = viz.bev_occupancy_image(occ2, GRID, classes=classes)
    assert np.allclose(image[GRID.shape[0] - 1 - i, GRID.shape[1] - 1 - j], viz.CLASS_COLOURS["vegetation"])


def test_error_map_counts_and_colours_cells_and_voxels():
    pred, true = np.zeros(GRID.shape, bool), np.zeros(GRID.shape, bool)
    true[0, 0, 0] = pred[0, 0, 0] = True          # tp
    true[1, 1, 0] = True                           # miss
    pred[2, 2, 3] = True                           # fp
    pred[3, 3, 1] = True; true[3, 3, 2] = True     # right cell, wrong height
    assert viz.error_counts(pred, true) == {"tp": 2, "miss": 1, "fp": 1}
    assert viz.error_counts(pred, true, per="voxel") == {"tp": 1, "miss": 2, "fp": 2}
    H, W = GRID.shape[:2]
    cell = viz.error_image(pred, true)
    voxel = viz.error_image(pred, true, per="voxel")
    px = lambda img, i, j: img[H - 1 - i, W - 1 - j]  # noqa: E731
    assert np.allclose(px(cell, 0, 0), viz.TP_COLOUR) and np.allclose(px(cell, 1, 1), viz.MISS_COLOUR)
    assert np.allclose(px(cell, 2, 2), viz.FP_COLOUR) and np.allclose(px(cell, 3, 3), viz.TP_COLOUR)
    assert np.allclose(px(voxel, 3, 3), viz.MISS_COLOUR)  # one miss, one fp: the tie goes to the miss
    assert np.allclose(px(cell, 5, 5), viz.BACKGROUND)
    with pytest.raises(TypError, match="per"):
        viz.error_image(pred, true, per="pixel")
    with pytest.raises(TypError, match="pred/true"):
        viz.error_counts(pred, true[:5])


def test_range_image_puts_every_ray_of_the_sensor_in_its_own_cell():
    spec = SensorSpec(name="t", elevations_deg=(-20.0, -8.0, -2.0, 1.0), max_range=80.0, min_range=0.5,
                      mount_height=1.8, range_noise_std=0.0, dropout=0.0, detection_energy=0.0,
                      intensity_model="attenuation", azimuth_step_deg=5.0)
    dirs = spec.ray_directions()  # beam-major, azimuths from -180 deg
    ranges = 5.0 + np.arange(len(dirs)) % 37
    image = viz.range_image((dirs * ranges[:, None]).astype(np.float32), spec)
    assert image.shape == (4, 72) and np.isfinite(image).all()
    expected = ranges.reshape(4, 72)[::-1]  # row 0 is the highest beam
    assert np.allclose(image, expected, atol=1e-4)
    # two points in one cell keep the nearer; a point far above the top beam is dropped
    b, a = 1, 20
    d = dirs[b * 72 + a]
    up = np.array([math.cos(math.radians(40)), 0.0, math.sin(math.radians(40))])
    image = viz.range_image(np.array([d * 30.0, d * 12.0, up * 10.0], dtype=np.float32), spec)
    assert np.isfinite(image).sum() == 1 and image[4 - 1 - b, a] == pytest.approx(12.0)
    fig = viz.range_figure(dirs.astype(np.float32) * 10, spec, title="rays")
    assert "100% of cells hit" in fig.axes[0].get_title()


def test_save_png_writes_the_canvas_and_the_same_bytes_twice(tmp_path):
    window = viz.Window((-20.0, 20.0), (-20.0, 20.0), 1.0)
    pts = _pts((3.0, 4.0, -1.0), (-12.0, 7.0, 0.0))
    a = viz.save_png(viz.bev_figure(pts, window=window, boxes=[[0, 0, 0, 4, 2, 1.5, 0.3]], title="t"), tmp_path / "a.png")
    fig = viz.bev_figure(pts, window=window, boxes=[[0, 0, 0, 4, 2, 1.5, 0.3]], title="t")
    b = viz.save_png(fig, tmp_path / "sub" / "b.png")
    assert a.read_bytes() == b.read_bytes()
    png = (mpimg.imread(b) * 255).round().astype(int)
    assert np.array_equal(png, viz.figure_array(fig).astype(int))
    assert not list(tmp_path.rglob(".tmp-*"))


def _sample(name, shift):
    rng = np.random.default_rng(int(shift))
    true = np.c_[rng.uniform(-19, 19, (300, 2)), np.full(300, -2.5), np.zeros(300)].astype(np.float32)
    generated = true.copy()
    generated[:, 0] += shift
    return {"name": name, "ego": true, "x_e": true, "generated": generated, "true": voxelize(true, GRID),
            "resim": true[:150], "boxes": np.array([[2.0, 3.0, -1.5, 4.5, 1.9, 1.5, 0.4]]),
            "reference_in_ego": [10.0, 5.0, math.pi / 2], "scores": {"iou": 0.5 - shift / 10, "method": "typ"}}


def test_sample_figure_has_every_panel_and_the_error_counts_in_its_legend():
    sample = _sample("s0", 4.0)
    fig = viz.sample_figure(sample, GRID)
    titles = [ax.get_title() for ax in fig.axes if ax.get_visible() and ax.get_title()]
    assert titles == list(viz.SAMPLE_PANELS.values())
    counts = viz.error_counts(voxelize(sample["generated"], GRID), sample["true"])
    legend = [t.get_text() for t in fig.axes[5].get_legend().get_texts()]
    assert legend == [f"true positive {counts['tp']}", f"miss {counts['miss']}", f"false positive {counts['fp']}"]
    assert "iou 0.1" in fig.get_suptitle() and "method typ" in fig.get_suptitle()
    only = viz.sample_figure({"generated": sample["generated"], "titles": {"generated": "mine"}}, GRID)
    assert [ax.get_title() for ax in only.axes if ax.get_title()] == ["mine"]
    with pytest.raises(TypError, match="sample"):
        viz.sample_figure({"scores": {}}, GRID)


def test_gallery_writes_one_png_per_sample_and_an_index_with_their_scores(tmp_path):
    samples = [_sample("town 1/frame 0", 0.0), _sample("town 1/frame 1", 4.0)]
    snippet = viz.gallery(samples, tmp_path / "gallery", GRID, link_prefix="gallery/", title="Samples")
    pngs = sorted(p.name for p in (tmp_path / "gallery").glob("*.png"))
    assert pngs == ["town_1_frame_0.png", "town_1_frame_1.png"]
    assert "| sample | iou | method |" in snippet
    assert "| [town_1_frame_1](gallery/town_1_frame_1.png) | 0.1 | typ |" in snippet
    assert "![town_1_frame_0](gallery/town_1_frame_0.png)" in snippet
    index = (tmp_path / "gallery" / "index.md").read_text()
    assert index.startswith("# Samples") and "](town_1_frame_0.png)" in index
    img = mpimg.imread(tmp_path / "gallery" / "town_1_frame_0.png")
    assert img.shape[0] > 500 and img[..., :3].std() > 0.05
    with pytest.raises(TypError, match="unique"):
        viz.gallery([samples[0], samples[0]], tmp_path / "g2", GRID)


def test_bad_input_names_the_field():
    with pytest.raises(TypError, match="points"):
        viz.bev_points_image(np.zeros((3, 2), np.float32))
    with pytest.raises(TypError, match="boxes"):
        viz.bev_figure(_pts((0, 0, 0)), boxes=np.zeros((1, 6)))
    with pytest.raises(TypError, match="occupancy"):
        viz.bev_occupancy_image(np.zeros((3, 3, 3), bool), GRID)
    with pytest.raises(TypError, match="resolution"):
        viz.Window(resolution=0.0)
    with pytest.raises(TypError, match="square"):
        viz.Window.of_grid(Grid((-20.0, 20.0), (-10.0, 10.0), (-3.0, 1.0), (10, 10, 4)))
    with pytest.raises(TypError, match="semantics"):
        viz.bev_points_image(_pts((0, 0, 0)), semantics=np.zeros(2, np.uint8))
    assert domain_spec("target").sensor.n_beams == viz.range_image(np.zeros((0, 3), np.float32),
                                                                    domain_spec("target").sensor).shape[0]
