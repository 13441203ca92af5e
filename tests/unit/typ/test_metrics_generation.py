"""typ.metrics: BEV JSD/MMD presets on hand-worked cases and against independent re-computations
of the published recipes; voxel IoU and Chamfer distance on hand cases; input errors."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.distance import jensenshannon

from typ.errors import TypError
from typ.metrics import (PRESETS, bev_histogram, chamfer_distance, jsd_bev, mmd_bev, occupancy_iou,
                         voxel_iou)
from typ.voxel import Grid
from repo_paths import SHARED_DATA

DATA = SHARED_DATA
KITTI = [DATA / "kitti_object_vis/training/velodyne/000000.bin",
         DATA / "kitti_object_vis/training/velodyne/000001.bin"]
SQRT_LN2 = math.sqrt(math.log(2.0))
ALL = sorted(PRESETS)
SQUARED_MMD = ["r2dm", "lidargen"]


def pts(*xyz, dtype=np.float64) -> np.ndarray:
    return np.array(xyz, dtype=dtype).reshape(-1, 3)


def centre(i: int) -> float:
    """Centre of 1.6 m cell i of the r2dm/lidargen grid over [-80, 80]."""
    return -80.0 + 1.6 * (i + 0.5)


def cell_point(i: int, j: int, z: float = 0.0) -> list[float]:
    return [centre(i), centre(j), z]


def lidm_point(i: int, j: int, cell: float = 0.5, offset: int = 100) -> list[float]:
    """Centre of lidm cell (i, j) on a grid of ``cell`` metres whose index 0 starts at -offset*cell."""
    return [(i - offset + 0.5) * cell, (j - offset + 0.5) * cell, 0.0]


def random_scan(rng, n=3000, reach=85.0, dtype=np.float32) -> np.ndarray:
    r = rng.uniform(0.5, reach, n)
    th = rng.uniform(0.0, 2 * np.pi, n)
    return np.stack([r * np.cos(th), r * np.sin(th), rng.normal(-1.0, 1.0, n)], 1).astype(dtype)


# --- JSD -------------------------------------------------------------------------------------

def test_scipy_jensenshannon_is_natural_log_square_root():
    assert jensenshannon([1.0, 0.0], [0.0, 1.0]) == pytest.approx(SQRT_LN2, abs=1e-15)
    assert jensenshannon([1.0, 0.0], [0.0, 1.0], base=2) == pytest.approx(1.0, abs=1e-15)


@pytest.mark.parametrize("preset", ALL)
def test_jsd_identical_sets_is_zero(preset):
    rng = np.random.default_rng(1)
    scans = [random_scan(rng) for _ in range(3)]
    assert jsd_bev(scans, scans, preset) == 0.0
    assert jsd_bev(scans, [s.copy() for s in scans], preset) == 0.0


@pytest.mark.parametrize("preset", ALL)
def test_jsd_disjoint_is_sqrt_ln2(preset):
    a = [pts([10.0, 5.0, 0.0]), pts([12.0, 5.0, 0.0], [12.0, 5.0, 1.0])]
    b = [pts([-10.0, -5.0, 0.0])]
    assert jsd_bev(a, b, preset) == pytest.approx(SQRT_LN2, abs=1e-12)


def test_jsd_hand_worked_partial_overlap():
    # r2dm: A puts one point in each of two cells, B one point in the first: p = (1/2, 1/2),
    # q = (1, 0), m = (3/4, 1/4).
    a = [pts(cell_point(56, 56), cell_point(40, 56))]
    b = [pts(cell_point(56, 56))]
    kl_pm = 0.5 * math.log(0.5 / 0.75) + 0.5 * math.log(0.5 / 0.25)
    kl_qm = 1.0 * math.log(1.0 / 0.75)
    expected = math.sqrt(0.5 * kl_pm + 0.5 * kl_qm)
    assert jsd_bev(a, b, "r2dm") == pytest.approx(expected, abs=1e-14)
    assert jsd_bev(a, b, "lidargen") == pytest.approx(expected, abs=1e-14)


def test_jsd_sums_counts_over_scans_before_normalising():
    # Two scans of 1 and 3 points in different cells sum to (1/4, 3/4), not (1/2, 1/2).
    a = [pts(cell_point(56, 56)), pts(*[cell_point(40, 56)] * 3)]
    b = [pts(cell_point(56, 56), cell_point(40, 56))]
    p, q = np.array([0.25, 0.75]), np.array([0.5, 0.5])
    assert jsd_bev(a, b, "r2dm") == pytest.approx(jensenshannon(p, q), abs=1e-14)


@pytest.mark.parametrize("preset", ALL)
def test_jsd_symmetric_and_order_free(preset):
    rng = np.random.default_rng(2)
    a = [random_scan(rng) for _ in range(3)]
    b = [random_scan(rng, reach=60.0) for _ in range(2)]
    value = jsd_bev(a, b, preset)
    assert 0.0 < value < SQRT_LN2
    assert jsd_bev(b, a, preset) == value
    shuffled = [s[rng.permutation(len(s))] for s in a[::-1]]
    assert jsd_bev(shuffled, b, preset) == pytest.approx(value, rel=1e-12)
    assert jsd_bev(tuple(a), np.stack([s[:2000] for s in b]), preset) > 0  # tuples and (M, N, 3) stacks are sets too


# x cells 48..51 hold points within 3 m of the sensor, which the range filter drops
_FAR = st.integers(30, 69).filter(lambda k: not 48 <= k <= 51)


@given(st.lists(st.tuples(_FAR, st.integers(30, 69), st.integers(1, 4)), min_size=1, max_size=8),
       st.lists(st.tuples(_FAR, st.integers(30, 69), st.integers(1, 4)), min_size=1, max_size=8))
@settings(max_examples=30, deadline=None)
def test_jsd_equals_scipy_on_the_counted_cells(cells_a, cells_b):
    """Whatever cells the points fall in, JSD is scipy's on the per-cell counts."""
    grid_a, grid_b = np.zeros((100, 100)), np.zeros((100, 100))
    scan_a, scan_b = [], []
    for grid, scan, cells in ((grid_a, scan_a, cells_a), (grid_b, scan_b, cells_b)):
        for i, j, n in cells:
            grid[i, j] += n
            scan += [cell_point(i, j)] * n
    for preset in SQUARED_MMD:  # same grid away from edges
        value = jsd_bev([pts(*scan_a)], [pts(*scan_b)], preset)
        assert value == pytest.approx(jensenshannon(grid_a.ravel(), grid_b.ravel()), abs=1e-12)
        assert 0.0 <= value <= SQRT_LN2 + 1e-12


