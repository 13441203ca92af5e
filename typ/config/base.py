"""What every config block shares: the profile names and limits, the bounds declared beside the fields
(:class:`Bound`, :class:`Length`, :class:`Product`), the value checks the blocks' ``check`` methods call,
and the typed build of a mapping into frozen dataclasses (:func:`build_typed`)."""
from __future__ import annotations

import copy
import dataclasses
import functools
import math
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from typ.errors import TypError
from typ.inputs import MiB
from typ.registry import SAMPLERS, SCHEDULES

PROFILES_FILE = Path(__file__).parent.parent / "profiles.yaml"
PROFILES = ("tiny", "small", "paper")
#: a params.yaml is a few KB
MAX_PARAMS_BYTES = 1 * MiB
DOMAINS = ("source", "target", "real_cav")
#: ``simulate.sources`` value for a domain the embedded simulator makes
SIMULATE = "simulate"
#: the names of the registries (:mod:`typ.registry`)
Schedule = Literal[tuple(SCHEDULES)]
Sampler = Literal[tuple(SAMPLERS)]


def _number(value) -> str:
    return str(value) if isinstance(value, int) else f"{value:g}"


@dataclass(frozen=True)
class Bound:
    """The interval a number must lie in, declared beside its field and checked when the config is built:
    ``epochs: Annotated[int, Bound(1, 10_000, "why")]``. ``why``: what a value past it costs (memory,
    time) or what fixes the interval; ``low_open`` / ``high_open`` leave that end out (a learning rate
    > 0); ``what``: what the number is, for the message ("a probability"; default an integer / a number).
    The same as pydantic's ``Field(ge=low, le=high)`` (``gt`` / ``lt`` for an open end)."""

    low: float
    high: float
    why: str
    low_open: bool = False
    high_open: bool = False
    what: str = ""

    def admits(self, value) -> bool:
        above = self.low < value if self.low_open else self.low <= value
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def interval(self) -> str:
        return (f"{'(' if self.low_open else '['}{_number(self.low)}, "
                f"{_number(self.high)}{')' if self.high_open else ']'}")

    def check(self, value, where: str, name: str, noun: str) -> None:
        if not self.admits(value):
            raise TypError(where, name, f"{self.what or noun} in {self.interval()} ({self.why})", value)


@dataclass(frozen=True)
class Length:
    """How many items a list (or mapping) may hold: ``Annotated[tuple[Width, ...], Length(1, 8, "why")]``;
    pydantic's ``Field(min_length=low, max_length=high)``."""

    low: int
    high: int
    why: str

    def check(self, value, where: str, name: str, noun: str) -> None:
        if not self.low <= len(value) <= self.high:
            raise TypError(where, name, f"{self.low} to {self.high} {noun} ({self.why})", len(value))


@dataclass(frozen=True)
class Product:
    """The most the numbers of a fixed-length list may multiply to (a grid's H x W x C voxels)."""

    high: int
    why: str

    def check(self, value, where: str, name: str, noun: str) -> None:
        if math.prod(value) > self.high:
            raise TypError(where, name, f"{noun} whose product is at most {self.high} ({self.why})", list(value))


#: the marks a field's ``Annotated`` type may carry, checked by :func:`build_typed`
LIMITS = (Bound, Length, Product)

# Families of fields that share one bound, each declared once here.
Seed = Annotated[int, Bound(0, 2**31 - 1, "a numpy seed, in [0, 2**32) with room for the seed + k of replicas "
                              "and batches")]
Epochs = Annotated[int, Bound(1, 10_000, "passes over the training set: the paper's longest run is 200")]
Steps = Annotated[int, Bound(1, 2_000_000, "optimiser steps: the paper profile's longest run is 200,000")]
BatchSize = Annotated[int, Bound(1, 1024, "samples held in memory at once: 1024 paper-scale grids "
                                   "(512 x 512 x 20 float32) are 21 GB")]
Workers = Annotated[int, Bound(1, 256, "processes, one each: past a large machine's cores they only cost "
                                  "memory and start-up")]
LearningRate = Annotated[float, Bound(0, 10, "an optimiser step size: past 10 every optimiser here diverges",
                                      low_open=True)]
#: diffusion steps T; a saved generator's (pipelines.typ.pipeline_typ) and a saved model's (typ.artifacts) too
MAX_TIMESTEPS = 10_000
#: the adapter's residuals times this at sampling: past it they drown the UNet (both params and pipeline.json)
MAX_ADAPTER_SCALE = 1000.0
#: the post-processing's logit noise, about 1 (both params and pipeline.json)
MAX_NOISE_STD = 100.0
Timesteps = Annotated[int, Bound(1, MAX_TIMESTEPS, "diffusion steps: the paper's T is 1000, and a sampler "
                                    "runs the network up to T times a sample")]
