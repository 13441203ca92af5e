"""One simulated scenario: a town, its traffic, and every agent's LiDAR sweep at every frame.

Randomness comes from ``np.random.SeedSequence(seed)`` split into independent streams for
the town, the traffic and each frame's sensor noise, so the same seed gives byte-identical
scenes and changing e.g. the azimuth step does not change the town or the traffic.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from typ.errors import TypError
from typ.geometry import invert, pose_to_matrix, transform_boxes
from typ.scene import AgentView, Scene
from typ.sim.raycast import cast, town_frame
from typ.sim.sensor import domain_spec
from typ.sim.town import Town, build_town
from typ.sim.traffic import Traffic, simulate_traffic

#: Vehicles further than this from a sensor (xy distance, m) get no box in its view.
BOX_RANGE = 120.0
MAX_AGENTS = 8
_WHERE = "typ.sim.simulate_scenario"


def sensor_pose(xy, yaw: float, mount_height: float) -> np.ndarray:
    """(4, 4) float64 sensor-to-world of a LiDAR ``mount_height`` m above a vehicle on flat ground
    at ``xy`` heading ``yaw`` (rad): roll = pitch = 0."""
    return pose_to_matrix([float(xy[0]), float(xy[1]), mount_height, 0.0, math.degrees(yaw), 0.0])


def _check_int(name: str, value, low: int, high: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low or (high is not None and value > high):
        rng = f"in [{low}, {high}]" if high is not None else f">= {low}"
        raise TypError(_WHERE, name, f"an integer {rng}", value)
    return int(value)


def _check_positive(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value) or value <= 0:
        raise TypError(_WHERE, name, "a positive finite number", value)
    return float(value)


def simulate_scenario(*, domain: str, seed: int, n_frames: int, n_agents: int, azimuth_step_deg: float = 0.4,
                      comm_range: float = 70.0, dt: float = 0.1, scenario: str = "", split: str = "") -> list[Scene]:
    """Simulate ``n_frames`` frames (``dt`` s apart) of ``n_agents`` connected vehicles in one town.

    Each :class:`Scene` holds one :class:`AgentView` per agent, the ego first, agent ids being
    the vehicles' ids as strings (OPV2V style). Points are in each agent's sensor frame, boxes
    (every other vehicle within :data:`BOX_RANGE`) too; box ids are stable across agents and
    frames. Every agent stays within ``comm_range`` m of the ego at every frame.
    Timestamps are ``"000000"``, ``"000001"``, ... Deterministic in ``seed``.
    """
    spec = domain_spec(domain)
    seed = _check_int("seed", seed, 0)
    n_frames = _check_int("n_frames", n_frames, 1)
    n_agents = _check_int("n_agents", n_agents, 1, MAX_AGENTS)
    azimuth_step_deg = _check_positive("azimuth_step_deg", azimuth_step_deg)
    comm_range = _check_positive("comm_range", comm_range)
    dt = _check_positive("dt", dt)
    # The fallback platoon spaces agents 12 m apart, alternately ahead of and behind the ego.
    min_range = 12.0 * (n_agents // 2) + 5.0
    if comm_range < min_range:
        raise TypError(_WHERE, "comm_range", f"at least {min_range:.0f} m to fit {n_agents} agents", comm_range)
    sensor = replace(spec.sensor, azimuth_step_deg=azimuth_step_deg)
    scenario = scenario or f"sim_{domain}_{seed:06d}"

    town, traffic, sensor_seed = _world(spec, seed, n_frames, n_agents, comm_range, dt)
    scenes = []
    for f, frame_seed in enumerate(sensor_seed.spawn(n_frames)):
        rng = np.random.default_rng(frame_seed)
        world = town_frame(town, traffic, f)
        timestamp = f"{f:06d}"
        agents: dict[str, AgentView] = {}
        for a in traffic.agents:
            agent_id = str(traffic.ids[a])
            pose = sensor_pose(traffic.xy[f, a], traffic.yaw[f, a], sensor.mount_height)
            points, semantics = cast(world, pose, sensor, rng, exclude_vehicle_id=int(traffic.ids[a]))
            boxes, labels, ids = _visible_boxes(traffic, f, int(a), pose)
            agents[agent_id] = AgentView(agent_id=agent_id, points=points, pose=pose, boxes=boxes, box_labels=labels,
                                         box_ids=ids, semantics=semantics,
                                         where=f"sim:{scenario}/{agent_id}/{timestamp}")
        scenes.append(Scene(scenario=scenario, timestamp=timestamp, agents=agents, dataset=f"sim_{domain}", split=split))
    return scenes


def _world(spec, seed: int, n_frames: int, n_agents: int, comm_range: float, dt: float):
    """(town, traffic, the SeedSequence of the frames' sensor noise) of a scenario: no rays cast."""
    town_seed, traffic_seed, sensor_seed = np.random.SeedSequence(seed).spawn(3)
    town = build_town(spec.town, np.random.default_rng(town_seed))
    traffic = simulate_traffic(town, np.random.default_rng(traffic_seed), n_frames=n_frames, dt=dt, n_agents=n_agents,
                               comm_range=comm_range, moving_vehicles=spec.moving_vehicles,
                               class_probs=spec.moving_class_probs)
    return town, traffic, sensor_seed


def scenario_world(*, domain: str, seed: int, n_frames: int, n_agents: int, comm_range: float = 70.0,
                   dt: float = 0.1) -> tuple[Town, Traffic, np.ndarray]:
    """The town, the traffic and the agents' (F, A, 4, 4) float64 sensor-to-world poses of the
    scenario :func:`simulate_scenario` builds from the same arguments, without casting a ray:
    the scene geometry behind its clouds (e.g. for semantic occupancy ground truth)."""
    spec = domain_spec(domain)
    seed = _check_int("seed", seed, 0)
    n_frames = _check_int("n_frames", n_frames, 1)
    n_agents = _check_int("n_agents", n_agents, 1, MAX_AGENTS)
    comm_range, dt = _check_positive("comm_range", comm_range), _check_positive("dt", dt)
    town, traffic, _ = _world(spec, seed, n_frames, n_agents, comm_range, dt)
    poses = np.array([[sensor_pose(traffic.xy[f, a], traffic.yaw[f, a], spec.sensor.mount_height) for a in traffic.agents]
                      for f in range(n_frames)]).reshape(n_frames, len(traffic.agents), 4, 4)
    return town, traffic, poses


def _visible_boxes(traffic: Traffic, frame: int, agent: int, pose: np.ndarray):
    """Boxes (K, 7) in the agent's sensor frame of every other vehicle within BOX_RANGE, labels, ids."""
    world = traffic.boxes(frame)
    dist = np.hypot(world[:, 0] - pose[0, 3], world[:, 1] - pose[1, 3])
    sel = np.flatnonzero((dist <= BOX_RANGE) & (np.arange(len(world)) != agent))
    boxes = transform_boxes(invert(pose), world[sel])
    return boxes, tuple(traffic.labels[i] for i in sel), traffic.ids[sel].copy()
