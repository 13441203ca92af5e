"""Crash-safe file output, what typ may replace or delete, and content hashing.

Every file typ writes goes to a temporary name beside its final path and is renamed
into place only once complete, so a killed run never leaves a half-written file under
a final name, and a failed stage leaves the previous outputs intact.

typ replaces or deletes a folder only when it can prove it wrote it: every folder it puts in
place holds a manifest naming the stage that wrote it (:func:`write_manifest`,
:func:`written_by`). A user's folder in an output folder is left alone. One run of a stage
at a time writes an output (:func:`output_lock`): a run deletes the temporaries a killed run
left, and another's would be in flight.
"""
from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import re
import shutil
import stat
import sys
import tempfile
from pathlib import Path
from typing import Iterator

from typ.errors import TypError
from typ.hashcache import cached_digest
from typ.inputs import MiB, read_regular

TMP_PREFIX = ".tmp-"
#: the longest file name ext4, xfs and btrfs take, in bytes (NAME_MAX)
NAME_MAX = 255
#: the most a temporary name adds to a name: the prefix, ``old-``, ``.`` and mkstemp's 8 characters or a pid
_TMP_EXTRA = len(TMP_PREFIX) + len("old-.") + 10

#: the manifest typ writes into every folder it makes (a scenario of simulate or generate, a
#: ``typ edit`` copy, a frame ``typ generate`` takes in); it names the stage that wrote the folder
SCENARIO_MANIFEST = "_typ.json"
#: a manifest larger than this is not typ's (typ's are a few hundred bytes)
_MANIFEST_MAX_BYTES = 1 << 20


def fit_name(name: str, room: int = NAME_MAX) -> str:
    """``name`` when it takes at most ``room`` bytes; else its start and its end (which says what a
    file is: ``_agents.png``) around a digest of the whole name, in ``room`` bytes: names that
    differ stay different."""
    raw = os.fsencode(name)
    if len(raw) <= room:
        return name
    tail = f"~{hashlib.sha256(raw).hexdigest()[:12]}~{name[-min(32, room // 4):]}"
    head = name[:room]
    while len(os.fsencode(head + tail)) > room:
        head = head[:-1]
    return head + tail


def check_folder(path: str | os.PathLike, *, where: str | os.PathLike, field: str) -> Path:
    """``path``, when it is a folder or one can be made there: no part of it is a file, no name in
    it is longer than :data:`NAME_MAX`. Otherwise TypError naming ``where`` and ``field``."""
    path = Path(path)
    for part in path.parts:
        if len(os.fsencode(part)) > NAME_MAX:
            raise TypError(where, field, f"a folder whose names take at most {NAME_MAX} bytes",
                           f"a name of {len(os.fsencode(part))} bytes: {part[:60]}...")
    for p in (path, *path.parents):
        # one stat per name: checking is_dir() and then exists() let a folder another writer made
        # between the two calls (parallel scenario writes under a new split) pass for a file
        try:
            if stat.S_ISDIR(os.stat(p).st_mode):
                break
        except (FileNotFoundError, NotADirectoryError):
            if not os.path.islink(p):   # nothing there (a dangling link is something)
                continue
        raise TypError(where, field, "a folder, or a path where one can be made", f"{p} is a file, not a folder")
    return path


def write_manifest(folder: str | os.PathLike, stage: str, fields: dict) -> None:
    """``folder``'s manifest: ``fields`` and the ``stage`` that wrote the folder, typ's proof that
    the folder is its own to replace or delete (:func:`written_by`)."""
    write_json(Path(folder) / SCENARIO_MANIFEST, {"stage": stage, **fields})


