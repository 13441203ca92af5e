"""Box edits for `typ edit`, and single-agent frames from real datasets written for `generate`."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tasks.edit import BoxEdit, edit_boxes, footprint_mask
from tasks.generate import candidate_ids, new_skip_counts
from typ.scene import VEHICLE_LABELS
from tasks.ingest import read_frames, to_sensor_frame, write_single_agent
from typ.config import config_from_dict
from typ.errors import TypError
from typ.formats.opv2v import list_agents, list_timestamps, read_scene, scenario_sensor
from typ.geometry import pose_to_matrix
from typ.scene import AgentView, Scene
from typ.resim import in_mask
from typ.voxel import Grid
from repo_paths import SHARED_DATA

GRID = Grid((-51.2, 51.2), (-51.2, 51.2), (-3.0, 1.0), (128, 128, 8))
DATA = SHARED_DATA


def _view():
    boxes = np.array([[10.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0],
                      [-15.0, 5.0, -1.2, 4.5, 1.9, 1.5, np.pi / 2],
                      [20.0, -8.0, -0.9, 0.6, 0.6, 1.7, 0.0]])
    pts = np.array([[10.0, 0.0, -1.0, 0.3], [10.5, 0.5, -0.5, 0.3], [-30.0, 0.0, -2.0, 0.1]], dtype=np.float32)
    return AgentView("7", pts, pose_to_matrix([5.0, 5.0, 2.0, 0.0, 10.0, 0.0]), boxes,
                     ("car", "truck", "pedestrian"), np.array([3, 4, 9]))


def test_edit_boxes_remove_move_add():
    view = _view()
    edited, old, new = edit_boxes(view, BoxEdit(remove=(3,), move={4: (2.0, -1.0, np.pi)}, add=((0.0, 20.0, 0.5),)))
    assert list(edited.box_ids) == [4, 9, 10] and edited.box_labels == ("truck", "pedestrian", "car")
    assert np.allclose(edited.boxes[0, :2], [-13.0, 4.0]) and np.isclose(edited.boxes[0, 6], -np.pi / 2)
    added = edited.boxes[2]
    assert np.allclose(added[[0, 1, 6]], [0.0, 20.0, 0.5]) and np.allclose(added[3:6], [4.5, 1.85, 1.5])
    assert np.isclose(added[2], np.median(view.boxes[:, 2]))  # stands on the same road as the labelled boxes
    assert len(old) == 2 and len(new) == 2  # removed + moved-from; moved-to + added
    with pytest.raises(TypError, match="box id"):
        edit_boxes(view, BoxEdit(remove=(42,)))
    with pytest.raises(TypError, match="--add"):
        edit_boxes(view, BoxEdit(add=((1.0, 2.0),)))


def test_footprint_cells_cover_the_box_and_only_its_neighbourhood():
    box = np.array([[10.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0]])
    mask = footprint_mask(box, GRID, margin=1.0)
    pts = np.array([[10.0, 0.0, 0.0], [12.5, 1.5, 0.0], [14.0, 0.0, 0.0], [10.0, 3.0, 0.0], [-40, -40, 0], [90, 0, 0]])
    assert list(in_mask(pts, mask, GRID)) == [True, True, False, False, False, False]
    # 6 x 4 m with the margin at 0.8 m cells: about 7.5 x 5 cells (box_map's edge slack aside)
    assert 30 <= mask.sum() <= 60


def test_only_vehicles_can_carry_a_reference_sensor():
    cfg = config_from_dict({"generate": {"min_distance": 1.0, "max_distance": 45.0}}).generate
    skipped = new_skip_counts()
    assert candidate_ids(_view(), cfg, skipped) == {3, 4}  # the pedestrian is not a candidate
    assert skipped["reference_too_close"] == skipped["reference_out_of_range"] == 0
    assert {"car", "van", "truck", "vehicle"} <= VEHICLE_LABELS


def test_vehicle_frame_to_sensor_frame_keeps_world_geometry():
    view = _view()
    scene = Scene("s", "000000", {"7": view})
    lifted = to_sensor_frame(scene, 2.2).ego
    world = lambda v, p: (v.pose @ np.append(p[:3].astype(np.float64), 1.0))[:3]  # noqa: E731
    for a, b in zip(view.points, lifted.points):
        assert np.allclose(world(view, a), world(lifted, b), atol=1e-5)
    assert np.allclose(lifted.boxes[:, 2], view.boxes[:, 2] - 2.2)


@pytest.mark.skipif(not (DATA / "kitti_object_vis").is_dir(), reason="../shared/data not present")
def test_kitti_frames_become_single_agent_opv2v_scenarios(tmp_path):
    scenarios = read_frames("kitti", DATA / "kitti_object_vis")
    assert [s.name for s in scenarios] == ["kitti_training_000000", "kitti_training_000001"]
    folders = write_single_agent(scenarios, tmp_path)
    for scenario, folder in zip(scenarios, folders):
        assert list_agents(folder) == ["ego"] and list_timestamps(folder) == ["000000"]
        assert scenario_sensor(folder) == "kitti"          # the LiDAR, for its mount height downstream
        back = read_scene(folder, "000000").ego
        src = next(iter(scenario)).ego
        assert back.points.shape == src.points.shape
        assert np.allclose(back.points[:, :3], src.points[:, :3], atol=1e-5)
        assert np.allclose(back.boxes, src.boxes, atol=1e-5) and back.box_labels == src.box_labels
    with pytest.raises(TypError, match="--format"):
        read_frames("lyft", DATA)
    with pytest.raises(TypError, match="none found"):
        read_frames("kitti", tmp_path)


class _BoxFollowingPipe:
    """Stands in for the diffusion model: ground everywhere, a car in every box of y_r.

    It makes the edit's plumbing observable: an added box can only appear, and a removed one
    only vanish, if edit_view conditions on the *edited* box map. Its points are the real
    pipeline's (one point per voxel, spread inside it).
    """

    conditions = 0

    @property
    def point_stats(self):
        from pipelines.typ.pipeline_typ import PointStats

        return PointStats.single()

    def occupancy(self, x_e, y_r, *, seed, resim=None):
        occ = np.zeros((len(y_r), GRID.shape[2], *GRID.shape[:2]), dtype=bool)
        occ[:, 0] = True
        occ[:, 1:4] |= y_r[:, :1].astype(bool)
        return occ

    def points(self, occupancy, grid, seed):
        from pipelines.typ.pipeline_typ import PointStats, occupancy_to_points

        return occupancy_to_points(occupancy, grid, PointStats.single(), np.random.default_rng(seed))


def _generator():
    from tasks.generate import Generator

    return Generator(_BoxFollowingPipe(), {"kitti": 1.73}, digest="")


def test_edit_view_makes_occupancy_appear_and_disappear_in_the_edited_footprints(monkeypatch):
    import tasks.edit as edit_module
    from typ.voxel import voxelize

    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-50, 50, (20000, 2)), np.full(20000, -2.7), np.zeros(20000)]
    car = np.c_[rng.uniform(8.5, 11.5, (400, 1)), rng.uniform(-0.8, 0.8, (400, 1)), rng.uniform(-2.2, -1.0, (400, 1)),
                np.zeros((400, 1))]
    view = AgentView("1", np.concatenate([ground, car]).astype(np.float32), np.eye(4),
                     np.array([[10.0, 0.0, -1.6, 4.0, 2.0, 1.5, 0.0]]), ("car",), np.array([5]))
    added_at = (-20.0, 15.0, 0.0)
    result = edit_module.edit_view(view, BoxEdit(remove=(5,), add=(added_at,)), generator=_generator(), grid=GRID, seed=0)

    def above_ground(points, box):
        occ = voxelize(points, GRID)[:, :, 1:]
        return int(occ[footprint_mask(np.array([box]), GRID, margin=0.0)].sum())

    removed_box = view.boxes[0]
    added_box = result.view.boxes[-1]
    assert above_ground(view.points, removed_box) > 0 and above_ground(result.view.points, removed_box) == 0
    assert above_ground(view.points, added_box) == 0 and above_ground(result.view.points, added_box) > 0
    assert list(result.view.box_ids) == [6] and result.y_r[0][footprint_mask(np.array([added_box]), GRID, 0.0)].all()
    # the removed car's points are not in the conditioning cloud either
    assert not result.x_e[1:][:, footprint_mask(np.array([removed_box]), GRID, 0.0)].any()
    # outside the edited footprints every real point is kept as it was
    outside = ~in_mask(view.points, result.footprint, GRID)
    kept = result.view.points[~in_mask(result.view.points, result.footprint, GRID)]
    assert np.array_equal(np.sort(kept, axis=0), np.sort(view.points[outside], axis=0))
    with pytest.raises(TypError, match="at least one"):
        edit_module.edit_view(view, BoxEdit(), generator=_generator(), grid=GRID, seed=0)


def _scan_of(boxes: np.ndarray, sensor) -> np.ndarray:
    """(N, 4) what ``sensor`` sees of flat ground at its mount height and ``boxes``, cast by typ."""
    from typ.castview import cast, oriented_boxes_mesh

    ground = np.array([[0.0, 0.0, -sensor.mount_height - 0.05, 200.0, 200.0, 0.1, 0.0]])
    verts, tris = oriented_boxes_mesh(np.concatenate([ground, boxes]))
    xyz = cast(verts, tris, sensor, np.random.default_rng(0))
    return np.c_[xyz, np.zeros(len(xyz))].astype(np.float32)


def test_a_cast_edit_is_a_scan_of_the_views_lidar_and_hides_what_an_added_car_covers():
    import dataclasses

    import tasks.edit as edit_module
    from typ.config import CastConfig
    from typ.geometry import points_in_boxes
    from typ.sensors import on_beam_fractions
    from typ.sim.sensor import SensorSpec

    sensor = SensorSpec(name="edit", elevations_deg=tuple(np.linspace(-24.0, 2.0, 32)), max_range=80.0, min_range=1.0,
                        mount_height=2.7, range_noise_std=0.0, dropout=0.0, detection_energy=0.0,
                        intensity_model="attenuation", azimuth_step_deg=0.5)
    car = np.array([[10.0, 0.0, -1.95, 4.0, 2.0, 1.5, 0.0]])
    view = AgentView("1", _scan_of(car, sensor), np.eye(4), car, ("car",), np.array([5]))
    edit = BoxEdit(remove=(5,), add=((-20.0, 15.0, 0.0),))
    result = edit_module.edit_view(view, edit, generator=_generator(), grid=GRID, seed=0, compose="cast", sensor=sensor)
    added = result.view.boxes[-1]
    inside = in_mask(result.view.points, result.footprint, GRID)
    regenerated = result.view.points[inside]
    # the footprints are a scan of the view's LiDAR: every point on one of its beams
    assert len(regenerated) > 500 and on_beam_fractions(regenerated, sensor, (0.05,), min_range=1.0)[0.05] > 0.99
    # the added car is there (its returns on the box the edit placed), the removed one is gone
    grown = added.copy()
    grown[3:6] += 0.3
    assert points_in_boxes(regenerated, grown[None]).sum() > 50
    assert points_in_boxes(result.view.points, car + [0, 0, 0.2, 0, 0, 0, 0]).sum() == 0
    # outside the footprints: the real points, less those the added car hides from the sensor
    outside = view.points[~in_mask(view.points, result.footprint, GRID)]
    kept = result.view.points[~inside]
    scaled = added * np.r_[1, 1, 1, [CastConfig().label_boxes] * 3, 1]
    behind = edit_module.behind_boxes(outside, scaled[None])
    assert np.array_equal(kept, outside[~behind])

    def sight_lines_meet(grow: float) -> np.ndarray:   # samples every <= 0.18 m of each sight line
        box = scaled + np.r_[0, 0, 0, [grow] * 3, 0]
        along = np.linspace(0.0, 1.0, 400)[:, None, None] * outside[None, :, :3]
        return points_in_boxes(along.reshape(-1, 3), box[None]).reshape(400, -1).any(axis=0)

    surely, maybe = sight_lines_meet(-0.1), sight_lines_meet(0.4)
    assert surely.sum() > 20 and not (surely & ~behind).any() and not (behind & ~maybe).any()
    # points in the generated voxels instead: nothing outside the footprints changes
    plain = edit_module.edit_view(view, edit, generator=_generator(), grid=GRID, seed=0)
    assert len(plain.view.points[~in_mask(plain.view.points, plain.footprint, GRID)]) == len(outside)
    with pytest.raises(TypError, match="sensor"):
        edit_module.edit_view(view, edit, generator=_generator(), grid=GRID, seed=0, compose="cast")
    with pytest.raises(TypError, match="--compose"):
        edit_module.edit_view(view, edit, generator=_generator(), grid=GRID, seed=0, compose="hybrid")
    assert dataclasses.replace(CastConfig(), carve=True).carve   # the default casts with carving; an edit does not


def test_edit_figure_shows_before_after_and_the_changed_cells(monkeypatch):
    import tasks.edit as edit_module
    from typ import viz
    from typ.voxel import voxelize

    rng = np.random.default_rng(0)
    ground = np.c_[rng.uniform(-50, 50, (20000, 2)), np.full(20000, -2.7), np.zeros(20000)]
    car = np.c_[rng.uniform(8.5, 11.5, (400, 1)), rng.uniform(-0.8, 0.8, (400, 1)), rng.uniform(-2.2, -1.0, (400, 1)),
                np.zeros((400, 1))]
    view = AgentView("1", np.concatenate([ground, car]).astype(np.float32), np.eye(4),
                     np.array([[10.0, 0.0, -1.6, 4.0, 2.0, 1.5, 0.0]]), ("car",), np.array([5]))
    result = edit_module.edit_view(view, BoxEdit(remove=(5,), add=((-20.0, 15.0, 0.0),)), generator=_generator(), grid=GRID,
                                   seed=0)
    fig = edit_module.edit_figure(view, result, GRID, title="edit")
    assert [ax.get_title() for ax in fig.axes if ax.get_title()] == ["before", "after",
                                                                         "change (after vs before, per voxel)"]
    counts = viz.error_counts(voxelize(result.view.points, GRID), voxelize(view.points, GRID), per="voxel")
    legend = [t.get_text() for t in fig.axes[2].get_legend().get_texts()]
    assert legend == [f"unchanged {counts['tp']}", f"removed {counts['miss']}", f"added {counts['fp']}"]
    assert counts["fp"] > 0 and counts["miss"] > 0  # the added car's voxels, the removed car's
    # every changed cell lies in the regenerated footprint
    change = viz.error_image(voxelize(result.view.points, GRID), voxelize(view.points, GRID), per="voxel")[::-1, ::-1]
    changed = ~np.all(np.isclose(change, viz.TP_COLOUR) | np.isclose(change, viz.BACKGROUND), axis=2)
    assert changed.any() and not (changed & ~result.footprint).any()


def test_a_pitched_and_rolled_vehicle_frame_moves_to_a_sensor_above_it_along_its_own_up():
    """A Waymo car on a ramp (pitch -6 deg, roll 4 deg): its LiDAR is 2.2 m along the car's own up
    axis, not the world's, so every point and box keeps its world position and the sensor sits at
    origin + 2.2 * (the car's z axis). With pitch and roll 0 (the test above) the two agree."""
    view = _view()
    view = AgentView(view.agent_id, view.points, pose_to_matrix([5.0, 5.0, 2.0, 4.0, 10.0, -6.0]),  # roll, yaw, pitch
                     view.boxes, view.box_labels, view.box_ids)
    lifted = to_sensor_frame(Scene("s", "000000", {"7": view}), 2.2).ego
    up = view.pose[:3, :3] @ [0.0, 0.0, 1.0]
    assert abs(up[2]) < 0.995                                            # the car's up is not the world's
    np.testing.assert_allclose(lifted.pose[:3, 3], view.pose[:3, 3] + 2.2 * up, atol=1e-12)
    np.testing.assert_array_equal(lifted.pose[:3, :3], view.pose[:3, :3])
    world = lambda v, p: v.pose[:3, :3] @ np.asarray(p[:3], np.float64) + v.pose[:3, 3]  # noqa: E731
    for a, b in zip(view.points, lifted.points):
        np.testing.assert_allclose(world(lifted, b), world(view, a), atol=1e-5)
    for a, b in zip(view.boxes, lifted.boxes):
        np.testing.assert_allclose(world(lifted, b), world(view, a), atol=1e-12)
    np.testing.assert_array_equal(lifted.boxes[:, 3:], view.boxes[:, 3:])