# --- range filter and bins -------------------------------------------------------------------

@pytest.mark.parametrize("preset", SQUARED_MMD)
def test_range_filter_3_to_70_m_strict(preset):
    base = [10.0, 0.0, 0.0]
    assert bev_histogram(pts(base), preset).sum() == 1
    assert bev_histogram(pts(base, [2.9, 0.0, 0.0]), preset).sum() == 1
    assert bev_histogram(pts(base, [3.1, 0.0, 0.0]), preset).sum() == 2
    assert bev_histogram(pts(base, [70.5, 0.0, 0.0]), preset).sum() == 1
    assert bev_histogram(pts(base, [3.0, 0.0, 0.0], [70.0, 0.0, 0.0]), preset).sum() == 1  # strict
    assert bev_histogram(pts(base, [0.0, 0.0, 3.2]), preset).sum() == 2  # |xyz| uses z, the grid doesn't
    assert bev_histogram(pts([0.0, 69.9, -1.0]), preset)[50, 93] == 1
    # Moving a point across 3 m changes the metric; adding one beyond 70 m does not.
    a = [pts(base, [2.9, 0.0, 0.0])]
    assert jsd_bev(a, [pts(base, [3.1, 0.0, 0.0])], preset) > 0.1
    assert jsd_bev(a, [pts(base, [70.5, 0.0, 0.0], [0.0, -75.0, 0.0])], preset) == 0.0
    assert mmd_bev(a, [pts(base, [70.5, 0.0, 0.0])], preset) == 0.0


