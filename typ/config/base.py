"""What every config block shares: the profile names and limits, the value checks the blocks' ``check``
methods call, and the typed build of a mapping into frozen dataclasses (:func:`build_typed`)."""
from __future__ import annotations

import copy
import dataclasses
import math
import types
import typing
from pathlib import Path
from typing import Any, Literal

from models.registry import SAMPLERS
from models.schedules import SCHEDULES
from typ.errors import TypError
from typ.inputs import MiB

PROFILES_FILE = Path(__file__).parent.parent / "profiles.yaml"
PROFILES = ("tiny", "small", "paper")
#: a params.yaml is a few KB
MAX_PARAMS_BYTES = 1 * MiB
DOMAINS = ("source", "target", "real_cav")
#: ``simulate.sources`` value for a domain the embedded simulator makes
SIMULATE = "simulate"
#: the names of the registries (:mod:`models.registry`, :data:`models.schedules.SCHEDULES`)
Schedule = Literal[tuple(SCHEDULES)]
Sampler = Literal[tuple(SAMPLERS)]


def _positive(where: str, name: str, value) -> None:
    if not value > 0:
        raise TypError(where, name, "a value > 0", value)


def _check_methods(where: str, name: str, methods, allowed: tuple[str, ...], *, allow_empty: bool = False) -> None:
    """``methods``: at least one (none too with ``allow_empty``), each of ``allowed`` and none twice;
    the error names the entry."""
    for i, method in enumerate(methods):
        if method not in allowed:
            raise TypError(where, f"{name}[{i}]", f"one of {list(allowed)}", method)
    if (not methods and not allow_empty) or len(set(methods)) != len(methods):
        raise TypError(where, name, f"each of {'/'.join(allowed)} at most once", list(methods))


def _positive_fields(block, where: str, name: str, *keys: str) -> None:
    """Every ``block.<key>`` must be > 0; the error names ``<name>.<key>``."""
    for key in keys:
        _positive(where, f"{name}.{key}", getattr(block, key))


#: mappings that params.yaml replaces whole instead of key by key: ``simulate.domains: {}``
#: drops the profile's per-domain lengths, so the block's frames / agents apply to every domain
WHOLE = frozenset({"simulate.domains"})


def _deep_merge(base: dict, over: dict, *, where: str = "", prefix: str = "", whole: frozenset = WHOLE) -> dict:
    out = dict(base)
    for key, value in over.items():
        if f"{prefix}{key}" in whole:
            out[key] = copy.deepcopy(value)
        elif isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value, where=where, prefix=f"{prefix}{key}.", whole=whole)
        else:
            out[key] = value
    return out


def _build(tp, value, where: str, name: str):
    """Convert ``value`` to type ``tp`` or raise TypError naming ``name``."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise TypError(where, name or "<top level>", f"a mapping for {tp.__name__}", value)
        hints = typing.get_type_hints(tp)
        fields = {f.name: f for f in dataclasses.fields(tp) if f.init and f.name != "source"}
        unknown = sorted(set(value) - set(fields))
        if unknown:
            raise TypError(where, _join(name, unknown[0]), f"one of the known keys {sorted(fields)}",
                           "an unknown key")
        kwargs = {}
        for fname, f in fields.items():
            if fname not in value:
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                    raise TypError(where, _join(name, fname), "a value (key missing)")
                continue
            kwargs[fname] = _build(hints[fname], value[fname], where, _join(name, fname))
        return tp(**kwargs)
    if origin is Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            raise TypError(where, name, f"one of {list(allowed)}", value)
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            if not isinstance(value, (list, tuple)):
                raise TypError(where, name, f"a list of {_tname(args[0])}s", value)
            return tuple(_build(args[0], v, where, f"{name}[{i}]") for i, v in enumerate(value))
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise TypError(where, name, f"a list of {len(args)} {_tname(args[0])}s", value)
        return tuple(_build(a, v, where, f"{name}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if origin is list:
        (arg,) = typing.get_args(tp)
        if not isinstance(value, list):
            raise TypError(where, name, f"a list of {_tname(arg)}", value)
        return [_build(arg, v, where, f"{name}[{i}]") for i, v in enumerate(value)]
    if origin is dict:
        karg, varg = typing.get_args(tp)
        if not isinstance(value, dict):
            raise TypError(where, name, f"a mapping of {_tname(karg)} to {_tname(varg)}", value)
        return {_build(karg, k, where, name): _build(varg, v, where, _join(name, str(k))) for k, v in value.items()}
    if origin in (typing.Union, types.UnionType):
        fitting = [arg for arg in typing.get_args(tp) if _fits(arg, value)]
        if len(fitting) == 1:  # one alternative of this shape: its own error names the bad field inside
            return _build(fitting[0], value, where, name)
        errors = []
        for arg in typing.get_args(tp):
            try:
                return _build(arg, value, where, name)
            except TypError as exc:
                errors.append(exc.expected)
        raise TypError(where, name, " or ".join(errors), value)
    if tp is type(None):
        if value is not None:
            raise TypError(where, name, "null", value)
        return None
    if tp is bool:
        if not isinstance(value, bool):
            raise TypError(where, name, "true or false", value)
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise TypError(where, name, "an integer", value)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypError(where, name, "a number", value)
        try:
            number = float(value)
        except OverflowError:  # an integer beyond float's range
            raise TypError(where, name, "a finite number", value) from None
        if not math.isfinite(number):
            raise TypError(where, name, "a finite number", value)
        return number
    if tp is str:
        if not isinstance(value, str):
            raise TypError(where, name, "a string", value)
        return value
    if tp is Any:
        return value
    raise TypeError(f"config type {tp!r} for {name} is not supported")


def _fits(tp, value) -> bool:
    """Whether ``value`` has the shape of ``tp`` (a mapping for a dataclass or dict, a list for a
    list or tuple), so that a union's error can come from the one alternative it could be."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp) or origin is dict:
        return isinstance(value, dict)
    if origin in (list, tuple):
        return isinstance(value, (list, tuple))
    return not isinstance(value, (dict, list, tuple))


def build_typed(tp, value, where: str, name: str = ""):
    """``value`` as type ``tp`` (a dataclass: from a mapping) by the rules params blocks are built with:
    a missing or unknown key, or a value of the wrong type, raises TypError naming ``where`` and the field."""
    return _build(tp, value, where, name)


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key


def _tname(tp) -> str:
    return getattr(tp, "__name__", str(tp))


def flatten(obj, prefix: str = "") -> dict[str, Any]:
    """Dotted-name view of a config (``voxelize.grid.shape`` -> ``[128, 128, 8]``), for MLflow."""
    if dataclasses.is_dataclass(obj):
        obj = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj) if f.name != "source"}
    out: dict[str, Any] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(flatten(v, _join(prefix, str(k))))
    else:
        out[prefix] = list(obj) if isinstance(obj, tuple) else obj
    return out


def as_dict(obj) -> dict:
    """Plain JSON-able dict of a config block (tuples become lists)."""
    if dataclasses.is_dataclass(obj):
        return {f.name: as_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj) if f.name != "source"}
    if isinstance(obj, dict):
        return {k: as_dict(v) for k, v in obj.items()}
    if isinstance(obj, (tuple, list)):
        return [as_dict(v) for v in obj]
    return obj
