"""Semantic occupancy ground truth (typ.ssc): the grid, rasterized solids, priority, trees, storage.

Voxel bounds by hand: along x, voxel i spans [-50 + 0.78125 i, -50 + 0.78125 (i + 1)) and its
sub-cell centres sit at -50 + 0.78125 (i + (k + 0.5) / 4), k = 0..3; along z, voxel k spans
[-3 + 0.4 k, ...) with sub-centres at offsets 0.1 and 0.3. A voxel is marked when a sub-centre
lies in the solid (half-open bounds).
"""
from __future__ import annotations

import numpy as np
import pytest

from typ.errors import TypError
from typ.metrics import SSC_CODE
from typ.scene import SEMANTIC_CODE as SEM
from typ.sim.mesh import MeshBuilder
from typ.sim.solids import SolidsBuilder
from typ.ssc import (SSC_GRID, SUFFIX, SscGrid, occupancy_path, rasterize, read_occupancy, scene_occupancy,
                     write_occupancy)

ROAD, CAR, TERRAIN, BUILDING, VEG, POLE = (SSC_CODE[c] for c in ("road", "car", "terrain", "building", "vegetation", "pole"))


def sensor_at(x=0.0, y=0.0, height=1.8, yaw_deg=0.0):
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    pose = np.eye(4)
    pose[:2, :2] = [[c, -s], [s, c]]
    pose[:3, 3] = [x, y, height]
    return pose


def car(x=10.0, y=0.0, yaw=0.0):
    return [x, y, 0.75, 4.5, 1.8, 1.5, yaw]  # on the ground: x 7.75..12.25, y -0.9..0.9, z 0..1.5


def voxels(labels, code):
    return {tuple(v) for v in np.argwhere(labels == code)}


def box_set(ix, iy, iz):
    return {(i, j, k) for i in ix for j in iy for k in iz}


def test_grid_is_v2vssc():
    assert SSC_GRID.shape == (128, 128, 20)
    assert SSC_GRID.voxel.tolist() == [0.78125, 0.78125, 0.4]
    assert SSC_GRID.centres(2)[[0, -1]].tolist() == pytest.approx([-2.8, 4.8])


def test_a_car_and_a_road_fill_the_right_voxels():
    s = SolidsBuilder()
    s.surfaces(-100, 100, -5, 5, 0.0, SEM["road"])   # slab z in [-0.2, 0): sensor [-2.0, -1.8) -> layer 2
    labels = rasterize(s.build(), np.array([car()]), sensor_at())
    # car x [7.75, 12.25): voxels 74..79; y [-0.9, 0.9): 62..65; sensor z [-1.8, -0.3): layers 3..6
    assert voxels(labels, CAR) == box_set(range(74, 80), range(62, 66), range(3, 7))
    # road y [-5, 5): rows 57..70, every x, layer 2 only
    assert voxels(labels, ROAD) == box_set(range(128), range(57, 71), [2])
    assert set(np.unique(labels).tolist()) == {0, ROAD, CAR}
    assert labels.dtype == np.uint8 and labels.shape == (128, 128, 20)


def test_overlaps_go_to_the_higher_priority_class():
    s = SolidsBuilder()
    s.surfaces(-100, 100, -5, 5, 0.0, SEM["road"])
    s.surfaces(-100, 100, 5, 100, 0.0, SEM["ground"])     # y [5, 100): rows 70..127; row 70 shared with road
    s.boxes([10.0, -0.5, -0.2], [20.0, 0.5, 30.0], SEM["building"])  # x 10..20 overlaps the car's voxels 76..79
    s.ellipsoids([-10.0, 10.0, 4.0], [2.0, 2.0, 2.0], SEM["vegetation"])
    s.cylinders([-10.0, 10.0], 0.0, 5.0, 0.1, SEM["pole"])  # inside the canopy from z = 2 up
    labels = rasterize(s.build(), np.array([car()]), sensor_at())
    assert (labels[:, 70, 2] == ROAD).all() and (labels[:, 71, 2] == TERRAIN).all()  # drivable > terrain
    assert voxels(labels, CAR) == box_set(range(74, 80), range(62, 66), range(3, 7))  # car > building
    assert (labels[80, 63, 3:7] == BUILDING).all() and labels[79, 63, 7] == BUILDING
    # pole column at x = -10 (voxel 51), y = 10 (voxel 76): pole all the way up, also inside the canopy
    ix, iy = 51, 76
    assert (labels[ix, iy, 3:16] == POLE).all()       # sensor z [-1.8, 3.2) = world [0, 5)
    assert labels[ix + 2, iy, 10] == VEG               # canopy next to the pole


