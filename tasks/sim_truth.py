"""True views at any pose of a simulated scenario: the simulator's world rebuilt and cast again.

A scenario written by ``simulate`` keeps its job (seed, domain, frames, agents, azimuth step)
and its key in ``_typ.json``. The town and the traffic are pure functions of the job's seed
(:mod:`typ.sim.scenario`), so the world of any frame can be rebuilt and a sensor cast from
any pose in it — the true view of a generated reference agent, which the simulator never
wrote because no agent stood there. The world is only rebuilt when the job's key, which
covers the simulator's code, equals the stored one: a changed simulator would cast another
world, and then there is no truth to show.

Dropout and range noise are drawn from ``[seed, frame, vehicle]``, a fresh draw: the
stored views' own draws belong to their poses. Rebuilding and casting one view takes about
0.1 s for the tiny target domain.
"""
from __future__ import annotations

import dataclasses
from functools import lru_cache
from pathlib import Path

import numpy as np

from tasks.simulate import MANIFEST, ScenarioJob
from typ.config import build_typed, check_simulation
from typ.errors import TypError
from typ.io import read_json_or_none
from typ.sim.raycast import TownFrame, cast, town_frame
from typ.sim.sensor import DOMAINS, SensorSpec, domain_spec
from typ.sim.town import build_town
from typ.sim.traffic import simulate_traffic


def scenario_job(sim_scenario: str | Path) -> ScenarioJob | None:
    """The job that wrote ``sim_scenario`` when its key still matches this code, else None.

    The manifest is not trusted: anyone can compute a key. A job whose key matches but whose
    settings this code would never write (an azimuth step of 1e-5 deg, a billion frames)
    raises TypError naming the file, instead of rebuilding a world that does not fit in memory.
    """
    path = Path(sim_scenario) / MANIFEST
    manifest = read_json_or_none(path)
    if not isinstance(manifest, dict):
        return None
    try:
        job = build_typed(ScenarioJob, manifest.get("job"), str(path), "job")
    except TypError:  # another version's manifest, or not a simulated scenario's
        return None
    if job.key() != manifest.get("key"):
        return None
    if job.domain not in DOMAINS or job.index < 0 or not 0 <= job.seed < 2**64:
        raise TypError(path, "job", f"a domain of {sorted(DOMAINS)}, an index >= 0 and a 64-bit seed",
                       [job.domain, job.index, job.seed])
    check_simulation(str(path), "job", frames=job.n_frames, agents=(job.n_agents, job.n_agents),
                     azimuth_step_deg=job.azimuth_step_deg, comm_range=job.comm_range, dt=job.dt)
    return job


def job_sensor(job: ScenarioJob) -> SensorSpec:
    """The job's LiDAR, at its azimuth step."""
    spec = domain_spec(job.domain).sensor
    return dataclasses.replace(spec, azimuth_step_deg=job.azimuth_step_deg)


@lru_cache(maxsize=4)
def _world(job: ScenarioJob, frame: int) -> TownFrame:
    spec = domain_spec(job.domain)
    town_seed, traffic_seed, _ = np.random.SeedSequence(job.seed).spawn(3)
    town = build_town(spec.town, np.random.default_rng(town_seed))
    traffic = simulate_traffic(town, np.random.default_rng(traffic_seed), n_frames=job.n_frames, dt=job.dt,
                               n_agents=job.n_agents, comm_range=job.comm_range,
                               moving_vehicles=spec.moving_vehicles, class_probs=spec.moving_class_probs)
    return town_frame(town, traffic, frame)


def true_view(job: ScenarioJob, timestamp: str, pose, *, vehicle_id: int | None = None,
              where: str = "sim truth") -> tuple[np.ndarray, np.ndarray]:
    """What the job's LiDAR at ``pose`` ((4, 4) float64 sensor-to-world) sees at ``timestamp``.

    vehicle_id: the vehicle carrying the sensor, left out of the world (None: a roadside
    unit). Returns (N, 4) float32 points in the sensor frame and (N,) uint8 class codes, as
    :func:`typ.sim.raycast.cast`.
    """
    if not str(timestamp).isdigit() or not 0 <= int(timestamp) < job.n_frames:
        raise TypError(where, "timestamp", f"a frame of the scenario (000000..{job.n_frames - 1:06d})", timestamp)
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise TypError(where, "pose", "a finite (4, 4) sensor-to-world matrix", pose.shape)
    frame = int(timestamp)
    world = _world(job, frame)
    if vehicle_id is not None and int(vehicle_id) not in set(world.vehicle_ids.tolist()):
        raise TypError(where, "vehicle_id", "a vehicle of the simulated scenario", vehicle_id)
    rng = np.random.default_rng([job.seed, frame, 0 if vehicle_id is None else int(vehicle_id) + 1])
    return cast(world, pose, job_sensor(job), rng, exclude_vehicle_id=vehicle_id)