def test_histogram_layout_is_x_rows_y_columns():
    h = bev_histogram(pts([-60.0, 10.0, 0.0], [-60.0, 10.0, 0.0], [10.0, -60.0, 0.0]), "r2dm")
    assert h.shape == (100, 100)
    assert h[12, 56] == 2 and h[56, 12] == 1  # floor((x + 80) / 1.6)


def test_r2dm_and_lidargen_edges_differ_on_float32_edge_values():
    # torch.linspace(-80, 80, 101) in float32 puts edge 55 at 7.999999 (fused multiply-add),
    # numpy's float64 edge is 8.0: a float32 point at 7.999999 m falls on either side.
    x = np.float32(7.999999046325684)
    scan = np.array([[x, 0.8, 0.0]], dtype=np.float32)
    assert bev_histogram(scan, "r2dm")[55, 50] == 1
    assert bev_histogram(scan, "lidargen")[54, 50] == 1
    assert jsd_bev([scan], [scan], "r2dm") == 0.0
    assert jsd_bev([scan], [scan.astype(np.float64)], "r2dm") == pytest.approx(SQRT_LN2)  # float64 edge is 8.0
    # Away from edges the two grids agree.
    s = random_scan(np.random.default_rng(3), n=2000)
    np.testing.assert_array_equal(bev_histogram(s, "r2dm"), bev_histogram(s, "lidargen"))


def test_lidm_occupancy_field_and_no_range_filter():
    dup = pts([10.0, 10.0, 0.0], [10.01, 10.01, 0.0], [10.0, 10.0, 5.0])  # one 0.05 m cell, three points
    assert bev_histogram(dup, "lidm64").sum() == 1  # occupancy
    assert bev_histogram(dup, "r2dm").sum() == 3  # counts
    near = pts([2.0, 0.0, 0.0])  # |xyz| < 3 m: lidm keeps it, r2dm drops it
    assert bev_histogram(near, "lidm64").sum() == 1 and bev_histogram(near, "r2dm").sum() == 0
    h = bev_histogram(pts([0.0, 0.0, 0.0], [-0.01, 49.99, 0.0]), "lidm64")
    assert h.shape == (2000, 2000) and h[1000, 1000] == 1 and h[999, 1999] == 1  # floor(x / 0.05) + 1000
    edge = pts([-50.0, 0.0, 0.0], [50.0, 0.0, 0.0], [0.0, -50.0, 0.0], [0.0, 50.0, 0.0])
    assert bev_histogram(edge, "lidm64").sum() == 0  # open field
    assert bev_histogram(pts([40.0, 0.0, 0.0]), "lidm32").sum() == 0
    assert bev_histogram(pts([-29.99, 0.0, 0.0]), "lidm32")[0, 600] == 1
    # float32 points just inside +-50 m still land inside the grid.
    inner = np.nextafter(np.float32(50.0), np.float32(0.0))
    f32 = np.array([[inner, -inner, 0.0]], dtype=np.float32)
    assert bev_histogram(f32, "lidm64")[1999, 0] == 1


# --- MMD -------------------------------------------------------------------------------------

# Three cells in distinct rows and columns, so grid differences are "generalised permutation"
# matrices whose singular values are the absolute entries.
E1, E2, E3 = cell_point(56, 56), cell_point(58, 60), cell_point(60, 58)
HAND_A = [pts(E1), pts(E1, E2)]  # p1 = e1, p2 = (e1 + e2) / 2
HAND_B = [pts(E2), pts(E2, E2, E2, E3)]  # q1 = e2, q2 = (3 e2 + e3) / 4


def k(d2: float) -> float:
    """Gaussian kernel, sigma = 0.5: exp(-d^2 / (2 * 0.25))."""
    return math.exp(-d2 / (2 * 0.5 ** 2))


