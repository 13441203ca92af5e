"""Reading what a user hands typ: a regular file of plausible size, YAML and JSON parsed within bounds.

A reader pointed at ``/dev/zero``, a FIFO or a sparse file of terabytes must fail at once with a
:class:`~typ.errors.TypError`, not read forever or until memory runs out. YAML nests and aliases
without bound: a 540-byte "billion laughs" document expands to 10^9 nodes, and 100 KB of ``[``
overflows the C stack of libyaml's composer (the interpreter dies). JSON nests until Python's
recursion limit. So every reader of user input opens its file through :func:`open_regular` (or
:func:`read_regular` / :func:`read_text`) and parses through :func:`load_yaml` / :func:`load_json`,
with a size cap that fits what the file holds; values that must be numbers go through
:func:`finite_numbers`, which turns a 400-digit integer into a TypError, not an OverflowError.

A path that a dataset names (an index's entry, a split file's frame id, a file or folder found in
it) is taken only through :func:`inside`: it must lead to a place inside the dataset's root, links
followed, so that a hostile or careless index cannot make typ read a file from elsewhere.
"""
from __future__ import annotations

import contextlib
import json
import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Iterator

import numpy as np
import yaml

from typ.errors import TypError

MiB = 1 << 20
#: deeper than this, no file typ reads has a reason to nest (OPV2V: 4 levels, params: 5)
MAX_DEPTH = 32
#: YAML nodes (scalars, lists, mappings) in one document once aliases are expanded: an OPV2V yaml
#: with 100 vehicles has about 3,000, params.yaml about 1,000
MAX_YAML_NODES = 100_000


def inside(path: str | os.PathLike, root: str | os.PathLike, *, where: str | os.PathLike | None = None,
           field: str = "path") -> Path:
    """``path`` as typ opens it (``root / path``; an absolute ``path`` as it is) when it leads to a place
    inside ``root``, else TypError naming ``where`` (default: the joined path) and ``field``.

    Every reader of a dataset takes each path the dataset names through this one check: an index's
    entry (a nuScenes ``lidar_path``), a split file's frame id, and a file or folder found by listing
    the root (a KITTI ``velodyne/*.bin``, an OPV2V agent's ``.pcd``: there each agent folder is the
    root, :func:`typ.formats.opv2v.agent_file`). "Inside" is decided on real paths
    (:func:`os.path.realpath`: ``..`` resolved and every link on the way followed, a link that
    does not resolve included), so an absolute path, a ``..`` that climbs out, and a link in the root
    whose target lies elsewhere are all refused before anything is opened. The root itself may be a
    link (a user pointing at a dataset kept elsewhere): the check compares against its real path.
    The path returned is the one named (not its real path), so names derived from it (a scenario
    named after its file) stay what the dataset calls them.

    Usage, for a new reader: ``bin_path = inside(record_path, root, where=index_file, field="lidar_path")``,
    then open ``bin_path`` with :func:`open_regular` / :func:`read_regular`.
    """
    named = Path(root) / path
    try:
        real_root, real = os.path.realpath(root), os.path.realpath(named)
    except ValueError:   # a NUL character, which no file name holds
        raise TypError(root if where is None else where, field, "a path without NUL characters",
                       os.fspath(path)) from None
    if real != real_root and not real.startswith(real_root.rstrip(os.sep) + os.sep):
        shown = str(root) if os.path.abspath(root) == real_root else f"{root} (real path {real_root})"
        raise TypError(named if where is None else where, field,
                       f"a path inside {shown}: relative to it, without a '..' that climbs out, and through "
                       "no link that leads elsewhere", f"{os.fspath(path)} -> {real}")
    return named


def _size_text(n: int) -> str:
    return f"{n / MiB:g} MiB" if n >= MiB else f"{n} bytes"


def _file_kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return f"{name}, not a regular file"
    return "not a regular file"


