"""Reference poses for generation: sampled from labelled vehicles, skips counted, frames consistent."""
import numpy as np

from tasks.generate import build_reference, sample_references
from typ.resim import EGO_CAR_LWH
from typ.config import config_from_dict
from typ.geometry import pose_to_matrix, transform_points
from typ.scene import AgentView
from typ.voxel import Grid

GRID = Grid((-51.2, 51.2), (-51.2, 51.2), (-3.0, 1.0), (128, 128, 8))


def _ego():
    boxes = np.array([[2.0, 1.0, -1.2, 4.5, 1.9, 1.5, 0.0],      # 2.2 m: too close
                      [20.0, 0.0, -1.2, 4.5, 1.9, 1.5, np.pi / 2],  # candidate
                      [0.0, -30.0, -1.2, 4.5, 1.9, 1.5, np.pi],    # candidate
                      [80.0, 0.0, -1.2, 4.5, 1.9, 1.5, 0.0]])      # out of range
    pts = np.array([[20.3, 5.3, -1.1, 0.5], [10.3, 0.3, -2.1, 0.1]], dtype=np.float32)  # off bin edges
    pose = pose_to_matrix([100.0, -50.0, 2.2, 0.0, 30.0, 0.0])
    return AgentView("5", pts, pose, boxes, ("car",) * 4, np.array([11, 12, 13, 14]))


def test_distance_band_and_skip_reasons():
    cfg = config_from_dict({"generate": {"references_per_frame": 5, "min_distance": 5.0, "max_distance": 45.0}}).generate
    skipped = {"reference_too_close": 0, "reference_out_of_range": 0, "scenario_without_candidate_vehicle": 0}
    ego = _ego()
    assert sample_references([ego, ego], cfg, np.random.default_rng(0), skipped) == [12, 13]
    assert skipped == {"reference_too_close": 2, "reference_out_of_range": 2, "scenario_without_candidate_vehicle": 0}
    cfg1 = config_from_dict({"generate": {"references_per_frame": 1}}).generate
    assert len(sample_references([ego], cfg1, np.random.default_rng(0), skipped)) == 1


def test_a_reference_must_qualify_in_every_frame():
    cfg = config_from_dict({"generate": {"references_per_frame": 5}}).generate
    skipped = {"reference_too_close": 0, "reference_out_of_range": 0, "scenario_without_candidate_vehicle": 0}
    first, later = _ego(), _ego()
    later.boxes[1, 0] = 90.0  # vehicle 12 drove out of range in the second frame
    assert sample_references([first, later], cfg, np.random.default_rng(0), skipped) == [13]
    later.boxes[2, 1] = -2.0  # and vehicle 13 came too close
    assert sample_references([first, later], cfg, np.random.default_rng(0), skipped) == []
    assert skipped["scenario_without_candidate_vehicle"] == 1


def test_reference_frame_boxes_and_ego_cloud():
    ego = _ego()
    ref = build_reference(ego, 1, GRID)
    # the reference sensor: on the vehicle at (20, 0) facing +y of the ego frame, same height as the ego's
    in_ego = np.linalg.inv(ego.pose) @ ref.pose
    assert np.allclose(in_ego[:3, 3], [20.0, 0.0, 0.0], atol=1e-9)
    assert np.allclose(in_ego[:3, 0], [0.0, 1.0, 0.0], atol=1e-9)
    assert ref.agent_id == "512"  # ego id "5" + vehicle id 12: sorts after the ego
    # its own box is gone, the ego car is added (id = the ego's), every other box is kept
    assert list(ref.ids) == [11, 13, 14, 5] and ref.labels[-1] == "car"
    ego_car = ref.boxes[-1]
    assert np.allclose(ego_car[:2], [0.0, 20.0], atol=1e-9)  # ego origin seen from the reference
    assert np.allclose(ego_car[3:6], EGO_CAR_LWH)
    # x_e' holds the ego's points moved into the reference frame
    moved = transform_points(np.linalg.inv(in_ego), ego.points[:, :3].astype(np.float64))
    i = np.floor((moved[:, :3] - GRID.lower) / GRID.voxel_size).astype(int)
    assert ref.x_e.sum() == 2 and all(ref.x_e[k, x, y] for x, y, k in i)
    assert ref.y_r.shape == (1, 128, 128) and ref.y_r.sum() > 0


