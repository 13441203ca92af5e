"""Crash-safe outputs: nothing half-written is ever visible under a final name."""
import os

import pytest

from typ.errors import TypError
from typ.io import atomic_path, hash_files, record_path, hash_obj, remove_stale_temporaries, write_bytes, write_json, write_manifest


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
    with atomic_path(target, stage="simulate") as tmp:
        tmp.mkdir()
        (tmp / "x.txt").write_text("one")
        write_manifest(tmp, "simulate", {"n": 1})
    with atomic_path(target, stage="simulate") as tmp:
        tmp.mkdir()
        (tmp / "y.txt").write_text("two")
        write_manifest(tmp, "simulate", {"n": 2})
    assert sorted(p.name for p in target.iterdir()) == ["_typ.json", "y.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]   # the scene alone; typ's record of it one folder up
    assert record_path(target) == tmp_path.parent / ".typ" / "written" / tmp_path.name / "scene.json"
    assert record_path(target).is_file()
    # another stage's folder, or one changed since typ wrote it (its manifest deleted), is not replaced
    for stage in ("generate", "simulate"):
        with pytest.raises(TypError, match="typ did not write"):
            with atomic_path(target, stage=stage) as tmp:
                tmp.mkdir()
                write_manifest(tmp, stage, {})
                if stage == "simulate":
                    (target / "_typ.json").unlink()
    assert sorted(p.name for p in target.iterdir()) == ["y.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_stale_temporaries_are_removed(tmp_path):
    (tmp_path / ".tmp-a.bin.123").write_bytes(b"x")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / ".tmp-dir.9").mkdir()
    (tmp_path / "sub" / ".tmp-scene.k2_x9abz").mkdir()
    (tmp_path / "sub" / ".tmp-scene.k2_x9abz" / ".tmp-a.pcd.12345678").write_bytes(b"x")
    (tmp_path / "sub" / ".tmp-notes").write_text("a user's, not named as typ names its temporaries")
    write_bytes(tmp_path / "keep.bin", b"y")
    assert remove_stale_temporaries(tmp_path) == 3
    assert sorted(p.name for p in tmp_path.rglob("*")) == [".tmp-notes", "keep.bin", "sub"]


def test_hashes_change_with_content_and_are_stable(tmp_path):
    a = tmp_path / "a"
    a.write_bytes(b"1")
    h1 = hash_files([a])
    assert h1 == hash_files([a])
    a.write_bytes(b"2")
    assert hash_files([a]) != h1
    assert hash_obj({"x": 1, "y": [1, 2]}) == hash_obj({"y": [1, 2], "x": 1})


def _reference_sha256(paths, extra=""):
    """hash_files' definition, computed here without typ: name, NUL, bytes, NUL per file, then extra."""
    import hashlib

    h = hashlib.sha256()
    for p in paths:
        h.update(p.name.encode() + b"\0" + p.read_bytes() + b"\0")
    return h.update(extra.encode()) or h.hexdigest()


@pytest.fixture
def hash_cache(tmp_path, monkeypatch):
    """A project hash cache, trusting files of any age (RACY_S 0), and a counter of file reads."""
    import typ.hashcache
    import typ.io

    path = tmp_path / ".typ" / "hashes.sqlite"
    monkeypatch.setenv(typ.hashcache.ENV, str(path))
    monkeypatch.setattr(typ.hashcache, "RACY_S", 0.0)
    reads = []
    real = typ.io._read_digest
    monkeypatch.setattr(typ.io, "_read_digest", lambda paths, extra: reads.append(len(paths)) or real(paths, extra))
    return path, reads


def test_cached_hashes_equal_read_ones_and_skip_the_read_of_unchanged_files(tmp_path, hash_cache):
    path, reads = hash_cache
    files = [tmp_path / "a.pcd", tmp_path / "b.yaml"]
    files[0].write_bytes(os.urandom(3000))
    files[1].write_text("lidar_pose: [0, 0, 1.9, 0, 0, 0]\n")
    want = _reference_sha256(files, "grid|code")
    assert hash_files(files, extra="grid|code") == want and reads == [2]
    assert hash_files(files, extra="grid|code") == want and reads == [2]      # from the cache: no read
    assert path.is_file()
    assert hash_files(files, extra="other") == _reference_sha256(files, "other") and reads == [2, 2]
    assert hash_files(files[:1], extra="grid|code") == _reference_sha256(files[:1], "grid|code")
    assert reads == [2, 2, 1]


def test_a_rewritten_file_is_read_again_even_with_its_size_and_mtime_restored(tmp_path, hash_cache):
    _, reads = hash_cache
    f = tmp_path / "a.bin"
    f.write_bytes(b"\x01" * 4096)
    first = hash_files([f])
    st = f.stat()
    f.write_bytes(b"\x02" * 4096)                                   # same size
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))                 # same mtime: only ctime moved
    assert f.stat().st_mtime_ns == st.st_mtime_ns and f.stat().st_size == st.st_size
    assert hash_files([f]) == _reference_sha256([f]) != first and reads == [1, 1]
    f.write_bytes(b"\x01" * 4096)                                   # the first bytes again: a new stat
    assert hash_files([f]) == first and reads == [1, 1, 1]


