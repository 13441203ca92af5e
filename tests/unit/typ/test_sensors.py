"""typ.sensors: the presets, the sensor registry and params block, and the beam/mount estimator,
on scans typ casts and on the real frames in shared/data (skipped when absent)."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from typ.config import SensorConfig
from typ.errors import TypError
from typ.formats.binfile import read_bin
from typ.sensors import SENSORS, fit_ground, fit_sensor, on_beam_fractions, resolve
from typ.sim import DOMAINS, build_town, cast, domain_spec, sensor_pose, simulate_traffic, town_frame
from typ.sim.sensor import SensorSpec
from repo_paths import SHARED_DATA

DATA = SHARED_DATA
KITTI = DATA / "kitti_object_vis" / "training" / "velodyne"
NUSCENES = DATA / "nuscenes_mmdet3d_demo" / "n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin"


@pytest.fixture(scope="module")
def world():
    """One frame of a simulated town and the pose of the first agent's car in it."""
    spec = domain_spec("target")
    town_seed, traffic_seed, _ = np.random.SeedSequence(7).spawn(3)
    town = build_town(spec.town, np.random.default_rng(town_seed))
    traffic = simulate_traffic(town, np.random.default_rng(traffic_seed), n_frames=1, dt=0.1, n_agents=1,
                               comm_range=70.0, moving_vehicles=spec.moving_vehicles,
                               class_probs=spec.moving_class_probs)
    car = traffic.agents[0]
    return town_frame(town, traffic, 0), traffic.xy[0, car], traffic.yaw[0, car], int(traffic.ids[car])


def _scan(world, spec: SensorSpec) -> np.ndarray:
    frame, xy, yaw, car = world
    points, _ = cast(frame, sensor_pose(xy, yaw, spec.mount_height), spec, np.random.default_rng(0),
                     exclude_vehicle_id=car)
    return points


# ---------------------------------------------------------------- recovering what typ casts


@pytest.mark.parametrize("name", sorted(SENSORS))
def test_a_sensor_is_recovered_from_a_scan_typ_casts_with_it(world, name):
    """Every beam (0.005 deg), every beam origin (5 mm), the mount height (2 cm) and the azimuth
    step, from one sweep: with range noise and dropout (the real presets), sparse upper beams
    (only walls and trees above the horizon) and KITTI's two laser blocks above the origin."""
    spec = SENSORS[name]
    fit = fit_sensor(_scan(world, spec))
    assert fit.n_beams == spec.n_beams
    assert np.abs(np.subtract(fit.elevations_deg, spec.elevations_deg)).max() <= 0.005
    if spec.beam_heights_m:
        assert np.abs(np.subtract(fit.beam_heights_m, spec.beam_heights_m)).max() <= 0.005
    else:
        assert fit.beam_heights_m == ()
    assert fit.mount_height == pytest.approx(spec.mount_height, abs=0.02)
    assert fit.azimuth_step_deg == pytest.approx(spec.azimuth_step_deg, rel=0.01)
    assert fit.quality >= 0.999
    assert fit.spec(spec) == dataclasses.replace(spec, elevations_deg=fit.elevations_deg,
                                                 beam_heights_m=fit.beam_heights_m, mount_height=fit.mount_height,
                                                 azimuth_step_deg=fit.azimuth_step_deg)


def test_beams_start_at_their_own_heights(world):
    """A KITTI scan lies on cones from each laser block's height above the origin, not from the
    origin: the caster moves each ray's origin (the estimator's on-beam test sees it)."""
    kitti = SENSORS["kitti"]
    points = _scan(world, kitti)
    assert on_beam_fractions(points, kitti)[0.05] == 1.0
    from_origin = dataclasses.replace(kitti, beam_heights_m=())
    assert on_beam_fractions(points, from_origin, min_range=3.0)[0.05] < 0.5
    lowest = np.argmin(kitti.elevations_deg)
    assert kitti.ray_origins()[lowest * kitti.n_azimuths] == pytest.approx([0.0, 0.0, kitti.beam_heights_m[lowest]])
    assert domain_spec("target").sensor.ray_origins() is None


def test_a_voxel_grid_is_off_the_beams():
    """The fraction is a property of the points: the voxel centres (what a generator writes) of
    a flat ground fall on the HDL-32E's beams, 1.33 deg apart, about as often as 0.1 deg in
    1.33 (7.5 %)."""
    spec = SENSORS["nuscenes"]
    x, y = np.meshgrid(np.arange(-40, 40, 0.4) + 0.2, np.arange(-40, 40, 0.4) + 0.2)
    centres = np.c_[x.ravel(), y.ravel(), np.full(x.size, -spec.mount_height + 0.1)]
    assert 0.02 < on_beam_fractions(centres, spec, min_range=3.0)[0.05] < 0.15


def test_a_scan_without_road_below_is_a_named_error(world):
    """A sweep upside down (the road 1.84 m above the sensor): no road, rather than a mount
    height of -1.84 m (the Waymo subsamples in shared/data hold only returns above the sensor)."""
    points = _scan(world, SENSORS["nuscenes"])[:, :3] * np.array([1.0, 1.0, -1.0], dtype=np.float32)
    with pytest.raises(TypError, match="ground plane"):
        fit_sensor(points)