def test_hybrid_views_are_resimulated_where_the_ego_saw_and_generated_elsewhere():
    # generate.compose: hybrid keeps the re-simulated points in the cells the ego covered and the
    # generator's points (the same sample as compose: generated) in every other cell
    import pytest

    from pipelines.typ import Reference
    from typ.resim import resimulated_points
    from tiny_pipeline import TINY_GRID as PGRID, tiny_pipeline as _pipeline
    from typ.errors import TypError
    from typ.resim import coverage_mask, in_mask
    from typ.sim import domain_spec, simulate_scenario
    from typ.voxel import box_map, points_to_reference, voxelize

    scene = simulate_scenario(domain="target", seed=2, n_frames=1, n_agents=1)[0]
    ego = scene.ego
    spec = domain_spec("target").sensor
    grid = PGRID.for_sensor(spec.mount_height)
    refs = []
    for x, yaw in ((4.0, 0.0), (-6.0, 40.0)):
        pose = pose_to_matrix([x, 1.0, 0.0, 0.0, 0.0, yaw])
        moved = points_to_reference(ego.points, np.eye(4), pose)
        refs.append(Reference(f"r{x:g}", pose, np.zeros((0, 7)), (), np.zeros(0, np.int64),
                              voxelize(moved, grid).transpose(2, 0, 1), box_map(np.zeros((0, 7)), grid).transpose(2, 0, 1),
                              moved, np.linalg.inv(pose)[:3, 3]))
    pipe = _pipeline()
    plain = pipe.generate(refs, grid, 5)
    mixed = pipe.generate(refs, grid, 5, sensor=spec, compose="hybrid")
    for ref, a, b in zip(refs, plain, mixed):
        seen = coverage_mask(ref.ego_points, grid)
        resim = resimulated_points(ref.ego_points, spec, EGO_CAR_LWH)
        assert seen.any() and (~seen).any() and in_mask(resim, seen, grid).any()
        assert b.dtype == np.float32 and b.shape[1] == 4
        inside = in_mask(b, seen, grid)
        z0, z1 = grid.lower[2], grid.lower[2] + grid.shape[2] * grid.voxel_size[2]
        kept = in_mask(resim, seen, grid) & (resim[:, 2] >= z0) & (resim[:, 2] < z1)
        assert np.array_equal(b[inside, :3], resim[kept]) and (b[:, 2] >= z0).all() and (b[:, 2] < z1).all()
        assert np.array_equal(b[~inside], a[~in_mask(a, seen, grid)])
        q = pipe.point_stats.intensity
        assert b[inside, 3].min() >= min(map(min, q)) and b[inside, 3].max() <= max(map(max, q))
        assert len(np.unique(b[inside, 3])) > 1           # drawn, not a constant
    with pytest.raises(TypError) as err:
        pipe.generate(refs, grid, 5, compose="hybrid")
    assert err.value.field == "sensor"
    with pytest.raises(TypError) as err:
        pipe.generate(refs, grid, 5, sensor=spec, compose="mixed")
    assert err.value.field == "generate.compose"
    # cast: one scan of the reference LiDAR, every point on one of its beams, the same bytes again
    from typ.sensors import on_beam_fractions

    cast = pipe.generate(refs, grid, 5, sensor=spec, compose="cast")
    assert all(np.array_equal(a, b) for a, b in zip(cast, pipe.generate(refs, grid, 5, sensor=spec,
                                                                           compose="cast")))
    for ref, c in zip(refs, cast):
        assert c.dtype == np.float32 and c.shape[1] == 4 and len(c) > 1000
        assert on_beam_fractions(c, spec, (0.05,), min_range=1.0)[0.05] > 0.999
        assert np.linalg.norm(c[:, :3], axis=1).max() <= spec.max_range + 3 * spec.range_noise_std + 1e-3
    with pytest.raises(TypError) as err:
        pipe.generate(refs, grid, 5, compose="cast")
    assert err.value.field == "sensor"
