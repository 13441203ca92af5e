"""Scan-pattern realism (tasks.realism): on-beam share, row-occupancy profile, FRID / FPVD with intervals."""
from __future__ import annotations

import numpy as np
import pytest

from tasks import realism
from typ.sim.sensor import SensorSpec

SENSOR = SensorSpec(name="probe", elevations_deg=tuple(np.linspace(-20.0, 2.0, 16)), max_range=80.0, min_range=1.0,
                    mount_height=1.8, range_noise_std=0.0, dropout=0.0, detection_energy=0.0,
                    intensity_model="attenuation", azimuth_step_deg=2.0)


def scan(distance: float, beams=None, step: int = 1, heights=None) -> np.ndarray:
    """Points on the sensor's beams (every ``step``-th azimuth) at ``distance`` metres, written out
    from the beam geometry itself, not through typ's projection."""
    e = np.radians(np.asarray(SENSOR.elevations_deg))
    beams = range(len(e)) if beams is None else beams
    az = np.radians(np.arange(-180.0, 180.0, SENSOR.azimuth_step_deg))[::step]
    out = []
    for b in beams:
        h = 0.0 if heights is None else heights[b]
        d = distance * np.cos(e[b])
        out.append(np.stack([d * np.cos(az), d * np.sin(az), h + distance * np.sin(e[b]) * np.ones_like(az),
                             np.ones_like(az)], axis=1))
    return np.concatenate(out)


def test_a_scan_of_the_sensor_lies_on_its_beams_and_voxel_centres_do_not():
    points = scan(20.0)
    layout = realism.layout_of(SENSOR)
    p = realism.view_pattern(points, SENSOR, layout)
    assert p.points == len(points) and p.on_beam == len(points)
    # every beam row is full: one return per azimuth bin
    assert layout.shape == (16, 180) and p.rows.tolist() == [180] * 16
    centres = (np.floor(points[:, :3] / 0.4) + 0.5) * 0.4
    q = realism.view_pattern(centres, SENSOR, layout)
    assert q.on_beam / q.points < 0.5


def test_points_inside_the_minimum_range_and_non_finite_points_are_left_out():
    points = np.concatenate([scan(20.0, beams=[3]), [[0.5, 0.0, 0.0, 1.0], [np.nan, 1.0, 1.0, 1.0]]])
    p = realism.view_pattern(points, SENSOR, realism.layout_of(SENSOR))
    assert p.points == 180 and p.on_beam == 180
    empty = realism.view_pattern(np.zeros((0, 4)), SENSOR, realism.layout_of(SENSOR))
    assert empty.points == 0 and empty.rows.sum() == 0


def test_beam_origins_above_the_sensor_are_honoured():
    heights = tuple(0.1 + 0.01 * b for b in range(16))
    sensor = SensorSpec(**{**SENSOR.__dict__, "beam_heights_m": heights})
    points = scan(15.0, heights=heights)
    layout = realism.layout_of(sensor)
    assert realism.view_pattern(points, sensor, layout).on_beam == len(points)
    # seen from the origin instead (the heights ignored), the near beams miss by more than 0.05 deg
    assert realism.view_pattern(points, SENSOR, layout).on_beam < len(points)


class _Nets:
    """Stands in for the ddpm stage's feature networks: a cloud's features are its centroid and spread."""

    def features(self, clouds):
        f = np.array([[*c[:, :3].mean(axis=0), *c[:, :3].std(axis=0)] for c in clouds], dtype=np.float64)
        return {"frid": f, "fpvd": f[:, :3] * 2.0}


def _pairs(n_scenes: int = 6, per: int = 3, seed: int = 0):
    rng = np.random.default_rng(seed)
    scenes = [f"s{k}" for k in range(n_scenes) for _ in range(per)]
    truth = [scan(float(rng.uniform(8, 30)), step=2) for _ in scenes]
    return scenes, truth


