"""Cluster-bootstrap intervals: hand-worked pooled ratios, coverage of a known mean, seeds;
the hierarchical (seeds, then samples) bootstrap of a set metric and its re-centring."""
import numpy as np
import pytest

from typ.errors import TypError
from typ.metrics.intervals import (Interval, bootstrap, bootstrap_figures, hierarchical_bootstrap, mean_of_means,
                                  pooled_ratio)


def test_pooled_ratio_point_estimate_is_the_pooled_figure_not_the_mean_of_ratios():
    tp = np.array([1.0, 9.0])
    union = np.array([10.0, 10.0])
    iv = pooled_ratio(tp, union, n_boot=200)
    assert iv.value == pytest.approx(10 / 20)
    # a scene that is all hits and one that is all misses: replicates range over 0.1 .. 0.9
    assert 0.1 <= iv.low <= iv.value <= iv.high <= 0.9


def test_identical_scenes_give_a_zero_width_interval():
    iv = pooled_ratio(np.full(8, 3.0), np.full(8, 4.0), n_boot=100)
    assert (iv.value, iv.low, iv.high) == pytest.approx((0.75, 0.75, 0.75))


def test_interval_covers_the_true_mean_about_95_percent_of_the_time():
    rng = np.random.default_rng(1)
    hits = 0
    for trial in range(120):
        x = rng.normal(2.0, 1.0, 40)
        iv = mean_of_means(x, n_boot=300, seed=trial)
        hits += iv.low <= 2.0 <= iv.high
    assert 0.85 <= hits / 120 <= 1.0


def test_seeds_are_averaged_and_resampled():
    num = np.array([[1.0, 1.0], [3.0, 3.0]])   # seed 0: 0.25, seed 1: 0.75
    den = np.full((2, 2), 4.0)
    iv = pooled_ratio(num, den, n_boot=400)
    assert iv.value == pytest.approx(0.5)
    assert iv.low == pytest.approx(0.25) and iv.high == pytest.approx(0.75)


def test_above_means_no_overlap():
    a, b = Interval(0.6, 0.55, 0.65), Interval(0.5, 0.45, 0.54)
    assert a.above(b) and not b.above(a)
    assert not Interval(0.6, 0.5, 0.7).above(b)


def test_bad_arguments_are_named():
    with pytest.raises(TypError, match="n_clusters"):
        bootstrap(lambda c, s: 0.0, 0)
    with pytest.raises(TypError, match="den"):
        pooled_ratio(np.ones(3), np.ones(4))


def test_basic_interval_reflects_a_resampling_bias_about_the_figure():
    """A statistic every resample inflates (distinct scenes drawn fall below K) has a percentile
    interval above the figure; the basic interval reflects it back around the figure."""
    from typ.metrics.intervals import bootstrap

    K = 10

    def missing_share(c, s):  # 0 on the full set, > 0 on any resample with repeats
        return 1.0 - len(np.unique(c)) / K

    p = bootstrap(missing_share, K, n_boot=400, seed=1)
    b = bootstrap(missing_share, K, n_boot=400, seed=1, method="basic")
    assert p.value == b.value == 0.0 and p.low > 0.0          # the percentile interval misses the figure
    assert (b.low, b.high) == pytest.approx((-p.high, -p.low))  # reflected about 0
    with pytest.raises(TypError, match="method"):
        bootstrap(missing_share, K, method="bca")


def test_hierarchical_bootstrap_resamples_seeds_then_samples():
    """A metric that is the mean of the chosen samples: the figure is the mean over seeds, and
    the interval spans both the spread between seeds and within each seed's samples."""
    values = [np.array([0.0, 1.0, 2.0, 3.0]), np.array([10.0, 11.0, 12.0, 13.0])]
    iv = hierarchical_bootstrap(lambda s, g, r: float(values[s][g].mean()), [4, 4], 5, n_boot=500)
    assert iv.value == pytest.approx(6.5) and iv.low < 2.0 and iv.high > 11.0
    again = hierarchical_bootstrap(lambda s, g, r: float(values[s][g].mean()), [4, 4], 5, n_boot=500)
    assert again == iv  # explicit seed: same inputs, same interval


def test_hierarchical_bootstrap_recentres_a_repeat_biased_metric_on_the_figure():
    """The share of a seed's K samples a resample misses is 0 on the full set and about
    (1 - 1/K)^K on a resample; the re-centred interval is the percentile interval moved down
    by the replicates' median, so it keeps their spread and holds the figure."""
    K = 10

    def missing_share(s, g, r):
        return 1.0 - len(np.unique(g)) / K

    pct = hierarchical_bootstrap(missing_share, [K], 7, n_boot=400, seed=1, method="percentile")
    rec = hierarchical_bootstrap(missing_share, [K], 7, n_boot=400, seed=1)
    assert pct.value == rec.value == 0.0 and pct.low > 0.0
    shift = pct.low - rec.low
    assert pct.high - rec.high == pytest.approx(shift)
    assert shift == pytest.approx((1 - 1 / K) ** K, abs=0.06)
    assert rec.low < 0.0 < rec.high


def test_hierarchical_bootstrap_names_bad_sizes():
    with pytest.raises(TypError, match="sizes"):
        hierarchical_bootstrap(lambda s, g, r: 0.0, [3, 0], 4)
    with pytest.raises(TypError, match="method"):
        hierarchical_bootstrap(lambda s, g, r: 0.0, [3], 4, method="bca")


@pytest.mark.parametrize("n_seeds", [1, 3])
def test_figures_of_one_resampling_equal_their_own_bootstraps(n_seeds):
    """bootstrap_figures draws each replicate once for all figures: figure i's interval is
    bit-for-bit bootstrap's of that figure alone with the same seed, NaN replicates left out alike."""
    rng = np.random.default_rng(4)
    tp, den = rng.integers(0, 5, (n_seeds, 9)).astype(float), rng.integers(1, 9, (n_seeds, 9)).astype(float)
    tp[:, 2] = 0

    def figures(c, s):
        pooled_tp, pooled_den = tp[s][:, c].sum(1), den[s][:, c].sum(1)
        # the last figure is undefined on replicates that drew scene 2 only or no tp at all
        return [float(np.mean(pooled_tp / pooled_den)), float(np.mean(pooled_den)),
                float(np.mean(pooled_tp / pooled_tp)) if (pooled_tp > 0).all() else float("nan")]

    ivs = bootstrap_figures(figures, 9, n_seeds, n_boot=300, seed=7, method="percentile")
    assert len(ivs) == 3
    for i, iv in enumerate(ivs):
        alone = bootstrap(lambda c, s, i=i: figures(c, s)[i], 9, n_seeds, n_boot=300, seed=7)
        assert (iv.value, iv.low, iv.high) == (alone.value, alone.low, alone.high)
    assert ivs[0].low < ivs[0].value < ivs[0].high      # a real spread, not a constant
    assert ivs[2].value == 1.0 and ivs[2].low == ivs[2].high == 1.0
