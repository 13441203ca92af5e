"""Crash-safe outputs: nothing half-written is ever visible under a final name."""
import os

import pytest

from typ.io import atomic_path, hash_files, hash_obj, remove_stale_temporaries, write_bytes, write_json


def test_file_appears_only_when_complete(tmp_path):
    target = tmp_path / "out" / "a.bin"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"partial")
            assert not target.exists()
            raise RuntimeError("killed mid-write")
    assert not target.exists()
    assert os.listdir(target.parent) == []


def test_failed_rewrite_keeps_previous_output(tmp_path):
    target = tmp_path / "a.json"
    write_json(target, {"v": 1})
    with pytest.raises(ValueError):
        with atomic_path(target) as tmp:
            tmp.write_text('{"v": 2')
            raise ValueError
    assert target.read_text().strip().endswith("}") and '"v": 1' in target.read_text()


def test_directory_swap(tmp_path):
    target = tmp_path / "scene"
    with atomic_path(target) as tmp:
        tmp.mkdir()
        (tmp / "x.txt").write_text("one")
    with atomic_path(target) as tmp:
        tmp.mkdir()
        (tmp / "y.txt").write_text("two")
    assert sorted(p.name for p in target.iterdir()) == ["y.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]


def test_stale_temporaries_are_removed(tmp_path):
    (tmp_path / ".tmp-a.bin.123").write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / ".tmp-dir.9").mkdir()
    write_bytes(tmp_path / "keep.bin", b"y")
    assert remove_stale_temporaries(tmp_path) == 2
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["keep.bin", "sub"]


def test_hashes_change_with_content_and_are_stable(tmp_path):
    a = tmp_path / "a"
    a.write_bytes(b"1")
    h1 = hash_files([a])
    assert h1 == hash_files([a])
    a.write_bytes(b"2")
    assert hash_files([a]) != h1
    assert hash_obj({"x": 1, "y": [1, 2]}) == hash_obj({"y": [1, 2], "x": 1})