def test_tree_trunk_is_pole_below_the_canopy_and_vegetation_above():
    from typ.sim.town import TownStyle, _add_trees

    s = SolidsBuilder()
    _add_trees(MeshBuilder(), s, np.array([[5.0, 5.0], [-20.0, 30.0]]), TownStyle(), np.random.default_rng(3))
    solids = s.build()
    canopy_bottom = solids.ellipsoids[:, 2] - solids.ellipsoids[:, 5]
    pole = solids.cylinder_code == SEM["pole"]
    assert pole.sum() == 2 and (~pole).sum() == 2
    assert np.allclose(solids.cylinders[pole, 3], canopy_bottom)       # trunk (pole) ends at the canopy ...
    assert np.allclose(solids.cylinders[~pole, 2], canopy_bottom)      # ... where the vegetation part starts
    labels = rasterize(solids, np.zeros((0, 7)), sensor_at())
    ix, iy = int((5.0 + 50) / 0.78125), int((5.0 + 50) / 0.78125)
    column = labels[ix, iy]
    z_top = -3 + 0.4 * np.arange(20) + 0.4           # voxel tops, sensor frame
    below = (z_top + 1.8 <= canopy_bottom[0]) & (z_top + 1.8 > 0.0)
    assert (column[below] == POLE).all() and below.sum() >= 1
    above = np.flatnonzero(column == VEG)
    assert len(above) >= 5 and above.min() > np.flatnonzero(below).max()
    assert set(column[~below].tolist()) <= {0, VEG, POLE}


@pytest.mark.parametrize("yaw", [0.0, 17.0, 45.0])
@pytest.mark.parametrize("offset", [0.0, 0.13, 0.37])
def test_thin_poles_are_never_missed(yaw, offset):
    s = SolidsBuilder()
    s.cylinders([[3.0 + offset, -7.0 + offset]], 0.0, 2.6, 0.04, SEM["pole"])
    labels = rasterize(s.build(), np.zeros((0, 7)), sensor_at(yaw_deg=yaw))
    layers = {k for _, _, k in voxels(labels, POLE)}
    assert layers == set(range(3, 10))  # sensor z [-1.8, 0.8): layers 3..9, a few voxels each
    assert len(voxels(labels, POLE)) <= 4 * 7


def test_the_map_is_in_the_agent_frame():
    # Sensor at (100, 50) looking along world +y (yaw 90 deg): a car 10 m ahead of it is at sensor x = +10.
    world_car = car(x=100.0, y=60.0, yaw=np.pi / 2)
    labels = rasterize(SolidsBuilder().build(), np.array([world_car]), sensor_at(100.0, 50.0, yaw_deg=90.0))
    assert voxels(labels, CAR) == box_set(range(74, 80), range(62, 66), range(3, 7))


def test_simulated_scenario_agrees_with_its_lidar_labels():
    from typ.sim import simulate_scenario

    kw = dict(domain="real_cav", seed=5, n_frames=1, n_agents=2)
    maps = scene_occupancy(**kw)
    scene = simulate_scenario(**kw)[0]
    assert len(maps) == 1 and len(maps[0]) == 2
    codes = {SEM["road"]: ROAD, SEM["vehicle"]: CAR, SEM["building"]: BUILDING, SEM["ground"]: TERRAIN}
    for view, labels in zip(scene.agents.values(), maps[0]):
        present = set(np.unique(labels).tolist())
        assert {ROAD, CAR, TERRAIN, BUILDING}.issubset(present)
        pts = view.points[:, :3].astype(np.float64)
        idx = np.floor((pts - SSC_GRID.lower) / SSC_GRID.voxel).astype(int)
        inside = ((idx >= 0) & (idx < SSC_GRID.shape)).all(axis=1)
        for sem, ssc in codes.items():
            sel = inside & (view.semantics == sem)
            # a return of class c lies on c's surface: in a voxel of c or one of its 26 neighbours
            hit = np.zeros(sel.sum(), dtype=bool)
            for d in np.array(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1])).reshape(3, -1).T:
                j = np.clip(idx[sel] + d, 0, np.array(SSC_GRID.shape) - 1)
                hit |= labels[j[:, 0], j[:, 1], j[:, 2]] == ssc
            assert sel.sum() > 20 and hit.mean() > 0.9, (sem, sel.sum(), hit.mean())


def test_storage_round_trip_is_sparse_and_exact(tmp_path):
    rng = np.random.default_rng(0)
    labels = np.where(rng.random(SSC_GRID.shape) < 0.05, rng.integers(1, 7, SSC_GRID.shape), 0).astype(np.uint8)
    path = write_occupancy(occupancy_path(tmp_path / "scn", "641", "000003"), labels)
    assert path == tmp_path / "scn" / "641" / "000003_semantic_occupancy.npz"
    assert np.array_equal(read_occupancy(path), labels)
    with np.load(path) as z:
        assert sorted(z.files) == ["index", "label", "lower", "shape", "upper"]
        assert len(z["index"]) == np.count_nonzero(labels) and (np.diff(z["index"]) > 0).all()