def test_recently_changed_files_are_hashed_but_not_remembered(tmp_path, hash_cache, monkeypatch):
    import typ.hashcache

    _, reads = hash_cache
    monkeypatch.setattr(typ.hashcache, "RACY_S", 60.0)              # the file was written < 60 s ago
    f = tmp_path / "fresh.bin"
    f.write_bytes(b"x")
    assert hash_files([f]) == hash_files([f]) == _reference_sha256([f]) and reads == [1, 1]


def test_a_damaged_cache_is_skipped_with_a_warning_and_never_answers(tmp_path, hash_cache, caplog, monkeypatch):
    import sqlite3

    import typ.hashcache

    path, reads = hash_cache
    f = tmp_path / "a.bin"
    f.write_bytes(b"abc")
    hash_files([f])
    # a row that is not a sha256 (written by hand, or a damaged page) is never returned
    key, _ = typ.hashcache.stat_key([f], "")
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE digests SET digest = 'not-a-digest' WHERE key = ?", (key,))
    assert hash_files([f]) == _reference_sha256([f]) and reads == [1, 1]
    # a file that is not a database at all: a warning naming it, then every call reads its files
    other = tmp_path / "garbage.sqlite"
    other.write_bytes(b"this is not sqlite" * 100)
    monkeypatch.setenv(typ.hashcache.ENV, str(other))
    with caplog.at_level("WARNING", logger="typ.hashcache"):
        assert hash_files([f]) == hash_files([f]) == _reference_sha256([f])
    assert reads == [1, 1, 1, 1]
    assert sum(str(other) in r.getMessage() for r in caplog.records) == 1


def test_without_a_cache_every_call_reads(tmp_path, hash_cache, monkeypatch):
    import typ.hashcache

    _, reads = hash_cache
    monkeypatch.delenv(typ.hashcache.ENV)
    f = tmp_path / "a.bin"
    f.write_bytes(b"abc")
    assert hash_files([f]) == hash_files([f]) == _reference_sha256([f]) and reads == [1, 1]


def test_check_folder_names_a_file_or_a_dangling_link_in_the_way(tmp_path):
    from typ.errors import TypError
    from typ.io import check_folder

    (tmp_path / "a").mkdir()
    assert check_folder(tmp_path / "a" / "b" / "c", where="w", field="f") == tmp_path / "a" / "b" / "c"
    (tmp_path / "a" / "file").write_text("x")
    with pytest.raises(TypError, match="a/file is a file, not a folder"):
        check_folder(tmp_path / "a" / "file" / "c", where="w", field="f")
    (tmp_path / "a" / "gone").symlink_to(tmp_path / "nowhere")
    with pytest.raises(TypError, match="a/gone is a file, not a folder"):
        check_folder(tmp_path / "a" / "gone" / "c", where="w", field="f")


def test_check_folder_is_not_fooled_by_a_folder_another_writer_makes(tmp_path):
    """Parallel scenario writes under a new split: a folder made between two checks of one name
    was taken for a file (a fresh clone's end-to-end run failed on it). 8 threads x 100 rounds
    raced 145 times in 2400 calls before the fix."""
    import os
    import threading

    from typ.errors import TypError
    from typ.io import check_folder

    errors = []

    def writer(base, k, barrier):
        barrier.wait()
        try:
            check_folder(base / "sim" / "split" / f"s{k}", where="w", field="f")
            os.makedirs(base / "sim" / "split" / f"s{k}", exist_ok=True)
        except TypError as exc:
            errors.append(str(exc))

    for r in range(100):
        barrier = threading.Barrier(8)
        threads = [threading.Thread(target=writer, args=(tmp_path / str(r), k, barrier)) for k in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert errors == []
