"""Crash-safe file output, what typ may replace or delete, and content hashing.

Every file typ writes goes to a temporary name beside its final path and is renamed
into place only once complete, so a killed run never leaves a half-written file under
a final name, and a failed stage leaves the previous outputs intact.

typ replaces or deletes only what it can prove it wrote. The proof is a record typ keeps beside
each thing a stage puts in place (:func:`atomic_path` with ``stage``): ``<folder>/../.typ/written/
<folder name>/<name>.json`` (:func:`record_path`) holds the stage, the inode and a fingerprint of the whole tree (every entry's name,
kind, size, modification time and inode), taken as typ renamed it into place. A copy, an
unpacked archive, a folder a user added a note to, or a manifest anyone wrote (``_typ.json``)
does not match its record, so it is left alone (:func:`written_by`, :func:`remove_written`).
typ never writes through a link: a folder it is building holds real files only, and a stage's
writes under its output folder never pass a link (``inside``). One run at a time writes an
output folder, whatever root or name reaches it (:func:`output_lock`: a lock beside the folder's
real path): a run deletes the temporaries a killed run left, and another's would be in flight.
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
    """``folder``'s manifest: ``fields`` and the ``stage`` that wrote the folder (what it was made
    from, for the stage's own cache keys; the proof that typ wrote it is its record, :func:`written_by`)."""
    write_json(Path(folder) / SCENARIO_MANIFEST, {"stage": stage, **fields})


#: typ's own state beside what it writes: ``written/`` (its records) and the locks of the outputs there
STATE_DIR = ".typ"
#: a record is a few hundred bytes
_RECORD_MAX_BYTES = 64 * 1024


def hidden_below(path: str | os.PathLike, root: str | os.PathLike) -> bool:
    """Whether a part of ``path`` below ``root`` is hidden: a temporary, or typ's own state
    (:data:`STATE_DIR`, where its records and locks sit beside what it wrote)."""
    return any(part.startswith(".") for part in Path(path).relative_to(root).parts)


def record_path(path: str | os.PathLike) -> Path:
    """Where typ keeps its record of ``path`` (:func:`written_by`): one folder up, in the :data:`STATE_DIR`
    beside ``path``'s folder (``a/b/c`` -> ``a/.typ/written/b/c.json``), where the lock of an output
    folder ``b`` lives too (:func:`lock_path`). Never in ``path``'s own folder: a folder of scenarios
    holds scenarios only (OpenCOOD takes every sub-folder of a split for one)."""
    path = Path(os.path.abspath(path))
    folder = path.parent
    return (folder.parent / STATE_DIR / "written" / fit_name(folder.name or "_", NAME_MAX)
            / (fit_name(path.name, NAME_MAX - 5) + ".json"))


def _fingerprint(path: Path) -> dict | None:
    """``path``'s inode and a digest of its whole tree, not following links: each entry's relative
    name, kind, size, modification time and inode. None when nothing (or a link) is there.

    A file with names outside the tree (a hard link, as simulate imports a real scenario's clouds)
    counts by name, kind and inode alone: its bytes are the user's to change where they keep them,
    and deleting typ's name for it loses nothing (the other name keeps them)."""
    try:
        top = os.lstat(path)
    except OSError:
        return None
    if stat.S_ISLNK(top.st_mode):
        return None
    h = hashlib.sha256()
    entries = [("", top)]
    if stat.S_ISDIR(top.st_mode):
        entries = []
        for folder, dirs, files in os.walk(path):  # links to folders come in dirs and are not walked
            dirs.sort()
            for name in sorted(dirs + files):
                full = os.path.join(folder, name)
                try:
                    entries.append((os.path.relpath(full, path), os.lstat(full)))
                except OSError:
                    entries.append((os.path.relpath(full, path), None))  # gone while walking: cannot match
        # a folder's own times change with a rename on some file systems; what it holds says all
        h.update(f"{top.st_ino}\n".encode())
    names: dict[int, int] = {}
    for _, info in entries:
        if info is not None and stat.S_ISREG(info.st_mode):
            names[info.st_ino] = names.get(info.st_ino, 0) + 1
    for rel, info in entries:
        if info is None:
            h.update(f"{rel}\0gone\n".encode(errors="surrogateescape"))
        elif stat.S_ISREG(info.st_mode) and info.st_nlink > names[info.st_ino]:
            h.update(f"{rel}\0{stat.S_IFMT(info.st_mode)}\0shared\0{info.st_ino}\n".encode(errors="surrogateescape"))
        else:
            h.update(f"{rel}\0{stat.S_IFMT(info.st_mode)}\0{info.st_size}\0{info.st_mtime_ns}\0{info.st_ino}\n"
                     .encode(errors="surrogateescape"))
    return {"ino": top.st_ino, "tree": h.hexdigest()}


