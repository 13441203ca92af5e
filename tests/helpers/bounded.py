"""Run a call in a forked child under a time and memory bound, for inputs built to hang or exhaust memory.

A hostile input that a regression lets through must fail its test, not hang the suite or get the
worker killed for memory: the call runs in a child process (``os.fork``: no start-up cost, the
parent's imports and compiled kernels are shared), whose address space may grow by at most
``memory`` bytes (``RLIMIT_AS``: an allocation beyond it is a MemoryError in the child) and which
is killed after ``seconds`` of wall time. The child sends back how the call ended.
"""
from __future__ import annotations

import os
import pickle
import resource
import select
import signal
import time
import traceback
from dataclasses import dataclass
from typing import Callable

from typ.errors import TypError

GiB = 1 << 30


@dataclass(frozen=True)
class Outcome:
    """How a bounded call ended: ``kind`` is ``returned``, ``TypError``, ``raised`` (another exception,
    ``text`` its traceback), ``timeout`` or ``crashed`` (killed by a signal, e.g. a segfault)."""

    kind: str
    text: str = ""
    seconds: float = 0.0
    value: object = None

    def __str__(self) -> str:
        return f"{self.kind} after {self.seconds:.2f} s: {self.text[-2000:]}"


def _address_space() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


def run_bounded(call: Callable[[], object], *, seconds: float = 2.0, memory: int = GiB,
                keep: Callable[[object], object] = lambda value: None) -> Outcome:
    """``call()`` in a child with at most ``seconds`` of wall time and ``memory`` more bytes of address
    space than this process has now. ``keep(value)``: what of a returned value to send back (picklable)."""
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into pytest
        os.close(read_end)
        code = 0
        try:
            limit = _address_space() + memory
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
            start = time.perf_counter()
            try:
                result = ("returned", "", keep(call()))
            except TypError as exc:
                result = ("TypError", str(exc), None)
            except BaseException:  # noqa: BLE001 - whatever escaped is the finding
                result = ("raised", traceback.format_exc(), None)
            payload = pickle.dumps(result + (time.perf_counter() - start,))
            with os.fdopen(write_end, "wb") as pipe:
                pipe.write(payload)
        except BaseException:  # noqa: BLE001
            code = 1
        finally:
            os._exit(code)
    os.close(write_end)
    deadline = time.monotonic() + seconds
    chunks, timed_out = [], False
    with os.fdopen(read_end, "rb") as pipe:
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([pipe], [], [], left)[0]:
                timed_out = True
                break
            chunk = os.read(pipe.fileno(), 1 << 16)
            if not chunk:
                break
            chunks.append(chunk)
    if timed_out:
        os.kill(pid, signal.SIGKILL)
    _, status = os.waitpid(pid, 0)
    if timed_out:
        return Outcome("timeout", f"no result within {seconds} s", seconds)
    if not chunks:
        sig = os.WTERMSIG(status) if os.WIFSIGNALED(status) else None
        return Outcome("crashed", f"the child died ({f'signal {sig}' if sig else f'exit {os.WEXITSTATUS(status)}'})")
    kind, text, value, took = pickle.loads(b"".join(chunks))
    return Outcome(kind, text, took, value)