def _write_raw(path, **over):
    arrays = dict(shape=np.array([128, 128, 20]), index=np.array([0, 5]), label=np.array([1, 2], np.uint8),
                  lower=np.array(SSC_GRID.lower), upper=np.array(SSC_GRID.upper))
    arrays.update(over)
    np.savez_compressed(path, **{k: v for k, v in arrays.items() if v is not None})
    return path


@pytest.mark.parametrize("over,field", [
    ({"shape": np.array([128, 128, 16])}, "shape"),
    ({"label": np.array([1, 7], np.uint8)}, "label"),
    ({"label": np.array([0, 1], np.uint8)}, "label"),
    ({"index": np.array([0, 128 * 128 * 20])}, "index"),
    ({"upper": np.array([51.2, 51.2, 5.0])}, "upper"),
    ({"label": None}, "label"),
])
def test_bad_maps_name_the_file_and_field(tmp_path, over, field):
    path = _write_raw(tmp_path / "000000_semantic_occupancy.npz", **over)
    with pytest.raises(TypError) as e:
        read_occupancy(path)
    assert e.value.field == field and e.value.where == str(path)


def test_missing_or_damaged_file_and_bad_writes_are_named(tmp_path):
    with pytest.raises(TypError, match="missing") as e:
        read_occupancy(tmp_path / "a" / "000000_semantic_occupancy.npz")
    assert e.value.field == "file"
    bad = tmp_path / "b.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(TypError) as e:
        read_occupancy(bad)
    assert e.value.field == "file"
    with pytest.raises(TypError, match="shape"):
        write_occupancy(tmp_path / "c.npz", np.zeros((128, 128, 16), np.uint8))
    with pytest.raises(TypError, match="class ids"):
        write_occupancy(tmp_path / "c.npz", np.full((128, 128, 20), 9, np.uint8))
    small = SscGrid(shape=(4, 4, 2))
    with pytest.raises(TypError) as e:
        read_occupancy(write_occupancy(tmp_path / "d.npz", np.ones((4, 4, 2), np.uint8), small))
    assert e.value.field == "shape"
    assert read_occupancy(tmp_path / "d.npz", small).sum() == 32


def test_simulate_writes_each_views_map_beside_its_cloud(tmp_path):
    from tasks.simulate import ScenarioJob
    from typ.formats.opv2v import check_scenario, list_agents
    from typ.sim import scenario_world

    job = ScenarioJob(domain="real_cav", split="train", index=0, seed=11, n_agents=2, n_frames=2,
                      azimuth_step_deg=2.0, comm_range=70.0, dt=0.1)
    folder = tmp_path / job.name
    folder.mkdir()
    job.write(folder)
    assert check_scenario(folder)["views"] == 4  # the OPV2V reader ignores the maps
    maps = scene_occupancy(domain="real_cav", seed=11, n_frames=2, n_agents=2)
    _, traffic, _ = scenario_world(domain="real_cav", seed=11, n_frames=2, n_agents=2)
    agents = [str(i) for i in traffic.ids[traffic.agents]]
    assert sorted(agents) == list_agents(folder)
    for f, frame_maps in enumerate(maps):
        for agent, labels in zip(agents, frame_maps):
            assert np.array_equal(read_occupancy(occupancy_path(folder, agent, f"{f:06d}")), labels)


def test_only_the_domains_in_simulate_occupancy_get_maps(tmp_path):
    """tiny writes the maps for real_cav alone (SSC's domain): the other domains' jobs skip the
    0.15-0.4 s a view, and a job without them writes the same clouds and no ``.npz``."""
    import dataclasses

    from tasks.simulate import ScenarioJob, plan_jobs
    from typ.config import config_from_dict

    cfg = config_from_dict({"profile": "tiny"}).simulate
    jobs = plan_jobs(cfg)
    assert cfg.occupancy == ("real_cav",)
    assert {j.domain for j in jobs if j.occupancy} == {"real_cav"}
    assert {j.domain for j in jobs if not j.occupancy} == {"source", "target"}
    with_maps = ScenarioJob(domain="target", split="train", index=0, seed=5, n_agents=2, n_frames=1,
                            azimuth_step_deg=2.0, comm_range=70.0, dt=0.1)
    without = dataclasses.replace(with_maps, occupancy=False)
    assert with_maps.key() != without.key()
    for job, name in ((with_maps, "a"), (without, "b")):
        (tmp_path / name).mkdir()
        job.write(tmp_path / name)
    files_a = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    files_b = sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file())
    assert [f for f in files_a if not f.name.endswith(SUFFIX)] == files_b
    assert len(files_a) - len(files_b) == 2 and not any(f.name.endswith(SUFFIX) for f in files_b)
    for f in files_b:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()
    with pytest.raises(TypError, match=r"params.yaml: simulate.occupancy: expected sensor domains"):
        config_from_dict({"profile": "tiny", "simulate": {"occupancy": ["lidar"]}})
