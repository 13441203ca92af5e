"""Trained modules on disk: weights in safetensors, configuration in JSON, never a pickle.

A module folder holds ``config.json`` (what rebuilds the module, plus any extra fields the
stage keeps with it) and ``model.safetensors`` (its state dict, buffers included). Both are
written to temporary names and renamed into place, the weights first, so a folder with a
``config.json`` is complete. Loading checks everything a damaged or foreign folder can get
wrong — a missing file, a truncated or corrupt safetensors file, JSON that does not parse, a
state dict whose names or shapes do not fit the config — and raises :class:`TypError`
naming the file, what was expected, and the stage that makes it.

Neither file is trusted before it is checked. ``config.json`` is at most :data:`MAX_CONFIG_BYTES`;
the safetensors header (an 8-byte length, then JSON naming each tensor's dtype, shape and byte
range) is read and checked against the file's size before any tensor is, and the file is at most
:data:`MAX_WEIGHTS_BYTES`. Every number of the config is then checked before anything is built
(:func:`check_config`): a module's sizes are counts of layers, each holding at least one tensor of
the file, or widths, each a dimension of one, so no integer may exceed the larger of the tensor
count and the largest dimension; the few fields that size the input instead (:data:`INPUT_SIZES`)
have bounds of their own, and a part of the config written from a params block (the detector's,
V2X-ViT's, the SSC network's) meets that block's bounds. The module is then built on torch's
``meta`` device, which allocates nothing, and the build stops as soon as it has registered more
parameters than the file holds tensors: a config of zero sizes that make the constructor divide by
zero is refused there, and so is one whose tensors are not the header's, before the module is built
for real.
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import math
import threading
from pathlib import Path
from typing import Any, Callable, Mapping, TypeVar

import torch
from torch import nn

from typ.config import MAX_TIMESTEPS, build_typed
from typ.errors import TypError
from typ.inputs import MiB, load_json, open_regular, read_regular
from typ.io import write_bytes, write_json

CONFIG = "config.json"
WEIGHTS = "model.safetensors"
#: a config.json holds a model's sizes and a training curve: kilobytes
MAX_CONFIG_BYTES = 16 * MiB
#: the paper-scale generator's largest part (its UNet, 8.4 M parameters) is about 34 MB
MAX_WEIGHTS_BYTES = 1024 * MiB
#: safetensors' header: a few hundred bytes per tensor
MAX_HEADER_BYTES = 16 * MiB
#: bytes per element of the safetensors dtypes a torch state dict can hold
_DTYPE_BYTES = {"F64": 8, "F32": 4, "F16": 2, "BF16": 2, "I64": 8, "I32": 4, "I16": 2, "I8": 1, "U8": 1,
                "BOOL": 1, "U16": 2, "U32": 4, "U64": 8, "C64": 8}

#: config keys that size a module's input, not its weights: no tensor of the file shows them, so each
#: has a bound of its own. An image's side and a pooling factor are a grid's (``voxelize.grid.shape``:
#: at most 8192 cells a side); a latent's side is 16x the paper's 64, as the UNet's coordinate
#: channels hold 3 floats per latent cell
INPUT_SIZES = {"sample_size": 1024, "height": 8192, "width": 8192, "downsample": 8192}
#: a float outside a params block is a rate, a decay or a threshold
MAX_FLOAT = 1e6
#: fields a stage saves beside the config that size work when the model is used (T: its noise schedule)
SAVED_SIZES = {"train_timesteps": MAX_TIMESTEPS}

M = TypeVar("M", bound=nn.Module)


def save_module(folder: Path, module: nn.Module, config: Mapping, **extra: Any) -> Path:
    """Write ``module``'s state dict and ``{"config": config, **extra}`` under ``folder``.

    config: the module's constructor arguments, e.g. a diffusers ``ConfigMixin``'s ``config``
    (its private ``_``-keys, such as ``_use_default_values``, are not written)."""
    from safetensors.torch import save

    # a copy per tensor: safetensors refuses tensors that share memory (tied weights, views)
    state = {k: v.detach().cpu().clone().contiguous() for k, v in module.state_dict().items()}
    write_bytes(folder / WEIGHTS, save(state))
    write_json(folder / CONFIG, {"config": {k: v for k, v in config.items() if not k.startswith("_")}, **extra})
    return folder


def _parse(path: Path, stage: str):
    return load_json(path, f"JSON config the {stage} stage writes", max_bytes=MAX_CONFIG_BYTES)


def read_config(folder: Path, stage: str) -> dict:
    """``config.json`` of a module folder; missing or unreadable raises naming ``stage``."""
    path = Path(folder) / CONFIG
    if not path.is_file():
        raise TypError(path, "file", f"a trained model's config (run the {stage} stage: dvc repro)", "missing")
    data = _parse(path, stage)
    if not isinstance(data, dict) or not isinstance(data.get("config"), dict):
        raise TypError(path, "config", f"a mapping with a 'config' mapping (written by the {stage} stage)",
                       type(data).__name__ if not isinstance(data, dict) else sorted(data))
    return data


def read_weights_header(folder: Path, stage: str) -> dict[str, tuple[str, tuple[int, ...]]]:
    """``{tensor name: (dtype, shape)}`` from ``model.safetensors``'s header, read without its tensors.

    The header must be JSON of at most the file's size; every tensor's byte range must hold
    exactly ``prod(shape) x dtype size`` bytes, and the ranges must tile the data that follows
    the header, to its last byte (as safetensors itself requires)."""
    path = Path(folder) / WEIGHTS
    noun = f"safetensors file written by the {stage} stage"
    with open_regular(path, noun, max_bytes=MAX_WEIGHTS_BYTES,
                      missing=f"trained weights (run the {stage} stage: dvc repro)") as (f, size):
        length = int.from_bytes(f.read(8), "little") if size >= 8 else -1
        if not 0 < length <= min(size - 8, MAX_HEADER_BYTES):
            raise TypError(path, "file", f"a complete {noun}: an 8-byte header length of at most "
                           f"{min(size - 8, MAX_HEADER_BYTES)} bytes",
                           length if length >= 0 else f"{size} bytes in all")
        try:
            header = json.loads(f.read(length))
        except (ValueError, RecursionError) as exc:  # not UTF-8, not JSON, 5,000-digit numbers
            raise TypError(path, "header", f"the JSON header of a {noun}", f"{type(exc).__name__}: {exc}") from None
    if not isinstance(header, dict):
        raise TypError(path, "header", f"a JSON mapping of tensors ({noun})", type(header).__name__)
    tensors, ranges = {}, []
    for name, entry in header.items():
        if name == "__metadata__":
            continue
        dtype, shape, offsets = (entry.get(k) for k in ("dtype", "shape", "data_offsets")) \
            if isinstance(entry, dict) else (None, None, None)
        if dtype not in _DTYPE_BYTES or not _ints(shape, 0) or not _ints(offsets, 2) or offsets[0] > offsets[1] or \
                offsets[1] - offsets[0] != math.prod(shape) * _DTYPE_BYTES[dtype]:
            raise TypError(path, f"header.{name}", f"dtype in {sorted(_DTYPE_BYTES)}, a shape of integers >= 0 and "
                           "data_offsets [begin, end] spanning prod(shape) x dtype size bytes", entry)
        tensors[name] = (dtype, tuple(shape))
        ranges.append(tuple(offsets))
    end = 0
    for begin, stop in sorted(ranges):
        if begin != end:
            raise TypError(path, "header", "tensor byte ranges that follow one another without gap or overlap",
                           f"a range starts at {begin}, the previous ends at {end}")
        end = stop
    if end != size - 8 - length:
        raise TypError(path, "file", f"a complete {noun}: {8 + length + end} bytes as its header says",
                       f"{size} bytes")
    return tensors


def _ints(value, length: int) -> bool:
    """A list of non-negative integers (of ``length`` items unless 0)."""
    return isinstance(value, list) and (not length or len(value) == length) and \
        all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in value)


def read_weights(folder: Path, stage: str) -> dict[str, torch.Tensor]:
    """The state dict in ``model.safetensors``; missing, truncated or corrupt raises naming ``stage``.

    The header is checked (:func:`read_weights_header`) before the tensors are read."""
    from safetensors import SafetensorError
    from safetensors.torch import load

    read_weights_header(folder, stage)
    path = Path(folder) / WEIGHTS
    try:
        return load(read_regular(path, f"safetensors file written by the {stage} stage", max_bytes=MAX_WEIGHTS_BYTES))
    except (SafetensorError, ValueError, RuntimeError) as exc:
        raise TypError(path, "file", f"a complete safetensors file written by the {stage} stage",
                       f"{type(exc).__name__}: {exc}") from None


def check_against_header(module: nn.Module, header: dict[str, tuple[str, tuple[int, ...]]], path: Path,
                         stage: str) -> None:
    """The module's tensors are the header's: the same names, each of the same shape."""
    own = module.state_dict()
    missing = sorted(set(own) - set(header))
    unexpected = sorted(set(header) - set(own))
    if missing or unexpected:
        raise TypError(path, "weights", f"the tensors of the configured model (from the {stage} stage)",
                       f"missing {missing[:3]}{'…' if len(missing) > 3 else ''}, "
                       f"unexpected {unexpected[:3]}{'…' if len(unexpected) > 3 else ''}")
    for k, (_, shape) in header.items():
        if tuple(own[k].shape) != shape:
            raise TypError(path, f"weights.{k}", f"shape {tuple(own[k].shape)} (from the {stage} stage's config)",
                           shape)


def load_into(module: M, state: dict[str, torch.Tensor], path: Path, stage: str) -> M:
    """``module.load_state_dict(state)`` with a named error for missing, unexpected or misshapen tensors."""
    check_against_header(module, {k: (str(v.dtype), tuple(v.shape)) for k, v in state.items()}, path, stage)
    module.load_state_dict(state)
    return module


def check_config(meta: dict, header: dict[str, tuple[str, tuple[int, ...]]], path: Path, stage: str) -> None:
    """Every number of a ``config.json`` (:func:`read_config`) before any module is built; the error names
    ``path`` and the field.

    In ``config``: a mapping with the fields of a params block (:func:`params_block`) meets that block's
    bounds and checks; elsewhere each integer is at most :func:`size_limit` in absolute value (a layer
    count holds a tensor of the file per layer, a width is a dimension of one) and each list at most that
    long, an :data:`INPUT_SIZES` key within its own bound, and each float finite and at most
    :data:`MAX_FLOAT` in size. Beside it, each :data:`SAVED_SIZES` field is an integer within its bound.
    """
    limit = size_limit(header)
    why = (f"a layer count holds a tensor of {WEIGHTS} per layer and a width is a dimension of one: the "
           f"{stage} stage's file holds {len(header)} tensors, none wider than {max_dimension(header)}")
    stack = [("config", "config", meta["config"])]
    while stack:
        name, key, value = stack.pop()
        if isinstance(value, bool) or value is None or isinstance(value, str):
            continue
        if isinstance(value, float):
            if not (math.isfinite(value) and abs(value) <= MAX_FLOAT):
                raise TypError(path, name, f"a finite number of at most {MAX_FLOAT:g} in size (a rate, a decay "
                               "or a threshold)", value)
        elif isinstance(value, int):
            most = INPUT_SIZES.get(key, limit)
            if abs(value) > most:
                raise TypError(path, name, f"an integer of at most {most} in size "
                               f"({'a size of the input' if key in INPUT_SIZES else why})", value)
        elif isinstance(value, list):
            if len(value) > limit:
                raise TypError(path, name, f"a list of at most {limit} items ({why})", len(value))
            stack.extend((f"{name}[{i}]", key, v) for i, v in enumerate(value))
        elif isinstance(value, dict):
            block = params_block(value)
            if block is None:
                stack.extend((f"{name}.{k}", k, v) for k, v in value.items())
                continue
            built = build_typed(block, value, str(path), name)
            if hasattr(built, "check"):
                built.check(str(path), name)
    for key, most in SAVED_SIZES.items():
        if key in meta and (isinstance(meta[key], bool) or not isinstance(meta[key], int) or
                            not 1 <= meta[key] <= most):
            raise TypError(path, key, f"an integer in [1, {most}] (written by the {stage} stage)", meta[key])


def size_limit(header: dict[str, tuple[str, tuple[int, ...]]]) -> int:
    """The largest size a module config's integer may give (:func:`check_config`): the header's tensor
    count or its largest dimension, whichever is larger."""
    return max(len(header), max_dimension(header))


def max_dimension(header: dict[str, tuple[str, tuple[int, ...]]]) -> int:
    return max((d for _, shape in header.values() for d in shape), default=0)


def params_block(value: dict):
    """The params config class (:mod:`typ.config`) whose fields are exactly ``value``'s keys, or None: a
    module config keeps its params block as written (``fusion.detector``, ``fusion.v2xvit``, ``ssc.network``)."""
    return _params_blocks().get(frozenset(value))


@functools.lru_cache(maxsize=1)
def _params_blocks() -> dict[frozenset, type]:
    import typ.config

    classes = {c for c in vars(typ.config).values()
               if isinstance(c, type) and dataclasses.is_dataclass(c) and c not in typ.config.LIMITS}
    return {frozenset(f.name for f in dataclasses.fields(c) if f.init and f.name != "source"): c for c in classes}


@contextlib.contextmanager
def _parameter_budget(tensors: int, path: Path, stage: str):
    """Stop a module's construction (in this thread) once it has registered more parameters than the
    file holds ``tensors``: a config whose depth builds more is not the file's module, and building all
    of it (100,000 layers) would take minutes even on the meta device."""
    from torch.nn.modules.module import register_module_parameter_registration_hook

    most = tensors + 16  # a few spare: a constructor may register a parameter and then replace it
    count, thread = 0, threading.get_ident()

    def hook(module, name, param):
        nonlocal count
        if threading.get_ident() != thread:
            return None
        count += 1
        if count > most:
            raise TypError(path, "config", f"a model config the {stage} stage writes, whose module holds the "
                           f"{tensors} tensors of {WEIGHTS} (a depth or count of it is too large)",
                           f"a module of more than {most} parameters")
        return None

    handle = register_module_parameter_registration_hook(hook)
    try:
        yield
    finally:
        handle.remove()


def load_module(folder: Path, build: Callable[[dict], M], stage: str) -> tuple[M, dict]:
    """Rebuild a module saved by :func:`save_module`: ``build(config)`` then its weights.

    Returns (module in eval mode, the whole config.json). A config whose numbers the weights'
    header rules out (:func:`check_config`), one ``build`` rejects (a missing key, a bad value,
    a size of zero), or one whose tensors are not those in the header, raises naming the file
    too, before anything is allocated.
    """
    folder = Path(folder)
    meta = read_config(folder, stage)
    header = read_weights_header(folder, stage)
    check_config(meta, header, folder / CONFIG, stage)
    # the meta device builds the structure and allocates none of its tensors; every parameter of
    # the module is one of the header's tensors, so a build registering more is cut short
    with torch.device("meta"), _parameter_budget(len(header), folder / CONFIG, stage):
        skeleton = _build(folder, build, meta["config"], stage)
    check_against_header(skeleton, header, folder / WEIGHTS, stage)
    module = _build(folder, build, meta["config"], stage)
    load_into(module, read_weights(folder, stage), folder / WEIGHTS, stage)
    return module.eval(), meta


def _build(folder: Path, build: Callable[[dict], M], config: dict, stage: str) -> M:
    try:
        return build(config)
    except TypError:
        raise
    except Exception as exc:  # the config is input: whatever its values make a constructor raise, name the file
        raise TypError(folder / CONFIG, "config", f"a model config the {stage} stage writes",
                       f"{type(exc).__name__}: {exc}") from None


def load_if_key(folder: Path, build: Callable[[dict], M], stage: str, key: str) -> tuple[M, dict] | None:
    """:func:`load_module` when ``folder`` holds a module saved with ``key=key``; None when it holds
    none, or one whose key differs (another run's: the caller trains it again and overwrites it).

    The key is compared before the folder's layout is checked, so a folder an older version of
    the stage wrote is retrained once its key changes; a config.json that does not parse raises.
    """
    path = Path(folder) / CONFIG
    if not path.is_file():
        return None
    saved = _parse(path, stage)
    if not isinstance(saved, dict) or saved.get("key") != key:
        return None
    return load_module(folder, build, stage)