def test_mmd_r2dm_hand_worked():
    # Squared Frobenius distances between the normalised grids, by hand:
    # |p1-p2|^2 = .5^2+.5^2 = .5; |q1-q2|^2 = .25^2+.25^2 = .125; |p1-q1|^2 = 1+1 = 2;
    # |p1-q2|^2 = 1+.75^2+.25^2 = 1.625; |p2-q1|^2 = .5^2+.5^2 = .5; |p2-q2|^2 = .5^2+.25^2+.25^2 = .375
    kaa = (k(0) + k(0) + 2 * k(0.5)) / 4
    kbb = (k(0) + k(0) + 2 * k(0.125)) / 4
    kab = (k(2.0) + k(1.625) + k(0.5) + k(0.375)) / 4
    assert mmd_bev(HAND_A, HAND_B, "r2dm") == pytest.approx(kaa + kbb - 2 * kab, abs=1e-14)


def test_mmd_lidargen_hand_worked_spectral():
    # Spectral norm of a difference with entries in distinct rows/columns = largest |entry|:
    # p1-p2 -> .5, q1-q2 -> .25, p1-q1 -> 1, p1-q2 -> 1, p2-q1 -> .5, p2-q2 -> .5 (squared below).
    kaa = (2 * k(0) + 2 * k(0.25)) / 4
    kbb = (2 * k(0) + 2 * k(0.0625)) / 4
    kab = (k(1.0) + k(1.0) + k(0.25) + k(0.25)) / 4
    value = mmd_bev(HAND_A, HAND_B, "lidargen")
    assert value == pytest.approx(kaa + kbb - 2 * kab, abs=1e-14)
    assert value != pytest.approx(mmd_bev(HAND_A, HAND_B, "r2dm"), rel=1e-3)  # distances differ
    assert jsd_bev(HAND_A, HAND_B, "lidargen") == jsd_bev(HAND_A, HAND_B, "r2dm")  # grids don't


def test_mmd_spectral_equals_frobenius_for_a_single_row_difference():
    # Cells in one x row: the difference is rank one, so spectral and Frobenius norms agree.
    a = [pts(cell_point(56, 50))]
    b = [pts(cell_point(56, 60))]
    expected = 2 - 2 * k(2.0)
    assert mmd_bev(a, b, "r2dm") == pytest.approx(expected, abs=1e-14)
    assert mmd_bev(a, b, "lidargen") == pytest.approx(expected, abs=1e-14)


@pytest.mark.parametrize("preset", ALL)
def test_mmd_identical_sets_is_zero(preset):
    rng = np.random.default_rng(4)
    scans = [random_scan(rng, n=1500) for _ in range(3)]
    assert mmd_bev(scans, scans, preset) == 0.0
    assert abs(mmd_bev(scans, [s[::-1].copy() for s in scans[::-1]], preset)) < 1e-12


@pytest.mark.parametrize("preset", SQUARED_MMD)
def test_mmd_symmetric_order_free_positive(preset):
    rng = np.random.default_rng(5)
    a = [random_scan(rng, n=1500) for _ in range(3)]
    b = [random_scan(rng, n=1500, reach=50.0) for _ in range(2)]
    value = mmd_bev(a, b, preset)
    assert value > 0
    assert mmd_bev(b, a, preset) == pytest.approx(value, rel=1e-12)
    shuffled = [s[rng.permutation(len(s))] for s in a[::-1]]
    assert mmd_bev(shuffled, b, preset) == pytest.approx(value, rel=1e-12)


