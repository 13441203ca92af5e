"""A spinning LiDAR's beam table and mount height, recovered from its scans in the sensor frame.

A return of beam b at horizontal distance d lies on the cone ``z = h_b + d tan e_b``: e_b is
the beam's elevation and h_b the height of its origin above the sensor origin (0 for most
sensors; 0.12 and 0.21 m for the two laser blocks of KITTI's HDL-64E, whose points are given
in a frame below the lasers). Range noise moves a point along its ray, never off its cone,
so the elevations seen from each beam's origin cluster in spikes, one per beam.

:func:`fit_sensor` takes those spikes, strongest first, out of a fine elevation histogram
(0.005 deg bins) seen from the sensor origin. When less than 0.9 of the points then lie within
0.05 deg of a beam, it searches each beam's origin height too (a histogram per height, 1 cm
apart, the spikes taken across all of them) and fits each beam's cone by least squares; it
keeps the heights when they put at least 0.9 of the points on a beam, and more than without.
Points nearer than ``min_range`` (the car's own body, no-return placeholders) are left out.
The ground is a plane fitted by RANSAC to the lowest point of each 1 m cell within 3..12 m of
the sensor (further, real roads bend and slope); the mount height is the sensor origin's
distance to it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import uniform_filter1d

from typ.errors import TypError
from typ.sim.sensor import SensorSpec

_WHERE = "typ.sensors.fit_sensor"
BIN_DEG = 0.005               #: elevation histogram bin
WINDOW_DEG = 0.03             #: a spike's mass: the points within this of its bin
MIN_SEPARATION_DEG = 0.08     #: two beams are at least this far apart (Waymo's closest pair: 0.12 deg)
BACKGROUND_DEG = 0.1          #: a spike's surroundings: the points within this of it, outside its window
CONTRAST = 3.0                #: a spike holds this many times the points its surroundings' density gives
HEIGHT_STEP_M = 0.01          #: origin heights tried when the beams do not share the origin
HEIGHT_SPAN_M = 0.4           #: ... within +-this of the sensor origin
#: below this fraction of points within 0.05 deg of a beam, the beams' origin heights are searched too
SHARED_ORIGIN_ENOUGH = 0.9
TOLERANCES_DEG = (0.05, 0.1, 0.2)
REFINE_ROUNDS = 6
HEIGHT_SE_M = 0.005           #: a beam's origin height is fitted only as precisely as this
REFINE_WINDOW_DEG = 0.25      #: a beam's points for its fit lie at most this far from it
SEARCH_POINTS = 40_000        #: beams are searched for and fitted on at most this many points
MIN_BEAM_SHARE = 1e-4         #: a beam holds at least this share of the points (and at least 5)


@dataclass(frozen=True)
class SensorFit:
    """What :func:`fit_sensor` recovered. Angles in degrees, lengths in metres.

    elevations_deg: (B,) ascending beam elevations; beam_heights_m: (B,) their origins' heights
    above the sensor origin, or () when they share it; mount_height: the sensor origin above the
    fitted ground plane; ground_normal: the plane's unit normal (sensor frame, z up);
    azimuth_step_deg: the commonest angle between neighbouring returns of one beam;
    on_beam: tolerance (deg) -> fraction of the points used within it of a fitted beam (the
    fit's quality at 0.05); n_points: points used (those at least ``min_range`` away).
    """

    elevations_deg: tuple[float, ...]
    beam_heights_m: tuple[float, ...]
    mount_height: float
    ground_normal: tuple[float, float, float]
    azimuth_step_deg: float
    on_beam: dict[float, float]
    n_points: int

    @property
    def n_beams(self) -> int:
        return len(self.elevations_deg)

    @property
    def quality(self) -> float:
        """The fraction of the points within 0.05 deg of a fitted beam."""
        return self.on_beam[TOLERANCES_DEG[0]]

    def spec(self, template: SensorSpec, name: str | None = None) -> SensorSpec:
        """``template`` with this fit's beams, mount height and azimuth step (its ranges, noise,
        dropout and intensity kept): the sensor of a dataset whose LiDAR is unknown."""
        return replace(template, name=name or template.name, elevations_deg=self.elevations_deg,
                       beam_heights_m=self.beam_heights_m, mount_height=self.mount_height,
                       azimuth_step_deg=self.azimuth_step_deg)


def fit_sensor(scans, *, min_range: float = 3.0, seed: int = 0) -> SensorFit:
    """Recover the beams and the mount height of the LiDAR that scanned ``scans``.

    scans: one (N, >=3) array in the sensor frame (x forward, y left, z up), or a list of
    such scans of the same sensor (the beams are fitted to all of them together; the mount
    height and the azimuth step are each scan's, medians taken). min_range: horizontal distance
    (m) under which points are left out. seed: the sample's and the ground fit's draws.
    """
    scans = [_xyz(s) for s in (scans if isinstance(scans, (list, tuple)) else [scans])]
    if not scans:
        raise TypError(_WHERE, "scans", "one (N, >=3) array or a list of them", "an empty list")
    scans = [s[np.hypot(s[:, 0], s[:, 1]) >= min_range] for s in scans]
    xyz = np.concatenate(scans)
    if len(xyz) < 100:
        raise TypError(_WHERE, "scans", f"at least 100 points {min_range} m or more from the sensor", len(xyz))
    d = np.hypot(xyz[:, 0], xyz[:, 1])
    # the beams are searched for and fitted on a sample (a cone is fixed by a few hundred of its
    # points); their quality is measured on every point
    sample = np.random.default_rng(seed).choice(len(xyz), min(len(xyz), SEARCH_POINTS), replace=False)
    elevations, heights = _shared_origin_beams(xyz[sample], d[sample])
    on_beam = _on_beam(xyz, elevations, heights)
    if on_beam[TOLERANCES_DEG[0]] < SHARED_ORIGIN_ENOUGH:
        e2, h2 = _offset_beams(xyz[sample], d[sample])
        on_beam2 = _on_beam(xyz, e2, h2)
        if on_beam2[TOLERANCES_DEG[0]] >= max(SHARED_ORIGIN_ENOUGH, on_beam[TOLERANCES_DEG[0]]):
            elevations, heights, on_beam = e2, h2, on_beam2
    grounds = [fit_ground(s, np.random.default_rng([seed, i])) for i, s in enumerate(scans)]
    normal = np.median([n for n, _ in grounds], axis=0)
    return SensorFit(elevations_deg=tuple(float(v) for v in elevations),
                     beam_heights_m=tuple(float(v) for v in heights) if np.any(heights) else (),
                     mount_height=float(np.median([h for _, h in grounds])),
                     ground_normal=tuple(float(v) for v in normal / np.linalg.norm(normal)),
                     azimuth_step_deg=float(np.nanmedian([azimuth_step(s, elevations, heights) for s in scans])),
                     on_beam=on_beam, n_points=len(xyz))


# ---------------------------------------------------------------- beams


def beam_residuals(xyz: np.ndarray, elevations_deg, beam_heights_m=()) -> tuple[np.ndarray, np.ndarray]:
    """Each point's nearest beam and its angle from it: ((N,) int beam index, (N,) float64 deg).

    The angle is the point's elevation seen from the beam's origin minus the beam's elevation.
    """
    xyz = np.asarray(xyz, dtype=np.float64)[:, :3]
    e = np.asarray(elevations_deg, dtype=np.float64)
    d = np.hypot(xyz[:, 0], xyz[:, 1])
    if not np.any(beam_heights_m):
        seen = np.degrees(np.arctan2(xyz[:, 2], d))
        beam = np.clip(np.searchsorted((e[1:] + e[:-1]) / 2, seen), 0, len(e) - 1)
        return beam, seen - e[beam]
    h = np.asarray(beam_heights_m, dtype=np.float64)
    # the nearest beam in tangent space, weighted by cos^2 e (d(tan e) = de / cos^2 e): no
    # arctangent per (point, beam) pair; the angle itself only for the beam chosen
    tan_e, weight = np.tan(np.radians(e)), np.cos(np.radians(e)) ** 2
    beam = np.empty(len(xyz), dtype=np.int64)
    for lo in range(0, len(xyz), 8192):   # (chunk, B) at a time: bounded memory for any cloud
        z, dd = xyz[lo:lo + 8192, 2:3], d[lo:lo + 8192, None]
        beam[lo:lo + 8192] = np.argmin(np.abs((z - h[None, :]) / dd - tan_e[None, :]) * weight[None, :], axis=1)
    return beam, np.degrees(np.arctan2(xyz[:, 2] - h[beam], d)) - e[beam]


def on_beam_fractions(points, sensor, tolerances_deg=TOLERANCES_DEG, *, min_range: float = 0.0) -> dict[float, float]:
    """Tolerance (deg) -> the fraction of ``points`` within it of one of ``sensor``'s beams, seen
    from the beam's origin: 1 for a scan typ casts with ``sensor``, less for voxel centres or
    another sensor's scan. points: (N, >=3) in the sensor's frame; those nearer than
    ``min_range`` (horizontally) are left out. sensor: a SensorSpec or a :class:`SensorFit`.
    """
    xyz = _xyz(points)
    xyz = xyz[np.hypot(xyz[:, 0], xyz[:, 1]) >= max(min_range, 1e-9)]
    return _on_beam(xyz, np.asarray(sensor.elevations_deg), np.asarray(sensor.beam_heights_m), tolerances_deg)


def _on_beam(xyz: np.ndarray, elevations, heights, tolerances_deg=TOLERANCES_DEG) -> dict[float, float]:
    if len(xyz) == 0:
        return {t: float("nan") for t in tolerances_deg}
    _, residual = beam_residuals(xyz, elevations, heights)
    return {t: float(np.mean(np.abs(residual) <= t)) for t in tolerances_deg}


def _greedy_beams(xyz: np.ndarray, d: np.ndarray, heights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(elevations, origin heights) of the spikes of the (height, elevation) histogram, strongest
    first: each accepted beam takes its points out of every height's histogram, so a beam seen
    at one distance only (sharp at any height, at a different elevation each) is taken once."""
    seen = np.degrees(np.arctan2(xyz[None, :, 2] - heights[:, None], d[None, :]))      # (K, N)
    wide = int(round(BACKGROUND_DEG / BIN_DEG))
    lo = seen.min() - 2 * BACKGROUND_DEG
    bins = np.floor((seen - lo) / BIN_DEG).astype(np.int64)
    n_bins = int(bins.max()) + 2 * wide + 2
    counts = np.bincount((bins + np.arange(len(heights))[:, None] * n_bins).ravel(),
                         minlength=len(heights) * n_bins).reshape(len(heights), n_bins).astype(np.float64)
    spike = _spike_mass(counts)
    min_points = max(5.0, MIN_BEAM_SHARE * len(xyz))
    alive = np.ones(len(xyz), dtype=bool)
    elevations: list[float] = []
    origins: list[float] = []
    while True:
        k, b = np.unravel_index(np.argmax(spike), spike.shape)
        if spike[k, b] < min_points - 1e-9:
            break
        e = lo + (b + 0.5) * BIN_DEG
        taken = alive & (np.abs(seen[k] - e) <= MIN_SEPARATION_DEG / 2)
        alive &= ~taken
        gone = bins[:, taken]
        counts -= np.bincount((gone + np.arange(len(heights))[:, None] * n_bins).ravel(),
                              minlength=counts.size).reshape(counts.shape)
        # only the bins within a background window of the points taken change; they are computed
        # from the counts a window further out
        lo_in, hi_in = max(int(gone.min()) - wide, 0), min(int(gone.max()) + wide + 1, n_bins)
        lo_out, hi_out = max(lo_in - wide, 0), min(hi_in + wide, n_bins)
        spike[:, lo_in:hi_in] = _spike_mass(counts[:, lo_out:hi_out])[:, lo_in - lo_out:hi_in - lo_out]
        # a spike too close to a beam already taken is that beam's skirt (noise), not a beam
        if all(abs(e - e2) >= MIN_SEPARATION_DEG or abs(heights[k] - h2) > HEIGHT_STEP_M
               for e2, h2 in zip(elevations, origins)):
            elevations.append(e)
            origins.append(float(heights[k]))
    order = np.argsort(elevations)
    return np.asarray(elevations)[order], np.asarray(origins)[order]


def _spike_mass(counts: np.ndarray) -> np.ndarray:
    """(K, M) the points within WINDOW_DEG of each bin, where they are a spike: CONTRAST times
    denser than the points within BACKGROUND_DEG around them (noise smears a beam into a hump
    whose every bin would pass a count threshold); 0 elsewhere."""
    w, wide = int(round(WINDOW_DEG / BIN_DEG)), int(round(BACKGROUND_DEG / BIN_DEG))
    mass = uniform_filter1d(counts, 2 * w + 1, axis=1, mode="constant") * (2 * w + 1)
    around = uniform_filter1d(counts, 2 * wide + 1, axis=1, mode="constant") * (2 * wide + 1) - mass
    return mass * (mass >= CONTRAST * around * (2 * w + 1) / (2 * (wide - w)))


def _shared_origin_beams(xyz: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    elevations, origins = _greedy_beams(xyz, d, np.zeros(1))
    return _refine(xyz, d, elevations, origins, fit_heights=False)


def _offset_beams(xyz: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # nearest the origin first: a beam that is as sharp at any height (seen at one distance) takes 0
    steps = np.arange(1, int(round(HEIGHT_SPAN_M / HEIGHT_STEP_M)) + 1) * HEIGHT_STEP_M
    heights = np.r_[0.0, np.column_stack([steps, -steps]).ravel()]
    elevations, origins = _greedy_beams(xyz, d, heights)
    return _refine(xyz, d, elevations, origins, fit_heights=True)


def _refine(xyz, d, elevations, origins, *, fit_heights: bool) -> tuple[np.ndarray, np.ndarray]:
    """Each beam's elevation (and origin height) fitted to its points, over REFINE_ROUNDS rounds.

    A beam's points are those nearer to it than 0.4 of the gap to its neighbours (at most
    REFINE_WINDOW_DEG): wide enough for a cone first found at one distance to swing onto the
    points at the others. With ``fit_heights`` a trimmed least-squares cone ``z = h + d tan e``
    where the points span distances enough to tell the height from the elevation; a beam
    whose returns all lie at one distance (a ring on flat ground) takes the height of the
    nearest beam that has one (its laser block's). Then the median elevation seen from there.
    """
    elevations, origins = elevations.copy(), origins.copy()
    for _ in range(REFINE_ROUNDS):
        gaps = np.diff(elevations)
        window = np.minimum(0.4 * np.minimum(np.r_[np.inf, gaps], np.r_[gaps, np.inf]), REFINE_WINDOW_DEG)
        beam, residual = beam_residuals(xyz, elevations, origins)
        near = np.flatnonzero(np.abs(residual) <= window[beam])
        near = near[np.argsort(beam[near], kind="stable")]
        members = np.split(near, np.searchsorted(beam[near], np.arange(1, len(elevations))))   # per beam
        if fit_heights:
            cones = [_trimmed_line(d[on], xyz[on, 2]) if len(on) >= 10 else None for on in members]
            fitted = [b for b, c in enumerate(cones) if c is not None and abs(c[1]) <= HEIGHT_SPAN_M]
            if fitted:
                origins = np.array([cones[fitted[i]][1] for i in _nearest(np.asarray(fitted), len(elevations))])
        for b, on in enumerate(members):
            if len(on):
                elevations[b] = float(np.median(np.degrees(np.arctan2(xyz[on, 2] - origins[b], d[on]))))
        order = np.argsort(elevations)
        elevations, origins = elevations[order], origins[order]
    return elevations, origins


def _nearest(known: np.ndarray, n: int) -> np.ndarray:
    """For each index 0..n-1, the position in the sorted ``known`` of the nearest of its indices."""
    right = np.clip(np.searchsorted(known, np.arange(n)), 0, len(known) - 1)
    left = np.clip(right - 1, 0, len(known) - 1)
    return np.where(np.abs(known[left] - np.arange(n)) <= np.abs(known[right] - np.arange(n)), left, right)


def _trimmed_line(x: np.ndarray, y: np.ndarray) -> tuple[float, float] | None:
    """(slope, intercept) of y on x, refitted on the points within 3 robust sigmas of the first
    fit; None when the intercept's standard error exceeds HEIGHT_SE_M (too short a lever for
    the noise: a beam seen at one distance on a noisy sensor)."""
    slope, intercept = np.polyfit(x, y, 1)
    residual = np.abs(y - (slope * x + intercept))
    keep = residual <= 3 * 1.4826 * np.median(residual) + 1e-4
    x, y = x[keep], y[keep]
    spread = np.sum((x - x.mean()) ** 2) if len(x) >= 3 else 0.0
    if spread <= 0:
        return None
    slope, intercept = np.polyfit(x, y, 1)
    sigma = np.sqrt(np.sum((y - slope * x - intercept) ** 2) / max(len(x) - 2, 1))
    if sigma * math.sqrt(1 / len(x) + x.mean() ** 2 / spread) > HEIGHT_SE_M:
        return None
    return float(slope), float(intercept)


def azimuth_step(xyz: np.ndarray, elevations_deg, beam_heights_m=()) -> float:
    """The commonest angle (deg) between azimuth-neighbouring returns of one beam: the step of a
    sensor that fires at fixed angles (gaps where returns are missing are its multiples)."""
    beam, residual = beam_residuals(xyz, elevations_deg, beam_heights_m)
    on = np.abs(residual) <= WINDOW_DEG
    az = np.degrees(np.arctan2(xyz[on, 1], xyz[on, 0]))
    order = np.lexsort((az, beam[on]))
    gaps = np.diff(az[order])[np.diff(beam[on][order]) == 0]
    gaps = gaps[gaps > 0.01]   # returns of one firing counted twice (dual return) are not a step
    if len(gaps) == 0:
        return float("nan")
    counts = np.bincount(np.rint(gaps / 0.001).astype(np.int64))
    mode = np.argmax(counts[:2000]) * 0.001          # at most 2 deg
    return float(np.median(gaps[np.abs(gaps - mode) <= 0.01]))


# ---------------------------------------------------------------- ground


def fit_ground(xyz: np.ndarray, rng: np.random.Generator, *, near: tuple[float, float] = (3.0, 12.0),
               cell: float = 1.0, inlier_m: float = 0.05, draws: int = 300) -> tuple[np.ndarray, float]:
    """The road under the sensor: (unit normal with z > 0, the sensor origin's height above it).

    Candidates are the lowest point of each ``cell`` m BEV cell between ``near`` m from the
    sensor (walls, cars and trees have ground below them; reflections below the road are rare
    and off any plane); RANSAC keeps the near-horizontal plane (within 15 deg) below the sensor
    with the most candidates within ``inlier_m``, refined by least squares on every return
    within ``inlier_m`` of it.
    """
    d = np.hypot(xyz[:, 0], xyz[:, 1])
    ring = xyz[(d >= near[0]) & (d <= near[1])]
    if len(ring) < 3:
        raise TypError(_WHERE, "scans", f"returns {near[0]}..{near[1]} m from the sensor to fit the ground on",
                       len(ring))
    keys = np.floor(ring[:, :2] / cell).astype(np.int64)
    order = np.lexsort((ring[:, 2], keys[:, 1], keys[:, 0]))
    first = np.r_[True, np.any(np.diff(keys[order], axis=0) != 0, axis=1)]
    lowest = ring[order[first]]
    if len(lowest) < 3:
        raise TypError(_WHERE, "scans", "ground returns in at least 3 BEV cells near the sensor", len(lowest))
    best, best_count = None, -1
    for _ in range(draws):
        a, b, c = lowest[rng.choice(len(lowest), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-9 or abs(n[2]) / norm < math.cos(math.radians(15.0)):
            continue
        n = n / norm * np.sign(n[2])
        if a @ n >= 0:   # a plane at or above the sensor is not its road (a roof, a ceiling)
            continue
        count = int(np.sum(np.abs((lowest - a) @ n) <= inlier_m))
        if count > best_count:
            best, best_count = (n, float(a @ n)), count
    if best is None:
        raise TypError(_WHERE, "scans", "a near-horizontal ground plane near the sensor", "none found")
    normal, offset = best
    # least squares z = p x + q y + r on every return near the plane, which it then moves: the
    # lowest point of a cell is biased low by the range noise, the band around the plane is not
    for _ in range(3):
        inliers = ring[np.abs(ring @ normal - offset) <= inlier_m]
        p, q, r = np.linalg.lstsq(np.c_[inliers[:, :2], np.ones(len(inliers))], inliers[:, 2], rcond=None)[0]
        scale = math.sqrt(p * p + q * q + 1.0)
        normal, offset = np.array([-p, -q, 1.0]) / scale, r / scale
    if offset >= 0:
        raise TypError(_WHERE, "scans", "a near-horizontal ground plane below the sensor", f"one {offset:.2f} m above it")
    return normal, float(-offset)


def _xyz(points) -> np.ndarray:
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] < 3 or not np.issubdtype(arr.dtype, np.number):
        raise TypError(_WHERE, "scans", "an (N, >=3) numeric array in the sensor frame", getattr(arr, "shape", None))
    xyz = arr[:, :3].astype(np.float64)
    return xyz[np.isfinite(xyz).all(axis=1)]