def _record(path: Path, stage: str, fingerprint: dict) -> None:
    record = record_path(path)
    state = record.parent.parent.parent
    # typ's state folder is typ's: a planted link or file there (an archive shipping a .typ/) is named, never followed
    for q in (state, state / "written", record.parent):
        if q.is_symlink() or (q.exists() and not q.is_dir()):
            raise TypError(record, f"{STATE_DIR}/ (typ's records of what it wrote)", "a folder typ made, not a link "
                           "or a file", f"{q} is {'a link to ' + os.readlink(q) if q.is_symlink() else 'a file'}")
    record.parent.mkdir(parents=True, exist_ok=True)
    write_json(record, {"stage": stage, **fingerprint})


def written_by(path: str | os.PathLike, stage: str) -> bool:
    """Whether ``path`` (a folder or a file, not a link) is exactly what ``stage`` put there: its
    record (:func:`record_path`) names ``stage`` and its inode and tree fingerprint are the ones typ
    recorded. A manifest inside a folder proves nothing: a copy, an archive, or a note a user added
    changes the fingerprint."""
    path = Path(path)
    record = record_path(path)
    try:
        info = os.lstat(record)
    except OSError:
        return False
    if not stat.S_ISREG(info.st_mode) or info.st_size > _RECORD_MAX_BYTES:
        return False
    found = read_json_or_none(record)
    if not isinstance(found, dict) or found.get("stage") != stage:
        return False
    now = _fingerprint(path)
    return now is not None and {k: found.get(k) for k in now} == now


def remove_written(path: str | os.PathLike, stage: str) -> bool:
    """Delete ``path`` and its record when ``stage`` wrote it (:func:`written_by`); returns whether it did.
    Anything else is left as it is."""
    path = Path(path)
    if not written_by(path, stage):
        return False
    shutil.rmtree(path) if path.is_dir() else path.unlink()
    forget(path)
    return True


def forget(path: str | os.PathLike) -> None:
    """Drop typ's record of ``path``, and the record folders that leaves empty."""
    record = record_path(path)
    record.unlink(missing_ok=True)
    for folder in (record.parent, record.parent.parent, record.parent.parent.parent):
        try:
            folder.rmdir()
        except OSError:  # not empty (other records, a lock) or not there
            return


def no_link_below(top: str | os.PathLike, path: str | os.PathLike, *, where: str | os.PathLike, field: str) -> None:
    """Raise TypError naming ``where`` and ``field`` when a folder between ``top`` (excluded: it may be a
    link the user made) and ``path`` (included) is a link, or ``path`` is not below ``top``: a write
    there would leave the output folder ``top`` through the link."""
    top, path = Path(os.path.abspath(top)), Path(os.path.abspath(path))
    if path != top and top not in path.parents:
        raise TypError(where, field, f"a path inside the output folder {top}", str(path))
    for p in (path, *path.parents):
        if p == top:
            return
        if os.path.islink(p):
            raise TypError(where, field, f"a path that stays inside the output folder {top}: typ never writes "
                           "through a link", f"{p} is a link to {os.readlink(p)}")