def test_too_few_points_is_a_named_error():
    with pytest.raises(TypError, match="scans"):
        fit_sensor(np.zeros((10, 3)))
    with pytest.raises(TypError, match=r"\(N, >=3\)"):
        fit_sensor(np.zeros((100, 2)))


# ---------------------------------------------------------------- registry and params block


def test_every_name_resolves_and_the_domains_keep_their_sensors():
    assert set(SENSORS) == set(DOMAINS) | {"kitti", "nuscenes", "waymo", "v2v4real", "opv2v"}
    for name, domain in DOMAINS.items():
        assert resolve(name) is domain.sensor
    for name, spec in SENSORS.items():
        assert resolve(name) is spec and spec.name == name and resolve(spec) is spec


def test_a_sensor_block_builds_the_sensor_it_describes():
    block = {"elevations_deg": {"n": 64, "low": -17.6, "high": 2.4, "spacing": "horizon_dense"},
             "azimuth_step_deg": 0.4, "max_range": 75, "min_range": 1, "mount_height": 2.2}
    spec = resolve(block, field="simulate.sources.target.sensor")
    assert spec.elevations_deg == domain_spec("target").sensor.elevations_deg   # the target domain's rule
    assert (spec.max_range, spec.mount_height, spec.azimuth_step_deg) == (75.0, 2.2, 0.4)
    uniform = resolve({**block, "elevations_deg": {"n": 64, "low": -25, "high": 2}})
    assert uniform.elevations_deg == SENSORS["opv2v"].elevations_deg
    listed = resolve({**block, "elevations_deg": [-10, -5, 0], "beam_heights_m": [0.1, 0.1, 0.2]})
    assert listed.elevations_deg == (-10.0, -5.0, 0.0) and listed.beam_heights_m == (0.1, 0.1, 0.2)
    assert resolve(SensorConfig(elevations_deg=(-10.0, 0.0), azimuth_step_deg=0.2, max_range=50.0,
                                mount_height=1.5)).n_beams == 2


@pytest.mark.parametrize("change, field", [
    ({"elevations_deg": [2.0, 1.0]}, "sensor.elevations_deg"),
    ({"elevations_deg": {"n": 4, "low": 5, "high": -5}}, "sensor.elevations_deg.low/high"),
    ({"elevations_deg": {"n": 4, "low": -5, "high": 5, "spacing": "log"}}, "sensor.elevations_deg.spacing"),
    ({"beam_heights_m": [0.1]}, "sensor.beam_heights_m"),
    ({"mount_height": -1.0}, "sensor.mount_height"),
    ({"max_range": 0.5}, "sensor.min_range/max_range"),
    ({"dropout": 1.5}, "sensor.dropout"),
    ({"intensity_model": "lidar"}, "sensor.intensity_model"),
    ({"azimuth_step_deg": "fine"}, "sensor.azimuth_step_deg"),
    ({"beams": 32}, "sensor.beams"),
])
def test_a_bad_sensor_block_names_its_field(change, field):
    block = {"elevations_deg": [-10.0, 0.0], "azimuth_step_deg": 0.2, "max_range": 50.0, "mount_height": 1.5}
    with pytest.raises(TypError) as err:
        resolve({**block, **change})
    assert err.value.field == field and err.value.where == "params.yaml"


def test_an_unknown_sensor_name_lists_the_known_ones():
    with pytest.raises(TypError, match="kitti") as err:
        resolve("velodyne")
    assert err.value.field == "sensor"
    with pytest.raises(TypError):
        resolve(32)


def test_beam_heights_must_match_the_beams():
    with pytest.raises(TypError, match="beam_heights_m"):
        dataclasses.replace(SENSORS["nuscenes"], beam_heights_m=(0.1,))


def test_ingest_lifts_vehicle_frame_points_by_their_lidars_height():
    """Waymo's points come in the vehicle frame, on the ground: lifted by the LiDAR's height, the
    preset's the scenario names (the format's own, or one named per source); the others come in
    the LiDAR's own frame."""
    from tasks.ingest import READERS

    assert {fmt: r.lift(r.preset) for fmt, r in READERS.items()} == {
        "kitti": 0.0, "nuscenes": 0.0, "waymo": SENSORS["waymo"].mount_height, "kitti-odometry": 0.0}
    assert READERS["waymo"].lift("nuscenes") == SENSORS["nuscenes"].mount_height
    with pytest.raises(TypError, match=r"the waymo reader \(tasks/ingest.py\).*sensor.*no-such-lidar"):
        READERS["waymo"].lift("no-such-lidar")


# ---------------------------------------------------------------- the presets against real frames


def _real(path: Path, columns: int) -> np.ndarray:
    if not path.is_file():
        pytest.skip(f"{path} is not available")
    return read_bin(path, columns)


@pytest.fixture(scope="module")
def kitti_fits():
    return {name: fit_sensor(_real(KITTI / f"{name}.bin", 4)) for name in ("000000", "000001")}


