"""The JSON Schema of ``params.yaml``, derived from :mod:`typ.config`'s dataclasses.

Editors with a YAML language server complete and check ``params.yaml`` against the committed
``params.schema.json`` (its first line names it: ``# yaml-language-server: $schema=...``);
``typ schema`` writes it again after a change to the config classes, and a test holds the two
equal. The schema says what :func:`typ.config.load_config` says about structure and types: the
known keys of every block (``additionalProperties: false``), integers, numbers (finite: YAML's
``.nan`` / ``.inf`` are rejected by the loader only), strings, booleans, the allowed values of a
choice, the length of a fixed list such as ``voxelize.grid.shape``, and the bounds declared beside
the fields (:class:`typ.config.Bound`: ``minimum`` / ``maximum``, exclusive at an open end;
:class:`typ.config.Length`: ``minItems`` / ``maxItems``). A product of a list's numbers
(:class:`typ.config.Product`, a grid's voxels) and relations between fields (``agents_min <=
agents_max``) are checked by the loader only. No key of a stage block is required: the profile's
defaults fill what ``params.yaml`` leaves out. A dataclass inside a list (``generate.sets``) is not
merged with defaults, so there its fields without a default are required.
"""
from __future__ import annotations

import dataclasses
import inspect
import types
import typing
from typing import Annotated, Any, Literal

from typ.config import PROFILES, Bound, Config, Length

SCHEMA_FILE = "params.schema.json"
DIALECT = "https://json-schema.org/draft/2020-12/schema"


def config_schema() -> dict:
    """The schema of a ``params.yaml`` (draft 2020-12), one ``$defs`` entry per config class."""
    defs: dict[str, dict] = {}
    top = _object(Config, defs, partial=True)
    top["properties"]["profile"] = {"enum": list(PROFILES), "description": "the defaults in typ/profiles.yaml"}
    return {"$schema": DIALECT, "title": "typ params.yaml", **top, "$defs": dict(sorted(defs.items()))}


def _object(tp, defs: dict, *, partial: bool) -> dict:
    hints = typing.get_type_hints(tp, include_extras=True)
    fields = [f for f in dataclasses.fields(tp) if f.init and f.name != "source"]
    out: dict[str, Any] = {"type": "object"}
    doc = inspect.getdoc(tp)
    if doc and tp.__doc__:  # the class's own docstring, not dataclass's generated signature
        out["description"] = doc.split("\n\n")[0].replace("\n", " ")
    out["properties"] = {f.name: _schema(hints[f.name], defs, partial=partial) for f in fields}
    required = [f.name for f in fields
                if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if required and not partial:
        out["required"] = required
    out["additionalProperties"] = False
    return out


def _schema(tp, defs: dict, *, partial: bool) -> dict:
    """The schema of one field type; ``partial``: a block merged over the profile's defaults."""
    origin = typing.get_origin(tp)
    if origin is Annotated:
        inner, *marks = typing.get_args(tp)
        out = _schema(inner, defs, partial=partial)
        for mark in marks:
            out.update(_limit(mark, out))
        return out
    if dataclasses.is_dataclass(tp):
        name = tp.__name__ if partial else f"{tp.__name__}Item"
        if name not in defs:
            defs[name] = {}  # placeholder: a class met again while it is being built
            defs[name] = _object(tp, defs, partial=partial)
        return {"$ref": f"#/$defs/{name}"}
    if origin is Literal:
        return {"enum": list(typing.get_args(tp))}
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return {"type": "array", "items": _schema(args[0], defs, partial=False)}
        return {"type": "array", "prefixItems": [_schema(a, defs, partial=False) for a in args],
                "minItems": len(args), "maxItems": len(args)}
    if origin is list:
        (arg,) = typing.get_args(tp)
        return {"type": "array", "items": _schema(arg, defs, partial=False)}
    if origin is dict:
        key, value = typing.get_args(tp)
        out = {"type": "object", "additionalProperties": _schema(value, defs, partial=partial)}
        if typing.get_origin(key) is Literal:
            out["propertyNames"] = _schema(key, defs, partial=False)
        return out
    if origin in (typing.Union, types.UnionType):
        return {"anyOf": [_schema(a, defs, partial=partial) for a in typing.get_args(tp)]}
    simple = {type(None): "null", bool: "boolean", int: "integer", float: "number", str: "string"}
    if tp in simple:
        return {"type": simple[tp]}
    if tp is Any:
        return {}
    raise TypeError(f"config type {tp!r} has no JSON Schema form")


def _limit(mark, schema: dict) -> dict:
    """The JSON Schema keywords of a bound on a number or a list's (or mapping's) length."""
    if isinstance(mark, Bound):
        return {"exclusiveMinimum" if mark.low_open else "minimum": mark.low,
                "exclusiveMaximum" if mark.high_open else "maximum": mark.high}
    if isinstance(mark, Length):
        if schema.get("type") == "object":
            return {"minProperties": mark.low, "maxProperties": mark.high}
        return {"minItems": mark.low, "maxItems": mark.high}
    return {}