def test_the_truth_scores_itself_perfectly_and_a_shifted_view_does_not():
    scenes, truth = _pairs()
    scorer = realism.RealismScorer(SENSOR, scenes, truth, _Nets())
    scorer.add("copy", truth)
    upper = [t[t[:, 2] > 0.0] for t in truth]                  # the upward beams only
    scorer.add("upper", upper)
    shifted = [t + np.array([3.0, 0.0, 0.5, 0.0]) for t in truth]
    scorer.add("shifted", shifted)
    out = scorer.summarize(n_boot=200)
    assert set(out) == {"truth", "copy", "upper", "shifted"}
    for key in ("truth", "copy"):
        assert out[key]["on_beam"].value == 1.0
        assert out[key]["row_profile_l1"].value == 0.0 and out[key]["row_profile_l1"].high == 0.0
        assert abs(out[key]["frid"].value) < 1e-9 and abs(out[key]["fpvd"].value) < 1e-9
    # upper beams only: the rows of the 15 lower beams are empty where the truth has 90 of 180 bins
    lower = sum(1 for e in SENSOR.elevations_deg if e < 0.0)
    assert out["upper"]["row_profile_l1"].value == pytest.approx(0.5 * lower / 16)
    assert out["upper"]["on_beam"].value == 1.0
    # a shifted cloud leaves the beams and moves the features: FRID = |mean shift|^2 (covariances equal)
    assert out["shifted"]["on_beam"].value < 0.2
    assert out["shifted"]["frid"].value == pytest.approx(3.0 ** 2 + 0.5 ** 2, rel=1e-6)
    assert out["shifted"]["fpvd"].value == pytest.approx(4 * (3.0 ** 2 + 0.5 ** 2), rel=1e-6)
    for figures in out.values():
        for fig, iv in figures.items():
            assert iv.low <= iv.value + 1e-12 and iv.value <= iv.high + 1e-12, (fig, iv)


def test_seeds_are_averaged_and_the_on_beam_share_is_pooled_over_points():
    scenes, truth = _pairs(n_scenes=4, per=2)
    scorer = realism.RealismScorer(SENSOR, scenes, truth)
    half = [np.concatenate([t, (np.floor(t[:, :3] / 0.4) + 0.5) * 0.4 @ np.eye(3, 4)]) for t in truth]
    scorer.add("m", truth)
    scorer.add("m", half)
    out = scorer.summarize(n_boot=100)
    assert "frid" not in out["m"] and scorer.truth_floor() == {}
    on = [realism.view_pattern(h, SENSOR, scorer.layout) for h in half]
    second = sum(p.on_beam for p in on) / sum(p.points for p in on)
    assert out["m"]["on_beam"].value == pytest.approx((1.0 + second) / 2)


def test_the_truth_floor_compares_two_halves_of_the_scenes():
    scenes, truth = _pairs(n_scenes=6, per=2)
    scorer = realism.RealismScorer(SENSOR, scenes, truth, _Nets())
    floor = scorer.truth_floor()
    f = _Nets().features(truth)["frid"]
    half = np.array([int(s[1:]) % 2 == 0 for s in scenes])
    from typ.metrics.frechet import frechet_from_features

    assert floor["frid"] == pytest.approx(frechet_from_features(f[half], f[~half])) and floor["frid"] > 0


def test_missing_feature_networks_are_a_reason_and_saved_ones_load(tmp_path):
    import torch

    from models.lidar_features import SegmentationFeatureNet
    from typ.artifacts import save_module
    from typ.voxel import Grid

    reason = realism.load_feature_nets(tmp_path / "features")
    assert isinstance(reason, str) and "ddpm stage" in reason and "features/range" in reason
    layout, grid = realism.layout_of(SENSOR), Grid((-8.0, 8.0), (-8.0, 8.0), (-2.0, 2.0), (32, 32, 8))
    torch.manual_seed(0)
    nets = {"range": SegmentationFeatureNet(in_channels=1, out_channels=6),
            "voxel": SegmentationFeatureNet(in_channels=grid.shape[2], out_channels=6 * grid.shape[2])}
    for kind, net in nets.items():
        save_module(tmp_path / "features" / kind, net, net.config, key="k", layout=layout.to_dict(),
                    voxel_grid=grid.to_dict())
    loaded = realism.load_feature_nets(tmp_path / "features")
    assert loaded.layout == layout and loaded.grid.shape == grid.shape
    clouds = [scan(6.0, step=3), scan(4.0, step=3)]
    feats = loaded.features(clouds)
    assert feats["frid"].shape == (2, nets["range"].feature_dim) and np.isfinite(feats["fpvd"]).all()
    assert not np.allclose(feats["frid"][0], feats["frid"][1])