@pytest.mark.parametrize("frame", ["000000", "000001"])
def test_the_estimator_finds_the_kitti_preset_in_each_real_frame(kitti_fits, frame):
    """The preset's 64 beams and their blocks' heights, from either frame alone (the preset was
    measured on both by their scan order, which the estimator does not use)."""
    kitti, fit = SENSORS["kitti"], kitti_fits[frame]
    assert fit.n_beams == 64 and fit.quality >= 0.99
    assert np.abs(np.subtract(fit.elevations_deg, kitti.elevations_deg)).max() <= 0.02
    assert np.abs(np.subtract(fit.beam_heights_m, kitti.beam_heights_m)).max() <= 0.005
    assert fit.mount_height == pytest.approx(kitti.mount_height, abs=0.03)
    assert fit.azimuth_step_deg == pytest.approx(kitti.azimuth_step_deg, abs=0.01)


def test_the_kitti_preset_fits_a_frame_it_was_not_measured_on():
    """KITTI testing frame 000002 (another drive; camera field of view only): every return on a
    beam of the preset, and far fewer on the datasheet's nominal two-block layout."""
    points = _real(DATA / "pointpillars_kitti_demo" / "testing" / "velodyne_reduced" / "000002.bin", 4)
    kitti = SENSORS["kitti"]
    assert on_beam_fractions(points, kitti, min_range=3.0)[0.05] >= 0.99
    nominal = np.r_[np.linspace(-24.33, -8.83, 32), np.linspace(-8.33, 2.0, 32)]
    as_sheet = dataclasses.replace(kitti, elevations_deg=tuple(nominal))
    assert on_beam_fractions(points, as_sheet, min_range=3.0)[0.05] < 0.5


def test_the_nuscenes_preset_matches_the_keyframe():
    """Its rings (the file's 5th column) lie at the HDL-32E's nominal elevations: the median of
    each ring above -9.5 deg within 0.05 deg; the fitted road lies 1.84 m down."""
    points = _real(NUSCENES, 5)
    spec = SENSORS["nuscenes"]
    far = np.hypot(points[:, 0], points[:, 1]) >= 3.0
    seen = np.degrees(np.arctan2(points[far, 2], np.hypot(points[far, 0], points[far, 1])))
    ring = points[far, 4].astype(int)
    upper = [r for r in range(32) if spec.elevations_deg[r] > -9.5]
    medians = np.array([np.median(seen[ring == r]) for r in upper])
    assert np.abs(medians - np.take(spec.elevations_deg, upper)).max() <= 0.05
    _, height = fit_ground(points[:, :3].astype(np.float64), np.random.default_rng(0))
    assert height == pytest.approx(spec.mount_height, abs=0.03)


def test_the_waymo_preset_is_the_real_top_lidar_calibration():
    record = DATA / "waymo_mmdet3d_testdata" / "val.tfrecord"
    if not record.is_file():
        pytest.skip(f"{record} is not available")
    dataset_pb2 = pytest.importorskip("waymo_open_dataset.dataset_pb2")
    from typ.formats.waymo import iter_tfrecord

    frame = dataset_pb2.Frame.FromString(next(iter_tfrecord(record)))
    (top,) = [c for c in frame.context.laser_calibrations if dataset_pb2.LaserName.Name.Name(c.name) == "TOP"]
    spec = SENSORS["waymo"]
    assert np.abs(np.degrees(top.beam_inclinations) - spec.elevations_deg).max() <= 0.0005
    assert np.reshape(top.extrinsic.transform, (4, 4))[2, 3] == pytest.approx(spec.mount_height, abs=0.0005)


def test_the_mount_height_on_a_sloped_road_is_the_distance_to_the_road_plane():
    """A sensor 1.8 m from a road that rises 8 deg ahead and falls 5 deg to the left, seen from
    the sensor (a pitched mount, or a road that changes grade): the mount height is the sensor's
    distance to the plane along its normal, not the plane's height under the sensor on its z axis
    (1.8 * sqrt(1 + p^2 + q^2) = 1.824 m here), and the normal is the plane's. Each return is the
    ray's intersection with the plane, written out here, not cast by typ."""
    p, q, height = np.tan(np.radians(8.0)), np.tan(np.radians(-5.0)), 1.8
    normal = np.array([-p, -q, 1.0]) / np.sqrt(1.0 + p * p + q * q)     # the road: normal . x = -height
    elevation = np.radians(np.arange(-28.0, -5.0, 1.5))
    azimuth = np.radians(np.arange(-180.0, 180.0, 0.4))
    e, a = np.meshgrid(elevation, azimuth, indexing="ij")
    rays = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=-1).reshape(-1, 3)
    down = rays @ normal
    scan = rays[down < 0] * (-height / down[down < 0])[:, None]
    assert np.allclose(scan @ normal, -height)
    fit = fit_sensor(scan)
    assert fit.mount_height == pytest.approx(height, abs=1e-6)
    np.testing.assert_allclose(fit.ground_normal, normal, atol=1e-6)
    assert fit.n_beams == len(elevation)