Decay = Annotated[float, Bound(0, 1, "an EMA decay (0: no averaging)", high_open=True)]
Probability = Annotated[float, Bound(0, 1, "a threshold on a probability", low_open=True, high_open=True,
                                     what="a probability")]
Dropout = Annotated[float, Bound(0, 1, "a share of units dropped", high_open=True, what="a probability")]
#: each replicate draws an index per row: 20,000 x 1,000 scenes x 8 B = 160 MB
Replicates = Annotated[int, Bound(1, 20_000, "bootstrap replicates: the paper's tables use 1000, and each "
                                     "resamples every row")]
TrainingSeeds = Annotated[int, Bound(1, 32, "trainings of every network, one per seed: the paper's tables use 3")]
Width = Annotated[int, Bound(1, 1024, "channels of a layer: 4x the paper's widest; a 3x3 conv of 1024 -> 1024 "
                                 "is 38 MB of weights, 10x wider is 3.8 GB per layer")]
LayersPerBlock = Annotated[int, Bound(1, 16, "layers per resolution level: the paper's networks use 1 or 2")]
NormGroups = Annotated[int, Bound(1, 1024, "GroupNorm groups, which divide every width")]
LEVELS = Length(1, 8, "resolution levels: each halves the grid, 8 take 512 cells to 4")
Distance = Annotated[float, Bound(0, 1000, "metres: 1 km is past every LiDAR's range")]
Coordinate = Annotated[float, Bound(-1000, 1000, "metres from the sensor: 1 km is past every LiDAR's range")]
Views = Annotated[int, Bound(1, 10_000, "views sampled or scored, each a diffusion sample of seconds")]


def _check_methods(where: str, name: str, methods, allowed: tuple[str, ...], *, allow_empty: bool = False) -> None:
    """``methods``: at least one (none too with ``allow_empty``), each of ``allowed`` and none twice;
    the error names the entry."""
    for i, method in enumerate(methods):
        if method not in allowed:
            raise TypError(where, f"{name}[{i}]", f"one of {list(allowed)}", method)
    if (not methods and not allow_empty) or len(set(methods)) != len(methods):
        raise TypError(where, name, f"each of {'/'.join(allowed)} at most once", list(methods))


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
    """Convert ``value`` to type ``tp`` or raise TypError naming ``name``; the limits an ``Annotated``
    type carries (:data:`LIMITS`) are checked on the converted value."""
    origin = typing.get_origin(tp)
    if origin is Annotated:
        inner, *marks = typing.get_args(tp)
        # a list's length first: a list of a million items is refused before they are built
        if isinstance(value, (list, tuple, dict)):
            for mark in marks:
                if isinstance(mark, Length):
                    mark.check(value, where, name, _noun(inner, mark))
        built = _build(inner, value, where, name)
        for mark in marks:
            if isinstance(mark, (Bound, Product)):
                mark.check(built, where, name, _noun(inner, mark))
        return built
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise TypError(where, name or "<top level>", f"a mapping for {tp.__name__}", value)
        hints = type_hints(tp)
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


@functools.lru_cache(maxsize=None)
def type_hints(tp) -> dict:
    """The field types of config class ``tp``, bounds (``Annotated``) kept; evaluated once per class, as the
    string annotations cost most of a config's build otherwise."""
    return typing.get_type_hints(tp, include_extras=True)


def _noun(tp, mark) -> str:
    """What a limit's message calls the value: a number's kind, a list's items."""
    if isinstance(mark, Product):
        return f"{len(typing.get_args(tp))} numbers"
    if isinstance(mark, Length):
        return "entries" if typing.get_origin(tp) is dict else "items"
    return "an integer" if tp is int else "a number"


def unannotated(tp):
    """``tp`` without its ``Annotated`` wrapper (the type a value is built as)."""
    return typing.get_args(tp)[0] if typing.get_origin(tp) is Annotated else tp


def limits(tp) -> tuple:
    """The limits (:data:`LIMITS`) an ``Annotated`` type carries; () for any other type."""
    if typing.get_origin(tp) is not Annotated:
        return ()
    return tuple(m for m in typing.get_args(tp)[1:] if isinstance(m, LIMITS))


def _fits(tp, value) -> bool:
    """Whether ``value`` has the shape of ``tp`` (a mapping for a dataclass or dict, a list for a
    list or tuple), so that a union's error can come from the one alternative it could be."""
    tp = unannotated(tp)
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
    tp = unannotated(tp)
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
