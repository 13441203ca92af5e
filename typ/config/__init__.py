"""Typed configuration: ``params.yaml`` -> one frozen dataclass per stage.

``params.yaml`` holds ``profile: tiny | paper`` and one block per stage. The profile picks
the defaults from ``typ/profiles.yaml`` (``tiny``: minutes on 2 CPU cores; ``paper``: TYP §4
scale); each block in ``params.yaml`` overrides them key by key. An unknown key, a wrong
type or an impossible value fails at load time with the dotted field name and what was
expected, e.g. ``params.yaml: voxelize.grid.shape: expected a list of 3 ints``. Every number
has a bound declared beside its field (:class:`Bound`: what a value past it would cost in memory
or time), and every list a length (:class:`Length`), checked as the config is built, so
``load_config`` and ``typ check`` refuse a size before any work starts.

The blocks live by job: :mod:`typ.config.data` (simulate, voxelize), :mod:`typ.config.generation`
(vqvae … generate), :mod:`typ.config.detection` (fusion, ssc), :mod:`typ.config.ddpm`,
:mod:`typ.config.run` (tracking, runtime, serve, evaluate and :class:`Config`), with the checks
and the typed build they share in :mod:`typ.config.base`. This module loads a params.yaml and
re-exports every name, so ``from typ.config import X`` is the one import a caller needs.
"""
from __future__ import annotations

import copy
import dataclasses
import functools
from pathlib import Path

import yaml

from typ.config.base import (DOMAINS, LIMITS, MAX_ADAPTER_SCALE, MAX_NOISE_STD, MAX_PARAMS_BYTES, MAX_TIMESTEPS,
                             PROFILES, PROFILES_FILE, SIMULATE, WHOLE, Bound, Length, Product, Sampler, Schedule,
                             _build, _check_methods, _deep_merge, _fits, _join, _tname, as_dict, build_typed, flatten,
                             limits, type_hints, unannotated)  # noqa: F401
from typ.config.data import (AZIMUTH_STEP_DEG, DomainSimulation, ElevationRule, GridConfig, MAX_AGENTS, MAX_BEAMS,
                             MAX_COMM_RANGE, MAX_DT, MAX_FRAMES, MAX_SCENARIOS, SINGLE_AGENT_FORMATS, SOURCE_FORMATS,
                             SensorConfig, SimulateConfig, SourceConfig, SourceFormat, VoxelizeConfig,
                             check_simulation)  # noqa: F401
from typ.config.generation import (COMPOSE, AdaptConfig, AutoencoderConfig, CastConfig, GenerateConfig, GenerateSet,
                                   PostprocessConfig, SelftrainConfig, Stage1Config, Stage2Config, UNetConfig,
                                   VQVAEStageConfig)  # noqa: F401
from typ.config.detection import (AugmentConfig, DetectorConfig, FUSION_METHODS, MAX_BEV_CELLS, MAX_PILLARS,
                                  PRETRAIN_SOURCES, FusionConfig, RobustnessConfig, SSC_METHODS, SscConfig,
                                  SscNetworkConfig, SscNoisyConfig, V2XViTConfig)  # noqa: F401
from typ.config.ddpm import (DdpmBevConfig, DdpmConfig, DdpmRangeConfig, DdpmRunConfig, FeatureNetConfig,
                             LatentRouteConfig, PixelUNetConfig, _check_samplers)  # noqa: F401
from typ.config.run import (Config, EvaluateConfig, NovelViewConfig, NovelViewSequence, RuntimeConfig, ServeConfig,
                             TrackingConfig)  # noqa: F401
from typ.errors import TypError
from typ.inputs import load_yaml


_YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def load_config(path: str | Path = "params.yaml", *, overrides: dict | None = None) -> Config:
    """Read ``path``, merge it over its profile's defaults, and return a checked :class:`Config`."""
    return config_from_dict(read_params(path), where=str(path), overrides=overrides)


def read_params(path: str | Path) -> dict:
    """The mapping in a params.yaml, as written (before the profile's defaults are merged in).

    A missing, unreadable, oversized, malformed or alias-bombed file raises TypError."""
    # libyaml's parser: PyYAML's own takes seconds on a params.yaml of a megabyte
    raw = load_yaml(path, "UTF-8 params.yaml", max_bytes=MAX_PARAMS_BYTES, loader=_YAML_LOADER,
                    missing="a params.yaml in the project root (run typ from there)") or {}
    if not isinstance(raw, dict):
        raise TypError(path, "<top level>", "a mapping of stage blocks", type(raw).__name__)
    return raw


def config_from_dict(raw: dict, *, where: str = "params.yaml", overrides: dict | None = None) -> Config:
    raw = _deep_merge(raw, overrides or {})
    profile = raw.get("profile", "tiny")
    if profile not in PROFILES:
        raise TypError(where, "profile", f"one of {list(PROFILES)}", profile)
    defaults = profile_defaults(profile)
    merged = _deep_merge(defaults, {k: v for k, v in raw.items() if k != "profile"}, where=where)
    merged["profile"] = profile
    cfg = _build(Config, merged, where, "")
    cfg = dataclasses.replace(cfg, source=where)
    for name in ("tracking", "runtime", "serve") + Config.STAGES:
        check = getattr(getattr(cfg, name), "check", None)   # the bounds beside the fields are the rest
        if check is not None:
            check(where, name)
    return cfg


def profile_defaults(profile: str) -> dict:
    """The defaults of ``profile`` in typ/profiles.yaml; a profile with ``extends: <other>``
    is that profile's defaults with its own keys merged over them."""
    data = _profiles()
    if profile not in data:
        raise TypError(PROFILES_FILE, "profile", f"one of {sorted(data)}", profile)
    own = copy.deepcopy(data[profile])
    parent = own.pop("extends", None)
    if parent is None:
        return own
    if parent == profile or parent not in data:
        raise TypError(PROFILES_FILE, f"{profile}.extends", f"another profile of {sorted(data)}", parent)
    return _deep_merge(profile_defaults(parent), own, whole=frozenset())  # a profile refines its parent


@functools.lru_cache(maxsize=1)
def _profiles() -> dict:
    # parsed once per process (a stage loads its params three times: CLI, stage, flow), with
    # libyaml when PyYAML has it: the pure-Python parser takes a tenth of a second on this file
    return yaml.load(PROFILES_FILE.read_text(), Loader=_YAML_LOADER)
