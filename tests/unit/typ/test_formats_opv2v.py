"""typ.formats.opv2v: OpenCOOD's box/pose conventions by hand, write -> read round trip, bad files."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from typ import geometry
from typ.errors import TypError
from typ.formats.opv2v import (list_agents, list_scenarios, list_timestamps, read_meta, read_scene,
                               write_scene)
from typ.formats.pcd import write_pcd
from typ.scene import AgentView, Scene

EXTENT = [2.0, 1.0, 0.75]


def _write_agent(scenario: Path, agent: str, doc: dict | str, timestamp="000068", n=20):
    folder = scenario / agent
    folder.mkdir(parents=True, exist_ok=True)
    text = doc if isinstance(doc, str) else yaml.safe_dump(doc)
    (folder / f"{timestamp}.yaml").write_text(text)
    pts = np.random.default_rng(0).uniform(-20, 20, (n, 4)).astype(np.float32)
    pts[:, 3] = 0.5
    write_pcd(folder / f"{timestamp}.pcd", pts)
    return folder / f"{timestamp}.yaml"


def test_boxes_in_lidar_frame_hand_worked(tmp_path):
    doc = {"lidar_pose": [10, 0, 0, 0, 90, 0],  # at (10, 0, 0) facing world +y
           "vehicles": {7: {"location": [10, 5, 0], "center": [0, 0, 0.5], "angle": [0, 90, 0], "extent": EXTENT},
                        8: {"location": [10, -3, 0], "center": [0, 0, 0], "angle": [0, 120, 0], "extent": EXTENT,
                            "obj_type": "Truck"}},
           "ego_speed": 3.5}
    _write_agent(tmp_path / "s", "1", doc)
    view = read_scene(tmp_path / "s", "000068").ego
    # vehicle 7 is 5 m ahead, its centre lifted by center z = 0.5, same heading
    # vehicle 8 is 3 m behind, turned 30 deg left of the LiDAR's heading
    np.testing.assert_allclose(view.boxes, [[5, 0, 0.5, 4, 2, 1.5, 0], [-3, 0, 0, 4, 2, 1.5, np.radians(30)]],
                               atol=1e-12)
    assert view.box_labels == ("car", "truck")  # OPV2V has no obj_type: cars
    np.testing.assert_array_equal(view.box_ids, [7, 8])
    np.testing.assert_allclose(view.pose, geometry.pose_to_matrix([10, 0, 0, 0, 90, 0]))
    assert read_meta(tmp_path / "s", "1", "000068") == {"ego_speed": 3.5}


def test_tilted_vehicle_follows_x1_to_x2(tmp_path):
    lidar = [3.0, -7.0, 1.9, 1.0, 10.0, 2.0]
    loc, center, angle = [30.0, 4.0, 0.2], [0.1, -0.2, 0.7], [2.0, 45.0, -3.0]
    _write_agent(tmp_path / "s", "1", {"lidar_pose": lidar, "vehicles": {
        5: {"location": loc, "center": center, "angle": angle, "extent": EXTENT}}})
    box = read_scene(tmp_path / "s", "000068").ego.boxes[0]
    object_to_lidar = geometry.relative_transform(np.r_[np.add(loc, center), angle], lidar)
    np.testing.assert_allclose(box[:3], object_to_lidar[:3, 3], atol=1e-9)
    heading = object_to_lidar[:3, 0]
    assert box[6] == pytest.approx(np.arctan2(heading[1], heading[0]), abs=1e-12)
    np.testing.assert_allclose(box[3:6], 2 * np.array(EXTENT))


def _scene(with_own_box=False) -> Scene:
    rng = np.random.default_rng(7)
    agents = {}
    for agent, pose, other in (("641", [10, -5, 1.9, 0.5, 30, -1.2], 650),
                               ("650", [40, 12, 1.8, -0.3, -150, 0.8], 641)):
        k = 4
        boxes = np.c_[rng.uniform(-40, 40, (k, 2)), rng.uniform(-1, 1, k),
                      rng.uniform(1, 6, (k, 3)), rng.uniform(-np.pi, np.pi, k)]
        ids = [1001, 1002, 1003, other]
        if with_own_box:
            ids[0] = int(agent)
        pts = np.c_[rng.uniform(-60, 60, (300, 3)), rng.uniform(0, 1, 300)].astype(np.float32)
        agents[agent] = AgentView(agent_id=agent, points=pts, pose=geometry.pose_to_matrix(pose), boxes=boxes,
                                  box_labels=("car", "van", "truck", "car"), box_ids=ids,
                                  semantics=rng.integers(0, 6, 300).astype(np.uint8) if agent == "641" else None)
    return Scene(scenario="2021_08_16_22_26_54", timestamp="000068", agents=agents, dataset="sim", split="train")


def test_write_read_round_trip(tmp_path):
    scene = _scene()
    meta = {"641": {"ego_speed": 12.5, "true_ego_pos": [10, -5, 0, 0, 30, 0], "sensor": "carla-64"}}
    folder = write_scene(scene, tmp_path, meta=meta)
    assert folder == tmp_path / scene.scenario
    assert sorted(p.name for p in (folder / "641").iterdir()) == ["000068.pcd", "000068.yaml"]
    assert list_scenarios(tmp_path) == [folder] and list_timestamps(folder) == ["000068"]
    back = read_scene(folder, "000068", dataset="sim", split="train")
    assert list(back.agents) == ["641", "650"] and back.ego_id == "641"
    assert (back.scenario, back.timestamp, back.dataset, back.split) == (scene.scenario, "000068", "sim", "train")
    for agent, want in scene.agents.items():
        got = back.agents[agent]
        np.testing.assert_array_equal(got.points[:, :3], want.points[:, :3])
        assert np.abs(got.points[:, 3] - want.points[:, 3]).max() <= 1 / 255
        np.testing.assert_allclose(got.pose, want.pose, atol=1e-9)
        np.testing.assert_allclose(got.boxes[:, :6], want.boxes[:, :6], atol=1e-6)
        np.testing.assert_allclose(geometry.wrap_angle(got.boxes[:, 6] - want.boxes[:, 6]), 0, atol=1e-6)
        assert got.box_labels == want.box_labels
        np.testing.assert_array_equal(got.box_ids, want.box_ids)
        if want.semantics is None:
            assert got.semantics is None
        else:
            np.testing.assert_array_equal(got.semantics, want.semantics)
    assert read_meta(folder, "641", "000068") == meta["641"]
    # writing into the scenario folder itself lands in the same place
    assert write_scene(scene, folder) == folder


def test_upright_lidar_writes_yaw_only_angles(tmp_path):
    view = AgentView(agent_id="1", points=np.zeros((1, 4), np.float32),
                     pose=geometry.pose_to_matrix([5, 6, 1.7, 0, 20, 0]),
                     boxes=[[10, 0, 0, 4, 2, 1.5, np.radians(15)]], box_labels=("car",), box_ids=[3])
    folder = write_scene(Scene("s", "000001", {"1": view}), tmp_path)
    vehicle = yaml.safe_load((folder / "1" / "000001.yaml").read_text())["vehicles"][3]
    np.testing.assert_allclose(vehicle["angle"], [0, 35, 0], atol=1e-12)
    np.testing.assert_allclose(vehicle["extent"], [2, 1, 0.75])
    assert vehicle["center"] == [0.0, 0.0, 0.0] and vehicle["obj_type"] == "car"


def test_own_vehicle_is_not_written(tmp_path):
    folder = write_scene(_scene(with_own_box=True), tmp_path)
    back = read_scene(folder, "000068")
    assert 641 not in back.agents["641"].box_ids and 650 not in back.agents["650"].box_ids
    assert len(back.agents["641"].boxes) == 3


def test_agent_order_rsu_last_and_hidden_skipped(tmp_path):
    for name in ("650", "-1", "1000", "641", ".tmp-650.x"):
        (tmp_path / name).mkdir()
    assert list_agents(tmp_path) == ["1000", "641", "650", "-1"]  # string order, as OpenCOOD sorts


def test_timestamps_skip_additional_files(tmp_path):
    for name in ("000070.yaml", "000068.yaml", "000068_additional.yaml", "000068.pcd"):
        (tmp_path / "1").mkdir(exist_ok=True)
        (tmp_path / "1" / name).write_text("")
    assert list_timestamps(tmp_path) == ["000068", "000070"]


def test_scientific_notation_is_a_number(tmp_path):
    _write_agent(tmp_path / "s", "1", "lidar_pose: [1e-3, 0, 0, 0, 0, 0]\nvehicles: {}\n")
    assert read_scene(tmp_path / "s", "000068").ego.pose[0, 3] == pytest.approx(1e-3)


GOOD = {"lidar_pose": [0, 0, 0, 0, 0, 0],
        "vehicles": {7: {"location": [5, 0, 0], "center": [0, 0, 0], "angle": [0, 0, 0], "extent": EXTENT}}}


def _bad(tmp_path, doc, field, *fragments, agent="1"):
    yaml_path = _write_agent(tmp_path / "s", agent, doc)
    with pytest.raises(TypError) as info:
        read_scene(tmp_path / "s", "000068")
    err = info.value
    assert err.where == str(yaml_path) and err.field == field, str(err)
    for fragment in fragments:
        assert fragment in str(err), str(err)


def test_missing_lidar_pose(tmp_path):
    _bad(tmp_path, {"vehicles": {}}, "lidar_pose", "missing")


def test_wrong_length_pose(tmp_path):
    _bad(tmp_path, {**GOOD, "lidar_pose": [1, 2, 3, 4, 5]}, "lidar_pose", "6 numbers")


def test_non_numeric_location(tmp_path):
    doc = {**GOOD, "vehicles": {7: {**GOOD["vehicles"][7], "location": ["a", 0, 0]}}}
    _bad(tmp_path, doc, "vehicles.7.location", "3 numbers")


def test_missing_vehicles_and_bad_extent(tmp_path):
    _bad(tmp_path, {"lidar_pose": GOOD["lidar_pose"]}, "vehicles", "missing")
    doc = {**GOOD, "vehicles": {7: {**GOOD["vehicles"][7], "extent": [2, 0, 1]}}}
    _bad(tmp_path, doc, "vehicles.7.extent", "positive")


def test_non_integer_vehicle_id(tmp_path):
    _bad(tmp_path, {**GOOD, "vehicles": {"car7": GOOD["vehicles"][7]}}, "vehicles.car7", "integer")


def test_malformed_yaml(tmp_path):
    _bad(tmp_path, "lidar_pose: [1, 2\nvehicles: {}\n", "yaml", "well-formed", "line")
    _bad(tmp_path, "- just\n- a list\n", "yaml", "mapping")


def test_missing_pcd(tmp_path):
    yaml_path = _write_agent(tmp_path / "s", "1", GOOD)
    yaml_path.with_suffix(".pcd").unlink()
    with pytest.raises(TypError) as info:
        read_scene(tmp_path / "s", "000068")
    assert info.value.where == str(yaml_path.with_suffix(".pcd")) and info.value.field == "pcd"


def test_missing_yaml_for_an_agent(tmp_path):
    _write_agent(tmp_path / "s", "1", GOOD)
    (tmp_path / "s" / "2").mkdir()
    with pytest.raises(TypError) as info:
        read_scene(tmp_path / "s", "000068")
    assert info.value.where == str(tmp_path / "s" / "2" / "000068.yaml") and info.value.field == "yaml"


def test_bad_meta_and_names(tmp_path):
    with pytest.raises(TypError, match="meta"):
        write_scene(_scene(), tmp_path, meta={"641": {"speed": 3}})
    scene = _scene()
    scene.timestamp = "../x"
    with pytest.raises(TypError, match="timestamp"):
        write_scene(scene, tmp_path)
    assert not list(tmp_path.iterdir())


def test_timestamps_of_different_lengths_are_in_time_order(tmp_path):
    """OPV2V's stamps are zero-padded (``000068``), where string and time order agree; a scenario
    stamped ``9``, ``10``, ``100`` (a user's own layout) is listed in time order, not as strings
    ("10" < "100" < "9"), so that a delay of one frame is the frame before."""
    (tmp_path / "1").mkdir()
    for name in ("10.yaml", "9.yaml", "100.yaml", "000011.yaml", "9_additional.yaml"):
        (tmp_path / "1" / name).write_text("")
    assert list_timestamps(tmp_path) == ["9", "10", "000011", "100"]