def _no_link_in_the_making(final: Path) -> None:
    """A file written into a folder typ is building (a temporary of :func:`atomic_path`) must land in
    that folder: no link between them (a copied scenario's agent folder linked to a dataset elsewhere
    would let the write replace the dataset's file)."""
    for p in final.parents:
        if is_temporary(p):
            no_link_below(p, final.parent, where=final, field="folder")
            return


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, stage: str | None = None,
                inside: str | os.PathLike | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    Works for files and folders. With ``stage``, what is renamed into place is recorded as that
    stage's (:func:`written_by`), and it replaces an existing ``path`` only when that is what the
    stage wrote; anything else there raises TypError and is left as it is. A folder made at the
    temporary path must then hold the manifest of ``stage`` (:func:`write_manifest`). A file never
    replaces a folder. With ``inside`` (the stage's output folder), no folder between it and
    ``path`` may be a link (:func:`no_link_below`); and a file written inside a folder typ is building
    never passes a link. The temporary names fit :data:`NAME_MAX` whatever the length of ``path``'s
    name; a name that does not fit itself, or a file where a parent folder goes, raises TypError.
    """
    final = Path(path)
    if len(os.fsencode(final.name)) > NAME_MAX:
        raise TypError(final.parent, "file name", f"at most {NAME_MAX} bytes",
                       f"{len(os.fsencode(final.name))} bytes: {final.name[:60]}...")
    check_folder(final.parent, where=final, field="folder")
    if inside is not None:
        no_link_below(inside, final, where=final, field="output")
    _no_link_in_the_making(final)
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
            _record(final, stage, _fingerprint(tmp))  # a rename keeps the inode and everything below it
            os.replace(tmp, final)
            if old is not None:
                shutil.rmtree(old, ignore_errors=True)
        else:
            if final.is_dir() and not final.is_symlink():
                raise TypError(final, "output", "a path free for a file", "a folder")
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
            if stage is not None:
                _check_replaceable(final, None, stage)
                _record(final, stage, _fingerprint(tmp))
            os.replace(tmp, final)
    finally:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        elif tmp.exists():
            tmp.unlink()


def _check_replaceable(final: Path, made: Path | None, stage: str | None) -> None:
    """Refuse to put ``made`` (a folder holding its stage's manifest; None: a file) at ``final`` unless
    ``final`` is free or is what that stage wrote."""
    if stage is None or (made is not None and (read_json_or_none(made / SCENARIO_MANIFEST) or {}).get("stage") != stage):
        raise ValueError(f"{final}: a folder typ writes names its stage and holds its manifest (typ.io.write_manifest)")
    if (final.exists() or final.is_symlink()) and not written_by(final, stage):
        what = "a link" if final.is_symlink() else "a folder" if final.is_dir() else "a file"
        raise TypError(final, "output", f"a path that is free or holds what typ's {stage} wrote there (its record "
                       f"in {record_path(final).parent.parent} matches it): typ replaces nothing it did not write, "
                       "and a copy, an archive or a file added since is not what it wrote; move it away",
                       f"{what} typ did not write, or changed since")


class OutputBusy(TypError):
    """Another run holds the lock on the same output folder (:func:`output_lock`)."""


#: what a lock file holds: its holder, written by typ (anything else there is not typ's lock file)
_LOCK_TEXT = re.compile(rb"(pid [0-9]+ \([^\n]*\): [^\n]*\n)?")
_LOCK_MAX_BYTES = 4096


def lock_path(out: str | os.PathLike) -> Path:
    """The lock file of output folder ``out``: beside its real path (``<parent>/.typ/<name>.lock``), so
    every root and every name that reaches the folder (relative, with ``..``, through a link) shares it."""
    real = Path(os.path.realpath(out))
    return real.parent / STATE_DIR / (fit_name(real.name, NAME_MAX - 5) + ".lock")


@contextlib.contextmanager
def output_lock(stage: str, out: str | os.PathLike) -> Iterator[None]:
    """Hold the lock on output folder ``out`` for ``stage``'s block; a second run, in this process or
    another, is refused at once with :class:`OutputBusy` naming the holder's pid.

    The lock is an flock on :func:`lock_path`: the kernel drops it when its holder ends, by SIGKILL
    too, so a crash never leaves the output locked. It is opened without following a link, and it
    must be a regular file with one name that typ wrote (empty, or its holder line): a link, a hard
    link to a user's file, a folder, a FIFO or a user's file there is named, never written. It holds
    the holder's pid, stage and command, for the message; it is not deleted (a lock file removed
    while another process waits on it would let a third one in).
    """
    path = lock_path(out)
    fd = _open_lock(path)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 512, 0).decode(errors="replace").strip() or "another process"
            raise OutputBusy(Path(os.path.realpath(out)), "lock", f"no other run writing this output ({stage}): "
                             "wait for it to end, or stop it", f"held by {holder} ({path})") from None
        os.ftruncate(fd, 0)
        holder = f"pid {os.getpid()} ({stage}): {' '.join(sys.argv)[:400]}".replace("\n", " ")
        os.pwrite(fd, holder.encode(errors="replace") + b"\n", 0)
        yield
    finally:
        os.close(fd)


def _open_lock(path: Path) -> int:
    """A descriptor of lock file ``path``, made by typ or checked to be typ's; else TypError naming it."""
    expected = "a lock file typ made (a regular file with one name, holding its holder's pid)"
    check_folder(path.parent, where=path, field="lock folder")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        folder = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        got = f"{path.parent} is a link" if os.path.islink(path.parent) else f"{path.parent}: {exc.strerror}"
        raise TypError(path, "lock folder", "a folder typ can make, not a link", got) from None
    try:
        fd = os.open(path.name, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o644,
                     dir_fd=folder)
    except OSError as exc:
        got = "a link" if os.path.islink(path) else "a folder" if os.path.isdir(path) else exc.strerror
        raise TypError(path, "lock", expected, got) from None
    finally:
        os.close(folder)
    info = os.fstat(fd)
    problem = ("not a regular file" if not stat.S_ISREG(info.st_mode)
               else f"a file with {info.st_nlink} names (a hard link)" if info.st_nlink != 1
               else "a file typ did not write" if info.st_size > _LOCK_MAX_BYTES
               or _LOCK_TEXT.fullmatch(os.pread(fd, _LOCK_MAX_BYTES, 0)) is None else None)
    if problem:
        os.close(fd)
        raise TypError(path, "lock", expected, problem)
    return fd


def write_bytes(path: str | os.PathLike, data: bytes, *, stage: str | None = None) -> None:
    """``data`` at ``path``, atomically; with ``stage``, recorded as that stage's (:func:`atomic_path`)."""
    with atomic_path(path, stage=stage) as tmp:
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


def seed_dir(parent: str | os.PathLike, seed: int) -> Path:
    """``parent/seed_<k>``: what training seed ``k`` of one network (or one stage's set of
    networks) made, its checkpoints too. Every stage names a seed's folder so."""
    return Path(parent) / f"seed_{seed}"


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