def test_lidm_minimum_matching_hand_worked():
    r = [pts(lidm_point(100, 100))]
    far, near = pts(lidm_point(103, 104)), pts(lidm_point(101, 100))  # 3-4-5 cells, 1 cell
    # One point each way: CD = (d^2 + d^2) / 2 = d^2, in cell units / 200^2; min picks the near one.
    assert mmd_bev(r, [far, near], "lidm64") == pytest.approx(1 / 200 ** 2, abs=1e-18)
    assert mmd_bev(r, [far], "lidm64") == pytest.approx(25 / 200 ** 2, abs=1e-18)
    # Two cells 2 apart vs one of them: a->b mean (0 + 4) / 2 = 2, b->a 0, CD = (2 + 0) / 2 = 1.
    two = [pts(lidm_point(100, 100), lidm_point(102, 100), lidm_point(102, 100))]
    assert mmd_bev(two, r, "lidm64") == pytest.approx(1 / 200 ** 2, abs=1e-18)
    # lidm32: 120 cells per axis, the 0.5 m grid starts at -30 m.
    assert mmd_bev([pts(lidm_point(60, 60, offset=60))], [pts(lidm_point(61, 60, offset=60))],
                   "lidm32") == pytest.approx(1 / 120 ** 2, abs=1e-18)
    # Points in one 0.5 m cell are one point; z and |xyz| play no part.
    assert mmd_bev(r, [pts([0.3, 0.4, 9.0], [0.49, 0.01, -3.0])], "lidm64") == 0.0


def test_lidm_minimum_matching_is_not_symmetric():
    a = [pts(lidm_point(100, 100)), pts(lidm_point(110, 100))]
    b = [pts(lidm_point(100, 100))]
    assert mmd_bev(a, b, "lidm64") == pytest.approx((0 + 100) / 2 / 200 ** 2, abs=1e-18)
    assert mmd_bev(b, a, "lidm64") == 0.0


# --- against independent re-computations of the published recipes ---------------------------

def edge_heavy_scans(rng, dtype):
    """Random scans plus points exactly on (and one ulp around) both kinds of 1.6 m edges."""
    torch = pytest.importorskip("torch")
    edges = np.concatenate([np.linspace(-80, 80, 101),
                            torch.linspace(-80, 80, 101, dtype=torch.float32).double().numpy()]).astype(dtype)
    on = np.concatenate([edges, np.nextafter(edges, dtype(np.inf)), np.nextafter(edges, dtype(-np.inf))])
    on = on[(np.abs(on) > 4) & (np.abs(on) < 65)]
    scans = []
    for _ in range(3):
        extra = np.stack([rng.choice(on, 300), rng.choice(on, 300), np.zeros(300)], 1).astype(dtype)
        scans.append(np.concatenate([random_scan(rng, n=2000, dtype=dtype), extra]))
    return scans


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_r2dm_matches_torch_recipe(dtype):
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(6)
    a, b = edge_heavy_scans(rng, dtype), edge_heavy_scans(rng, dtype)[:2]

    def hist(scan):
        t = torch.from_numpy(scan[:, :3])
        depth = t.norm(p=2, dim=1)
        keep = (depth > 3.0) & (depth < 70.0)
        return torch.histogramdd(t[keep, 0:2], bins=100, range=[-80.0, 80.0, -80.0, 80.0]).hist.double()

    ha, hb = torch.stack([hist(s) for s in a]).flatten(1), torch.stack([hist(s) for s in b]).flatten(1)
    for s, h in zip(a, ha):
        np.testing.assert_array_equal(bev_histogram(s, "r2dm").ravel(), h.numpy())
    p, q = ha.sum(0) / ha.sum(), hb.sum(0) / hb.sum()
    assert jsd_bev(a, b, "r2dm") == pytest.approx(jensenshannon(p.numpy(), q.numpy()), abs=1e-12)
    pa, pb = ha / ha.sum(1, keepdim=True), hb / hb.sum(1, keepdim=True)

    def rbf(x, y):
        return torch.exp(-torch.cdist(x, y) ** 2 / (2 * 0.5 ** 2))

    expected = (rbf(pa, pa).mean() + rbf(pb, pb).mean() - 2 * rbf(pa, pb).mean()).item()
    assert mmd_bev(a, b, "r2dm") == pytest.approx(expected, rel=1e-9, abs=1e-15)