@contextlib.contextmanager
def open_regular(path: str | os.PathLike, noun: str, *, max_bytes: int, field: str = "file",
                 missing: str | None = None) -> Iterator[tuple[BinaryIO, int]]:
    """Yield ``(binary file, size in bytes)`` of a regular file of at most ``max_bytes``.

    Opened without blocking (a FIFO with no writer would block ``open`` itself) and checked by
    ``fstat`` on the open descriptor, so what is checked is what is read. TypError ``field``:
    ``an existing <noun>`` (or ``missing``) when there is no such file, ``a readable <noun>``
    when it cannot be opened or is a directory, FIFO, device or socket, and the cap when larger.
    """
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise TypError(p, field, missing or f"an existing {noun}", "no such file") from None
    except OSError as exc:
        raise TypError(p, field, f"a readable {noun}", f"{type(exc).__name__}: {exc.strerror}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise TypError(p, field, f"a readable {noun}", _file_kind(info.st_mode))
        if info.st_size > max_bytes:
            raise TypError(p, field, f"a {noun} of at most {_size_text(max_bytes)}", f"{info.st_size} bytes")
        os.set_blocking(fd, True)
        f = os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
    with f:
        yield f, info.st_size


def read_regular(path: str | os.PathLike, noun: str, *, max_bytes: int, field: str = "file",
                 missing: str | None = None) -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (:func:`open_regular`'s checks)."""
    with open_regular(path, noun, max_bytes=max_bytes, field=field, missing=missing) as (f, size):
        try:
            return f.read(size)  # no more than fstat said: a file that grows while read is not followed
        except OSError as exc:
            raise TypError(path, field, f"a readable {noun}", f"{type(exc).__name__}: {exc.strerror}") from None


def read_text(path: str | os.PathLike, noun: str, *, max_bytes: int, field: str = "file",
              missing: str | None = None, encoding: str = "utf-8") -> str:
    """:func:`read_regular` decoded; bytes that are not ``encoding`` raise ``a readable <noun>``."""
    raw = read_regular(path, noun, max_bytes=max_bytes, field=field, missing=missing)
    try:
        return raw.decode(encoding)
    except UnicodeDecodeError as exc:
        raise TypError(path, field, f"a readable {noun}",
                       f"not {encoding.upper()} text (UnicodeDecodeError at byte {exc.start})") from None


def load_yaml(path: str | os.PathLike, noun: str, *, max_bytes: int, loader: type = yaml.SafeLoader,
              field: str = "file", missing: str | None = None):
    """The YAML document in ``path``, parsed by ``loader`` (a safe loader) within bounds.

    Before anything is built, the parser's events are counted: nesting deeper than
    :data:`MAX_DEPTH`, more than :data:`MAX_YAML_NODES` nodes with every alias expanded
    (a "billion laughs"), or a key repeated in one mapping, raises TypError. Aliases
    themselves are allowed: PyYAML's own ``safe_dump`` writes one wherever a list appears
    twice in what it dumps. Malformed YAML,
    and scalars the loader cannot build (an integer of 5,000 digits, a date of month 13),
    raise TypError with the position, field ``yaml`` (the file's own problems: ``field``).
    """
    text = read_text(path, noun, max_bytes=max_bytes, field=field, missing=missing)
    field = "yaml"
    try:
        _check_yaml_events(path, noun, field, yaml.parse(text, Loader=loader))
        return yaml.load(text, Loader=loader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f"line {mark.line + 1}, column {mark.column + 1}" if mark else "unknown position"
        raise TypError(path, field, "well-formed YAML", f"{getattr(exc, 'problem', None) or exc} at {at}") from None
    except (ValueError, OverflowError, RecursionError) as exc:  # a scalar the constructor cannot build
        raise TypError(path, field, "well-formed YAML with values of their type", f"{type(exc).__name__}: {exc}") \
            from None


def _check_yaml_events(path, noun: str, field: str, events) -> None:
    """Refuse nesting deeper than MAX_DEPTH, more than MAX_YAML_NODES nodes once aliases are
    expanded, and a mapping that repeats a key (PyYAML keeps the last one silently: a vehicle
    whose id was mistyped as another's would vanish).

    The parser (libyaml's or PyYAML's) produces events without recursion; only the composer
    that builds the document recurses, and it runs after this check.
    """
    nodes = 0
    open_: list[_Collection] = []
    sizes: dict[str, int] = {}  # anchor -> expanded node count of the node it names
    for event in events:
        at = f"line {event.start_mark.line + 1}"
        if isinstance(event, yaml.NodeEvent) and open_ and open_[-1].keys is not None:
            parent = open_[-1]
            if parent.expect_key and isinstance(event, yaml.ScalarEvent):
                if event.value in parent.keys:
                    raise TypError(path, field, f"a {noun} whose mappings name each key once",
                                   f"key {event.value[:40]!r} again at {at}")
                parent.keys.add(event.value)
            parent.expect_key = not parent.expect_key
        if isinstance(event, yaml.AliasEvent):
            nodes += sizes.get(event.anchor, 1)
        elif isinstance(event, yaml.ScalarEvent):
            nodes += 1
            if event.anchor is not None:
                sizes[event.anchor] = 1
        elif isinstance(event, yaml.CollectionStartEvent):
            open_.append(_Collection(event.anchor, nodes, set() if isinstance(event, yaml.MappingStartEvent) else None))
            nodes += 1
            if len(open_) > MAX_DEPTH:
                raise TypError(path, field, f"a {noun} nested at most {MAX_DEPTH} levels deep", f"deeper at {at}")
        elif isinstance(event, yaml.CollectionEndEvent):
            done = open_.pop()
            if done.anchor is not None:
                sizes[done.anchor] = nodes - done.before
        if nodes > MAX_YAML_NODES:
            raise TypError(path, field, f"a {noun} of at most {MAX_YAML_NODES} YAML nodes, aliases expanded",
                           f"more by {at}")


@dataclass
class _Collection:
    """A YAML sequence or mapping being parsed: its anchor, the node count before it, and for a
    mapping the scalar keys seen so far and whether the next node is a key."""

    anchor: str | None
    before: int
    keys: set[str] | None
    expect_key: bool = True


def load_json(path: str | os.PathLike, noun: str, *, max_bytes: int, field: str = "file",
              missing: str | None = None):
    """The JSON document in ``path`` (UTF-8, at most ``max_bytes``, nested at most :data:`MAX_DEPTH`).

    Anything the parser refuses (syntax, an integer of 5,000 digits, nesting past Python's
    recursion limit) raises ``a readable <noun>`` with the parser's message.
    """
    text = read_text(path, noun, max_bytes=max_bytes, field=field, missing=missing)
    try:
        doc = json.loads(text)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError is a ValueError
        raise TypError(path, field, f"a readable {noun}", f"{type(exc).__name__}: {exc}") from None
    if _depth_exceeds(doc, MAX_DEPTH):
        raise TypError(path, field, f"a {noun} nested at most {MAX_DEPTH} levels deep", "deeper")
    return doc


def _depth_exceeds(doc, limit: int) -> bool:
    """Whether lists/dicts in ``doc`` nest deeper than ``limit`` (iterative: no recursion to exhaust)."""
    stack = [(doc, 1)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, (list, dict)):
            if depth > limit:
                return True
            stack.extend((v, depth + 1) for v in (value.values() if isinstance(value, dict) else value))
    return False


def finite_numbers(where, field: str, value, length: int) -> np.ndarray:
    """``value`` as a float64 vector of ``length`` finite numbers, else TypError naming ``field``.

    Numbers are ints or floats, not bools or strings; an integer beyond float64's range is
    refused like an infinity (``float()`` of it would raise OverflowError).
    """
    if value is None:
        raise TypError(where, field, f"a list of {length} numbers", "missing")
    if not isinstance(value, (list, tuple)) or len(value) != length:
        raise TypError(where, field, f"a list of {length} numbers", value)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise TypError(where, field, f"{length} numbers", value)
    try:
        arr = np.array([float(v) for v in value], dtype=np.float64)
    except OverflowError:
        raise TypError(where, field, "finite numbers", value) from None
    if not np.isfinite(arr).all():
        raise TypError(where, field, "finite numbers", value)
    return arr


def finite_matrix(where, field: str, value, rows: int, cols: int) -> np.ndarray:
    """``value`` as a ``(rows, cols)`` float64 matrix of finite numbers (a list of row lists)."""
    if not isinstance(value, (list, tuple)) or len(value) != rows:
        got = "missing" if value is None else value if isinstance(value, (list, tuple)) else type(value).__name__
        raise TypError(where, field, f"a finite {rows}x{cols} matrix (a list of {rows} rows)", got)
    return np.stack([finite_numbers(where, f"{field}[{r}]", row, cols) for r, row in enumerate(value)])
