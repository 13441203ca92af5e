"""typ.store: Parquet round trips, metadata-only hash reads, atomic writes, bad files."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from typ import store
from typ.errors import TypError
from typ.io import TMP_PREFIX
from typ.store import (list_scenes, read_scene_voxels, scene_path, stored_input_hash, voxel_dataset,
                       write_scene_voxels)
from typ.voxel import PAPER_GRID, Grid, box_map, voxelize
from repo_paths import SHARED_DATA

DATA = SHARED_DATA
GRID = Grid((-8.0, 8.0), (-8.0, 8.0), (-2.0, 1.0), (32, 24, 6))


def random_records(n: int, seed: int = 0, grid: Grid = GRID) -> dict:
    rng = np.random.default_rng(seed)
    records = {}
    for r in range(n):
        occ = rng.random(grid.shape) < rng.uniform(0.0, 0.1)
        boxes = rng.random(grid.shape[:2] + (1,)) < 0.05
        records[(f"agent{r % 3}", f"{r:06d}")] = (occ, boxes)
    return records


def assert_same(got: dict, expected: dict):
    assert list(got) == list(expected)
    for key, (occ, boxes) in expected.items():
        assert got[key][0].dtype == bool and got[key][1].dtype == bool
        np.testing.assert_array_equal(got[key][0], occ)
        np.testing.assert_array_equal(got[key][1], boxes)


def test_round_trip(tmp_path):
    records = random_records(37)  # more than two row groups
    records[("agent9", "000999")] = (np.zeros(GRID.shape, bool), np.zeros(GRID.shape[:2] + (1,), bool))
    path = scene_path(tmp_path, "opv2v", "train", "2021_08_18_19_48_05")
    assert write_scene_voxels(path, records, grid=GRID, input_hash="h1") == path
    assert path == tmp_path / "dataset=opv2v" / "split=train" / "2021_08_18_19_48_05.parquet"
    grid, input_hash, got = read_scene_voxels(path)
    assert grid == GRID and input_hash == "h1"
    assert_same(got, records)
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporaries left


def test_round_trip_from_a_generator_and_empty_scene(tmp_path):
    records = random_records(5, seed=1)
    path = tmp_path / "s.parquet"
    write_scene_voxels(path, iter(records.items()), grid=GRID, input_hash="h")
    assert_same(read_scene_voxels(path)[2], records)
    write_scene_voxels(path, {}, grid=GRID, input_hash="h")
    assert read_scene_voxels(path)[2] == {}


def test_real_frame_round_trip_and_size(tmp_path):
    velo = DATA / "kitti_object_vis" / "training" / "velodyne" / "000000.bin"
    if not velo.is_file():
        pytest.skip(f"real frame not available: {velo}")
    pts = np.fromfile(velo, np.float32).reshape(-1, 4)
    records = {("ego", "000000"): (voxelize(pts, PAPER_GRID), box_map([[8.0, 1.0, -1.0, 4.2, 1.8, 1.5, 0.2]], PAPER_GRID))}
    path = write_scene_voxels(tmp_path / "000000.parquet", records, grid=PAPER_GRID, input_hash="k")
    assert_same(read_scene_voxels(path)[2], records)
    # sparse indices: far below the packed bits (655,360 B), let alone the dense grid
    assert path.stat().st_size < 40_000


def test_stored_input_hash(tmp_path):
    path = tmp_path / "s.parquet"
    assert stored_input_hash(path) is None
    write_scene_voxels(path, random_records(2), grid=GRID, input_hash="first")
    assert stored_input_hash(path) == "first"
    write_scene_voxels(path, random_records(2), grid=GRID, input_hash="second")
    assert stored_input_hash(path) == "second"


def test_failed_write_leaves_no_partial_file(tmp_path):
    path = tmp_path / "s.parquet"
    records = random_records(3 * store.ROW_GROUP_RECORDS)

    def failing():
        for n, item in enumerate(records.items()):
            if n == 2 * store.ROW_GROUP_RECORDS + 1:  # two row groups already on disk
                raise RuntimeError("worker killed")
            yield item

    with pytest.raises(RuntimeError, match="worker killed"):
        write_scene_voxels(path, failing(), grid=GRID, input_hash="h")
    assert list(tmp_path.iterdir()) == []

    write_scene_voxels(path, random_records(2), grid=GRID, input_hash="old")
    before = path.read_bytes()
    with pytest.raises(RuntimeError):
        write_scene_voxels(path, failing(), grid=GRID, input_hash="new")
    assert path.read_bytes() == before and stored_input_hash(path) == "old"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(TMP_PREFIX)]


def test_corrupt_and_foreign_files_name_the_file(tmp_path):
    good = write_scene_voxels(tmp_path / "good.parquet", random_records(4), grid=GRID, input_hash="h")
    data = good.read_bytes()
    garbage = tmp_path / "garbage.parquet"
    garbage.write_bytes(b"not a parquet file at all")
    truncated = tmp_path / "truncated.parquet"
    truncated.write_bytes(data[: len(data) // 2])
    flipped = tmp_path / "flipped.parquet"
    flipped.write_bytes(data[:4] + bytes(b ^ 0xFF for b in data[4:200]) + data[200:])
    foreign = tmp_path / "foreign.parquet"
    pq.write_table(pa.table({"x": [1, 2, 3]}), foreign)
    for bad in (garbage, truncated, foreign):
        for read in (read_scene_voxels, stored_input_hash):
            with pytest.raises(TypError) as exc:
                read(bad)
            assert exc.value.where == str(bad)
    with pytest.raises(TypError) as exc:
        read_scene_voxels(flipped)  # footer intact, data pages broken
    assert exc.value.where == str(flipped)
    with pytest.raises(TypError, match="missing"):
        read_scene_voxels(tmp_path / "absent.parquet")


def forged(path: Path, meta: dict, rows: dict) -> Path:
    schema = store._SCHEMA.with_metadata({store.METADATA_KEY: json.dumps(meta).encode()})
    pq.write_table(pa.Table.from_pydict(rows, schema=schema), path)
    return path


def test_forged_files_rejected(tmp_path):
    meta = {"format": store.FORMAT, "version": store.FORMAT_VERSION, "grid": GRID.to_dict(), "input_hash": "h"}
    row = {"scene": ["s"], "agent_id": ["a"], "timestamp": ["t"], "occ_ix": [[40]], "occ_iy": [[0]],
           "occ_iz": [[0]], "box_ix": [[]], "box_iy": [[]]}
    with pytest.raises(TypError, match="occ_ix"):  # 40 >= H = 32
        read_scene_voxels(forged(tmp_path / "a.parquet", meta, row))
    with pytest.raises(TypError, match="version"):
        stored_input_hash(forged(tmp_path / "b.parquet", meta | {"version": 99}, row))
    with pytest.raises(TypError, match="grid"):
        read_scene_voxels(forged(tmp_path / "c.parquet", meta | {"grid": {"shape": [1, 1, 1]}}, row))
    twice = {k: v * 2 for k, v in row.items()} | {"occ_ix": [[1], [1]]}
    with pytest.raises(TypError, match="one row per"):
        read_scene_voxels(forged(tmp_path / "d.parquet", meta, twice))


def test_bad_records_rejected(tmp_path):
    path = tmp_path / "s.parquet"
    occ, boxes = np.zeros(GRID.shape, bool), np.zeros((32, 24, 1), bool)
    cases = [
        ({("a", "t"): (occ[:, :, :3], boxes)}, "occupancy"),
        ({("a", "t"): (occ.astype(np.uint8), boxes)}, "occupancy"),
        ({("a", "t"): (occ, boxes[:, :, 0])}, "box_map"),
        ({("a", 7): (occ, boxes)}, "records"),
        ([(("a", "t"), (occ, boxes)), (("a", "t"), (occ, boxes))], "records"),
    ]
    for records, field in cases:
        with pytest.raises(TypError, match=field):
            write_scene_voxels(path, records, grid=GRID, input_hash="h")
        assert not path.exists()
    with pytest.raises(TypError, match="input_hash"):
        write_scene_voxels(path, {}, grid=GRID, input_hash="")
    with pytest.raises(TypError, match="path"):
        write_scene_voxels(tmp_path / "s.npz", {}, grid=GRID, input_hash="h")
    with pytest.raises(TypError, match="split"):
        scene_path(tmp_path, "opv2v", "../train", "s")


def test_listing_and_dataset_reader(tmp_path):
    for dataset, split, scene in [("opv2v", "train", "s1"), ("opv2v", "train", "s0"), ("opv2v", "test", "s2"),
                                  ("colwaymo", "train", "w0")]:
        write_scene_voxels(scene_path(tmp_path, dataset, split, scene), random_records(2, seed=len(scene)),
                           grid=GRID, input_hash=scene)
    (tmp_path / "dataset=opv2v" / "split=train" / f"{TMP_PREFIX}s9.parquet.x").write_bytes(b"partial")
    assert [(s.dataset, s.split, s.scene) for s in list_scenes(tmp_path)] == [
        ("colwaymo", "train", "w0"), ("opv2v", "test", "s2"), ("opv2v", "train", "s0"), ("opv2v", "train", "s1")]
    assert [s.scene for s in list_scenes(tmp_path, dataset="opv2v", split="train")] == ["s0", "s1"]
    table = voxel_dataset(tmp_path).to_table(columns=["dataset", "split", "scene", "agent_id"])
    assert table.num_rows == 8
    assert sorted(set(zip(*[table.column(c).to_pylist() for c in ("dataset", "split", "scene")]))) == [
        ("colwaymo", "train", "w0"), ("opv2v", "test", "s2"), ("opv2v", "train", "s0"), ("opv2v", "train", "s1")]


def test_sparse_read_densifies_to_the_dense_read(tmp_path):
    from typ.store import densify, read_scene_indices, read_scene_voxels, write_scene_voxels
    from typ.voxel import Grid

    grid = Grid((-4.0, 4.0), (-4.0, 4.0), (-1.0, 1.0), (8, 8, 4))
    rng = np.random.default_rng(3)
    recs = {("1", "000000"): (rng.random((8, 8, 4)) < 0.2, rng.random((8, 8, 1)) < 0.3),
            ("2", "000000"): (np.zeros((8, 8, 4), bool), np.zeros((8, 8, 1), bool))}
    path = write_scene_voxels(tmp_path / "s.parquet", recs, grid=grid, input_hash="h")
    g, h, sparse = read_scene_indices(path)
    _, _, dense = read_scene_voxels(path)
    assert g == grid and h == "h" and list(sparse) == list(recs)
    for key, (occ, box) in recs.items():
        assert sparse[key][0].shape == (occ.sum(), 3) and sparse[key][1].shape == (box.sum(), 2)
        d_occ, d_box = densify(sparse[key], grid)
        assert np.array_equal(d_occ, occ) and np.array_equal(d_box, box)
        assert np.array_equal(dense[key][0], occ)