def test_the_report_section_ranks_against_re_simulation_and_says_when_frid_is_missing():
    from tasks.evaluate import realism_section
    from typ.metrics.intervals import Interval

    good, bad = Interval(0.99, 0.98, 1.0), Interval(0.5, 0.4, 0.6)
    result = {"realism": {"truth": {"on_beam": good}, "resim": {"on_beam": bad}, "cast": {"on_beam": good},
                          "hybrid": {"on_beam": bad}},
              "realism_floor": {}, "layout": realism.layout_of(SENSOR),
              "realism_missing": "artifacts/ddpm/features/range holds no trained network"}
    text = "\n".join(realism_section(result))
    assert "| true reference scan | 0.990 [0.980, 1.000]" in text
    assert "FRID / FPVD not scored: artifacts/ddpm/features/range" in text
    assert "**beats** re-simulation on on_beam" in text and "hybrid" in text and "does not beat" in text


def test_the_row_profile_interval_resamples_views_when_scenes_hold_different_numbers():
    """Scenes of 1, 2, 3 and 6 views, every view with the same rows (truth: half the azimuth bins
    of every beam; the method: of the upward beams only). Whichever scenes a resample draws, the
    pooled profiles are those rows over the drawn views, so the L1 is the same in every replicate
    and the interval has no width. Dividing by the whole set's view count (equal to the drawn
    views' only when every scene holds as many) or not resampling the truth would spread it."""
    per = {"s0": 1, "s1": 2, "s2": 3, "s3": 6}
    scenes = [s for s, n in per.items() for _ in range(n)]
    truth = [scan(20.0, step=2) for _ in scenes]
    scorer = realism.RealismScorer(SENSOR, scenes, truth)
    scorer.add("upper", [t[t[:, 2] > 0.0] for t in truth])
    iv = scorer.summarize(n_boot=200)["upper"]["row_profile_l1"]
    lower = sum(1 for e in SENSOR.elevations_deg if e < 0.0)
    assert iv.value == pytest.approx(0.5 * lower / 16, abs=1e-12)
    assert iv.low == pytest.approx(iv.value, abs=1e-12) and iv.high == pytest.approx(iv.value, abs=1e-12)
    # scenes that fill their rows differently (every 1st, 2nd, 3rd or 4th azimuth bin), copied:
    # the drawn scenes' truth against the same scenes' views is 0 in every replicate
    fill = {"s0": 1, "s1": 2, "s2": 3, "s3": 4}
    truth = [scan(20.0, step=fill[s]) for s in scenes]
    scorer = realism.RealismScorer(SENSOR, scenes, truth)
    scorer.add("copy", truth)
    assert scorer.summarize(n_boot=200)["copy"]["row_profile_l1"].to_dict() == {"value": 0.0, "low": 0.0, "high": 0.0}


def test_the_row_profile_lists_the_lowest_beam_first_as_the_elevations_do():
    """profiles() pairs with ``layout.elevations_deg`` (ascending) in row_profile.csv: the method
    that keeps the upward beams only has its returns in the last rows, the ones above 0 deg."""
    scenes, truth = _pairs(n_scenes=2, per=1)
    scorer = realism.RealismScorer(SENSOR, scenes, truth)
    scorer.add("upper", [t[t[:, 2] > 0.0] for t in truth])
    profiles = scorer.profiles(["upper", "absent"])
    elevations = scorer.layout.elevations_deg
    assert list(elevations) == sorted(elevations)
    assert profiles["upper"] == [0.5 if e > 0.0 else 0.0 for e in elevations]
    assert profiles["truth"] == [0.5] * 16 and np.isnan(profiles["absent"]).all()