def test_lidargen_matches_numpy_recipe():
    rng = np.random.default_rng(7)
    a, b = edge_heavy_scans(rng, np.float32), edge_heavy_scans(rng, np.float32)[:2]

    def hist(scan):
        depth = np.linalg.norm(scan[:, :3].astype(np.float64), axis=1).astype(scan.dtype)
        s = scan[(depth > 3.0) & (depth < 70.0)]
        return np.histogramdd(s[:, :2], bins=100, range=([-80.0, 80.0], [-80.0, 80.0]))[0]

    ha, hb = [hist(s) for s in a], [hist(s) for s in b]
    for s, h in zip(a, ha):
        np.testing.assert_array_equal(bev_histogram(s, "lidargen"), h)
    p, q = sum(ha) / sum(ha).sum(), sum(hb) / sum(hb).sum()
    assert jsd_bev(a, b, "lidargen") == pytest.approx(jensenshannon(p.ravel(), q.ravel()), abs=1e-12)
    na, nb = [h / h.sum() for h in ha], [h / h.sum() for h in hb]

    def disc(xs, ys):
        return np.mean([math.exp(-np.linalg.norm(x - y, 2) ** 2 / (2 * 0.5 ** 2)) for x in xs for y in ys])

    expected = disc(na, na) + disc(nb, nb) - 2 * disc(na, nb)
    assert mmd_bev(a, b, "lidargen") == pytest.approx(expected, rel=1e-9, abs=1e-15)


