"""The numeric leaves of a config type, found through its type hints, and a value put at one of them.

A leaf's path is a tuple of steps: ``("field", name)`` into a dataclass, ``("key", k)`` into a mapping,
``("item", i)`` into a list, ``("alt", i)`` through the i-th alternative of a union (it names no field).
:func:`dotted` gives the name a :class:`typ.errors.TypError` uses for it; :func:`put` builds the value
of a type that holds ``value`` at a path, filling what the path passes through from a base value (a
profile's) or with valid values of its own.
"""
from __future__ import annotations

import dataclasses
import types
import typing
from typing import Literal

from typ.config import Bound, Length, limits, unannotated

#: a key for each mapping a path passes through, chosen so that the mapping's own checks pass
KEYS = {"simulate.scenarios": "target", "simulate.scenarios.target": "train", "simulate.domains": "target",
        "simulate.sources": "target", "voxelize.mount_height": "target"}


def _hints(tp) -> dict:
    return typing.get_type_hints(tp, include_extras=True)


def _fields(tp) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(tp) if f.init and f.name != "source"]


def _is_union(tp) -> bool:
    return typing.get_origin(tp) in (typing.Union, types.UnionType)


def _variable(tp) -> bool:
    args = typing.get_args(tp)
    return typing.get_origin(tp) is list or (typing.get_origin(tp) is tuple and len(args) == 2 and args[1] is Ellipsis)


def dotted(path: tuple) -> str:
    out = ""
    for kind, step in path:
        if kind in ("field", "key"):
            out = f"{out}.{step}" if out else str(step)
        elif kind == "item":
            out += f"[{step}]"
    return out


def numeric_leaves(tp, path: tuple = ()):
    """``(path, annotated type)`` of every int or float a value of ``tp`` can hold (bool and the numbers
    of a ``Literal`` are not leaves: a choice bounds them)."""
    base = unannotated(tp)
    origin = typing.get_origin(base)
    if dataclasses.is_dataclass(base):
        hints = _hints(base)
        for f in _fields(base):
            yield from numeric_leaves(hints[f.name], path + (("field", f.name),))
    elif _is_union(base):
        for i, alt in enumerate(typing.get_args(base)):
            yield from numeric_leaves(alt, path + (("alt", i),))
    elif origin is dict:
        key = KEYS.get(dotted(path), "x")
        yield from numeric_leaves(typing.get_args(base)[1], path + (("key", key),))
    elif origin in (tuple, list):
        args = typing.get_args(base)
        if _variable(base):
            yield from numeric_leaves(args[0], path + (("item", 0),))
        else:
            for i, arg in enumerate(args):
                yield from numeric_leaves(arg, path + (("item", i),))
    elif base in (int, float):
        yield path, tp


def variable_lists(tp, path: tuple = ()):
    """``(path, annotated type)`` of every list of variable length a value of ``tp`` can hold (of any
    items but strings: a registry's names, each allowed once, bound those)."""
    base = unannotated(tp)
    if dataclasses.is_dataclass(base):
        hints = _hints(base)
        for f in _fields(base):
            yield from variable_lists(hints[f.name], path + (("field", f.name),))
    elif _is_union(base):
        for i, alt in enumerate(typing.get_args(base)):
            yield from variable_lists(alt, path + (("alt", i),))
    elif typing.get_origin(base) is dict:
        yield from variable_lists(typing.get_args(base)[1], path + (("key", "x"),))
    elif typing.get_origin(base) in (tuple, list):
        if _variable(base) and unannotated(typing.get_args(base)[0]) is not str and \
                typing.get_origin(unannotated(typing.get_args(base)[0])) is not Literal:
            yield path, tp
        for i, arg in enumerate(typing.get_args(base)):
            if arg is not Ellipsis:
                yield from variable_lists(arg, path + (("item", i),))


def bound_of(tp) -> Bound:
    (bound,) = [m for m in limits(tp) if isinstance(m, Bound)]
    return bound


def length_of(tp) -> Length | None:
    found = [m for m in limits(tp) if isinstance(m, Length)]
    return found[0] if found else None


def sample(tp):
    """A valid value of ``tp`` (a dataclass: its fields without defaults), for what a path passes through."""
    base = unannotated(tp)
    origin = typing.get_origin(base)
    if dataclasses.is_dataclass(base):
        hints = _hints(base)
        return {f.name: sample(hints[f.name]) for f in _fields(base)
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING}
    if origin is Literal:
        return typing.get_args(base)[0]
    if _is_union(base):
        return sample(typing.get_args(base)[0])
    if origin is dict:
        return {}
    if origin in (tuple, list):
        args = typing.get_args(base)
        return [] if _variable(base) else [sample(a) for a in args]
    if base in (int, float):
        bound = bound_of(tp)
        low = bound.low + (1 if bound.low_open else 0)
        return base(min(max(low, 0), bound.high))
    if base is bool:
        return False
    return "x"


def put(tp, base, path: tuple, value):
    """A value of ``tp`` that is ``base`` (or a valid one) with ``value`` at ``path``."""
    if not path:
        return value
    (kind, step), rest = path[0], path[1:]
    inner = unannotated(tp)
    if kind == "alt":
        alt = typing.get_args(inner)[step]
        fitting = base if base is not None and _shape_fits(alt, base) else None
        return put(alt, fitting, rest, value)
    if kind == "field":
        out = dict(base) if isinstance(base, dict) else sample(inner)
        out[step] = put(_hints(inner)[step], out.get(step), rest, value)
        return out
    if kind == "key":
        out = dict(base) if isinstance(base, dict) else {}
        out[step] = put(typing.get_args(inner)[1], out.get(step), rest, value)
        return out
    args = typing.get_args(inner)
    item = args[0] if _variable(inner) else args[step]
    out = list(base) if isinstance(base, (list, tuple)) and len(base) > step else (
        [sample(item)] if _variable(inner) else sample(inner))
    out[step] = put(item, out[step], rest, value)
    return out


def _shape_fits(tp, value) -> bool:
    base = unannotated(tp)
    if dataclasses.is_dataclass(base) or typing.get_origin(base) is dict:
        return isinstance(value, dict)
    if typing.get_origin(base) in (tuple, list):
        return isinstance(value, (list, tuple))
    return not isinstance(value, (dict, list, tuple))


def past(tp) -> list:
    """Values past the bound of the leaf type ``tp``: 10x its high end, 10**15, and below its low end."""
    bound, kind = bound_of(tp), unannotated(tp)
    values = [kind(10 * bound.high), kind(10**15)]
    values.append(kind(-1) if bound.low >= 0 else kind(10 * bound.low))
    return values

