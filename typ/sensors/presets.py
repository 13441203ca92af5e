"""The LiDARs of the real datasets typ reads, each value with its source.

Elevations are seen from each beam's origin in the frame the dataset gives its points in (the
LiDAR's own frame; Waymo's TOP LiDAR frame through its extrinsic); mount heights are that
frame's origin above the road. Range noise, dropout and echo detection only matter when typ
casts the sensor; where a datasheet gives no number they are the simulated target domain's,
marked "estimate". ``reports/sensor_presets.md`` (``bench/sensor_presets.py``) checks every
preset against the real frames in ``shared/data``.
"""
from __future__ import annotations

import numpy as np

from typ.sim.sensor import SensorSpec

# KITTI, Velodyne HDL-64E S2 (Geiger et al., "Vision meets robotics: the KITTI dataset",
# IJRR 2013, Fig. 3). KITTI ships no per-laser calibration, so the table is measured: every
# ring of object training frames 000000 and 000001 (its points come laser by laser, a ring
# ending where the azimuth wraps), a line z = h + d tan(e) fitted to both frames' returns,
# residuals under 0.3 mm. Two laser blocks: the upper 32 beams (+1.94 .. -8.71 deg, 0.25 ..
# 0.40 deg apart, 0.198 .. 0.209 m above the origin) and the lower 32 (-9.03 .. -25.00 deg,
# 0.41 .. 0.65 deg apart, 0.116 .. 0.126 m up); the datasheet's nominal layout (+2 .. -8.33 at
# 1/3 deg, -8.83 .. -24.33 at 1/2 deg) is off by up to 0.67 deg. typ.sensors.fit_sensor
# recovers the same table from either frame within 0.01 deg.
_KITTI_ELEVATIONS = (
    -24.997, -24.506, -23.971, -23.323, -22.856, -22.440, -21.935, -21.317, -20.789, -20.223, -19.736,
    -19.320, -18.798, -18.323, -17.729, -17.188, -16.554, -16.177, -15.657, -15.189, -14.598, -14.049,
    -13.485, -13.041, -12.562, -12.115, -11.599, -10.957, -10.471, -10.062, -9.573, -9.026,
    -8.711, -8.310, -8.058, -7.679, -7.287, -6.999, -6.676, -6.329, -5.958, -5.611, -5.251, -4.914,
    -4.588, -4.216, -3.936, -3.539, -3.236, -2.874, -2.547, -2.208, -1.833, -1.494, -1.201, -0.803,
    -0.452, -0.089, 0.181, 0.579, 0.872, 1.305, 1.574, 1.937)
_KITTI_BEAM_HEIGHTS = (
    0.116, 0.116, 0.117, 0.117, 0.117, 0.118, 0.118, 0.118, 0.118, 0.119, 0.119, 0.119, 0.119, 0.120,
    0.120, 0.120, 0.121, 0.121, 0.121, 0.122, 0.122, 0.122, 0.123, 0.123, 0.123, 0.124, 0.124, 0.124,
    0.125, 0.125, 0.125, 0.126,
    0.198, 0.198, 0.198, 0.199, 0.199, 0.199, 0.199, 0.200, 0.200, 0.200, 0.201, 0.201, 0.201, 0.202,
    0.202, 0.203, 0.203, 0.203, 0.204, 0.204, 0.204, 0.205, 0.205, 0.206, 0.206, 0.206, 0.207, 0.207,
    0.208, 0.208, 0.209, 0.209)

KITTI = SensorSpec(
    name="kitti", elevations_deg=_KITTI_ELEVATIONS, beam_heights_m=_KITTI_BEAM_HEIGHTS,
    # the commonest angle between neighbouring returns of a ring in frames 000000 / 000001
    azimuth_step_deg=0.18,
    # HDL-64E S2 manual: 120 m (cars, foliage); KITTI's frames reach 80 m
    max_range=120.0, min_range=1.0,           # min_range: estimate (the frames' nearest returns: 1.46 m)
    # KITTI's setup paper says 1.73 m; the road plane typ.sensors.fit_ground finds lies 1.761 and
    # 1.751 m below the origin in frames 000000 / 000001: the data's value is kept
    mount_height=1.76,
    range_noise_std=0.02,                     # HDL-64E S2 manual: < 2 cm (1 sigma)
    dropout=0.05, detection_energy=0.002,     # estimate
    intensity_model="material", incidence_weight=0.7, intensity_noise=0.02)

# nuScenes LIDAR_TOP, Velodyne HDL-32E at 20 Hz (Caesar et al., "nuScenes", CVPR 2020, Tab. 1:
# 32 channels, +10 to -30 deg). Elevations: the HDL-32E's nominal 32 beams 4/3 deg apart from
# -30.67 to +10.67 deg (Velodyne's standard calibration, ros-drivers/velodyne 32db.yaml); the
# keyframe's ring medians agree within 0.05 deg above -9 deg (report). Azimuth: 1084 firings
# per turn (every ring of the keyframe holds 1084 returns). Mount height: calibrated_sensor
# z = 1.840 .. 1.843 m above the ego frame, whose origin is on the ground (nuscenes-devkit
# issue #161); the keyframe's fitted road plane: 1.841 m.
NUSCENES = SensorSpec(
    name="nuscenes", elevations_deg=tuple(float(v) for v in (np.arange(32) - 23) * 4.0 / 3.0),
    azimuth_step_deg=360.0 / 1084,
    max_range=100.0, min_range=1.0,           # HDL-32E datasheet: 100 m (the paper: <= 70 m usable)
    mount_height=1.84,
    range_noise_std=0.02,                     # HDL-32E datasheet: +-2 cm
    dropout=0.05, detection_energy=0.002,     # estimate
    intensity_model="material", incidence_weight=0.7, intensity_noise=0.02)

