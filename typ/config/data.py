"""The blocks of the data stages: ``simulate`` (the simulator's domains, real datasets as sources, the
sensors) and ``voxelize`` (the grid)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from typ.config.base import DOMAINS, SIMULATE, Bound, Coordinate, Length, Product, Seed, Workers
from typ.errors import TypError
from typ.registry import READERS
from typ.voxel import MAX_VOXELS

Side = Annotated[int, Bound(1, 8192, "cells along one axis: 8x the paper's largest image (1024)")]
GridShape = Annotated[tuple[Side, Side, Side], Product(MAX_VOXELS, "voxels of one grid (H x W x C): the paper's "
                                                       "is 512 x 512 x 20 = 5.2 M, and a stage holds several grids")]


@dataclass(frozen=True)
class GridConfig:
    """The voxel grid of TYP §3.2, in the sensor frame (metres); shape is (H, W, C) = (x, y, z)."""

    x_range: tuple[Coordinate, Coordinate]
    y_range: tuple[Coordinate, Coordinate]
    z_range: tuple[Coordinate, Coordinate]
    shape: GridShape

    def check(self, where: str, name: str) -> None:
        for axis in ("x_range", "y_range", "z_range"):
            lo, hi = getattr(self, axis)
            if not lo < hi:
                raise TypError(where, f"{name}.{axis}", "[min, max] with min < max", [lo, hi])


#: The simulator's plausible ranges, for params.yaml and a simulated scenario's ``_typ.json`` alike:
#: beyond them a scenario allocates gigabytes (an azimuth step of 1e-5 deg casts 8.6 GiB of rays)
#: or runs for hours. Real spinning LiDARs step 0.08 to 0.4 deg; OPV2V's scenarios are ~200 frames.
AZIMUTH_STEP_DEG = (0.05, 10.0)
MAX_FRAMES = 10_000
MAX_AGENTS = 8
MAX_COMM_RANGE = 1_000.0
MAX_DT = 10.0
#: scenarios of one split
MAX_SCENARIOS = 100_000
#: beams of one LiDAR
MAX_BEAMS = 256

Frames = Annotated[int, Bound(1, MAX_FRAMES, "10 Hz frames per scenario: OPV2V's run about 200")]
Agents = Annotated[int, Bound(1, MAX_AGENTS, "connected vehicles per scenario: OPV2V has at most 7")]
AzimuthStep = Annotated[float, Bound(*AZIMUTH_STEP_DEG, "degrees between firings: real LiDARs step 0.08 to 0.4; "
                                     "1e-5 would cast 8.6 GiB of rays a scan")]
CommRange = Annotated[float, Bound(0, MAX_COMM_RANGE, "metres of a V2V link: OPV2V's is 70", low_open=True)]
Scenarios = Annotated[int, Bound(0, MAX_SCENARIOS, "scenarios of one split: nuScenes' 28,130 training frames fit, "
                                 "and each is simulated or linked, then voxelized")]
Elevation = Annotated[float, Bound(-90, 90, "degrees above the horizon", low_open=True, high_open=True)]


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

    n: Annotated[int, Bound(1, MAX_BEAMS, "beams of one LiDAR: the largest made have 128, and each is a row "
                                "of every scan")]
    low: Elevation
    high: Elevation
    spacing: Literal["uniform", "horizon_dense"] = "uniform"
    scale: Annotated[float, Bound(0.01, 90, "degrees: asinh(e / scale) overflows for a tiny scale; Waymo's is 4")] \
        = 4.0

    def check(self, where: str, name: str) -> None:
        if not self.low < self.high:
            raise TypError(where, f"{name}.low/high", "-90 < low < high < 90 degrees", [self.low, self.high])


@dataclass(frozen=True)
class SensorConfig:
    """A ``sensor:`` block: a spinning LiDAR without a preset (``typ.sensors.SENSORS`` names the
    presets; ``typ.sensors.resolve`` turns either into a SensorSpec). Angles in degrees, lengths
    in metres; noise, dropout and echo detection only matter where typ casts the sensor."""

    #: ascending beam elevations, or ``{n, low, high, spacing, scale}`` (:class:`ElevationRule`)
    elevations_deg: Annotated[tuple[Elevation, ...], Length(1, MAX_BEAMS, "beams of one LiDAR: the largest made "
                                                            "have 128")] | ElevationRule
    azimuth_step_deg: AzimuthStep
    max_range: Annotated[float, Bound(0, 1000, "metres: the longest-reaching LiDARs see about 300", low_open=True)]
    #: the sensor origin above the road
    mount_height: Annotated[float, Bound(0, 10, "metres above the road", low_open=True, high_open=True)]
    min_range: Annotated[float, Bound(0, 1000, "metres: nearer returns are dropped")] = 1.0
    #: each beam's origin above the sensor origin, one per elevation (empty: all at the origin)
    beam_heights_m: Annotated[tuple[Annotated[float, Bound(-1, 1, "metres from the sensor origin", low_open=True,
                                                           high_open=True)], ...],
                              Length(0, MAX_BEAMS, "one height per beam")] = ()
    range_noise_std: Annotated[float, Bound(0, 10, "metres of range noise: datasheets give 0.02 to 0.03")] = 0.02
    dropout: Annotated[float, Bound(0, 1, "a share of returns lost", high_open=True)] = 0.0
    #: echo strength at which a return is kept with probability 1 - 1/e (0: every echo)
    detection_energy: Annotated[float, Bound(0, 1000, "an echo strength: a white wall at 1 m gives 400")] = 0.0
    #: "attenuation": exp(-0.004 r) as CARLA; "material": reflectivity and incidence angle
    intensity_model: Literal["attenuation", "material"] = "material"
    name: str = "sensor"

    def check(self, where: str, name: str) -> None:
        rule = self.elevations_deg
        if isinstance(rule, ElevationRule):
            rule.check(where, f"{name}.elevations_deg")
        elif any(b <= a for a, b in zip(rule, rule[1:])):
            raise TypError(where, f"{name}.elevations_deg", "ascending beam elevations in (-90, 90) degrees", list(rule))
        n_beams = rule.n if isinstance(rule, ElevationRule) else len(rule)
        if self.beam_heights_m and len(self.beam_heights_m) != n_beams:
            raise TypError(where, f"{name}.beam_heights_m", f"empty or {n_beams} heights in (-1, 1) m, one per beam",
                           list(self.beam_heights_m))
        if not self.min_range < self.max_range:
            raise TypError(where, f"{name}.min_range/max_range", "0 <= min_range < max_range metres",
                           [self.min_range, self.max_range])


@dataclass(frozen=True)
class DomainSimulation:
    """Per-domain overrides of the simulation's ``frames`` and agent counts (unset: the defaults)."""

    frames: Frames | None = None
    agents_min: Agents | None = None
    agents_max: Agents | None = None


