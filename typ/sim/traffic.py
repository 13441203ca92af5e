"""Traffic over a scenario: the connected agents, background traffic and parked cars.

Moving vehicles drive closed loops (:mod:`typ.sim.routes`) at a desired speed of 5-12 m/s
and slow down for whatever is in the lane ahead of them (a corridor along their own future
path, so curves and crossing traffic count). At crossings a vehicle yields to vehicles
spawned before it, which puts the agents first, so they rarely wait. The agents (ego
first) are placed so they stay within ``comm_range`` of the ego at every frame; the whole
traffic is drawn again if they would not, and as a last resort they drive as a platoon.
Everything is precomputed for all frames before any ray is cast, so frames of a scenario
are temporally consistent: same ids, motion of ``speed * dt`` per frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from typ.sim.routes import LoopRoute, town_routes
from typ.sim.town import Town
from typ.sim.vehicles import sample_labels, sample_paint, sample_sizes, vehicle_boxes

_SPEED = (5.0, 12.0)      # desired speeds (m/s)
_MIN_GAP = 2.0            # bumper-to-obstacle distance kept when stopped (m)
_HEADWAY = 1.2            # time gap kept to the obstacle ahead (s)
_ACCEL = 3.0              # maximum acceleration (m/s^2); braking is not limited
_ATTEMPTS = 6             # fresh draws of the traffic before the agents fall back to a platoon


@dataclass
class Traffic:
    """Every vehicle of a scenario at every frame; index m is a vehicle, agents first (ego at 0).

    ids (M,) int64 stable object ids; labels M class names; sizes (M, 3) ``(l, w, h)``;
    paint (M,) float32 reflectivity; moving (M,) bool; xy (F, M, 2) world position of the
    vehicle's ground centre; yaw (F, M) rad; speed (F, M) m/s; agents (A,) indices, ego first.
    """

    ids: np.ndarray
    labels: tuple[str, ...]
    sizes: np.ndarray
    paint: np.ndarray
    moving: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    agents: np.ndarray
    dt: float

    @property
    def n_frames(self) -> int:
        return self.xy.shape[0]

    def boxes(self, frame: int) -> np.ndarray:
        """(M, 7) world boxes ``[x, y, z, l, w, h, yaw]`` at ``frame``."""
        return vehicle_boxes(self.xy[frame], self.yaw[frame], self.sizes)


@dataclass
class _Plan:
    route: list[int]
    s0: list[float]
    v_des: list[float]
    labels: list[str]
    sizes: list[np.ndarray]

    def add(self, route: int, s: float, v_des: float, label: str, size: np.ndarray) -> None:
        self.route.append(route)
        self.s0.append(s)
        self.v_des.append(v_des)
        self.labels.append(label)
        self.sizes.append(size)


def simulate_traffic(town: Town, rng: np.random.Generator, *, n_frames: int, dt: float, n_agents: int,
                     comm_range: float, moving_vehicles: tuple[int, int],
                     class_probs: tuple[float, float, float]) -> Traffic:
    """Spawn and drive all vehicles for ``n_frames`` frames of ``dt`` seconds (uses only ``rng``)."""
    routes = town_routes(town)
    grid = _route_grid(routes)
    for attempt in range(_ATTEMPTS + 1):
        plan = _spawn_agents(routes, grid, rng, n_frames, dt, n_agents, comm_range, platoon=attempt == _ATTEMPTS)
        _spawn_background(plan, routes, grid, rng, moving_vehicles, class_probs)
        xy, yaw, speed = _drive(plan, routes, n_frames, dt)
        reach = np.linalg.norm(xy[:, :n_agents] - xy[:, :1], axis=-1).max()
        if reach <= comm_range:
            break
    else:
        raise RuntimeError(f"agents drifted {reach:.1f} m apart, beyond comm_range={comm_range} m, even as a platoon")

    n_moving, n_parked = len(plan.labels), len(town.parked_labels)
    m = n_moving + n_parked
    parked_xy = np.broadcast_to(town.parked_xy, (n_frames, n_parked, 2))
    parked_yaw = np.broadcast_to(town.parked_yaw, (n_frames, n_parked))
    # CARLA-like actor ids: increasing with random gaps, then shuffled so the agents' ids
    # aren't simply the smallest.
    ids = rng.permutation(int(rng.integers(100, 600)) + np.cumsum(rng.integers(1, 10, m))).astype(np.int64)
    # OpenCOOD (and typ.formats.opv2v) take the agent folder that sorts first, as a string, as
    # the ego: hand the agents their ids in that order so the ego on disk is the ego here.
    ids[:n_agents] = sorted(ids[:n_agents], key=str)
    return Traffic(
        ids=ids, labels=tuple(plan.labels) + town.parked_labels,
        sizes=np.concatenate([np.array(plan.sizes).reshape(-1, 3), town.parked_sizes]),
        paint=np.concatenate([sample_paint(n_moving, rng), town.parked_paint]),
        moving=np.r_[np.ones(n_moving, bool), np.zeros(n_parked, bool)],
        xy=np.concatenate([xy, parked_xy], axis=1), yaw=np.concatenate([yaw, parked_yaw], axis=1),
        speed=np.concatenate([speed, np.zeros((n_frames, n_parked))], axis=1),
        agents=np.arange(n_agents), dt=dt)


def _route_grid(routes: list[LoopRoute], step: float = 1.0) -> np.ndarray:
    """Points every ``step`` m along every route: rows ``[route, s, x, y]``."""
    rows = []
    for r, route in enumerate(routes):
        s = np.arange(0.0, route.length, step)
        x, y, _ = route.pose_at(s)
        rows.append(np.c_[np.full(len(s), r), s, x, y])
    return np.concatenate(rows)


def _clear(xy: np.ndarray, length: float, plan: _Plan, routes: list[LoopRoute], margin: float = 3.0) -> bool:
    """True if a vehicle of ``length`` at ``xy`` keeps ``margin`` from every planned vehicle."""
    for r, s, size in zip(plan.route, plan.s0, plan.sizes):
        x, y, _ = routes[r].pose_at(s)
        if np.hypot(x - xy[0], y - xy[1]) < (length + size[0]) / 2.0 + margin:
            return False
    return True


def _spawn_agents(routes, grid, rng, n_frames, dt, n_agents, comm_range, platoon: bool) -> _Plan:
    """Ego on a random lane, then CAVs near it whose free-flow paths stay in range of the ego's."""
    plan = _Plan([], [], [], [], [])
    k = int(rng.integers(len(grid)))
    ego_route, ego_s = int(grid[k, 0]), float(grid[k, 1])
    ego_v = float(rng.uniform(*_SPEED))
    labels = ["car"] * n_agents
    sizes = sample_sizes(labels, rng)
    plan.add(ego_route, ego_s, ego_v, "car", sizes[0])
    t = np.arange(n_frames) * dt
    ex, ey, _ = routes[ego_route].pose_at(ego_s + ego_v * t)
    near = np.hypot(grid[:, 2] - ex[0], grid[:, 3] - ey[0])
    candidates = np.flatnonzero((near >= 10.0) & (near <= min(45.0, 0.65 * comm_range)))
    for a in range(1, n_agents):
        if platoon:
            # Same lane and speed as the ego, alternately ahead and behind: the gaps along the
            # loop bound the distance, whatever the turns.
            offset = 12.0 * ((a + 1) // 2) * (1 if a % 2 else -1)
            route, s, v = ego_route, ego_s + offset, ego_v
        else:
            route = -1
            for c in rng.permutation(candidates)[:400]:
                r, s = int(grid[c, 0]), float(grid[c, 1])
                v = float(np.clip(ego_v + rng.uniform(-2.0, 2.0), *_SPEED))
                x, y, _ = routes[r].pose_at(s + v * t)
                if np.hypot(x - ex, y - ey).max() <= comm_range - 10.0 and _clear((x[0], y[0]), sizes[a, 0], plan, routes):
                    route = r
                    break
            if route < 0:  # nothing fits next to the ego: tail it
                route, s, v = ego_route, ego_s - 12.0 * a, ego_v
        plan.add(route, s, v, "car", sizes[a])
    return plan


def _spawn_background(plan: _Plan, routes, grid, rng, count: tuple[int, int], class_probs) -> None:
    n = int(rng.integers(count[0], count[1] + 1))
    labels = sample_labels(n, class_probs, rng)
    sizes = sample_sizes(labels, rng)
    for label, size in zip(labels, sizes):
        for _ in range(30):
            r, s = grid[int(rng.integers(len(grid)))][:2]
            x, y, _ = routes[int(r)].pose_at(s)
            if _clear((x, y), size[0], plan, routes, margin=5.0):
                top = 9.0 if label == "truck" else _SPEED[1]  # trucks drive slower
                plan.add(int(r), float(s), float(rng.uniform(_SPEED[0], top)), label, size)
                break


def _outline(sizes: np.ndarray) -> np.ndarray:
    """(M, 18, 2) points on each vehicle's footprint (6 stations x left/centre/right), vehicle frame."""
    u = np.linspace(-0.5, 0.5, 6)
    v = np.array([-0.5, 0.0, 0.5])
    grid = np.stack(np.meshgrid(u, v, indexing="ij"), -1).reshape(-1, 2)
    return grid[None] * sizes[:, None, :2]


def _footprints(xy: np.ndarray, yaw: np.ndarray, outline: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    return np.stack([xy[:, None, 0] + c * outline[..., 0] - s * outline[..., 1],
                     xy[:, None, 1] + s * outline[..., 0] + c * outline[..., 1]], -1)


def _drive(plan: _Plan, routes: list[LoopRoute], n_frames: int, dt: float):
    """Integrate all moving vehicles: -> xy (F, M, 2), yaw (F, M), speed (F, M)."""
    m = len(plan.labels)
    route = [routes[r] for r in plan.route]
    sizes = np.array(plan.sizes).reshape(m, 3)
    v_des = np.array(plan.v_des)
    s = np.array(plan.s0, dtype=np.float64)
    v = v_des.copy()
    outline = _outline(sizes)
    xy_out, yaw_out, v_out = np.empty((n_frames, m, 2)), np.empty((n_frames, m)), np.empty((n_frames, m))
    pose = np.array([route[i].pose_at(s[i]) for i in range(m)]).reshape(m, 3)
    for f in range(n_frames):
        xy_out[f], yaw_out[f], v_out[f] = pose[:, :2], pose[:, 2], v
        if f == n_frames - 1:
            break
        foot = _footprints(pose[:, :2], pose[:, 2], outline)
        for i in range(m):  # in priority order; later vehicles see the earlier ones' new positions
            d_free = _free_distance(i, route[i], s[i], sizes[i], v_des[i], pose, foot)
            v_target = min(v_des[i], max(0.0, (d_free - _MIN_GAP) / _HEADWAY))
            v[i] = min(v_target, v[i] + _ACCEL * dt)
            s[i] += v[i] * dt
            pose[i] = route[i].pose_at(s[i])
            foot[i] = _footprints(pose[i:i + 1, :2], pose[i:i + 1, 2], outline[i:i + 1])[0]
    return xy_out, yaw_out, v_out


def _free_distance(i: int, route: LoopRoute, s: float, size: np.ndarray, v_des: float,
                   pose: np.ndarray, foot: np.ndarray) -> float:
    """Distance (m) from vehicle i's front bumper along its path to the first thing it must stop for."""
    step = 0.5
    look = 4.0 + 2.5 * v_des
    ahead = np.arange(0.0, look, step)
    px, py, pyaw = route.pose_at(s + size[0] / 2.0 + ahead)
    near = np.hypot(pose[:, 0] - pose[i, 0], pose[:, 1] - pose[i, 1]) < look + size[0] + 12.0
    near[i] = False
    others = np.flatnonzero(near)
    if len(others) == 0:
        return np.inf
    q = foot[others]                                        # (K, 18, 2)
    d = np.hypot(q[..., 0, None] - px, q[..., 1, None] - py)  # (K, 18, P)
    nearest = d.argmin(axis=-1)
    dist = np.take_along_axis(d, nearest[..., None], -1)[..., 0]
    along = nearest * step
    blocks = [along[dist <= size[1] / 2.0 + 0.35]]
    # Yield to earlier-spawned vehicles crossing close ahead (not ones in parallel or oncoming
    # lanes, nor ones beside our bumper: those wait for us, and yielding back would deadlock).
    turn = np.abs(np.mod(pose[others, 2, None] - pyaw[nearest] + np.pi, 2 * np.pi) - np.pi)
    crossing = (turn > np.radians(35)) & (turn < np.radians(145)) & (others < i)[:, None] & (nearest > 0)
    blocks.append(np.maximum(along[crossing & (dist <= size[1] / 2.0 + 3.0)] - 3.0, 0.0))
    cand = np.concatenate(blocks)
    return float(cand.min()) if len(cand) else np.inf
