"""Pins found by a mutation audit of the ownership, lock, path and bound checks: each test
fails on one planted bug the rest of the suite let through, and passes on the code as it is."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from typ.errors import TypError

STAGE = "generate"


def _typ_folder(folder: Path) -> Path:
    from typ.io import atomic_path, write_manifest

    with atomic_path(folder, stage=STAGE) as tmp:
        tmp.mkdir(parents=True)
        (tmp / "1").mkdir()
        (tmp / "1" / "000000.pcd").write_bytes(b"points")
        write_manifest(tmp, STAGE, {"key": "k"})
    return folder


def test_a_link_to_what_typ_wrote_is_not_typs(tmp_path):
    """written_by looks at the path itself (lstat), never through a link to typ's moved output."""
    from typ.io import remove_written, write_bytes, written_by

    split = tmp_path / "out" / "split"
    f = split / "a.bin"
    write_bytes(f, b"x", stage=STAGE)
    assert written_by(f, STAGE)
    os.replace(f, tmp_path / "moved.bin")
    f.symlink_to(tmp_path / "moved.bin")
    assert not written_by(f, STAGE)
    d = _typ_folder(split / "scen")
    assert written_by(d, STAGE)
    os.replace(d, tmp_path / "moved_dir")
    d.symlink_to(tmp_path / "moved_dir")
    assert not written_by(d, STAGE)
    assert not remove_written(d, STAGE) and not remove_written(f, STAGE)
    assert d.is_symlink() and f.is_symlink()
    assert (tmp_path / "moved_dir" / "1" / "000000.pcd").read_bytes() == b"points"
    assert (tmp_path / "moved.bin").read_bytes() == b"x"


def test_an_empty_folder_added_to_typs_folder_makes_it_not_typs(tmp_path):
    """The fingerprint holds every sub-folder, an empty one a user made included."""
    from typ.io import remove_written, written_by

    d = _typ_folder(tmp_path / "out" / "split" / "scen")
    assert written_by(d, STAGE)
    (d / "mine").mkdir()
    assert not written_by(d, STAGE)
    assert not remove_written(d, STAGE) and (d / "mine").is_dir()


def test_a_link_planted_as_typs_state_folder_is_named_and_never_written_through(tmp_path):
    from typ.io import write_bytes

    split = tmp_path / "out" / "split"
    split.mkdir(parents=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "out" / ".typ").symlink_to(elsewhere)
    with pytest.raises(TypError) as err:
        write_bytes(split / "a.bin", b"x", stage=STAGE)
    assert "link" in str(err.value) and str(tmp_path / "out" / ".typ") in str(err.value)
    assert list(elsewhere.iterdir()) == [] and list(split.iterdir()) == []


def test_no_link_below_refuses_a_path_outside_its_top(tmp_path):
    from typ.io import atomic_path, no_link_below

    top, other = tmp_path / "out", tmp_path / "other"
    top.mkdir()
    other.mkdir()
    no_link_below(top, top / "a" / "b", where="w", field="output")   # below: fine
    no_link_below(top, top, where="w", field="output")
    with pytest.raises(TypError, match="inside the output folder"):
        no_link_below(top, other / "x", where="w", field="output")
    with pytest.raises(TypError, match="inside the output folder"):
        with atomic_path(other / "x.bin", inside=top) as tmp:
            tmp.write_bytes(b"x")
    assert list(other.iterdir()) == []


def test_a_dangling_link_where_typ_writes_is_named_and_kept(tmp_path):
    from typ.io import write_bytes

    split = tmp_path / "out" / "split"
    split.mkdir(parents=True)
    (split / "scen").symlink_to(tmp_path / "nowhere")
    (split / "a.bin").symlink_to(tmp_path / "nowhere.bin")
    with pytest.raises(TypError, match="did not write"):
        _typ_folder(split / "scen")
    with pytest.raises(TypError, match="did not write"):
        write_bytes(split / "a.bin", b"x", stage=STAGE)
    assert os.readlink(split / "scen") == str(tmp_path / "nowhere")
    assert os.readlink(split / "a.bin") == str(tmp_path / "nowhere.bin")
    assert sorted(p.name for p in split.iterdir()) == ["a.bin", "scen"]


