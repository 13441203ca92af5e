"""Crash-safe file output and content hashing.

Every file typ writes goes to a temporary name beside its final path and is renamed
into place only once complete, so a killed run never leaves a half-written file under
a final name, and a failed stage leaves the previous outputs intact.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from typ.hashcache import cached_digest
from typ.inputs import MiB, read_regular

TMP_PREFIX = ".tmp-"


#: the manifest a per-scene stage (simulate, generate) writes beside each scenario it made
SCENARIO_MANIFEST = "_typ.json"


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    Works for files and directories: whatever the block creates at the temporary path
    replaces ``path`` (an existing directory is swapped out, then removed).
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=TMP_PREFIX + final.name + ".", dir=final.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    tmp.unlink()
    try:
        yield tmp
        if tmp.is_dir():
            old = None
            if final.exists():
                old = final.with_name(f"{TMP_PREFIX}old-{final.name}.{os.getpid()}")
                os.replace(final, old)
            os.replace(tmp, final)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        else:
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, final)
    finally:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        elif tmp.exists():
            tmp.unlink()


def write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | os.PathLike, text: str) -> None:
    write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj) -> None:
    write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n")


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def remove_stale_temporaries(root: str | os.PathLike) -> int:
    """Delete temporaries a killed run left under ``root``; returns how many."""
    n = 0
    for p in Path(root).rglob(TMP_PREFIX + "*"):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        n += 1
    return n


def hash_files(paths, *, extra: str = "") -> str:
    """sha256 over the bytes of ``paths`` (in the given order) and their names, plus ``extra``.

    Files whose stat is as it was when they were last hashed are not read again when the CLI has
    set up the project's cache (:mod:`typ.hashcache`); the digest is the same either way."""
    paths = [Path(p) for p in paths]
    return cached_digest(paths, extra, lambda: _read_digest(paths, extra))


def _read_digest(paths: list[Path], extra: str) -> str:
    h = hashlib.sha256()
    for p in paths:
        h.update(p.name.encode())
        h.update(b"\0")
        with open(p, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
        h.update(b"\0")
    h.update(extra.encode())
    return h.hexdigest()


def hash_obj(obj) -> str:
    """Stable sha256 of a JSON-able object (dict keys sorted)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=_json_default).encode()).hexdigest()


def read_json_or_none(path: str | os.PathLike):
    """Parsed JSON at ``path``, or None when the file is absent or not valid JSON (e.g. foreign).

    A path that is there but is no regular file (a FIFO, a device) or is larger than a manifest
    can be raises TypError (:func:`typ.inputs.read_regular`): reading it could block or never end."""
    if not os.path.exists(path):
        return None
    raw = read_regular(path, "JSON file", max_bytes=16 * MiB)
    try:
        return json.loads(raw.decode("utf-8"))
    except (ValueError, RecursionError):  # not JSON, not UTF-8 (UnicodeDecodeError is a ValueError), too deep
        return None


def code_digest(*modules) -> str:
    """sha256 of the source files of ``modules`` (a package counts with all its ``.py`` files).

    Part of every per-scene cache key, so that a change to the code that produced a stored
    output redoes it even when its inputs and params did not change.
    """
    files = []
    for mod in modules:
        path = Path(mod.__file__)
        files.extend(sorted(path.parent.glob("*.py")) if path.name == "__init__.py" else [path])
    return hash_files(files)[:16]
