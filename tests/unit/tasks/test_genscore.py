"""Generation scores on hand-made grids: pooled IoU by mask, the above-ground mask, object hits,
JSD against itself, and intervals that pool scenes."""
import numpy as np
import pytest

from tasks import genscore
from typ.metrics.generation import above_ground, local_ground, object_hits
from typ.voxel import Grid

GRID = Grid((-25.6, 25.6), (-25.6, 25.6), (-0.75, 3.25), (64, 64, 8))   # 0.8 m cells, 0.5 m bins


def _flat_view():
    """(C, H, W): ground (channel 1) everywhere but the sensor's shadow, a wall 2 m high at x = 10 m."""
    v = np.zeros((8, 64, 64), bool)
    v[1] = True
    v[1, 30:34, 30:34] = False
    v[1:5, 44, 10:50] = True
    return v


def test_local_ground_is_the_lowest_occupied_height_around_a_cell():
    v = _flat_view().transpose(1, 2, 0)
    ground = local_ground(v, GRID)
    assert np.allclose(ground, GRID.centers(2)[1])      # the ground bin everywhere, shadow and wall included
    above = above_ground(v, GRID)
    assert above[..., 2:].all() and not above[..., :2].any()   # 0.5 m and up is > 0.3 m over the ground


def test_a_perfect_view_scores_one_and_a_copy_shifted_off_the_walls_scores_less():
    truth = _flat_view()
    seen = np.zeros((64, 64), bool)
    seen[:32] = True
    stats = genscore.true_view_stats(truth, GRID)
    boxes = np.zeros((0, 7))
    perfect = genscore.score_pair(truth, np.zeros((0, 3)), truth, seen, boxes, GRID, stats)
    ious = {k: v for k, v in perfect.items() if k.startswith("iou")}
    assert len(ious) == 7 and all(0 < tp == union for tp, union in ious.values() if union), ious
    assert perfect["chamfer_m"] == 0.0
    ground_only = truth.copy()
    ground_only[2:] = False
    s = genscore.score_pair(ground_only, np.zeros((0, 3)), truth, seen, boxes, GRID, stats)
    tp, union = s["iou_above_ground"]
    assert tp == 0 and union == truth[2:].sum()        # the wall is all that is above the ground
    assert s["iou"] == (truth[:2].sum(), truth.sum())
    assert s["precision"] == (truth[:2].sum(), truth[:2].sum())   # no false positive
    seen_tp, seen_union = s["iou_seen"]
    assert seen_union == truth[:, :32].sum() and seen_tp == truth[:2, :32].sum()


def test_object_hits_count_boxes_within_range_holding_enough_points():
    rng = np.random.default_rng(0)
    boxes = np.array([[10.0, 0, 0.75, 4.5, 1.8, 1.5, 0.0],     # 12 points inside: hit
                      [0.0, 20, 0.75, 4.5, 1.8, 1.5, 0.3],     # 9 points: miss
                      [60.0, 0, 0.75, 4.5, 1.8, 1.5, 0.0]])    # beyond 50 m: not counted
    inside = lambda b, n: b[:3] + (rng.random((n, 3)) - 0.5) * np.array([4.0, 1.5, 1.2]) @ np.eye(3)
    pts = np.concatenate([inside(boxes[0], 12), boxes[1, :3] + np.zeros((9, 3)), inside(boxes[2], 30)])
    assert object_hits(pts, boxes) == (1, 2)
    assert object_hits(np.zeros((0, 3)), boxes) == (0, 2)


def test_summary_pools_scenes_and_seeds_with_intervals():
    truth = _flat_view()
    seen = np.ones((64, 64), bool)
    stats = genscore.true_view_stats(truth, GRID)
    half = truth.copy()
    half[:, :32] = False
    perfect = genscore.score_pair(truth, np.zeros((0, 3)), truth, seen, np.zeros((0, 7)), GRID, stats)
    worse = genscore.score_pair(half, np.zeros((0, 3)), truth, seen, np.zeros((0, 7)), GRID, stats)
    # scene a: perfect, scene b: half, for both seeds
    table = genscore.summarize([[perfect, worse], [perfect, worse]], ["a", "b"], [stats["histogram"]] * 2,
                               [stats["centres"]] * 2, n_boot=200)
    tp = perfect["iou"][0] + worse["iou"][0]
    union = perfect["iou"][1] + worse["iou"][1]
    assert table["iou"].value == pytest.approx(tp / union)
    assert table["iou"].low < table["iou"].value < table["iou"].high
    assert table["jsd_r2dm"].value > 0
    same = genscore.summarize([[perfect, perfect]], ["a", "b"], [stats["histogram"]] * 2, [stats["centres"]] * 2,
                              n_boot=50)
    assert same["jsd_r2dm"].value == pytest.approx(0.0, abs=1e-12) and same["iou"].value == 1.0


def test_pairwise_iou_of_samples():
    a = np.zeros((1, 2, 4, 4), bool)
    a[0, 0, :2] = True
    b = a.copy()
    assert genscore.pairwise_iou(a, b) == 1.0
    b[0, 0, 1] = False
    assert genscore.pairwise_iou(a, b) == pytest.approx(0.5)