# Waymo Open Dataset TOP LiDAR (Sun et al., "Scalability in perception for autonomous driving",
# CVPR 2020: 64 beams, +2.4 .. -17.6 deg, range truncated to 75 m, 2650 columns per turn).
# Elevations: laser_calibrations[TOP].beam_inclinations of validation frame
# 1071392229495085036_1844_790_1864_790 (mmdetection3d's test tfrecord, shared/data), dense
# near the horizon (0.12 .. 0.20 deg apart above -2 deg, 0.6 deg at the bottom); other
# vehicles' calibrations differ slightly. Mount height: that frame's TOP extrinsic z, 2.184 m
# above the vehicle frame, whose origin is on the ground (its labelled car's box bottom sits
# at z = 0.05 m, 77 m away).
WAYMO = SensorSpec(
    name="waymo", elevations_deg=(
        -17.609, -16.985, -16.381, -15.789, -15.182, -14.612, -14.082, -13.535, -12.998, -12.472, -11.941,
        -11.433, -10.946, -10.461, -9.991, -9.537, -9.088, -8.635, -8.218, -7.787, -7.389, -6.992, -6.602,
        -6.209, -5.841, -5.481, -5.147, -4.814, -4.511, -4.185, -3.901, -3.612, -3.328, -3.074, -2.829,
        -2.562, -2.335, -2.114, -1.895, -1.691, -1.526, -1.328, -1.160, -0.991, -0.818, -0.656, -0.517,
        -0.329, -0.163, 0.004, 0.185, 0.354, 0.474, 0.672, 0.838, 0.979, 1.182, 1.350, 1.491, 1.666,
        1.827, 2.014, 2.186, 2.343),
    azimuth_step_deg=360.0 / 2650,
    max_range=75.0, min_range=1.0,            # min_range: estimate
    mount_height=2.184,
    range_noise_std=0.02, dropout=0.05, detection_energy=0.002,   # estimate (the target domain's)
    intensity_model="material", incidence_weight=0.7, intensity_noise=0.02)

# V2V4Real: a Velodyne VLP-32C on each of its two cars (Xu et al., "V2V4Real", CVPR 2023).
# Elevations: the VLP-32C user manual's 32 vertical angles (63-9325 Rev. C), -25 .. +15 deg,
# 1/3 deg apart between -4 and +1.67 deg. Azimuth 0.2 deg (the manual, at 600 rpm = 10 Hz, the
# dataset's rate); range 200 m (datasheet). Mount height: not published: 1.8 m, an estimate
# (a roof-mounted VLP-32C on a sedan; the simulated real_cav domain's value); fit_sensor on a
# V2V4Real frame checks it (none is available here).
V2V4REAL = SensorSpec(
    name="v2v4real", elevations_deg=(
        -25.0, -15.639, -11.31, -8.843, -7.254, -6.148, -5.333, -4.667, -4.0, -3.667, -3.333, -3.0, -2.667,
        -2.333, -2.0, -1.667, -1.333, -1.0, -0.667, -0.333, 0.0, 0.333, 0.667, 1.0, 1.333, 1.667, 2.333,
        3.333, 4.667, 7.0, 10.333, 15.0),
    azimuth_step_deg=0.2,
    max_range=200.0, min_range=1.0,           # min_range: estimate
    mount_height=1.8,
    range_noise_std=0.03,                     # VLP-32C datasheet: +-3 cm
    dropout=0.08, detection_energy=0.003,     # estimate (the real_cav domain's)
    intensity_model="material", incidence_weight=0.5, intensity_noise=0.03)

# OPV2V: CARLA's ray-cast LiDAR as OpenCDA's OPV2V data protocol configures it
# (opencda/scenario_testing/config_yaml/opv2v_data_protocol_*.yaml: 64 channels, upper_fov 2,
# lower_fov -25, range 120, 1.3 M points/s, 20 Hz, noise_stddev 0.02, dropoff_general_rate 0.1),
# mounted 1.9 m above the vehicle's origin on the ground (OpenCDA's LidarSensor spawn point).
# CARLA spaces the channels evenly from upper_fov to lower_fov, and each fires
# round(1.3e6 * 0.05 / 64) = 1016 times per 0.05 s tick, one turn at 20 Hz. CARLA's extra
# drop of weak returns (intensity < 0.7, beyond 89 m) is not modelled.
OPV2V = SensorSpec(
    name="opv2v", elevations_deg=tuple(float(v) for v in np.linspace(-25.0, 2.0, 64)),
    azimuth_step_deg=360.0 / 1016,
    max_range=120.0, min_range=0.0, mount_height=1.9,
    range_noise_std=0.02, dropout=0.1, detection_energy=0.0,
    intensity_model="attenuation", attenuation_rate=0.004)

#: the real datasets' LiDARs, by dataset name
PRESETS: dict[str, SensorSpec] = {s.name: s for s in (KITTI, NUSCENES, WAYMO, V2V4REAL, OPV2V)}
