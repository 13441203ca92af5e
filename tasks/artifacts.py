"""Trained modules on disk: weights in safetensors, configuration in JSON, never a pickle.

A module folder holds ``config.json`` (what rebuilds the module, plus any extra fields the
stage keeps with it) and ``model.safetensors`` (its state dict, buffers included). Both are
written to temporary names and renamed into place, the weights first, so a folder with a
``config.json`` is complete. Loading checks everything a damaged or foreign folder can get
wrong — a missing file, a truncated or corrupt safetensors file, JSON that does not parse, a
state dict whose names or shapes do not fit the config — and raises :class:`TypError`
naming the file, what was expected, and the stage that makes it.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, TypeVar

import torch
from torch import nn

from typ.errors import TypError
from typ.io import write_bytes, write_json

CONFIG = "config.json"
WEIGHTS = "model.safetensors"

M = TypeVar("M", bound=nn.Module)


def save_module(folder: Path, module: nn.Module, config: dict, **extra: Any) -> Path:
    """Write ``module``'s state dict and ``{"config": config, **extra}`` under ``folder``."""
    from safetensors.torch import save

    # a copy per tensor: safetensors refuses tensors that share memory (tied weights, views)
    state = {k: v.detach().cpu().clone().contiguous() for k, v in module.state_dict().items()}
    write_bytes(folder / WEIGHTS, save(state))
    write_json(folder / CONFIG, {"config": config, **extra})
    return folder


def _parse(path: Path, stage: str):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise TypError(path, "file", f"the JSON config the {stage} stage writes", f"{type(exc).__name__}: {exc}") from None


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


def read_weights(folder: Path, stage: str) -> dict[str, torch.Tensor]:
    """The state dict in ``model.safetensors``; missing, truncated or corrupt raises naming ``stage``."""
    from safetensors import SafetensorError
    from safetensors.torch import load

    path = Path(folder) / WEIGHTS
    if not path.is_file():
        raise TypError(path, "file", f"trained weights (run the {stage} stage: dvc repro)", "missing")
    try:
        return load(path.read_bytes())
    except (SafetensorError, OSError, ValueError, RuntimeError) as exc:
        raise TypError(path, "file", f"a complete safetensors file written by the {stage} stage",
                       f"{type(exc).__name__}: {exc}") from None


def load_into(module: M, state: dict[str, torch.Tensor], path: Path, stage: str) -> M:
    """``module.load_state_dict(state)`` with a named error for missing, unexpected or misshapen tensors."""
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    if missing or unexpected:
        raise TypError(path, "weights", f"the tensors of the configured model (from the {stage} stage)",
                       f"missing {missing[:3]}{'…' if len(missing) > 3 else ''}, "
                       f"unexpected {unexpected[:3]}{'…' if len(unexpected) > 3 else ''}")
    for k, v in state.items():
        if own[k].shape != v.shape:
            raise TypError(path, f"weights.{k}", f"shape {tuple(own[k].shape)} (from the {stage} stage's config)",
                           tuple(v.shape))
    module.load_state_dict(state)
    return module


def load_module(folder: Path, build: Callable[[dict], M], stage: str) -> tuple[M, dict]:
    """Rebuild a module saved by :func:`save_module`: ``build(config)`` then its weights.

    Returns (module in eval mode, the whole config.json). A config ``build`` rejects (a
    missing key, a bad value) raises naming the file too.
    """
    folder = Path(folder)
    meta = read_config(folder, stage)
    try:
        module = build(meta["config"])
    except (KeyError, TypeError, ValueError) as exc:
        raise TypError(folder / CONFIG, "config", f"a model config the {stage} stage writes",
                       f"{type(exc).__name__}: {exc}") from None
    load_into(module, read_weights(folder, stage), folder / WEIGHTS, stage)
    return module.eval(), meta


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