@pytest.mark.parametrize("manifest", [None, "simulate"])
def test_a_folder_typ_puts_in_place_holds_its_own_stages_manifest(tmp_path, manifest):
    from typ.io import atomic_path, write_manifest

    final = tmp_path / "out" / "scen"
    with pytest.raises(ValueError, match="manifest"):
        with atomic_path(final, stage=STAGE) as tmp:
            tmp.mkdir(parents=True)
            (tmp / "000000.pcd").write_bytes(b"points")
            if manifest:
                write_manifest(tmp, manifest, {"key": "k"})
    assert not final.exists() and list(final.parent.iterdir()) == []


def test_a_lock_that_is_a_link_to_an_empty_file_is_named_and_not_written(tmp_path):
    """O_NOFOLLOW: an empty file passes every content check, so only the open refuses the link."""
    from typ.io import lock_path, output_lock

    out = tmp_path / "data" / "gen"
    path = lock_path(out)
    path.parent.mkdir(parents=True)
    empty = tmp_path / "empty.txt"
    empty.write_bytes(b"")
    path.symlink_to(empty)
    with pytest.raises(TypError, match="a link"):
        with output_lock(STAGE, out):
            pass
    assert empty.read_bytes() == b"" and os.readlink(path) == str(empty)


def test_a_lock_folder_that_is_a_link_to_an_empty_folder_is_named_and_not_written(tmp_path):
    """O_NOFOLLOW on the lock's folder: an empty folder elsewhere gets no lock file."""
    from typ.io import lock_path, output_lock

    out = tmp_path / "data" / "gen"
    out.parent.mkdir(parents=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    lock_path(out).parent.symlink_to(elsewhere)
    with pytest.raises(TypError, match="link"):
        with output_lock(STAGE, out):
            pass
    assert list(elsewhere.iterdir()) == []


def test_a_lock_that_is_a_hard_link_to_an_empty_file_is_named_and_not_written(tmp_path):
    """nlink == 1: an empty user file passes the content check, so only its second name refuses it."""
    from typ.io import lock_path, output_lock

    out = tmp_path / "data" / "gen"
    path = lock_path(out)
    path.parent.mkdir(parents=True)
    empty = tmp_path / "empty.txt"
    empty.write_bytes(b"")
    os.link(empty, path)
    with pytest.raises(TypError, match="hard link"):
        with output_lock(STAGE, out):
            pass
    assert empty.read_bytes() == b""


def test_a_lock_left_by_a_longer_holder_line_is_rewritten_whole(tmp_path):
    """The holder line replaces the last one (ftruncate): what is left is one line, and the next run opens it."""
    from typ.io import lock_path, output_lock

    out = tmp_path / "data" / "gen"
    path = lock_path(out)
    path.parent.mkdir(parents=True)
    path.write_bytes(b"pid 1 (generate): " + b"x" * 1000 + b"\n")
    with output_lock(STAGE, out):
        text = path.read_bytes()
        assert text.startswith(f"pid {os.getpid()} ({STAGE}): ".encode()) and text.count(b"\n") == 1
        assert b"x" * 1000 not in text
    with output_lock("simulate", out):
        assert path.read_bytes().startswith(f"pid {os.getpid()} (simulate): ".encode())


def test_inside_refuses_a_sibling_whose_name_extends_the_roots(tmp_path):
    """``/data2/f`` is not inside ``/data``: the prefix compared ends in a separator."""
    from typ.inputs import inside

    root, sibling = tmp_path / "data", tmp_path / "data2"
    root.mkdir()
    sibling.mkdir()
    (sibling / "f.bin").write_bytes(b"not the dataset's")
    (root / "link.bin").symlink_to(sibling / "f.bin")
    for path in ("../data2/f.bin", str(sibling / "f.bin"), "link.bin"):
        with pytest.raises(TypError, match="a path inside"):
            inside(path, root, where="index.json", field="lidar_path")
    assert inside("sub/../x.bin", root) == root / "sub/../x.bin"


def test_a_length_and_the_seed_bound_take_both_ends_and_refuse_one_past():
    from typing import Annotated

    from typ.config.base import LEVELS, Length, Seed, build_typed

    levels = Annotated[tuple[int, ...], LEVELS]
    assert build_typed(levels, list(range(8)), "params.yaml", "ddpm.block_out_channels") == tuple(range(8))
    assert build_typed(levels, [64], "params.yaml", "ddpm.block_out_channels") == (64,)
    for bad in (list(range(9)), []):
        with pytest.raises(TypError, match="1 to 8 items"):
            build_typed(levels, bad, "params.yaml", "ddpm.block_out_channels")
    splits = Annotated[dict[str, int], Length(0, 2, "why")]
    assert build_typed(splits, {"a": 1, "b": 2}, "w", "f") == {"a": 1, "b": 2}
    with pytest.raises(TypError, match="0 to 2 entries"):
        build_typed(splits, {"a": 1, "b": 2, "c": 3}, "w", "f")
    assert build_typed(Seed, 2**31 - 1, "params.yaml", "seed") == 2**31 - 1
    assert build_typed(Seed, 0, "params.yaml", "seed") == 0
    for bad in (2**31, 2**32 - 1, -1):
        with pytest.raises(TypError, match=r"\[0, 2147483647\]"):
            build_typed(Seed, bad, "params.yaml", "seed")


def test_a_sensor_config_built_in_code_meets_the_bounds_a_block_does():
    from typ.config import SensorConfig
    from typ.sensors import resolve

    good = SensorConfig(elevations_deg=(-10.0, 0.0, 5.0), azimuth_step_deg=0.2, max_range=100.0, mount_height=1.7)
    assert resolve(good, where="code", field="sensor").max_range == 100.0
    for bad in (dict(max_range=5000.0), dict(mount_height=50.0), dict(dropout=1.0)):
        cfg = SensorConfig(**{**dict(elevations_deg=(-10.0, 0.0, 5.0), azimuth_step_deg=0.2, max_range=100.0,
                                     mount_height=1.7), **bad})
        with pytest.raises(TypError) as err:
            resolve(cfg, where="code", field="sensor")
        assert f"sensor.{next(iter(bad))}" in str(err.value)


def test_check_config_bounds_negative_integers_and_a_saved_schedule_of_zero(tmp_path):
    from typ.artifacts import check_config
    from typ.config import MAX_TIMESTEPS

    header = {"w": ("F32", (4, 6)), "b": ("F32", (6,))}   # size limit: max(2 tensors, widest 6) = 6
    path = tmp_path / "config.json"
    check_config({"config": {"layers": 6, "offset": -6, "widths": [4, 6]}}, header, path, "stage")
    for value in (7, -7, -10**15):
        with pytest.raises(TypError, match="config.layers") as err:
            check_config({"config": {"layers": value}}, header, path, "stage")
        assert "at most 6" in str(err.value)
    for ok in (1, MAX_TIMESTEPS):
        check_config({"config": {}, "train_timesteps": ok}, header, path, "stage")
    for bad in (0, -1, MAX_TIMESTEPS + 1, True, 1.0):
        with pytest.raises(TypError, match="train_timesteps"):
            check_config({"config": {}, "train_timesteps": bad}, header, path, "stage")


def test_a_bound_child_outlives_the_thread_that_asked_for_it():
    """Linux's parent-death signal follows the forking *thread*: start_bound forks from its own
    long-lived thread, so a child asked for by a thread that then ends keeps running."""
    import threading
    import time

    from flows.server import start_bound

    box = {}

    def ask():
        box["p"] = start_bound(["sleep", "30"])
        time.sleep(1.0)   # the child has set its parent-death signal and become sleep by now

    t = threading.Thread(target=ask)
    t.start()
    t.join()
    p = box["p"]
    try:
        time.sleep(0.5)
        assert p.poll() is None
    finally:
        p.kill()
        p.wait()


def test_a_scenario_copy_takes_exactly_its_depth_and_entry_limits(tmp_path, monkeypatch):
    import tasks.edit as edit

    monkeypatch.setattr(edit, "MAX_COPY_DEPTH", 3)
    monkeypatch.setattr(edit, "MAX_COPY_ENTRIES", 5)
    src = tmp_path / "scen"
    (src / "a" / "b" / "c").mkdir(parents=True)          # 3 levels below the scenario: at the limit
    (src / "a" / "b" / "c" / "000000.pcd").write_bytes(b"p")
    (src / "x.yaml").write_text("y")                       # 5 entries: a, b, c, 000000.pcd, x.yaml
    edit.copy_scenario(src, tmp_path / "ok")
    assert (tmp_path / "ok" / "a" / "b" / "c" / "000000.pcd").read_bytes() == b"p"
    (src / "z.yaml").write_text("z")                       # 6 entries: one past
    with pytest.raises(TypError, match="at most 5 files"):
        edit.copy_scenario(src, tmp_path / "too_many")
    (src / "z.yaml").unlink()
    (src / "a" / "b" / "c" / "000000.pcd").unlink()
    (src / "a" / "b" / "c" / "d").mkdir()                  # 4 levels: one past
    with pytest.raises(TypError, match="at most 3 levels"):
        edit.copy_scenario(src, tmp_path / "too_deep")


def test_a_scenario_copy_leaves_out_hidden_and_typs_own_entries(tmp_path):
    from tasks.edit import copy_scenario

    src = tmp_path / "scen"
    (src / "1").mkdir(parents=True)
    (src / "1" / "000000.pcd").write_bytes(b"p")
    (src / ".git").mkdir()
    (src / ".git" / "HEAD").write_text("ref")
    (src / "1" / ".000000.pcd.swp").write_bytes(b"s")
    (src / "_typ.json").write_text("{}")
    (src / "1" / "_cache").mkdir()
    copy_scenario(src, tmp_path / "copy")
    got = sorted(str(p.relative_to(tmp_path / "copy")) for p in (tmp_path / "copy").rglob("*"))
    assert got == ["1", "1/000000.pcd"]
    assert (tmp_path / "copy" / "1" / "000000.pcd").read_bytes() == b"p"


def test_time_order_puts_numbers_by_value_then_other_stamps_after():
    from typ.formats.opv2v import time_order

    stamps = ["abc", "10", "000068", "9", "0a", "000000"]
    assert sorted(stamps, key=time_order) == ["000000", "9", "10", "000068", "0a", "abc"]


def test_the_ground_window_rounds_4_m_to_the_nearest_odd_count_of_the_smaller_cell_side():
    from typ.metrics.generation import ground_window
    from typ.voxel import Grid

    def grid(nx, ny):
        return Grid((-51.2, 51.2), (-51.2, 51.2), (-3.0, 1.0), (nx, ny, 8))

    assert ground_window(grid(128, 128)) == 5     # 0.8 m: 5 cells
    assert ground_window(grid(512, 512)) == 21    # 0.2 m: 20 cells, odd: 21 (not 19)
    assert ground_window(grid(256, 256)) == 11    # 0.4 m: 10 cells, odd: 11 (not 9)
    assert ground_window(grid(512, 128)) == 21    # the smaller side decides
    assert ground_window(grid(128, 512)) == 21
