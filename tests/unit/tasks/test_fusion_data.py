"""The collaborative sample loader (tasks/fusion_data.py): OpenCOOD's conventions on hand-made scenes."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from tasks.fusion_data import FusionDataset, boxes_in_range, mask_ego_points, noisy_pose
from typ.errors import TypError
from typ.formats.opv2v import write_scene
from typ.geometry import invert, pose_to_matrix, transform_boxes, transform_points
from typ.scene import AgentView, Scene

RANGE = (-50.0, -30.0, -3.0, 50.0, 30.0, 1.0)
EGO, NEAR, FAR = "100", "200", "300"
#: world boxes [x, y, z, l, w, h, yaw] on the ground (z = 0) by id; 100/200/300 are the agents' own cars
WORLD = {7: [20.0, 4.0, 0.75, 4.5, 1.8, 1.5, 0.3],       # seen by the ego and by NEAR: one gt
         8: [45.0, 10.0, 0.75, 4.0, 1.7, 1.5, 1.0],      # NEAR's only
         9: [120.0, 0.0, 0.75, 4.0, 1.7, 1.5, 0.0],      # FAR's only, and FAR is out of range
         10: [95.0, 2.0, 0.75, 4.0, 1.7, 1.5, 0.0],      # NEAR's, but outside the detection range
         100: [0.0, 0.0, 0.75, 4.6, 1.9, 1.5, 0.0], 200: [30.0, -3.0, 0.75, 4.6, 1.9, 1.5, 0.0],
         300: [95.0, 0.0, 0.75, 4.6, 1.9, 1.5, 0.0]}
LABELLED = {EGO: [7, 200, 300], NEAR: [7, 8, 10, 100], FAR: [9, 100, 200]}


def _poses(frame: int) -> dict[str, list[float]]:
    """Sensor poses [x, y, z, roll, yaw, pitch]; agents move 1 m a frame along x, yaws differ."""
    return {EGO: [1.0 * frame, 0.0, 1.8, 0.0, 10.0, 0.0], NEAR: [30.0 + frame, -3.0, 1.8, 0.0, 170.0, 0.0],
            FAR: [95.0 + frame, 0.0, 1.8, 0.0, -45.0, 0.0]}


def _cloud(agent: str, frame: int) -> np.ndarray:
    """A few points whose values say whose and which frame they are; one on the sensor's own car."""
    rng = np.random.default_rng([int(agent), frame])
    pts = np.c_[rng.uniform(-40, 40, (50, 2)), rng.uniform(-2, 0, 50), np.full(50, frame / 10)]
    pts[0, :2] = [0.5, 0.3]                                   # hits its own roof: dropped by the loader
    return pts.astype(np.float32)


def _same_cloud(actual: np.ndarray, expected: np.ndarray) -> None:
    """xyz exactly (float32 in the pcd), intensity to the pcd's 8 bits."""
    np.testing.assert_array_equal(actual[:, :3], expected[:, :3])
    np.testing.assert_allclose(actual[:, 3], expected[:, 3], atol=1 / 255)


def _write(root, *, frames: int = 3, scenario: str = "s0", clouds=_cloud, poses=_poses) -> None:
    for f in range(frames):
        agents = {}
        for agent, pose in poses(f).items():
            m = pose_to_matrix(pose)
            ids = LABELLED[agent]
            world = np.array([WORLD[i] for i in ids], dtype=np.float64)
            world[:, 0] += f                                    # traffic moves too
            agents[agent] = AgentView(agent_id=agent, points=clouds(agent, f), pose=m,
                                      boxes=transform_boxes(invert(m), world), box_labels=("car",) * len(ids),
                                      box_ids=np.array(ids))
        write_scene(Scene(scenario=scenario, timestamp=f"{f:06d}", agents=agents), root)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    r = tmp_path_factory.mktemp("split")
    _write(r)
    return r


def _x_to_world(pose):
    """OpenCOOD ``transformation_utils.x_to_world``, written out here independently of typ.geometry."""
    x, y, z, roll, yaw, pitch = pose
    c_y, s_y = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    c_r, s_r = np.cos(np.radians(roll)), np.sin(np.radians(roll))
    c_p, s_p = np.cos(np.radians(pitch)), np.sin(np.radians(pitch))
    m = np.identity(4)
    m[0, 3], m[1, 3], m[2, 3] = x, y, z
    m[0, 0], m[0, 1], m[0, 2] = c_p * c_y, c_y * s_p * s_r - s_y * c_r, -c_y * s_p * c_r - s_y * s_r
    m[1, 0], m[1, 1], m[1, 2] = s_y * c_p, s_y * s_p * s_r + c_y * c_r, -s_y * s_p * c_r + c_y * s_r
    m[2, 0], m[2, 1], m[2, 2] = s_p, -c_p * s_r, c_p * c_r
    return m


