"""Every LiDAR typ knows, in one place: the simulated domains' and the real datasets'.

    from typ.sensors import resolve
    resolve("kitti")            # a dataset's preset (typ.sensors.presets)
    resolve("target")           # a simulated domain's sensor (typ.sim.sensor.DOMAINS)
    resolve({"elevations_deg": {"n": 32, "low": -25, "high": 15, "spacing": "horizon_dense"},
             "azimuth_step_deg": 0.2, "max_range": 100, "mount_height": 1.8})   # a params sensor: block

all return a :class:`typ.sim.sensor.SensorSpec`. :func:`fit_sensor` recovers a sensor's beams
and mount height from its scans (:mod:`typ.sensors.fit`), for a dataset whose LiDAR is unknown
and to check the presets (``bench/sensor_presets.py``).
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from typ.config import ElevationRule, SensorConfig, _build, as_dict
from typ.errors import TypError
from typ.sensors.fit import SensorFit, beam_residuals, fit_ground, fit_sensor, on_beam_fractions
from typ.sensors.presets import PRESETS
from typ.sim.sensor import DOMAINS, SensorSpec, horizon_dense_elevations

#: sensor name -> SensorSpec: the simulated domains' (``source``, ``target``, ``real_cav``) and the
#: real datasets' (``kitti``, ``nuscenes``, ``waymo``, ``v2v4real``, ``opv2v``)
SENSORS: dict[str, SensorSpec] = {**{name: d.sensor for name, d in DOMAINS.items()}, **PRESETS}


def resolve(sensor, *, where: str = "params.yaml", field: str = "sensor") -> SensorSpec:
    """The SensorSpec of ``sensor``: a name in :data:`SENSORS`, a ``sensor:`` block (a mapping as
    params.yaml holds it, or a checked :class:`typ.config.SensorConfig`), or a SensorSpec itself.

    where, field: what a TypError names (``params.yaml``, ``simulate.sources.target.sensor``). Every number
    of a block is checked against the bound beside its field in :class:`typ.config.SensorConfig` (beams,
    azimuth step, ranges) before anything is allocated for it.
    """
    if isinstance(sensor, SensorSpec):
        return sensor
    if isinstance(sensor, str):
        if sensor not in SENSORS:
            raise TypError(where, field, f"a sensor name in {sorted(SENSORS)} or a sensor block", sensor)
        return SENSORS[sensor]
    if isinstance(sensor, SensorConfig):  # built in code: its numbers meet the bounds a block's must
        sensor = as_dict(sensor)
    if not isinstance(sensor, Mapping):
        raise TypError(where, field, f"a sensor name in {sorted(SENSORS)} or a sensor block", type(sensor).__name__)
    sensor = _build(SensorConfig, dict(sensor), where, field)
    sensor.check(where, field)
    return SensorSpec(name=sensor.name, elevations_deg=elevations(sensor.elevations_deg),
                      azimuth_step_deg=sensor.azimuth_step_deg, max_range=sensor.max_range,
                      min_range=sensor.min_range, mount_height=sensor.mount_height,
                      beam_heights_m=sensor.beam_heights_m, range_noise_std=sensor.range_noise_std,
                      dropout=sensor.dropout, detection_energy=sensor.detection_energy,
                      intensity_model=sensor.intensity_model)


def mount_height(name: str, heights: Mapping[str, float], *, where: str = "params.yaml",
                 field: str = "voxelize.mount_height") -> float:
    """The LiDAR height above the road of dataset or domain ``name``: ``heights[name]`` (params'
    ``voxelize.mount_height``) when it is there, else its sensor's in :data:`SENSORS`."""
    if name in heights:
        return heights[name]
    if name in SENSORS:
        return SENSORS[name].mount_height
    raise TypError(where, f"{field}.{name}",
                   f"the sensor height of dataset {name!r} (known: {sorted({*heights, *SENSORS})})", "missing")


def elevations(table: tuple[float, ...] | ElevationRule) -> tuple[float, ...]:
    """A sensor block's beam elevations: its list, or its rule's (``uniform`` as CARLA spaces its
    channels, ``horizon_dense`` as :func:`typ.sim.sensor.horizon_dense_elevations`)."""
    if not isinstance(table, ElevationRule):
        return tuple(float(v) for v in table)
    if table.spacing == "uniform":
        return tuple(float(v) for v in np.linspace(table.low, table.high, table.n))
    return horizon_dense_elevations(table.n, table.low, table.high, table.scale)


__all__ = ["SENSORS", "SensorFit", "beam_residuals", "elevations", "fit_ground", "fit_sensor", "mount_height",
           "on_beam_fractions", "resolve"]
