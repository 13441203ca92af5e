"""Tests for the procedural simulator (typ.sim): determinism, geometry, labels, domains."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from typ.errors import TypError
from typ.geometry import points_in_boxes, pose_to_matrix, transform_boxes
from typ.scene import SEMANTIC_CLASSES, SEMANTIC_CODE
from typ.sim import (
    DOMAINS, build_town, cast, domain_spec, sensor_pose, simulate_scenario, simulate_traffic, town_frame,
)
from typ.sim.vehicles import sample_sizes

SEED = 7


@pytest.fixture(scope="module")
def scenes():
    """Three frames of three agents in every domain (coarse azimuth to keep the suite fast)."""
    return {d: simulate_scenario(domain=d, seed=SEED, n_frames=3, n_agents=3, azimuth_step_deg=0.8) for d in DOMAINS}


def _views(scene_list):
    return [v for s in scene_list for v in s.agents.values()]


def _traffic(domain: str, seed: int, n_frames: int, n_agents: int, comm_range: float = 70.0):
    spec = domain_spec(domain)
    town_seed, traffic_seed, _ = np.random.SeedSequence(seed).spawn(3)
    town = build_town(spec.town, np.random.default_rng(town_seed))
    traffic = simulate_traffic(town, np.random.default_rng(traffic_seed), n_frames=n_frames, dt=0.1, n_agents=n_agents,
                               comm_range=comm_range, moving_vehicles=spec.moving_vehicles,
                               class_probs=spec.moving_class_probs)
    return spec, town, traffic


def test_same_seed_gives_identical_arrays(scenes):
    again = simulate_scenario(domain="source", seed=SEED, n_frames=3, n_agents=3, azimuth_step_deg=0.8)
    for a, b in zip(scenes["source"], again):
        assert (a.scenario, a.timestamp, list(a.agents)) == (b.scenario, b.timestamp, list(b.agents))
        for va, vb in zip(a.agents.values(), b.agents.values()):
            assert va.points.tobytes() == vb.points.tobytes()
            assert va.semantics.tobytes() == vb.semantics.tobytes()
            assert va.pose.tobytes() == vb.pose.tobytes()
            assert va.boxes.tobytes() == vb.boxes.tobytes()
            assert va.box_ids.tobytes() == vb.box_ids.tobytes() and va.box_labels == vb.box_labels


def test_noisy_domain_is_deterministic_too(scenes):
    again = simulate_scenario(domain="target", seed=SEED, n_frames=1, n_agents=3, azimuth_step_deg=0.8)
    for va, vb in zip(scenes["target"][0].agents.values(), again[0].agents.values()):
        assert va.points.tobytes() == vb.points.tobytes()


def test_different_seed_differs(scenes):
    other = simulate_scenario(domain="source", seed=SEED + 1, n_frames=1, n_agents=3, azimuth_step_deg=0.8)
    a, b = scenes["source"][0].ego, other[0].ego
    assert a.points.shape != b.points.shape or not np.array_equal(a.points, b.points)
    assert not np.array_equal(a.pose, b.pose)


def test_scene_layout(scenes):
    for domain, scene_list in scenes.items():
        assert [s.timestamp for s in scene_list] == ["000000", "000001", "000002"]
        for s in scene_list:
            assert len(s.agents) == 3 and list(s.agents) == list(scene_list[0].agents)  # same agents, ego first
            assert s.dataset == f"sim_{domain}" and s.scenario == f"sim_{domain}_{SEED:06d}"
            for agent_id, v in s.agents.items():
                assert agent_id.isdigit() and v.agent_id == agent_id
                assert int(agent_id) not in v.box_ids  # an agent has no box of its own
                assert v.pose.dtype == np.float64
                assert v.pose[2, 3] == pytest.approx(domain_spec(domain).sensor.mount_height)
                np.testing.assert_allclose(v.pose[2, :3], [0, 0, 1], atol=1e-12)  # roll = pitch = 0
            # The other agents appear among each agent's boxes.
            ego = s.ego
            assert {int(a) for a in s.agents if a != s.ego_id} <= set(ego.box_ids.tolist())


@pytest.mark.parametrize("domain", sorted(DOMAINS))
def test_agents_stay_in_comm_range(scenes, domain):
    for s in scenes[domain]:
        ego = s.ego.pose[:2, 3]
        for v in s.agents.values():
            assert np.linalg.norm(v.pose[:2, 3] - ego) <= 70.0
    # A long sequence with five agents and a tighter range, without casting rays.
    for seed in range(3):
        _, _, traffic = _traffic(domain, seed, n_frames=150, n_agents=5, comm_range=60.0)
        dist = np.linalg.norm(traffic.xy[:, traffic.agents] - traffic.xy[:, traffic.agents[:1]], axis=-1)
        assert dist.max() <= 60.0


@pytest.mark.parametrize("domain", sorted(DOMAINS))
def test_points_are_valid(scenes, domain):
    sensor = domain_spec(domain).sensor
    for v in _views(scenes[domain]):
        assert v.points.dtype == np.float32 and v.semantics.dtype == np.uint8
        assert len(v.points) > 1000 and np.isfinite(v.points).all()
        rng = np.linalg.norm(v.points[:, :3].astype(np.float64), axis=1)
        assert rng.max() <= sensor.max_range + 3 * sensor.range_noise_std + 1e-3
        assert rng.min() >= sensor.min_range - 3 * sensor.range_noise_std - 1e-3
        assert v.points[:, 3].min() >= 0.0 and v.points[:, 3].max() <= 1.0
        assert v.semantics.max() < len(SEMANTIC_CLASSES)
    seen = np.unique(np.concatenate([v.semantics for v in _views(scenes[domain])]))
    assert seen.tolist() == list(range(len(SEMANTIC_CLASSES)))


@pytest.mark.parametrize("domain", sorted(DOMAINS))
def test_ground_is_flat_at_minus_mount_height(scenes, domain):
    sensor = domain_spec(domain).sensor
    kerb = domain_spec(domain).town.kerb_height
    tol = 3 * sensor.range_noise_std + 1e-4
    for v in _views(scenes[domain]):
        dz = v.points[:, 2].astype(np.float64) + sensor.mount_height
        road = dz[v.semantics == SEMANTIC_CODE["road"]]
        ground = dz[v.semantics == SEMANTIC_CODE["ground"]]
        assert len(road) > 100 and np.abs(road).max() <= tol
        # Ground includes sidewalks and kerbs, raised by up to the kerb height.
        assert ground.min() >= -tol and ground.max() <= kerb + tol


def test_source_is_noise_free_and_target_is_not(scenes):
    def road_dz(domain):
        h = domain_spec(domain).sensor.mount_height
        return np.concatenate([v.points[v.semantics == SEMANTIC_CODE["road"], 2] + h for v in _views(scenes[domain])])

    assert np.abs(road_dz("source")).max() < 1e-4
    assert road_dz("target").std() > 1e-3 and np.abs(road_dz("target")).max() > 5e-3
    assert road_dz("real_cav").std() > road_dz("target").std()  # 3 cm vs 2 cm range noise


@pytest.mark.parametrize("domain", sorted(DOMAINS))
def test_vehicle_points_lie_in_boxes(scenes, domain):
    inside = total = 0
    for v in _views(scenes[domain]):
        pts = v.points[v.semantics == SEMANTIC_CODE["vehicle"]]
        boxes = v.boxes.copy()
        boxes[:, 3:6] += 0.2
        inside += points_in_boxes(pts, boxes).any(axis=1).sum()
        total += len(pts)
    assert total > 100 and inside / total >= 0.99


@pytest.mark.parametrize("domain", sorted(DOMAINS))
def test_no_hits_on_own_vehicle(scenes, domain):
    sensor = domain_spec(domain).sensor
    for v in _views(scenes[domain]):
        p = v.points
        over_roof = (np.abs(p[:, 0]) < 3.5) & (np.abs(p[:, 1]) < 2.0) & (p[:, 2] > -sensor.mount_height + 0.3)
        assert not over_roof.any()


def test_own_vehicle_would_be_seen_without_exclusion():
    """The exclusion is what keeps the roof out: casting with the car in the scene hits it."""
    spec, town, traffic = _traffic("source", SEED, n_frames=1, n_agents=2)
    world = town_frame(town, traffic, 0)
    pose = sensor_pose(traffic.xy[0, 0], traffic.yaw[0, 0], spec.sensor.mount_height)
    rng = np.random.default_rng(0)
    with_car, sem = cast(world, pose, spec.sensor, rng)
    without, _ = cast(world, pose, spec.sensor, rng, exclude_vehicle_id=int(traffic.ids[0]))

    def roof(p):
        return (np.abs(p[:, 0]) < 3.0) & (np.abs(p[:, 1]) < 1.2) & (p[:, 2] > -spec.sensor.mount_height + 0.3)

    assert roof(with_car).sum() > 50 and (sem[roof(with_car)] == SEMANTIC_CODE["vehicle"]).all()
    assert roof(without).sum() == 0


def test_cast_from_arbitrary_pose_and_bad_exclusion():
    spec, town, traffic = _traffic("target", 3, n_frames=1, n_agents=1)
    world = town_frame(town, traffic, 0)
    # A roadside unit: 4 m up a pole at a road crossing, tilted down 10 degrees.
    pose = pose_to_matrix([town.road_x[0], town.road_y[0], 4.0, 0.0, 30.0, -10.0])
    points, sem = cast(world, pose, spec.sensor, np.random.default_rng(0))
    assert len(points) > 1000 and points.dtype == np.float32 and len(sem) == len(points)
    with pytest.raises(TypError, match="exclude_vehicle_id"):
        cast(world, pose, spec.sensor, np.random.default_rng(0), exclude_vehicle_id=-5)


def test_box_ids_agree_across_agents(scenes):
    for domain in DOMAINS:
        for s in scenes[domain]:
            world: dict[int, np.ndarray] = {}
            shared = 0
            for v in s.agents.values():
                boxes = transform_boxes(v.pose, v.boxes)
                for oid, label, box in zip(v.box_ids.tolist(), v.box_labels, boxes):
                    if oid in world:
                        shared += 1
                        np.testing.assert_allclose(box[:6], world[oid][:6], atol=1e-6)
                        assert abs(np.angle(np.exp(1j * (box[6] - world[oid][6])))) < 1e-6
                    world[oid] = box
                assert set(v.box_labels) <= {"car", "van", "truck"}
            assert shared > 10


def test_box_motion_is_smooth_across_frames(scenes):
    dt = 0.1
    for scene_list in scenes.values():
        prev = None
        for s in scene_list:
            v = s.ego
            world = dict(zip(v.box_ids.tolist(), transform_boxes(v.pose, v.boxes)))
            if prev is not None:
                common = set(world) & set(prev)
                assert len(common) > 10
                step = np.array([np.linalg.norm(world[i][:2] - prev[i][:2]) for i in common])
                assert step.max() <= 12.0 * dt + 1e-6
                assert (step > 0.3).sum() >= 3  # moving traffic moves, parked cars don't
                sizes_same = all(np.array_equal(world[i][3:6], prev[i][3:6]) for i in common)
                assert sizes_same
            prev = world


def test_displacement_matches_speed():
    _, _, traffic = _traffic("source", 2, n_frames=40, n_agents=3)
    step = np.linalg.norm(np.diff(traffic.xy, axis=0), axis=-1)  # (F-1, M)
    expected = traffic.speed[1:] * traffic.dt
    # Chords on the corner arcs are a hair shorter than the arc length travelled.
    assert np.all(step <= expected + 1e-9)
    assert np.all(step >= expected * 0.995 - 1e-9)
    moving = traffic.moving
    assert (traffic.speed[:, moving] <= 12.0 + 1e-9).all() and np.median(traffic.speed[:, moving]) >= 5.0
    assert (step[:, ~moving] == 0).all()


def test_vehicle_boxes_never_overlap():
    _, _, traffic = _traffic("target", 4, n_frames=120, n_agents=4)
    for f in range(0, 120, 4):
        boxes = traffic.boxes(f)
        shrunk = boxes.copy()
        shrunk[:, 3:5] -= 0.05
        c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
        corners = []
        for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1), (0, 0)):
            dx, dy = sx * boxes[:, 3] / 2, sy * boxes[:, 4] / 2
            corners.append(np.c_[boxes[:, 0] + c * dx - s * dy, boxes[:, 1] + s * dx + c * dy, boxes[:, 2]])
        pts = np.stack(corners, 1).reshape(-1, 3)
        owner = np.repeat(np.arange(len(boxes)), 5)
        inside = points_in_boxes(pts, shrunk)
        inside[np.arange(len(pts)), owner] = False
        assert not inside.any(), f"overlapping vehicles at frame {f}"


def test_domains_differ_in_beams(scenes):
    def beams(domain):
        pts = np.concatenate([v.points for v in _views(scenes[domain])]).astype(np.float64)
        elev = np.sort(np.degrees(np.arctan2(pts[:, 2], np.hypot(pts[:, 0], pts[:, 1]))))
        return np.r_[elev[0], elev[1:][np.diff(elev) > 0.02]]

    source, target, real = beams("source"), beams("target"), beams("real_cav")
    assert len(source) == 64 and len(real) == 32 and 60 <= len(target) <= 64
    assert source.min() == pytest.approx(-25.0, abs=1e-3) and target.min() == pytest.approx(-17.6, abs=1e-3)
    assert np.ptp(np.diff(source)) < 1e-3                       # uniform
    spacing = np.diff(domain_spec("target").sensor.elevations_deg)
    assert spacing[-1] < 0.5 * spacing[0]                         # denser towards the horizon
    assert {domain_spec(d).sensor.mount_height for d in DOMAINS} == {1.9, 2.2, 1.8}


def test_intensity_models():
    spec, town, traffic = _traffic("source", 5, n_frames=1, n_agents=1)
    world = town_frame(town, traffic, 0)
    pose = sensor_pose(traffic.xy[0, 0], traffic.yaw[0, 0], 2.0)
    pts, _ = cast(world, pose, spec.sensor, np.random.default_rng(0), exclude_vehicle_id=int(traffic.ids[0]))
    r = np.linalg.norm(pts[:, :3].astype(np.float64), axis=1)
    np.testing.assert_allclose(pts[:, 3], np.exp(-0.004 * r), atol=1e-6)  # CARLA attenuation
    material = domain_spec("target").sensor
    pts, sem = cast(world, pose, replace(material, max_range=120.0), np.random.default_rng(0),
                    exclude_vehicle_id=int(traffic.ids[0]))
    road = pts[sem == SEMANTIC_CODE["road"], 3].mean()
    veg = pts[sem == SEMANTIC_CODE["vegetation"], 3].mean()
    assert road < 0.15 < veg  # dark asphalt vs bright foliage


def test_dropout_loses_returns():
    spec, town, traffic = _traffic("target", 6, n_frames=1, n_agents=1)
    world = town_frame(town, traffic, 0)
    pose = sensor_pose(traffic.xy[0, 0], traffic.yaw[0, 0], spec.sensor.mount_height)
    eid = int(traffic.ids[0])
    full, _ = cast(world, pose, replace(spec.sensor, dropout=0.0, detection_energy=0.0), np.random.default_rng(0), eid)
    random_only, _ = cast(world, pose, replace(spec.sensor, detection_energy=0.0), np.random.default_rng(0), eid)
    real, _ = cast(world, pose, spec.sensor, np.random.default_rng(0), eid)
    assert len(random_only) / len(full) == pytest.approx(0.95, abs=0.01)
    assert len(real) < len(random_only)
    # Weak echoes fade with range: the far returns lose more than the near ones.
    def share(p, lo, hi):
        r = np.linalg.norm(p[:, :3], axis=1)
        return ((r > lo) & (r <= hi)).sum()

    assert share(real, 40, 80) / share(random_only, 40, 80) < share(real, 0, 20) / share(random_only, 0, 20)


def test_vehicle_size_distributions():
    rng = np.random.default_rng(0)
    cars = sample_sizes(("car",) * 4000, rng)
    np.testing.assert_allclose(cars.mean(0), [4.5, 1.85, 1.5], atol=0.03)
    np.testing.assert_allclose(cars.std(0), [0.4, 0.1, 0.1], rtol=0.1)
    trucks = sample_sizes(("truck",) * 500, rng)
    assert trucks[:, 0].min() >= 8.0 and trucks[:, 0].max() <= 11.0
    np.testing.assert_allclose(sample_sizes(("van",) * 1000, rng).mean(0), [5.2, 2.0, 2.1], atol=0.05)


def test_town_is_built_from_all_static_classes():
    spec = domain_spec("source")
    town = build_town(spec.town, np.random.default_rng(0))
    assert set(np.unique(town.tri_class)) == {SEMANTIC_CODE[c] for c in ("ground", "road", "building", "vegetation", "pole")}
    assert town.vertices.dtype == np.float32 and town.triangles.max() < len(town.vertices)
    assert 2 <= len(town.road_x) <= 3 and 2 <= len(town.road_y) <= 3
    assert np.isclose(town.vertices[:, 2], spec.town.kerb_height).any()  # raised sidewalks
    assert len(town.parked_labels) > 5


@pytest.mark.parametrize("kwargs, field", [
    ({"domain": "carla"}, "domain"),
    ({"n_agents": 0}, "n_agents"),
    ({"n_agents": 9}, "n_agents"),
    ({"n_frames": 0}, "n_frames"),
    ({"azimuth_step_deg": 0.0}, "azimuth_step_deg"),
    ({"azimuth_step_deg": float("nan")}, "azimuth_step_deg"),
    ({"seed": -1}, "seed"),
    ({"dt": -0.1}, "dt"),
    ({"comm_range": 10.0}, "comm_range"),
])
def test_bad_arguments_raise_typerror(kwargs, field):
    args = {"domain": "source", "seed": 0, "n_frames": 1, "n_agents": 2} | kwargs
    with pytest.raises(TypError) as info:
        simulate_scenario(**args)
    assert info.value.field == field
    if field == "domain":
        for name in DOMAINS:
            assert name in str(info.value)


def test_domain_spec_lookup():
    assert domain_spec("real_cav").sensor.n_beams == 32
    assert domain_spec("source", azimuth_step_deg=0.2).sensor.n_azimuths == 1800
    with pytest.raises(TypError, match="domain"):
        domain_spec("waymo")


def test_ego_is_the_agent_opencood_picks_on_disk(tmp_path):
    """OpenCOOD's ego is the agent folder that sorts first; the simulator's ego must be that one."""
    from typ.formats.opv2v import list_agents, write_scene

    for seed in range(6):
        scene = simulate_scenario(domain="real_cav", seed=seed, n_frames=1, n_agents=4, azimuth_step_deg=2.0,
                                  scenario=f"s{seed}")[0]
        ids = list(scene.agents)
        assert ids == sorted(ids, key=str)
        folder = write_scene(scene, tmp_path)
        assert list_agents(folder)[0] == scene.ego_id