def _x1_to_x2(x1, x2):
    return np.dot(np.linalg.inv(_x_to_world(x2)), _x_to_world(x1))


def test_ego_and_agents_in_communication_range(root):
    ds = FusionDataset(root, lidar_range=RANGE)
    assert len(ds) == 3
    s = ds[1]
    assert (s.scenario, s.timestamp, s.agent_ids) == ("s0", "000001", (EGO, NEAR))   # FAR is 95 m away
    assert FusionDataset(root, lidar_range=RANGE, comm_range=100.0)[1].agent_ids == (EGO, NEAR, FAR)
    assert FusionDataset(root, lidar_range=RANGE, comm_range=20.0)[1].agent_ids == (EGO,)
    assert FusionDataset(root, lidar_range=RANGE, comm_range=100.0, max_agents=2)[1].agent_ids == (EGO, NEAR)


def test_transforms_are_float64_and_opencoods_x1_to_x2(root):
    s = FusionDataset(root, lidar_range=RANGE, comm_range=100.0)[2]
    assert s.transforms.dtype == np.float64 and s.transforms.shape == (3, 4, 4)
    np.testing.assert_array_equal(s.transforms[0], np.eye(4))
    for k, agent in enumerate(s.agent_ids):
        np.testing.assert_allclose(s.transforms[k], _x1_to_x2(_poses(2)[agent], _poses(2)[EGO]), atol=1e-12)
    np.testing.assert_allclose(s.true_transforms, s.transforms, atol=1e-12)
    # a world point seen by NEAR lands where the ego sees it
    world = np.array([[12.0, 7.0, -1.0, 0.0]])
    in_near = transform_points(invert(pose_to_matrix(_poses(2)[NEAR])), world)
    in_ego = transform_points(invert(pose_to_matrix(_poses(2)[EGO])), world)
    np.testing.assert_allclose(transform_points(s.transforms[1], in_near), in_ego, atol=1e-9)


def test_gt_is_the_union_of_agents_in_range_by_id_in_the_ego_frame(root):
    s = FusionDataset(root, lidar_range=RANGE)[0]
    # ego: 7, 200 (300 is outside the range); NEAR adds 8 and the ego's own car 100; 10 is out of range;
    # 9 only FAR labels, and FAR is out of communication range
    assert s.gt_ids.tolist() == [7, 200, 8, 100]
    ego_pose = pose_to_matrix(_poses(0)[EGO])
    expected = transform_boxes(invert(ego_pose), np.array([WORLD[i] for i in s.gt_ids.tolist()]))
    np.testing.assert_allclose(s.gt_boxes, expected, atol=1e-9)
    assert s.gt_boxes.dtype == np.float64
    # own labels stay in each agent's frame, restricted to the range
    near = pose_to_matrix(_poses(0)[NEAR])
    np.testing.assert_allclose(s.agent_boxes[1], transform_boxes(invert(near), np.array([WORLD[i] for i in (7, 8, 100)])),
                               atol=1e-9)
    # a wider comm range brings FAR's label of 9, still clipped by the detection range -> not in gt
    wide = FusionDataset(root, lidar_range=(-130.0, -30.0, -3.0, 130.0, 30.0, 1.0), comm_range=100.0)[0]
    assert sorted(wide.gt_ids.tolist()) == [7, 8, 9, 10, 100, 200, 300]


def test_boxes_in_range_needs_all_corners_inside():
    boxes = np.array([[0, 0, -1, 4, 2, 1.5, 0], [48.5, 0, -1, 4, 2, 1.5, 0], [47.9, 0, -1, 4, 2, 1.5, 0],
                      [47.9, 0, -1, 4, 2, 1.5, np.pi / 2], [0, 0, 0.5, 4, 2, 1.5, 0]])
    assert boxes_in_range(boxes, RANGE).tolist() == [True, False, True, True, False]
    assert boxes_in_range(np.zeros((0, 7)), RANGE).shape == (0,)


def test_points_on_the_own_car_are_dropped(root):
    s = FusionDataset(root, lidar_range=RANGE)[0]
    assert [len(c) for c in s.clouds] == [49, 49]
    assert mask_ego_points(np.array([[1.9, -1.0, 0, 0], [2.0, 0, 0, 0], [0, 1.2, 0, 0]], np.float32)).shape == (2, 4)


