"""The one error type typ raises for bad user input.

Every message names where the problem is (a file path, a params field, a CLI
argument), which field, and what was expected, so a user can fix the input
without reading a traceback.
"""
from __future__ import annotations

import os


class TypError(Exception):
    """Bad input: ``where`` (file or dotted params name), ``field``, and ``expected``."""

    def __init__(self, where: str | os.PathLike | None, field: str, expected: str, got: object = None):
        self.where = str(where) if where is not None else "<input>"
        self.field = field
        self.expected = expected
        self.got = got
        msg = f"{self.where}: {field}: expected {expected}"
        if got is not None:
            text = repr(got)
            msg += f", got {text[:200]}"
        super().__init__(msg)

    def __reduce__(self):  # keep the error picklable across Prefect/Dask workers
        return (type(self), (self.where, self.field, self.expected, self.got))
