"""Content hashes of unchanged files, remembered by their stat, as DVC and git keep them.

A per-scene stage decides what to redo by hashing each scenario's input files
(:func:`typ.io.hash_files`). With nothing changed, that hashing was most of a no-op stage:
573 MB read for the default profile's 118 scenes, 2-4 s. The cache maps what ``os.stat`` says
of every file of one :func:`~typ.io.hash_files` call (path, device, inode, size, mtime and
ctime in ns) plus its ``extra`` to the digest the call returned, so the second call on the same
files returns it after a stat of each.

When it may answer:
- Any write to a file changes its mtime and ctime, and ctime cannot be set back (``touch -d``
  sets mtime only), so a file whose stat is unchanged has the bytes it was hashed with. A copy,
  a rename or a new inode is a miss.
- A file changed within :data:`RACY_S` seconds of being hashed could change again within the
  same clock tick without its stat showing it (git's "racy clean" case): such a digest is
  computed but not stored.
- Wrong answers are never traded for speed: a cache that cannot be opened, is damaged, or holds
  a value that is not a sha256 is skipped (one warning) and the files are read.

Where: the file named by ``TYP_HASH_CACHE`` (the CLI sets ``<root>/.typ/hashes.sqlite``); unset
or empty, there is no cache and every call reads its files. sqlite serialises writers from
threads and processes (Prefect's thread pool, Dask workers on this machine); a worker on
another machine that cannot open the file runs without it.
"""
from __future__ import annotations

import hashlib
import logging
import os
import re
import sqlite3
import threading
import time
from pathlib import Path

log = logging.getLogger(__name__)

ENV = "TYP_HASH_CACHE"
#: a file whose mtime or ctime is this close to now is hashed but its digest not stored
RACY_S = 2.0
#: rows kept; beyond this the oldest go (each row is about 150 bytes)
MAX_ROWS = 200_000
_DIGEST = re.compile(r"[0-9a-f]{64}")
_local = threading.local()
_broken: set[str] = set()


def _connection(path: str) -> sqlite3.Connection | None:
    """This thread's connection to the cache at ``path`` (created with its table), or None."""
    conns = getattr(_local, "conns", None)
    if conns is None:
        conns = _local.conns = {}
    if path in conns:
        return conns[path]
    conn = None
    try:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        conn = sqlite3.connect(path, timeout=30, isolation_level=None)
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("CREATE TABLE IF NOT EXISTS digests (key TEXT PRIMARY KEY, digest TEXT NOT NULL)")
        conn.execute("DELETE FROM digests WHERE rowid <= (SELECT max(rowid) FROM digests) - ?", (MAX_ROWS,))
    except (OSError, sqlite3.Error) as exc:
        _disable(path, exc)
        if conn is not None:
            conn.close()
        conn = None
    conns[path] = conn
    return conn


def _disable(path: str, exc: Exception) -> None:
    if path not in _broken:
        _broken.add(path)
        log.warning("hash cache %s unusable (%s: %s): hashing every file", path, type(exc).__name__, exc)
    conns = getattr(_local, "conns", {})
    conns[path] = None


def stat_key(paths: list[Path], extra: str) -> tuple[str, bool]:
    """(the cache key of hashing ``paths`` with ``extra``, whether any file changed too recently
    to be trusted by its stat). Raises OSError as ``open`` would for a missing file."""
    h = hashlib.sha256(extra.encode())
    newest = 0
    for p in paths:
        st = os.stat(p)
        newest = max(newest, st.st_mtime_ns, st.st_ctime_ns)
        h.update(f"\0{os.path.abspath(p)}\0{st.st_dev}:{st.st_ino}:{st.st_size}:{st.st_mtime_ns}:"
                 f"{st.st_ctime_ns}".encode())
    return h.hexdigest(), newest >= time.time_ns() - int(RACY_S * 1e9)


def cached_digest(paths: list[Path], extra: str, compute) -> str:
    """``compute()`` (the digest of ``paths`` with ``extra``), or the digest it returned before
    for the same files with the same stat."""
    path = os.environ.get(ENV)
    conn = _connection(path) if path else None
    if conn is None:
        return compute()
    key, racy = stat_key(paths, extra)
    try:
        row = conn.execute("SELECT digest FROM digests WHERE key = ?", (key,)).fetchone()
    except sqlite3.Error as exc:
        _disable(path, exc)
        return compute()
    if row is not None and isinstance(row[0], str) and _DIGEST.fullmatch(row[0]):
        return row[0]
    digest = compute()
    if not racy:
        try:
            conn.execute("INSERT OR REPLACE INTO digests (key, digest) VALUES (?, ?)", (key, digest))
        except sqlite3.Error as exc:
            _disable(path, exc)
    return digest