def written_by(folder: str | os.PathLike, stage: str) -> bool:
    """Whether ``folder`` is a folder (not a link) holding the manifest of ``stage``.

    A manifest from before manifests named their stage (a ``key`` and ``counts``, no ``stage``)
    counts as the stage's: only typ wrote those."""
    folder, manifest = Path(folder), Path(folder) / SCENARIO_MANIFEST
    if folder.is_symlink() or not folder.is_dir() or not manifest.is_file() or manifest.is_symlink() \
            or manifest.stat().st_size > _MANIFEST_MAX_BYTES:
        return False
    found = read_json_or_none(manifest)
    if not isinstance(found, dict):
        return False
    if "stage" in found:
        return found["stage"] == stage
    return isinstance(found.get("key"), str) and isinstance(found.get("counts"), dict)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, stage: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    Works for files and folders. A folder made at the temporary path must hold the manifest of
    ``stage`` (:func:`write_manifest`), and it replaces an existing ``path`` (swapped out, then
    removed) only when that is a folder ``stage`` wrote (:func:`written_by`); anything else there
    raises TypError and is left as it is. A file never replaces a folder. The temporary names
    fit :data:`NAME_MAX` whatever the length of ``path``'s name; a name that does not fit itself,
    or a file where a parent folder goes, raises TypError naming the path.
    """
    final = Path(path)
    if len(os.fsencode(final.name)) > NAME_MAX:
        raise TypError(final.parent, "file name", f"at most {NAME_MAX} bytes",
                       f"{len(os.fsencode(final.name))} bytes: {final.name[:60]}...")
    check_folder(final.parent, where=final, field="folder")
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TypError(final, "folder", "a folder typ can make", f"{final.parent}: {exc.strerror}") from None
    short = fit_name(final.name, NAME_MAX - _TMP_EXTRA)
    fd, tmp_name = tempfile.mkstemp(prefix=f"{TMP_PREFIX}{short}.", dir=final.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    tmp.unlink()
    try:
        yield tmp
        if tmp.is_dir():
            _check_replaceable(final, tmp, stage)
            old = None
            if final.exists():
                old = final.with_name(f"{TMP_PREFIX}old-{short}.{os.getpid()}")
                os.replace(final, old)
            os.replace(tmp, final)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        else:
            if final.is_dir() and not final.is_symlink():
                raise TypError(final, "output", "a path free for a file", "a folder")
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
            os.replace(tmp, final)
    finally:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        elif tmp.exists():
            tmp.unlink()


def _check_replaceable(final: Path, made: Path, stage: str | None) -> None:
    """Refuse to put folder ``made`` at ``final`` unless it names its stage and ``final`` is free or
    that stage's folder."""
    if stage is None or not written_by(made, stage):
        raise ValueError(f"{final}: a folder typ writes holds the manifest of its stage (typ.io.write_manifest)")
    if (final.exists() or final.is_symlink()) and not written_by(final, stage):
        raise TypError(final, "output folder", f"a path that is free or holds a folder typ's {stage} wrote "
                       f"(its {SCENARIO_MANIFEST}): typ replaces nothing it did not write; move it away",
                       "a folder typ did not write" if final.is_dir() else "a file")


class OutputBusy(TypError):
    """Another run of the stage holds the lock on the same output (:func:`output_lock`)."""


@contextlib.contextmanager
def output_lock(root: str | os.PathLike, stage: str, out: str | os.PathLike) -> Iterator[None]:
    """Hold ``stage``'s lock on its output folder ``out`` for the block; a second run, in this
    process or another, is refused at once with :class:`OutputBusy` naming the holder's pid.

    The lock is an flock on ``<root>/.typ/locks/<stage>-<digest of out>.lock``: the kernel drops
    it when its holder ends, by SIGKILL too, so a crash never leaves the output locked. The file
    holds the holder's pid and command, for the message; it is not deleted (a lock file removed
    while another process waits on it would let a third one in).
    """
    target = Path(out).resolve()
    locks = Path(root) / ".typ" / "locks"
    locks.mkdir(parents=True, exist_ok=True)
    path = locks / f"{stage}-{hashlib.sha256(str(target).encode()).hexdigest()[:16]}.lock"
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 512, 0).decode(errors="replace").strip() or "another process"
            raise OutputBusy(target, "lock", f"no other run of stage {stage} writing this output: wait for it to "
                             f"end, or stop it", f"held by {holder} ({path})") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()}: {' '.join(sys.argv)[:400]}\n".encode(), 0)
        yield
    finally:
        os.close(fd)


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


#: the names :func:`atomic_path` gives its temporaries: the prefix, the final name, and mkstemp's
#: 8 characters or (the folder being swapped out) a pid
_TEMPORARY = re.compile(re.escape(TMP_PREFIX) + r".+\.([a-z0-9_]{8}|[0-9]+)")


def is_temporary(path: str | os.PathLike) -> bool:
    """Whether ``path`` is named as :func:`atomic_path` names its temporaries."""
    return _TEMPORARY.fullmatch(Path(path).name) is not None


def temporaries(root: str | os.PathLike) -> Iterator[Path]:
    """The temporaries of :func:`atomic_path` under ``root`` (a killed run's, or one in flight)."""
    return (p for p in Path(root).rglob(TMP_PREFIX + "*") if is_temporary(p))


def remove_stale_temporaries(root: str | os.PathLike) -> int:
    """Delete the temporaries a killed run left under ``root`` (:func:`temporaries`: named as typ names
    them; hold the stage's :func:`output_lock`, or another run's may be in flight); returns how many."""
    removed: list[Path] = []
    for p in sorted(temporaries(root)):  # a folder before what it holds, which goes with it
        if any(folder in p.parents for folder in removed):
            continue
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        removed.append(p)
    return len(removed)


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