def test_jsd_interval_holds_its_figure_when_resampling_biases_it():
    """Eight scenes of random ground: a resample with repeated scenes pools fewer distinct views,
    so its JSD lies above the figure; the interval must still contain the figure."""
    rng = np.random.default_rng(0)
    scores, scenes, hists, centres = [], [], [], []
    for k in range(8):
        truth, gen = np.zeros((2, 8, 64, 64), bool)
        truth[1], gen[1] = rng.random((2, 64, 64)) < 0.5
        stats = genscore.true_view_stats(truth, GRID)
        scores.append(genscore.score_pair(gen, np.zeros((0, 3)), truth, np.ones((64, 64), bool), np.zeros((0, 7)),
                                          GRID, stats))
        scenes.append(f"s{k}")
        hists.append(stats["histogram"])
        centres.append(stats["centres"])
    jsd = genscore.summarize([scores], scenes, hists, centres, n_boot=200)["jsd_r2dm"]
    assert 0 < jsd.low <= jsd.value <= jsd.high


def test_a_new_figure_is_one_registry_entry_scored_pooled_and_tabled(monkeypatch):
    """Adding a generation figure to :data:`genscore.METRICS` is all it takes: every pair gets
    its value, summarize pools it, and the generation report's table has its column."""
    from tasks import evaluate

    metric = genscore.Metric("ground voxels", lambda p: (int(p.occupancy[1].sum()), int(p.truth[1].sum())),
                             genscore.pool_ratio, lower_is_better=True)
    monkeypatch.setitem(genscore.METRICS, "ground_ratio", metric)
    truth = _flat_view()
    stats = genscore.true_view_stats(truth, GRID)
    half = truth.copy()
    half[1, :, :32] = False
    seen = np.ones((64, 64), bool)
    rows = [[genscore.score_pair(v, np.zeros((0, 3)), truth, seen, np.zeros((0, 7)), GRID, stats)
             for v in (truth, half)]]
    assert rows[0][1]["ground_ratio"] == (half[1].sum(), truth[1].sum())
    table = genscore.summarize(rows, ["a", "b"], [stats["histogram"]] * 2, [stats["centres"]] * 2, n_boot=50)
    assert table["ground_ratio"].value == pytest.approx((truth[1].sum() + half[1].sum()) / (2 * truth[1].sum()))
    monkeypatch.setattr(evaluate, "ACCURACY_COLUMNS",
                        [(k, m.label) for k, m in genscore.METRICS.items() if m.in_table])
    md = evaluate.table({"typ": table}, evaluate.ACCURACY_COLUMNS)
    assert "ground voxels" in md.splitlines()[0] and genscore.lower_is_better("ground_ratio")
    pooled = {name: genscore.summarize([[r] * 2], ["a", "b"], [stats["histogram"]] * 2, [stats["centres"]] * 2,
                                       n_boot=50) for name, r in (("half", rows[0][1]), ("same", rows[0][0]))}
    lines = evaluate.comparisons(pooled, [("half", "same", "ground_ratio"), ("same", "half", "ground_ratio")])
    assert "**beats**" in lines[0] and "does not beat" in lines[1]     # lower wins: the flag is read


def test_the_report_columns_are_the_registry_in_order():
    from tasks import evaluate

    assert [k for k, _ in evaluate.ACCURACY_COLUMNS] == [
        "iou", "iou_0-20", "iou_20-40", "iou_40-80", "iou_seen", "iou_unseen", "iou_above_ground",
        "object_hit_rate", "chamfer_m", "jsd_r2dm", "mmd_r2dm"]
    assert {k for k, m in genscore.METRICS.items() if m.lower_is_better} == {"chamfer_m", "jsd_r2dm", "mmd_r2dm"}


@pytest.mark.parametrize("grid", [GRID, Grid((-12.8, 12.8), (-12.8, 12.8), (-0.75, 3.25), (128, 128, 8))],
                         ids=["tiny-0.8m-cells", "paper-0.2m-cells"])
def test_a_cell_whose_only_return_is_a_car_roof_takes_the_road_around_it(grid):
    """A car 4 x 2.4 m whose roof, 1.5 m up, is all the sensor saw of its cells (the road under it
    hidden): their ground is the road beside the car, so the roof is above the ground; the roof's
    own height as the ground would hide the car. On the tiny grid the car is 5 x 3 cells, on the
    paper's 0.2 m cells 20 x 12, where a neighbourhood of 5 cells (1 m) would not reach the road."""
    x, y = grid.centers(0), grid.centers(1)
    car = ((x > 4.0) & (x < 8.0))[:, None] & ((y > -1.6) & (y < 0.8))[None, :]
    assert car.sum() * grid.voxel_size[0] * grid.voxel_size[1] == pytest.approx(4.0 * 2.4)
    v = np.zeros(grid.shape, bool)
    v[..., 1] = True                        # the road, z = 0
    v[car] = False
    v[car, 4] = True                        # the roof, z = 1.5 m, and nothing below it
    assert grid.centers(2)[[1, 4]].tolist() == [0.0, 1.5]
    np.testing.assert_array_equal(local_ground(v, grid), np.zeros(grid.shape[:2]))
    above = above_ground(v, grid)
    assert above[car, 4].all() and (above & v).sum() == car.sum()