def test_delay_takes_cooperating_agents_from_earlier_frames(root):
    ds = FusionDataset(root, lidar_range=RANGE, delay_frames=1)
    assert [x.timestamp for x in ds] == ["000001", "000002"]
    s = ds[1]
    _same_cloud(s.clouds[0], mask_ego_points(_cloud(EGO, 2)))                          # the ego is never late
    _same_cloud(s.clouds[1], mask_ego_points(_cloud(NEAR, 1)))
    assert s.time_delay.tolist() == [0, 1]
    np.testing.assert_allclose(s.transforms[1], _x1_to_x2(_poses(1)[NEAR], _poses(2)[EGO]), atol=1e-12)
    np.testing.assert_allclose(s.true_transforms[1], _x1_to_x2(_poses(2)[NEAR], _poses(2)[EGO]), atol=1e-12)
    current = FusionDataset(root, lidar_range=RANGE)[2]
    np.testing.assert_array_equal(s.gt_boxes, current.gt_boxes)                      # gt: the current frame
    np.testing.assert_allclose(s.agent_boxes[1], transform_boxes(
        invert(pose_to_matrix(_poses(1)[NEAR])), np.array([WORLD[i] for i in (7, 8, 100)]) + [1, 0, 0, 0, 0, 0, 0]),
        atol=1e-9)                                                                   # own labels: the sent frame


def test_delay_is_never_clamped_at_the_sequence_start(root):
    """Defect 3: OpenCOOD clamps at frame 0, so on 3-frame scenes "200 ms" averaged 100 ms. Only
    frames t >= delay are samples, and every message is exactly that old."""
    ds = FusionDataset(root, lidar_range=RANGE, delay_frames=2)
    assert [s.timestamp for s in ds] == ["000002"]
    assert ds[0].time_delay.tolist() == [0, 2]
    _same_cloud(ds[0].clouds[1], mask_ego_points(_cloud(NEAR, 0)))
    # several delays scored on the same frames
    same = [FusionDataset(root, lidar_range=RANGE, delay_frames=d, first_frame=2) for d in (0, 1, 2)]
    assert [[s.timestamp for s in d] for d in same] == [["000002"]] * 3
    assert [d[0].time_delay.tolist() for d in same] == [[0, 0], [0, 1], [0, 2]]
    assert [s.timestamp for s in ds.with_options(delay_frames=1)] == ["000001", "000002"]
    with pytest.raises(TypError) as err:
        FusionDataset(root, lidar_range=RANGE, delay_frames=3)               # no frame is that late
    assert err.value.field == "delay_frames"


def test_cooperating_labels_are_cut_to_the_generated_extent(root, tmp_path):
    """Generated clouds cover +-extent around their agent: labels beyond it are not learned from.
    NEAR (at x = 30 + t) labels car 8 (45 m, 13 m from it) and car 10 (95 m, 65 m from it)."""
    full = FusionDataset(root, lidar_range=(-100.0, -30.0, -3.0, 100.0, 30.0, 1.0))
    cut = full.with_options(cav_extent=40.0)
    a, b = full[0], cut[0]
    assert 10 in a.gt_ids and 10 not in b.gt_ids and 8 in b.gt_ids
    assert len(b.agent_boxes[1]) == len(a.agent_boxes[1]) - 1
    np.testing.assert_array_equal(a.agent_boxes[0], b.agent_boxes[0])            # the ego's are whole
    assert set(a.gt_ids) - set(b.gt_ids) == {10}


def test_pose_noise_has_the_asked_spread_and_spares_the_ego(root):
    rng = np.random.default_rng(0)
    pose = pose_to_matrix([5.0, -2.0, 1.8, 0.0, 30.0, 0.0])
    draws = np.stack([noisy_pose(pose, rng, 0.2, 0.8) for _ in range(4000)])
    dxy = draws[:, :2, 3] - pose[:2, 3]
    dyaw = np.degrees(np.arctan2(draws[:, 1, 0], draws[:, 0, 0])) - 30.0
    np.testing.assert_allclose(dxy.std(0), [0.2, 0.2], rtol=0.06)
    np.testing.assert_allclose(dxy.mean(0), [0, 0], atol=0.02)
    assert dyaw.std() == pytest.approx(0.8, rel=0.06) and abs(dyaw.mean()) < 0.04
    np.testing.assert_array_equal(draws[:, 2, 3], pose[2, 3])                        # z, roll, pitch untouched
    np.testing.assert_allclose(draws[:, 2, :3], np.tile(pose[2, :3], (4000, 1)), atol=1e-12)

    clean = FusionDataset(root, lidar_range=RANGE)
    noisy = clean.with_options(position_std=0.4, heading_std_deg=0.8, seed=3)
    for i in range(len(clean)):
        a, b = clean[i], noisy[i]
        np.testing.assert_array_equal(b.transforms[0], np.eye(4))
        np.testing.assert_array_equal(a.gt_boxes, b.gt_boxes)
        np.testing.assert_array_equal(a.true_transforms, b.true_transforms)
        assert not np.allclose(a.transforms[1], b.transforms[1])
    again = clean.with_options(position_std=0.4, heading_std_deg=0.8, seed=3)
    np.testing.assert_array_equal(noisy[1].transforms, again[1].transforms)
    other = clean.with_options(position_std=0.4, heading_std_deg=0.8, seed=4)
    assert not np.array_equal(noisy[1].transforms, other[1].transforms)


