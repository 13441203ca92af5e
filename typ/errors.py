"""The one error type typ raises for bad user input.

Every message names where the problem is (a file path, a params field, a CLI
argument), which field, and what was expected, so a user can fix the input
without reading a traceback.
"""
from __future__ import annotations

import math
import os
import reprlib

#: the most characters of the offending value a message shows
MAX_GOT_CHARS = 200


class _BoundedRepr(reprlib.Repr):
    """``repr`` that never walks more than a few levels and items of a value.

    The value in an error can be anything a file held: a YAML alias bomb shares one list
    a billion times over, and ``repr`` of it never ends; an integer of 5000 digits makes
    ``repr`` itself raise. This one stops at a few levels and items, whatever the value.
    """

    def __init__(self):
        super().__init__()
        self.maxlevel = 3
        self.maxtuple = self.maxlist = self.maxarray = 16
        self.maxdict = self.maxset = self.maxfrozenset = self.maxdeque = 8
        self.maxstring = self.maxother = MAX_GOT_CHARS
        self.maxlong = 40

    def repr_int(self, x, level):
        if x.bit_length() > 128:  # beyond this, the exact digits tell the user nothing
            return f"<an integer of about {int(x.bit_length() * math.log10(2)) + 1} digits>"
        return super().repr_int(x, level)

    def repr_bytes(self, x, level):
        shown = repr(x[:MAX_GOT_CHARS])
        return shown if len(x) <= MAX_GOT_CHARS else f"{shown}... ({len(x)} bytes)"


_repr = _BoundedRepr()


def bounded_repr(value: object) -> str:
    """``repr(value)`` in at most :data:`MAX_GOT_CHARS` characters, in bounded time for any value."""
    try:
        text = _repr.repr(value)
    except Exception as exc:  # a foreign object whose __repr__ fails: the message must still be made
        text = f"<{type(value).__name__}: repr failed with {type(exc).__name__}>"
    return text if len(text) <= MAX_GOT_CHARS else text[:MAX_GOT_CHARS - 3] + "..."


class TypError(Exception):
    """Bad input: ``where`` (file or dotted params name), ``field``, and ``expected``."""

    def __init__(self, where: str | os.PathLike | None, field: str, expected: str, got: object = None):
        self.where = str(where) if where is not None else "<input>"
        self.field = field
        self.expected = expected
        self.got = got
        msg = f"{self.where}: {field}: expected {expected}"
        if got is not None:
            msg += f", got {bounded_repr(got)}"
        super().__init__(msg)

    def __reduce__(self):  # keep the error picklable across Prefect/Dask workers
        return (type(self), (self.where, self.field, self.expected, self.got))