#: ``simulate.sources.<domain>.format``: the datasets typ reads a domain from. ``opv2v``: a
#: collaborative root in OPV2V layout (OPV2V, V2V4Real), taken as it is; the others: single-agent
#: datasets, each frame moved into its LiDAR's frame and written as a one-agent scenario. The
#: single-agent names are the reader registry's (:data:`typ.registry.READERS`; the config reads
#: no dataset code)
SINGLE_AGENT_FORMATS = tuple(READERS)
SOURCE_FORMATS = SINGLE_AGENT_FORMATS + ("opv2v",)
SourceFormat = Literal[SOURCE_FORMATS]
#: a drive's scans, at most (KITTI odometry's longest sequence holds 4,661; a day at 10 Hz 864,000)
MAX_SCANS = 1_000_000


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
    splits: dict[str, list[str] | Annotated[float, Bound(0, 1, "a share of the scenarios", low_open=True,
                                                         what="a fraction")]] = field(default_factory=dict)
    #: the LiDAR preset of the dataset's scans (``typ.sensors.SENSORS``); empty: the format's own
    #: (``kitti-odometry``: estimated from each drive's first scan)
    sensor: str = ""
    #: ``kitti-odometry`` only: typ split -> ``[first, stop)`` scans of every drive, which become that
    #: split's scenario (a drive shared out by frame range, e.g. train on its start, test on its end);
    #: ranges may not overlap, and replace ``splits``
    frame_ranges: dict[str, tuple[Annotated[int, Bound(0, MAX_SCANS, "a scan index: a day at 10 Hz is 864,000")],
                                  Annotated[int, Bound(0, MAX_SCANS, "a scan index: a day at 10 Hz is 864,000")]]] \
        = field(default_factory=dict)

    def check(self, where: str, name: str) -> None:
        if not self.root.strip():
            raise TypError(where, f"{name}.root", "the path of the dataset root", self.root)
        if self.frame_ranges:
            if self.format != "kitti-odometry" or self.splits:
                raise TypError(where, f"{name}.frame_ranges", "frame ranges of a kitti-odometry source without "
                               "splits", self.format if self.format != "kitti-odometry" else "splits given too")
            spans = sorted((r, split) for split, r in self.frame_ranges.items())
            for (first, stop), split in spans:
                if not first < stop:
                    raise TypError(where, f"{name}.frame_ranges.{split}", "[first, stop) with first < stop",
                                   [first, stop])
            for ((_, stop), a), ((first, _), b) in zip(spans, spans[1:]):
                if first < stop:
                    raise TypError(where, f"{name}.frame_ranges", "ranges that share no scan", f"{a} and {b}")
        fractions = {split: v for split, v in self.splits.items() if isinstance(v, float)}
        for split, value in self.splits.items():
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

    seed: Seed
    frames: Frames
    agents_min: Agents
    agents_max: Agents
    azimuth_step_deg: AzimuthStep
    comm_range: CommRange
    dt: Annotated[float, Bound(0, MAX_DT, "seconds between frames: 0.1 at 10 Hz", low_open=True)]
    #: domain -> split -> number of scenarios, e.g. {"target": {"train": 4, "test": 2}}; for a domain
    #: read from a real dataset (``sources``), the first that many scenarios of each split folder
    scenarios: dict[str, Annotated[dict[str, Scenarios], Length(0, 16, "splits of one domain")]]
    workers: Workers
    out: str
    #: domain -> ``simulate`` (the embedded simulator); the root of a real dataset in OPV2V layout
    #: (``<root>/<split>/<scenario>/<agent>/<timestamp>.pcd|.yaml``: OPV2V, V2V4Real), relative to
    #: the project root or absolute, its scenarios linked into ``out``; or a :class:`SourceConfig`
    #: (``{format, root, splits}``), or a list of them whose scenarios the domain's splits share.
    #: A real dataset is checked whole at start, before anything is written
    sources: dict[str, str | SourceConfig | Annotated[list[SourceConfig], Length(1, 64, "dataset blocks of one "
                                                                                   "domain, each read whole")]] \
        = field(default_factory=dict)
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
        for domain in self.scenarios:
            if domain not in DOMAINS:
                raise TypError(where, f"{name}.scenarios.{domain}", f"a sensor domain in {list(DOMAINS)}", domain)
        for domain in self.occupancy:
            if domain not in DOMAINS:
                raise TypError(where, f"{name}.occupancy", f"sensor domains in {list(DOMAINS)}", domain)
        for domain, source in self.sources.items():
            if domain not in DOMAINS:
                raise TypError(where, f"{name}.sources.{domain}", f"a sensor domain in {list(DOMAINS)}", domain)
            if isinstance(source, str) and not source.strip():
                raise TypError(where, f"{name}.sources.{domain}",
                               f"{SIMULATE!r} or the path of a dataset root in OPV2V layout", source)
            for index, block in enumerate(self.source_blocks(domain)):
                block.check(where, self.source_field(domain, index).replace("simulate", name, 1))


