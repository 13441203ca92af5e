"""Bad-input cases: what typ may write and delete: links, manifests, locks, two roots, archives
(registered with :func:`bad_inputs.make_corpus.case`).

Each case puts something in typ's way that, trusted, would make it write over or delete a file it
did not write: a lock path that is a link, a hard link, a FIFO or a user's file; a folder claiming to
be typ's by a manifest, a record or an archive; an output folder reached through a link. The call
must raise typ's named error, and the case's folder (a user's file ``precious.txt`` in it) must be
byte for byte as it was (tests/fuzz/test_bad_inputs.py; the top-level ``.typ/`` it ignores is where
these cases plant their locks, so the precious file beside it is what shows a write).
"""
from __future__ import annotations

import json
import os
import tarfile
from pathlib import Path

from bad_inputs.make_corpus import Probe, case, write
from typ.io import atomic_path, lock_path, output_lock, record_path, write_manifest

PRECIOUS = "years of work"


def _precious(d: Path) -> Path:
    return write(d / "precious.txt", PRECIOUS)


def _hold(out: Path) -> None:
    with output_lock("generate", out):
        pass


def _lock_probe(d: Path, plant) -> Probe:
    """An output folder ``d/out`` whose lock path ``plant(path, precious)`` fills; taking the lock must fail."""
    out, precious = d / "out", _precious(d)
    path = lock_path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    plant(path, precious)
    return Probe(says=("lock", str(path.parent)), call=lambda: _hold(out))


@case("io", "lock_is_a_link_to_a_users_file", "link")
def _(d):
    return _lock_probe(d, lambda path, precious: path.symlink_to(precious))


@case("io", "lock_is_a_hard_link_to_a_users_file", "link")
def _(d):
    probe = _lock_probe(d, lambda path, precious: os.link(precious, path))
    probe.says += ("hard link",)
    return probe


@case("io", "lock_is_a_users_file", "forged")
def _(d):
    probe = _lock_probe(d, lambda path, precious: path.write_text("a note of mine, not typ's lock"))
    probe.says += ("a file typ did not write",)
    return probe


@case("io", "lock_is_a_fifo", "not a regular file")
def _(d):
    return _lock_probe(d, lambda path, precious: os.mkfifo(path))


@case("io", "lock_folder_is_a_file", "not a regular file")
def _(d):
    def plant(path, precious):
        path.parent.rmdir()
        path.parent.write_text("mine")
    return _lock_probe(d, plant)


@case("io", "lock_folder_is_a_link", "link")
def _(d):
    def plant(path, precious):
        path.parent.rmdir()
        path.parent.symlink_to(precious.parent / "elsewhere")
        write(precious.parent / "elsewhere" / path.name, "mine")
    return _lock_probe(d, plant)


def _replace(target: Path, stage: str) -> None:
    """What a stage does to put a folder at ``target``."""
    with atomic_path(target, stage=stage) as tmp:
        tmp.mkdir()
        write_manifest(tmp, stage, {"key": "new"})


def _users_folder(d: Path, manifest: dict) -> Path:
    folder = d / "out" / "scen"
    write(folder / "_typ.json", json.dumps(manifest))
    write(folder / "notes.txt", PRECIOUS)
    return folder


@case("io", "folder_with_a_manifest_claiming_the_stage", "forged")
def _(d):
    folder = _users_folder(d, {"stage": "generate", "key": "k"})
    return Probe(says=(str(folder), "typ did not write"), call=lambda: _replace(folder, "generate"))


@case("io", "folder_with_a_legacy_manifest", "forged")
def _(d):
    folder = _users_folder(d, {"key": "k", "counts": {}})
    return Probe(says=(str(folder), "typ did not write"), call=lambda: _replace(folder, "simulate"))


@case("io", "folder_with_a_forged_record", "forged")
def _(d):
    folder = _users_folder(d, {"stage": "generate", "key": "k"})
    write(record_path(folder), json.dumps({"stage": "generate", "ino": os.stat(folder).st_ino, "tree": "0" * 64}))
    return Probe(says=(str(folder), "typ did not write"), call=lambda: _replace(folder, "generate"))


@case("io", "archive_of_typ_outputs_unpacked_in_place", "forged")
def _(d):
    """typ wrote the folder, it was archived with its record, deleted, and the archive unpacked where
    it was: the same bytes and record, but not the folder typ wrote (its inodes are new)."""
    folder = d / "out" / "scen"
    _replace(folder, "generate")
    archive = d.parent / f"{d.name}.tar"
    with tarfile.open(archive, "w") as tar:
        tar.add(d / "out", arcname="out")
    for p in sorted((d / "out").rglob("*"), reverse=True):
        p.rmdir() if p.is_dir() else p.unlink()
    with tarfile.open(archive) as tar:
        tar.extractall(d, filter="tar")
    archive.unlink()
    write(folder / "notes.txt", PRECIOUS)
    return Probe(says=(str(folder), "typ did not write"), call=lambda: _replace(folder, "generate"))


@case("io", "output_split_folder_is_a_link_out", "link")
def _(d):
    """A stage's output folder holds a link (an archive's, a careless user's) to a folder of the user's:
    writing a scenario below it would write there."""
    precious = _precious(d)
    out = d / "out"
    (out / "target").mkdir(parents=True)
    (out / "target" / "test").symlink_to(precious.parent)

    def write_scenario():
        with atomic_path(out / "target" / "test" / "precious.txt", stage="generate", inside=out) as tmp:
            tmp.write_text("typ's")
    return Probe(says=(str(out / "target" / "test"), "never writes through a link"), call=write_scenario)


@case("io", "file_in_a_folder_being_built_through_a_link", "link")
def _(d):
    _precious(d)
    (d / "out").mkdir()   # the output folder is there: what the case watches is that nothing lands anywhere

    def build():
        with atomic_path(d / "out" / "scen", stage="edit") as tmp:
            tmp.mkdir(parents=True)
            (tmp / "agent").symlink_to(d)
            with atomic_path(tmp / "agent" / "precious.txt") as inner:
                inner.write_text("typ's")
    return Probe(says=("agent", "never writes through a link"), call=build)
