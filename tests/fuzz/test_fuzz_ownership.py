"""Seeded fuzzing of what typ may delete or replace: random output folders, nothing lost.

Each seed fills a stage's output split with a random mix of what a user's disk holds: folders
typ's stage wrote (some with a note added since), folders claiming to be typ's (a manifest naming
the stage, the legacy form, a forged record, a copy of typ's folder, an archive of one unpacked
where it was), links to a user's folder or file outside, and plain files. Then the stage's clean-up
of stale outputs (:func:`flows.common.remove_stale`) and a replacement of every entry
(:func:`typ.io.atomic_path`) run over all of them. Exactly the folders typ wrote and nobody touched
go; everything else, and everything outside, is byte for byte as it was, and every refusal is
typ's named error. A seed runs in a forked child bounded to 20 s and 1 GiB more (tests/helpers/bounded.py).
"""
from __future__ import annotations

import json
import os
import random
import shutil
import tarfile
from pathlib import Path

import pytest

from bounded import run_bounded

STAGE = "generate"
KINDS = ("typ", "typ_noted", "manifest", "legacy", "forged_record", "copy", "archive", "link_folder", "link_file",
         "file")


def _typ_wrote(folder: Path, rng: random.Random) -> None:
    from typ.io import atomic_path, write_manifest

    with atomic_path(folder, stage=STAGE) as tmp:
        tmp.mkdir(parents=True)
        for k in range(rng.randint(1, 3)):
            (tmp / "1").mkdir(exist_ok=True)
            (tmp / "1" / f"{k:06d}.pcd").write_bytes(rng.randbytes(rng.randint(0, 64)))
        write_manifest(tmp, STAGE, {"key": "k"})


def _arrange(root: Path, rng: random.Random) -> dict[str, str]:
    """A random output split under ``root/out`` and a user's folder ``root/outside``; {entry: kind}."""
    from typ.io import record_path

    split, outside = root / "out" / "target" / "test", root / "outside"
    split.mkdir(parents=True)
    outside.mkdir()
    (outside / "thesis.tex").write_text("years of work")
    kinds = {}
    for i in range(rng.randint(4, 12)):
        kind, name = rng.choice(KINDS), f"s{i:02d}"
        folder = split / name
        if kind in ("typ", "typ_noted", "copy", "archive"):
            _typ_wrote(folder, rng)
        if kind == "typ_noted":
            (folder / rng.choice(["notes.txt", "1/notes.txt"])).write_text("mine")
        elif kind in ("manifest", "legacy", "forged_record"):
            folder.mkdir()
            (folder / "000000.pcd").write_bytes(b"points")
            (folder / "_typ.json").write_text(json.dumps({"stage": STAGE, "key": "k"} if kind != "legacy"
                                                         else {"key": "k", "counts": {}}))
            if kind == "forged_record":
                record_path(folder).parent.mkdir(parents=True, exist_ok=True)
                record_path(folder).write_text(json.dumps({"stage": STAGE, "ino": os.stat(folder).st_ino,
                                                           "tree": "%064x" % rng.getrandbits(256)}))
        elif kind == "copy":   # typ's folder, moved away and copied back: same bytes, same times, new inodes
            shutil.move(folder, root / "moved")
            shutil.copytree(root / "moved", folder, copy_function=shutil.copy2)
            shutil.rmtree(root / "moved")
        elif kind == "archive":
            with tarfile.open(root / "a.tar", "w") as tar:
                tar.add(folder, arcname=name)
            shutil.rmtree(folder)
            with tarfile.open(root / "a.tar") as tar:
                tar.extractall(split, filter="tar")
            (root / "a.tar").unlink()
        elif kind == "link_folder":
            folder.symlink_to(outside)
        elif kind == "link_file":
            folder.symlink_to(outside / "thesis.tex")
        elif kind == "file":
            folder.write_text("a file of mine")
        kinds[name] = kind
    return kinds


def _state(root: Path) -> dict[str, object]:
    """Every path under ``root`` but typ's records: a file's bytes, a link's target, None for a folder."""
    return {str(p.relative_to(root)): (f"-> {os.readlink(p)}" if p.is_symlink() else p.read_bytes() if p.is_file()
                                       else None)
            for p in sorted(root.rglob("*")) if ".typ" not in p.parts}


def _one_seed(root: Path, seed: int) -> str:
    from flows.common import remove_stale
    from typ.errors import TypError
    from typ.io import atomic_path, write_manifest

    rng = random.Random(seed)
    kinds = _arrange(root, rng)
    split = root / "out" / "target" / "test"
    ours = {name for name, kind in kinds.items() if kind == "typ"}
    before = _state(root)
    removed = remove_stale(STAGE, root / "out", [split / name for name in sorted(kinds)])
    assert removed == len(ours), (removed, kinds)
    assert not any((split / name).exists() for name in ours)
    kept = {k: v for k, v in before.items() if not any(k.startswith(f"out/target/test/{n}") for n in ours)}
    assert _state(root) == kept, kinds
    for name in sorted(set(kinds) - ours):
        try:
            with atomic_path(split / name, stage=STAGE) as tmp:
                tmp.mkdir()
                write_manifest(tmp, STAGE, {"key": "new"})
        except TypError as exc:
            assert str(split / name) in str(exc) and "did not write" in str(exc), exc
        else:
            raise AssertionError(f"{name} ({kinds[name]}) was replaced")
    assert _state(root) == kept, kinds
    return "ok"


@pytest.mark.parametrize("seed", range(24))
def test_random_output_folders_lose_nothing_typ_did_not_write(tmp_path, seed):
    outcome = run_bounded(lambda: _one_seed(tmp_path, seed), seconds=20, memory=1 << 30, keep=lambda v: v)
    assert outcome.kind == "returned" and outcome.value == "ok", str(outcome)