def test_cav_root_replaces_the_cooperating_clouds_only(root, tmp_path):
    generated = tmp_path / "generated"
    _write(generated, clouds=lambda agent, frame: _cloud(agent, frame)[:10] * 2)
    real = FusionDataset(root, lidar_range=RANGE)
    mixed = FusionDataset(root, lidar_range=RANGE, cav_root=generated)
    for i in range(len(real)):
        a, b = real[i], mixed[i]
        np.testing.assert_array_equal(a.clouds[0], b.clouds[0])
        _same_cloud(b.clouds[1], mask_ego_points(_cloud(NEAR, i)[:10] * 2))
        np.testing.assert_array_equal(a.transforms, b.transforms)
        np.testing.assert_array_equal(a.gt_boxes, b.gt_boxes)

    shutil.rmtree(generated / "s0" / NEAR)
    with pytest.raises(TypError, match="cav_root"):
        FusionDataset(root, lidar_range=RANGE, cav_root=generated)[0]
    moved = tmp_path / "moved"
    _write(moved, poses=lambda f: {**_poses(f), NEAR: [31.0 + f, -3.0, 1.8, 0.0, 170.0, 0.0]})
    with pytest.raises(TypError, match="lidar_pose"):
        FusionDataset(root, lidar_range=RANGE, cav_root=moved)[0]


@pytest.mark.parametrize("kwargs, field", [
    ({"lidar_range": (0, 0, 0, 1, 1)}, "lidar_range"),
    ({"lidar_range": (5, -1, -1, 1, 1, 1)}, "lidar_range"),
    ({"comm_range": 0.0}, "comm_range"),
    ({"delay_frames": -1}, "delay_frames"),
    ({"delay_frames": 1.5}, "delay_frames"),
    ({"position_std": -0.1}, "position_std"),
    ({"heading_std_deg": float("nan")}, "heading_std_deg"),
    ({"max_scenarios": 0}, "max_scenarios"),
    ({"first_frame": -1}, "first_frame"),
    ({"cav_extent": 0.0}, "cav_extent"),
    ({"min_points": -1}, "min_points"),
    ({"cav_root": "/nonexistent/typ"}, "cav_root"),
])
def test_bad_arguments_raise_typerror(root, kwargs, field):
    with pytest.raises(TypError) as err:
        FusionDataset(root, **{"lidar_range": RANGE, **kwargs})
    assert err.value.field == field


def test_bad_folders_raise_typerror(root, tmp_path):
    with pytest.raises(TypError):
        FusionDataset(tmp_path / "missing", lidar_range=RANGE)
    (tmp_path / "empty").mkdir()
    with pytest.raises(TypError, match="scenario"):
        FusionDataset(tmp_path / "empty", lidar_range=RANGE)
    broken = tmp_path / "broken"
    shutil.copytree(root, broken)
    (broken / "s0" / NEAR / "000001.yaml").write_text("lidar_pose: [1, 2]\nvehicles: {}\n")
    ds = FusionDataset(broken, lidar_range=RANGE)
    with pytest.raises(TypError) as err:
        ds[1]
    assert err.value.field == "lidar_pose" and "000001.yaml" in err.value.where
    with pytest.raises(IndexError):
        ds[3]


def test_labels_need_points_of_the_true_clouds(tmp_path):
    """min_points: a vehicle is ground truth when the agents' true clouds put that many points in
    its box (the ego: 5 points in car 7; NEAR: 3 in car 8; nobody sees the others)."""
    def clouds(agent, frame):
        pts = _cloud(agent, frame)
        pts = pts[(np.abs(pts[:, 0]) > 1) | (np.abs(pts[:, 1]) > 1)][:5]           # a few far points
        pose = pose_to_matrix(_poses(frame)[agent])
        car = {EGO: 7, NEAR: 8}.get(agent)
        if car is None:
            return pts
        centre = np.array(WORLD[car][:3]) + [frame, 0, 0]
        local = transform_points(invert(pose), np.tile(centre, (5 if agent == EGO else 3, 1)))
        return np.concatenate([pts, np.c_[local[:, :3] + 0.1, np.zeros(len(local))]]).astype(np.float32)

    _write(tmp_path, clouds=clouds)
    every = FusionDataset(tmp_path, lidar_range=RANGE)
    seen = every.with_options(min_points=1)
    for a, b in zip(every, seen):
        assert set(b.gt_ids) == {7, 8} < set(a.gt_ids)
        assert len(b.agent_boxes[0]) == 1 and len(b.agent_boxes[1]) == 1            # ego: car 7; NEAR: car 8
    many = every.with_options(min_points=4)
    assert set(many[0].gt_ids) == {7} and len(many[0].agent_boxes[1]) == 0
