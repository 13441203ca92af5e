"""LiDAR and domain presets: ``source`` (OPV2V/CARLA), ``target`` (Waymo), ``real_cav`` (V2V4Real).

A :class:`SensorSpec` fixes the beam pattern, range, mount height, noise, dropout and
intensity model of one spinning LiDAR; a :class:`DomainSpec` pairs it with the town style
and traffic of the dataset it imitates. The three domains differ the way the real datasets
do: beam count and vertical spacing, mount height, range, noise, missing returns on dark or
far surfaces, and what intensity means.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from typ.errors import TypError
from typ.sim.town import TownStyle

INTENSITY_MODELS = ("attenuation", "material")


@dataclass(frozen=True, kw_only=True)
class SensorSpec:
    """One spinning LiDAR. Angles in degrees, lengths in metres.

    Ray directions are in the sensor frame (x forward, y left, z up): beam b, azimuth a ->
    ``[cos e_b cos a, cos e_b sin a, sin e_b]``; azimuths run from -180 deg in steps of
    ``azimuth_step_deg``. Rays start at the origin, or ``beam_heights_m[b]`` above it.
    """

    name: str
    elevations_deg: tuple[float, ...]   #: beam elevations, ascending
    max_range: float
    min_range: float                    #: returns closer than this are dropped (sensor housing)
    mount_height: float                 #: sensor above the vehicle's ground contact
    range_noise_std: float              #: Gaussian range noise, clipped at 3 std
    dropout: float                      #: fraction of returns lost at random
    detection_energy: float             #: echo strength e = reflectivity*|cos|*(20/r)^2 at which a return
                                        #: is kept with probability 1-1/e; 0 = every echo is detected
    intensity_model: str                #: "attenuation": exp(-rate*r) (CARLA); "material": reflectivity & incidence
    attenuation_rate: float = 0.004     #: CARLA's atmosphere_attenuation_rate default
    incidence_weight: float = 0.7       #: material model: intensity = refl * (1 - w + w*|cos|)
    intensity_noise: float = 0.0        #: std of additive intensity noise
    azimuth_step_deg: float = 0.4
    #: each beam's origin above the sensor origin (m), in the order of ``elevations_deg``; empty:
    #: every beam starts at the origin. A Velodyne HDL-64E's two laser blocks sit 0.12 and 0.21 m
    #: above the origin of the frame its points come in (Velodyne's per-laser vertical offsets)
    beam_heights_m: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        where = f"SensorSpec[{self.name}]"
        e = np.asarray(self.elevations_deg, dtype=np.float64)
        if e.ndim != 1 or len(e) == 0 or not np.all(np.abs(e) < 90) or not np.all(np.diff(e) > 0):
            raise TypError(where, "elevations_deg", "a non-empty ascending tuple of angles in (-90, 90) deg", self.elevations_deg)
        for field_name in ("max_range", "mount_height", "azimuth_step_deg"):
            v = getattr(self, field_name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise TypError(where, field_name, "a positive finite number", v)
        if not 0.0 <= self.min_range < self.max_range:
            raise TypError(where, "min_range", f"a number in [0, max_range={self.max_range})", self.min_range)
        if not 0.0 <= self.dropout < 1.0:
            raise TypError(where, "dropout", "a fraction in [0, 1)", self.dropout)
        for field_name in ("range_noise_std", "detection_energy", "attenuation_rate", "intensity_noise"):
            v = getattr(self, field_name)
            if not (np.isfinite(v) and v >= 0):
                raise TypError(where, field_name, "a finite number >= 0", v)
        if self.intensity_model not in INTENSITY_MODELS:
            raise TypError(where, "intensity_model", f"one of {INTENSITY_MODELS}", self.intensity_model)
        if self.azimuth_step_deg > 10.0:
            raise TypError(where, "azimuth_step_deg", "a step in (0, 10] deg", self.azimuth_step_deg)
        h = np.asarray(self.beam_heights_m, dtype=np.float64)
        if h.ndim != 1 or len(h) not in (0, len(e)) or not np.all(np.abs(h) < 1.0):
            raise TypError(where, "beam_heights_m", f"empty or {len(e)} heights in (-1, 1) m, one per beam",
                           self.beam_heights_m)

    @property
    def n_beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def n_azimuths(self) -> int:
        return int(round(360.0 / self.azimuth_step_deg))

    def ray_directions(self) -> np.ndarray:
        """(n_beams * n_azimuths, 3) float64 unit directions in the sensor frame, beam-major."""
        return _directions(tuple(self.elevations_deg), self.n_azimuths)

    def ray_origins(self) -> np.ndarray | None:
        """(n_beams * n_azimuths, 3) float64 ray origins in the sensor frame, in the order of
        :meth:`ray_directions`; None when every beam starts at the sensor origin."""
        if not self.beam_heights_m:
            return None
        origins = np.zeros((self.n_beams, self.n_azimuths, 3))
        origins[:, :, 2] = np.asarray(self.beam_heights_m, dtype=np.float64)[:, None]
        return origins.reshape(-1, 3)


@lru_cache(maxsize=16)
def _directions(elevations_deg: tuple[float, ...], n_az: int) -> np.ndarray:
    e = np.radians(np.asarray(elevations_deg))[:, None]
    a = np.radians(-180.0 + 360.0 * np.arange(n_az) / n_az)[None, :]
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.broadcast_to(np.sin(e), (len(elevations_deg), n_az))], -1)
    d = d.reshape(-1, 3)
    d.flags.writeable = False  # shared through the cache
    return d


def horizon_dense_elevations(n: int, low: float, high: float, scale: float) -> tuple[float, ...]:
    """n beam elevations in [low, high] deg, evenly spaced in asinh(e/scale) so they crowd near 0 deg.

    Spacing near the horizon is about ``scale * (asinh(high/scale) - asinh(low/scale)) / (n-1)``
    and grows like cosh towards the ends (Waymo's and the VLP-32C's non-uniform layouts).
    """
    w = np.linspace(np.arcsinh(low / scale), np.arcsinh(high / scale), n)
    return tuple(float(v) for v in scale * np.sinh(w))


@dataclass(frozen=True, kw_only=True)
class DomainSpec:
    """A simulated dataset: its LiDAR, its towns and its traffic."""

    name: str
    dataset: str                         #: the dataset it imitates
    sensor: SensorSpec
    town: TownStyle
    moving_vehicles: tuple[int, int]     #: background moving vehicles per scenario (uniform)
    moving_class_probs: tuple[float, float, float] = (0.8, 0.13, 0.07)  #: car, van, truck


_SOURCE = DomainSpec(
    name="source", dataset="opv2v",
    sensor=SensorSpec(
        name="source", elevations_deg=tuple(float(v) for v in np.linspace(-25.0, 2.0, 64)),
        max_range=120.0, min_range=0.0, mount_height=1.9, range_noise_std=0.0, dropout=0.0,
        detection_energy=0.0, intensity_model="attenuation", attenuation_rate=0.004),
    town=TownStyle(block_size=(65.0, 95.0), lane_width=3.5, building_density=0.85, building_height=(8.0, 35.0),
                   building_setback=(1.0, 4.0), tree_density=3.0, yard_trees=0.3, parked_density=0.3),
    moving_vehicles=(18, 30))

_TARGET = DomainSpec(
    name="target", dataset="waymo",
    sensor=SensorSpec(
        name="target", elevations_deg=horizon_dense_elevations(64, -17.6, 2.4, 4.0),
        max_range=75.0, min_range=1.0, mount_height=2.2, range_noise_std=0.02, dropout=0.05,
        detection_energy=0.002, intensity_model="material", incidence_weight=0.7, intensity_noise=0.02),
    town=TownStyle(block_size=(80.0, 115.0), lane_width=3.7, building_density=0.6, building_height=(4.0, 12.0),
                   building_setback=(6.0, 14.0), building_depth=(10.0, 20.0), lot_width=(12.0, 22.0), tree_density=7.0, yard_trees=1.0,
                   parked_density=0.5),
    moving_vehicles=(14, 26))

_REAL_CAV = DomainSpec(
    name="real_cav", dataset="v2v4real",
    sensor=SensorSpec(
        name="real_cav", elevations_deg=horizon_dense_elevations(32, -25.0, 15.0, 4.0),
        max_range=100.0, min_range=1.0, mount_height=1.8, range_noise_std=0.03, dropout=0.08,
        detection_energy=0.003, intensity_model="material", incidence_weight=0.5, intensity_noise=0.03),
    town=TownStyle(block_size=(90.0, 130.0), lane_width=3.6, building_density=0.4, building_height=(5.0, 20.0),
                   building_setback=(5.0, 12.0), tree_density=2.0, yard_trees=0.4, parked_density=0.15),
    moving_vehicles=(12, 24))

#: The named domains.
DOMAINS: dict[str, DomainSpec] = {d.name: d for d in (_SOURCE, _TARGET, _REAL_CAV)}


def domain_spec(name: str, *, azimuth_step_deg: float | None = None) -> DomainSpec:
    """The preset called ``name`` (one of :data:`DOMAINS`), optionally with another azimuth step."""
    if not isinstance(name, str) or name not in DOMAINS:
        raise TypError("typ.sim", "domain", f"one of {sorted(DOMAINS)}", name)
    spec = DOMAINS[name]
    if azimuth_step_deg is not None:
        spec = replace(spec, sensor=replace(spec.sensor, azimuth_step_deg=azimuth_step_deg))
    return spec
