"""The blocks of the data stages: ``simulate`` (the simulator's domains, real datasets as sources, the
sensors) and ``voxelize`` (the grid)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from typ.config.base import DOMAINS, SIMULATE, _positive
from typ.errors import TypError


@dataclass(frozen=True)
class GridConfig:
    """The voxel grid of TYP §3.2, in the sensor frame (metres); shape is (H, W, C) = (x, y, z)."""

    x_range: tuple[float, float]
    y_range: tuple[float, float]
    z_range: tuple[float, float]
    shape: tuple[int, int, int]

    def check(self, where: str, name: str) -> None:
        for axis in ("x_range", "y_range", "z_range"):
            lo, hi = getattr(self, axis)
            if not lo < hi:
                raise TypError(where, f"{name}.{axis}", "[min, max] with min < max", [lo, hi])
        if any(n <= 0 for n in self.shape):
            raise TypError(where, f"{name}.shape", "3 positive integers (H, W, C)", list(self.shape))


#: The simulator's plausible ranges, for params.yaml and a simulated scenario's ``_typ.json`` alike:
#: beyond them a scenario allocates gigabytes (an azimuth step of 1e-5 deg casts 8.6 GiB of rays)
#: or runs for hours. Real spinning LiDARs step 0.08 to 0.4 deg; OPV2V's scenarios are ~200 frames.
AZIMUTH_STEP_DEG = (0.05, 10.0)
MAX_FRAMES = 10_000
MAX_AGENTS = 8
MAX_COMM_RANGE = 1_000.0
MAX_DT = 10.0


def check_simulation(where: str, name: str, *, frames: int, agents: tuple[int, int], azimuth_step_deg: float,
                     comm_range: float, dt: float) -> None:
    """The simulation settings against :data:`AZIMUTH_STEP_DEG`, :data:`MAX_FRAMES` and the other caps;
    the error names ``<name>.<field>``."""
    if not 1 <= frames <= MAX_FRAMES:
        raise TypError(where, f"{name}.frames", f"an integer in [1, {MAX_FRAMES}]", frames)
    lo, hi = agents
    if not 1 <= lo <= hi <= MAX_AGENTS:
        raise TypError(where, f"{name}.agents_min/agents_max", f"1 <= agents_min <= agents_max <= {MAX_AGENTS}",
                       [lo, hi])
    low, high = AZIMUTH_STEP_DEG
    if not low <= azimuth_step_deg <= high:
        raise TypError(where, f"{name}.azimuth_step_deg", f"a step in [{low:g}, {high:g}] deg", azimuth_step_deg)
    if not 0 < comm_range <= MAX_COMM_RANGE:
        raise TypError(where, f"{name}.comm_range", f"a distance in (0, {MAX_COMM_RANGE:g}] m", comm_range)
    if not 0 < dt <= MAX_DT:
        raise TypError(where, f"{name}.dt", f"a frame interval in (0, {MAX_DT:g}] s", dt)


@dataclass(frozen=True)
class ElevationRule:
    """``n`` beam elevations from ``low`` to ``high`` degrees: ``uniform`` steps (CARLA's LiDAR) or
    ``horizon_dense``, even steps in asinh(e / scale) that crowd the beams near 0 deg (Waymo's
    top LiDAR, the VLP-32C)."""

    n: int
    low: float
    high: float
    spacing: Literal["uniform", "horizon_dense"] = "uniform"
    scale: float = 4.0

    def check(self, where: str, name: str) -> None:
        _positive(where, f"{name}.n", self.n)
        if not -90 < self.low < self.high < 90:
            raise TypError(where, f"{name}.low/high", "-90 < low < high < 90 degrees", [self.low, self.high])
        _positive(where, f"{name}.scale", self.scale)


@dataclass(frozen=True)
class SensorConfig:
    """A ``sensor:`` block: a spinning LiDAR without a preset (``typ.sensors.SENSORS`` names the
    presets; ``typ.sensors.resolve`` turns either into a SensorSpec). Angles in degrees, lengths
    in metres; noise, dropout and echo detection only matter where typ casts the sensor."""

    #: ascending beam elevations, or ``{n, low, high, spacing, scale}`` (:class:`ElevationRule`)
    elevations_deg: tuple[float, ...] | ElevationRule
    azimuth_step_deg: float
    max_range: float
    #: the sensor origin above the road
    mount_height: float
    min_range: float = 1.0
    #: each beam's origin above the sensor origin, one per elevation (empty: all at the origin)
    beam_heights_m: tuple[float, ...] = ()
    range_noise_std: float = 0.02
    dropout: float = 0.0
    #: echo strength at which a return is kept with probability 1 - 1/e (0: every echo)
    detection_energy: float = 0.0
    #: "attenuation": exp(-0.004 r) as CARLA; "material": reflectivity and incidence angle
    intensity_model: Literal["attenuation", "material"] = "material"
    name: str = "sensor"

    def check(self, where: str, name: str) -> None:
        rule = self.elevations_deg
        if isinstance(rule, ElevationRule):
            rule.check(where, f"{name}.elevations_deg")
        elif not rule or not all(-90 < e < 90 for e in rule) or any(b <= a for a, b in zip(rule, rule[1:])):
            raise TypError(where, f"{name}.elevations_deg", "ascending beam elevations in (-90, 90) degrees", list(rule))
        n_beams = rule.n if isinstance(rule, ElevationRule) else len(rule)
        if self.beam_heights_m and (len(self.beam_heights_m) != n_beams or any(abs(h) >= 1 for h in self.beam_heights_m)):
            raise TypError(where, f"{name}.beam_heights_m", f"empty or {n_beams} heights in (-1, 1) m, one per beam",
                           list(self.beam_heights_m))
        if not 0 < self.azimuth_step_deg <= 10:
            raise TypError(where, f"{name}.azimuth_step_deg", "a step in (0, 10] deg", self.azimuth_step_deg)
        if not 0 < self.mount_height < 10:
            raise TypError(where, f"{name}.mount_height", "a sensor height in (0, 10) m", self.mount_height)
        if not 0 <= self.min_range < self.max_range:
            raise TypError(where, f"{name}.min_range/max_range", "0 <= min_range < max_range metres",
                           [self.min_range, self.max_range])
        if not 0 <= self.dropout < 1:
            raise TypError(where, f"{name}.dropout", "a fraction in [0, 1)", self.dropout)
        for key in ("range_noise_std", "detection_energy"):
            if getattr(self, key) < 0:
                raise TypError(where, f"{name}.{key}", "a number >= 0", getattr(self, key))


@dataclass(frozen=True)
class DomainSimulation:
    """Per-domain overrides of the simulation's ``frames`` and agent counts (unset: the defaults)."""

    frames: int | None = None
    agents_min: int | None = None
    agents_max: int | None = None


#: ``simulate.sources.<domain>.format``: the datasets typ reads a domain from. ``opv2v``: a
#: collaborative root in OPV2V layout (OPV2V, V2V4Real), taken as it is; the others: single-agent
#: datasets, each frame moved into its LiDAR's frame and written as a one-agent scenario. The
#: single-agent names are ``tasks.ingest.READERS``'s (a test holds them equal; the config reads no
#: dataset code)
SINGLE_AGENT_FORMATS = ("kitti", "nuscenes", "waymo")
SOURCE_FORMATS = SINGLE_AGENT_FORMATS + ("opv2v",)
SourceFormat = Literal[SOURCE_FORMATS]


@dataclass(frozen=True)
class SourceConfig:
    """A real dataset a domain's scenarios come from (``simulate.sources.<domain>``, or one entry of
    a list of them), with how its own splits become typ's."""

    format: SourceFormat
    #: the dataset root, relative to the project root or absolute
    root: str
    #: typ split -> the dataset's split names (a list: KITTI ImageSets files or training/testing,
    #: Waymo's training/validation/testing folders, nuScenes info files *_train/*_val/*_test,
    #: OPV2V's split folders), or a fraction of the scenarios that no listed split takes (by a
    #: hash of the scenario name). Unset: each typ split takes the dataset split of its name
    #: (train/training, val/validation, test/testing), and a dataset without splits is shared
    #: out by ``DEFAULT_FRACTIONS``
    splits: dict[str, list[str] | float] = field(default_factory=dict)

    def check(self, where: str, name: str) -> None:
        if not self.root.strip():
            raise TypError(where, f"{name}.root", "the path of the dataset root", self.root)
        fractions = {split: v for split, v in self.splits.items() if isinstance(v, float)}
        for split, value in self.splits.items():
            if isinstance(value, float) and not 0 < value <= 1:
                raise TypError(where, f"{name}.splits.{split}", "a fraction in (0, 1]", value)
            if isinstance(value, list) and not (value and all(v.strip() for v in value)):
                raise TypError(where, f"{name}.splits.{split}", "a list of the dataset's split names", value)
        if sum(fractions.values()) > 1 + 1e-9:
            raise TypError(where, f"{name}.splits", "fractions that add up to at most 1", fractions)
        if self.format == "opv2v" and fractions:
            raise TypError(where, f"{name}.splits", "split folder names (an OPV2V root's splits are its folders)",
                           fractions)


@dataclass(frozen=True)
class SimulateConfig:
    """Embedded simulator: which scenarios of which sensor domain go to which split."""

    seed: int
    frames: int
    agents_min: int
    agents_max: int
    azimuth_step_deg: float
    comm_range: float
    dt: float
    #: domain -> split -> number of scenarios, e.g. {"target": {"train": 4, "test": 2}}; for a domain
    #: read from a real dataset (``sources``), the first that many scenarios of each split folder
    scenarios: dict[str, dict[str, int]]
    workers: int
    out: str
    #: domain -> ``simulate`` (the embedded simulator); the root of a real dataset in OPV2V layout
    #: (``<root>/<split>/<scenario>/<agent>/<timestamp>.pcd|.yaml``: OPV2V, V2V4Real), relative to
    #: the project root or absolute, its scenarios linked into ``out``; or a :class:`SourceConfig`
    #: (``{format, root, splits}``), or a list of them whose scenarios the domain's splits share.
    #: A real dataset is checked whole at start, before anything is written
    sources: dict[str, str | SourceConfig | list[SourceConfig]] = field(default_factory=dict)
    #: domain -> frames / agents_min / agents_max for that domain's scenarios
    domains: dict[str, DomainSimulation] = field(default_factory=dict)
    #: the simulated domains whose views also get semantic occupancy ground truth (:mod:`typ.ssc`,
    #: 0.15-0.4 s a view): only the domains that semantic scene completion trains and scores on
    occupancy: tuple[str, ...] = ("real_cav",)

    def source_blocks(self, domain: str) -> tuple[SourceConfig, ...]:
        """The real datasets ``domain`` is read from, in order (a plain root is an ``opv2v`` block);
        empty when the simulator makes it."""
        source = self.sources.get(domain, SIMULATE)
        if source == SIMULATE:
            return ()
        if isinstance(source, str):
            return (SourceConfig(format="opv2v", root=source),)
        return tuple(source) if isinstance(source, list) else (source,)

    def source_field(self, domain: str, index: int) -> str:
        """The params field of ``source_blocks(domain)[index]``, for errors."""
        return f"simulate.sources.{domain}" + (f"[{index}]" if isinstance(self.sources.get(domain), list) else "")

    def for_domain(self, domain: str) -> tuple[int, int, int]:
        """(frames, agents_min, agents_max) of ``domain``'s scenarios."""
        d = self.domains.get(domain, DomainSimulation())
        return (d.frames if d.frames is not None else self.frames,
                d.agents_min if d.agents_min is not None else self.agents_min,
                d.agents_max if d.agents_max is not None else self.agents_max)

    def check(self, where: str, name: str) -> None:
        checks = [(name, self.frames, self.agents_min, self.agents_max)]
        for domain in self.domains:
            if domain not in DOMAINS:
                raise TypError(where, f"{name}.domains.{domain}", f"a sensor domain in {list(DOMAINS)}", domain)
            checks.append((f"{name}.domains.{domain}", *self.for_domain(domain)))
        for label, frames, lo, hi in checks:
            check_simulation(where, label, frames=frames, agents=(lo, hi), azimuth_step_deg=self.azimuth_step_deg,
                             comm_range=self.comm_range, dt=self.dt)
        _positive(where, f"{name}.workers", self.workers)
        for domain, splits in self.scenarios.items():
            if domain not in DOMAINS:
                raise TypError(where, f"{name}.scenarios.{domain}", f"a sensor domain in {list(DOMAINS)}", domain)
            for split, count in splits.items():
                if count < 0:
                    raise TypError(where, f"{name}.scenarios.{domain}.{split}", "a count >= 0", count)
        for domain in self.occupancy:
            if domain not in DOMAINS:
                raise TypError(where, f"{name}.occupancy", f"sensor domains in {list(DOMAINS)}", domain)
        for domain, source in self.sources.items():
            if domain not in DOMAINS:
                raise TypError(where, f"{name}.sources.{domain}", f"a sensor domain in {list(DOMAINS)}", domain)
            if isinstance(source, str) and not source.strip():
                raise TypError(where, f"{name}.sources.{domain}",
                               f"{SIMULATE!r} or the path of a dataset root in OPV2V layout", source)
            if isinstance(source, list) and not source:
                raise TypError(where, f"{name}.sources.{domain}", "at least one dataset block", source)
            for index, block in enumerate(self.source_blocks(domain)):
                block.check(where, self.source_field(domain, index).replace("simulate", name, 1))


@dataclass(frozen=True)
class VoxelizeConfig:
    """Voxelize stage: every agent view under ``input`` onto ``grid``, stored per scene under ``out``.

    ``grid.z_range`` is height above the ground under the sensor; ``mount_height`` gives each
    dataset's LiDAR height above its ground (metres), so the ground lands in the same height
    channel in every domain (TYP §4.1: the z range is dataset-dependent)."""

    grid: GridConfig
    mount_height: dict[str, float]
    input: str
    out: str
    workers: int

    def check(self, where: str, name: str) -> None:
        self.grid.check(where, f"{name}.grid")
        _positive(where, f"{name}.workers", self.workers)
        for dataset, height in self.mount_height.items():
            if not (math.isfinite(height) and 0 <= height < 10):
                raise TypError(where, f"{name}.mount_height.{dataset}", "a sensor height in [0, 10) m", height)

    def sensor_grid(self, dataset: str, where: str = "voxelize") -> "Grid":
        """The grid in the sensor frame of ``dataset``'s LiDAR (see :meth:`typ.voxel.Grid.for_sensor`)."""
        from typ.voxel import Grid
        if dataset not in self.mount_height:
            raise TypError(where, f"voxelize.mount_height.{dataset}",
                           f"the sensor height of dataset {dataset!r} (known: {sorted(self.mount_height)})", "missing")
        g = self.grid
        return Grid(g.x_range, g.y_range, g.z_range, g.shape).for_sensor(self.mount_height[dataset])