@dataclass(frozen=True)
class VoxelizeConfig:
    """Voxelize stage: every agent view under ``input`` onto ``grid``, stored per scene under ``out``.

    ``grid.z_range`` is height above the ground under the sensor; ``mount_height`` gives each
    dataset's LiDAR height above its ground (metres), so the ground lands in the same height
    channel in every domain (TYP §4.1: the z range is dataset-dependent)."""

    grid: GridConfig
    mount_height: dict[str, Annotated[float, Bound(0, 10, "metres of a LiDAR above its road", high_open=True,
                                                   what="a sensor height")]]
    input: str
    out: str
    workers: Workers

    def check(self, where: str, name: str) -> None:
        self.grid.check(where, f"{name}.grid")

    def sensor_grid(self, dataset: str, where: str = "voxelize") -> "Grid":
        """The grid in the sensor frame of ``dataset``'s LiDAR (see :meth:`typ.voxel.Grid.for_sensor`)."""
        from typ.voxel import Grid
        if dataset not in self.mount_height:
            raise TypError(where, f"voxelize.mount_height.{dataset}",
                           f"the sensor height of dataset {dataset!r} (known: {sorted(self.mount_height)})", "missing")
        g = self.grid
        return Grid(g.x_range, g.y_range, g.z_range, g.shape).for_sensor(self.mount_height[dataset])