@pytest.mark.parametrize("preset,half,jsd_cells", [("lidm64", 50, 2000), ("lidm32", 30, 1200)])
def test_lidm_matches_direct_recipe(preset, half, jsd_cells):
    rng = np.random.default_rng(8)
    a = [random_scan(rng, n=n, reach=70.0) for n in (800, 1500, 300)]
    b = [random_scan(rng, n=n, reach=40.0) for n in (600, 1000)]

    def inside(scan):
        x, y = scan[:, 0], scan[:, 1]
        return scan[(x > -half) & (x < half) & (y > -half) & (y < half), :2]

    def occupancy_sum(scans):
        total = np.zeros((jsd_cells, jsd_cells))
        for s in scans:
            cells = np.unique(np.floor(inside(s) / np.float32(0.05)).astype(int), axis=0) + jsd_cells // 2
            total[cells[:, 0], cells[:, 1]] += 1
        return total

    ta, tb = occupancy_sum(a), occupancy_sum(b)
    expected_jsd = jensenshannon((ta / ta.sum()).ravel(), (tb / tb.sum()).ravel())
    assert jsd_bev(a, b, preset) == pytest.approx(expected_jsd, abs=1e-12)

    n = 2 * half * 2  # 0.5 m cells per axis

    def cell_points(s):
        # Cells in float64; LiDM stores (cell / n) as float32, a ~1e-8 relative difference.
        return (np.unique(np.floor(inside(s) / np.float32(0.5)), axis=0).astype(np.float64) + n // 2) / n

    def cd(x, y):
        d_xy = cKDTree(y).query(x)[0] ** 2
        d_yx = cKDTree(x).query(y)[0] ** 2
        return (d_xy.mean() + d_yx.mean()) / 2

    ca, cb = [cell_points(s) for s in a], [cell_points(s) for s in b]
    expected_mmd = np.mean([min(cd(r, s) for s in cb) for r in ca])
    assert mmd_bev(a, b, preset) == pytest.approx(expected_mmd, rel=1e-12)
    expected_rev = np.mean([min(cd(s, r) for r in ca) for s in cb])
    assert mmd_bev(b, a, preset) == pytest.approx(expected_rev, rel=1e-12)


def test_real_kitti_frames_r2dm_against_torch():
    torch = pytest.importorskip("torch")
    scans = []
    for path in KITTI:
        if not path.is_file():
            pytest.skip(f"real frame not available: {path}")
        scans.append(np.fromfile(path, dtype=np.float32).reshape(-1, 4))
    hists = []
    for s in scans:
        t = torch.from_numpy(s[:, :3])
        d = t.norm(dim=1)
        hists.append(torch.histogramdd(t[(d > 3) & (d < 70), :2], bins=100,
                                       range=[-80.0, 80.0, -80.0, 80.0]).hist.double().numpy())
        np.testing.assert_array_equal(bev_histogram(s, "r2dm"), hists[-1])
    value = jsd_bev(scans[:1], scans[1:], "r2dm")
    assert value == pytest.approx(jensenshannon(hists[0].ravel(), hists[1].ravel()), abs=1e-12)
    assert 0.05 < value < SQRT_LN2
    for preset in ALL:
        assert mmd_bev(scans[:1], scans[1:], preset) > 0


# --- presets ---------------------------------------------------------------------------------

def test_presets_describe_their_conventions():
    assert set(PRESETS) == {"r2dm", "lidargen", "lidm64", "lidm32"}
    r2dm, lidargen, l64, l32 = (PRESETS[n] for n in ("r2dm", "lidargen", "lidm64", "lidm32"))
    assert (r2dm.cells, r2dm.half_width, r2dm.depth_range, r2dm.sigma) == (100, 80.0, (3.0, 70.0), 0.5)
    assert r2dm.cell == pytest.approx(1.6)
    assert (r2dm.mmd_distance, lidargen.mmd_distance) == ("frobenius", "spectral")
    assert (l64.cells, l64.mmd_cells, l32.cells, l32.mmd_cells) == (2000, 200, 1200, 120)
    assert l64.mmd == "minimum-matching" and l64.depth_range is None
    for p in PRESETS.values():
        assert p.source.split()[0] in p.convention  # the repository is named in the quotable text
    assert "minimum matching" in l64.convention and "sigma = 0.5" in r2dm.convention
    assert "spectral" in lidargen.convention and "100x100" in lidargen.convention


# --- truth: chamfer and IoU ------------------------------------------------------------------

def test_chamfer_hand_cases():
    rng = np.random.default_rng(9)
    cloud = rng.normal(size=(50, 4))
    assert chamfer_distance(cloud, cloud) == 0.0
    assert chamfer_distance(pts([0.0, 0.0, 0.0]), pts([1.0, 2.0, 2.0])) == pytest.approx(3.0, abs=1e-15)
    # a -> b: 0; b -> a: (0 + 3) / 2; CD = (0 + 1.5) / 2, not squared.
    assert chamfer_distance(pts([0.0, 0.0, 0.0]), pts([0.0, 0.0, 0.0], [3.0, 0.0, 0.0])) == pytest.approx(0.75)
    assert chamfer_distance(pts([0.0, 0.0, 0.0], [3.0, 0.0, 0.0]), pts([0.0, 0.0, 0.0])) == pytest.approx(0.75)
    # Columns past z are ignored; float32 is fine.
    a = np.array([[0, 0, 0, 100.0]], dtype=np.float32)
    b = np.array([[0, 0, 2, -5.0]], dtype=np.float32)
    assert chamfer_distance(a, b) == 2.0


def test_chamfer_empty_or_bad_raises():
    with pytest.raises(TypError) as e:
        chamfer_distance(np.zeros((0, 3)), pts([0.0, 0.0, 0.0]))
    assert e.value.field == "a"
    with pytest.raises(TypError) as e:
        chamfer_distance(pts([0.0, 0.0, 0.0]), np.zeros((0, 3)))
    assert e.value.field == "b"
    with pytest.raises(TypError) as e:
        chamfer_distance(pts([0.0, 0.0, 0.0]), pts([np.nan, 0.0, 0.0]))
    assert e.value.field == "b" and "NaN" in str(e.value)


UNIT = Grid((0.0, 4.0), (0.0, 4.0), (0.0, 1.0), (4, 4, 1))  # 1 m voxels


def test_voxel_iou_hand_case():
    pred = pts([0.5, 0.5, 0.5], [1.5, 1.5, 0.5], [1.6, 1.4, 0.2])  # voxels (0,0), (1,1)
    true = pts([1.5, 1.5, 0.5], [2.5, 2.5, 0.5], [3.5, 3.5, 0.5], [9.0, 9.0, 0.5])  # (1,1), (2,2), (3,3); one outside
    out = voxel_iou(pred, true, UNIT)
    assert out == {"iou": pytest.approx(1 / 4), "precision": pytest.approx(1 / 2), "recall": pytest.approx(1 / 3)}
    assert voxel_iou(true, true, UNIT) == {"iou": 1.0, "precision": 1.0, "recall": 1.0}


def test_occupancy_iou_hand_case_and_undefined_ratios():
    p = np.zeros((3, 3), dtype=bool)
    t = np.zeros((3, 3), dtype=bool)
    p[0, :] = True  # 3 cells
    t[:, 0] = True  # 3 cells, 1 shared
    assert occupancy_iou(p, t) == {"iou": 0.2, "precision": pytest.approx(1 / 3), "recall": pytest.approx(1 / 3)}
    empty = np.zeros((3, 3), dtype=bool)
    out = occupancy_iou(empty, t)
    assert out["iou"] == 0.0 and out["recall"] == 0.0 and math.isnan(out["precision"])
    assert all(math.isnan(v) for v in occupancy_iou(empty, empty).values())


def test_occupancy_iou_bad_input():
    with pytest.raises(TypError) as e:
        occupancy_iou(np.zeros((3, 3), dtype=bool), np.zeros((3, 4), dtype=bool))
    assert e.value.field == "true"
    with pytest.raises(TypError) as e:
        occupancy_iou(np.zeros((3, 3)), np.zeros((3, 3), dtype=bool))
    assert e.value.field == "pred"
    with pytest.raises(TypError) as e:
        voxel_iou(np.zeros((4, 2)), pts([0.5, 0.5, 0.5]), UNIT)
    assert e.value.field == "pred_points"


# --- bad input for the BEV metrics -----------------------------------------------------------

GOOD = [pts([10.0, 0.0, 0.0])]


@pytest.mark.parametrize("fn", [jsd_bev, mmd_bev])
@pytest.mark.parametrize("set_a,set_b,field,fragment", [
    ([], GOOD, "set_a", "at least one scan"),
    (GOOD, [np.zeros((4, 2))], "set_b[0]", "(N, >=3)"),
    (GOOD + [np.array([[1.0, np.nan, 0.0]])], GOOD, "set_a[1]", "NaN"),
    (GOOD, [np.array([[10, 0, 0]])], "set_b[0]", "float32 or float64"),
    (pts([10.0, 0.0, 0.0], [11.0, 0.0, 0.0]), GOOD, "set_a", "list of (N, >=3) point arrays"),
    (GOOD, "scans.bin", "set_b", "list of (N, >=3) point arrays"),
])
def test_bad_sets_raise_naming_the_field(fn, set_a, set_b, field, fragment):
    with pytest.raises(TypError) as e:
        fn(set_a, set_b, "r2dm")
    assert e.value.field == field and fragment in str(e.value)
    assert e.value.where == fn.__name__


@pytest.mark.parametrize("fn", [jsd_bev, mmd_bev, bev_histogram])
def test_unknown_preset_raises(fn):
    args = (GOOD[0],) if fn is bev_histogram else (GOOD, GOOD)
    with pytest.raises(TypError) as e:
        fn(*args, preset="R2DM")
    assert e.value.field == "preset" and "lidargen" in str(e.value)


@pytest.mark.parametrize("preset", ALL)
def test_scans_without_points_in_field(preset):
    nothing = pts([60.0, 0.0, 0.0]) if preset.startswith("lidm") else pts([1.0, 0.0, 0.0])  # outside the field
    empty = np.zeros((0, 3))
    # JSD: an empty scan adds nothing; a set with no point at all is an error.
    assert jsd_bev(GOOD + [empty, nothing], GOOD, preset) == 0.0
    with pytest.raises(TypError) as e:
        jsd_bev(GOOD, [empty, nothing], preset)
    assert e.value.field == "set_b"
    # MMD normalises per scan (or takes a Chamfer distance): every scan needs a point.
    with pytest.raises(TypError) as e:
        mmd_bev(GOOD, GOOD + [nothing], preset)
    assert e.value.field == "set_b[1]"
