"""Every size bounded before work starts: each number of params.yaml, of a sensor block and of a saved
model's config.json has a bound, and a value past it is refused by name, fast and in little memory.

Params and sensor blocks: every int or float a config type can hold (found through its type hints,
dict values and list items included) carries a :class:`typ.config.Bound`, and every list of numbers or
blocks a :class:`typ.config.Length`; each leaf set to 10x its bound's high end, to 10**15 and below its
low end is a TypError naming the dotted field, the bound and its reason, within 2 s and 1 GiB
(tests/helpers/bounded.py), from ``load_config`` and from ``typ check`` alike. Model configs: every number of
one module of each kind typ saves, at 10x its bound and at 10**15 (:func:`typ.artifacts.check_config`).
"""
from __future__ import annotations

import json
import shutil
import time
import typing
from pathlib import Path

import jsonschema
import pytest
import yaml

from bound_walk import bound_of, dotted, length_of, numeric_leaves, past, put, variable_lists
from bounded import run_bounded
from typ.config import (PROFILES, Bound, Config, ElevationRule, SensorConfig, config_from_dict, limits, load_config,
                        profile_defaults, unannotated)
from typ.errors import TypError
from repo_paths import REPO

SECONDS, MEMORY = 2.0, 1 << 30
LEAVES = list(numeric_leaves(Config))
BASE = {"profile": "tiny", **profile_defaults("tiny")}
DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


def _id(path) -> str:
    return dotted(path)


def write_params(folder: Path, path: tuple, value, name: str = "params.yaml") -> Path:
    """A params.yaml of the tiny profile with ``value`` at ``path``: the block the path enters, whole."""
    raw = put(Config, BASE, path, value)
    block = path[0][1]
    out = folder / name
    out.write_text(yaml.dump({"profile": "tiny", block: raw[block]}, Dumper=DUMPER, sort_keys=False))
    return out


def _timed(call) -> tuple[str, float]:
    """(the TypError's message, or "returned", the seconds ``call`` took)."""
    start = time.perf_counter()
    try:
        call()
    except TypError as exc:
        return str(exc), time.perf_counter() - start
    return "returned", time.perf_counter() - start


def refusals(*calls) -> list[tuple[str, float]]:
    """:func:`_timed` of each call, all in one child bounded to 2 s each and 1 GiB (tests/helpers/bounded.py)."""
    outcome = run_bounded(lambda: [_timed(c) for c in calls], seconds=SECONDS * len(calls), memory=MEMORY,
                          keep=lambda value: value)
    assert outcome.kind == "returned", str(outcome)
    for text, seconds in outcome.value:
        assert seconds < SECONDS, f"{seconds:.2f} s: {text}"
    return outcome.value


def assert_refused(text: str, field: str, bound: Bound) -> None:
    assert f": {field}: expected " in text, text
    assert bound.interval() in text and bound.why in text, text


# ---------------------------------------------------------------- every leaf has a bound


@pytest.mark.parametrize("tp", [Config, SensorConfig, ElevationRule], ids=lambda t: t.__name__)
def test_every_number_and_list_of_the_config_types_has_a_bound(tp):
    leaves = list(numeric_leaves(tp))
    assert leaves
    for path, leaf in leaves:
        bounds = [m for m in limits(leaf) if isinstance(m, Bound)]
        assert len(bounds) == 1, f"{dotted(path)}: {leaf} carries no Bound"
        bound = bounds[0]
        assert bound.low < bound.high and bound.why.strip(), dotted(path)
    for path, lst in variable_lists(tp):
        assert length_of(lst) is not None, f"{dotted(path)}: a list of any length"
    if tp is Config:  # the walk reaches the families the issue names
        names = {dotted(p) for p, _ in leaves}
        assert {"simulate.scenarios.target.train", "simulate.seed", "voxelize.workers", "voxelize.grid.shape[2]",
                "generate.references_per_frame", "stage1.epochs", "stage1.batch_size", "stage1.lr",
                "ddpm.configs[0].samplers[0][1]", "ddpm.seeds[0]", "simulate.domains.target.frames",
                "simulate.sources.target.splits.x", "fusion.detector.layer_nums[0]"} <= names


@pytest.mark.parametrize("profile", PROFILES)
def test_every_profile_and_params_yaml_lie_within_the_bounds(profile):
    config_from_dict({"profile": profile})
    load_config(REPO / "params.yaml")


def test_a_bound_message_names_the_field_the_interval_and_why():
    with pytest.raises(TypError) as info:
        config_from_dict({"stage1": {"epochs": 10**18}})
    err = info.value
    assert err.field == "stage1.epochs"
    assert str(err).startswith("params.yaml: stage1.epochs: expected an integer in [1, 10000] (passes over the "
                               "training set")
    assert str(err).endswith("got 1000000000000000000")


# ---------------------------------------------------------------- each leaf past its bound, in a params.yaml


@pytest.mark.parametrize("path, leaf", LEAVES, ids=[_id(p) for p, _ in LEAVES])
def test_a_number_past_its_bound_is_refused_by_name_at_load(path, leaf, tmp_path):
    field, bound = dotted(path), bound_of(leaf)
    huge, at_1e15, below = past(leaf)
    files = [write_params(tmp_path, path, value, f"{i}.yaml") for i, value in enumerate((huge, at_1e15))]
    for text, _ in refusals(*(lambda f=f: load_config(f) for f in files)):
        assert_refused(text, field, bound)
    with pytest.raises(TypError) as info:  # below the low end (a negative seed, count or size)
        load_config(write_params(tmp_path, path, below))
    assert info.value.field == field and bound.interval() in info.value.expected


#: typ check on the fields issue 57 found unbounded, and one leaf of every block
CHECKED = ["simulate.scenarios.target.train", "simulate.seed", "generate.references_per_frame", "stage1.epochs",
           "stage1.batch_size", "voxelize.workers", "voxelize.grid.shape[0]", "ddpm.configs[0].samplers[0][1]",
           "fusion.detector.max_pillars", "ssc.v2xvit.depth", "vqvae.x.num_codes", "evaluate.n_boot",
           "selftrain.pseudo_references", "stage2.epochs", "adapt.disc_width", "simulate.domains.target.frames"]


@pytest.mark.parametrize("field", CHECKED)
def test_typ_check_refuses_the_same_fields(field, tmp_path, capsys):
    from cli.main import main

    path, leaf = next((p, t) for p, t in LEAVES if dotted(p) == field)
    bound = bound_of(leaf)
    for value in past(leaf):
        write_params(tmp_path, path, value)
        assert main(["--root", str(tmp_path), "check"]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"typ: error: {tmp_path / 'params.yaml'}: {field}: expected ")
        assert bound.interval() in err and bound.why in err and "Traceback" not in err


def test_the_grid_is_bounded_by_its_voxels_too(tmp_path):
    from typ.voxel import MAX_VOXELS

    params = tmp_path / "params.yaml"
    params.write_text(yaml.safe_dump({"voxelize": {"grid": {"shape": [8192, 8192, 8192]}}}))  # each side in bounds
    outcome = run_bounded(lambda: load_config(params), seconds=SECONDS, memory=MEMORY)
    assert outcome.kind == "TypError" and "voxelize.grid.shape: expected 3 numbers whose product is at most " \
        f"{MAX_VOXELS}" in outcome.text, str(outcome)


def test_a_list_is_refused_by_its_length_before_its_items_are_built(tmp_path):
    params = tmp_path / "params.yaml"
    params.write_text("stage1:\n  postprocess:\n    candidates: [" + ", ".join(["0.5"] * 20_000) + "]\n")
    outcome = run_bounded(lambda: load_config(params), seconds=SECONDS, memory=MEMORY)
    assert outcome.kind == "TypError" and "stage1.postprocess.candidates: expected 1 to 32 items" in outcome.text, \
        str(outcome)


def test_the_schema_carries_the_bounds(tmp_path):
    from typ.config_schema import config_schema

    validator = jsonschema.Draft202012Validator(config_schema())
    for path, leaf in LEAVES:
        raw = put(Config, BASE, path, past(leaf)[0])
        block = path[0][1]
        assert list(validator.iter_errors({"profile": "tiny", block: raw[block]})), dotted(path)
    grid = validator.schema["$defs"]["GridConfig"]["properties"]["shape"]["prefixItems"][0]
    assert (grid["minimum"], grid["maximum"]) == (1, 8192)


# ---------------------------------------------------------------- sensor blocks (typ.sensors.resolve)

SENSOR = {"elevations_deg": [-10.0, 0.0], "azimuth_step_deg": 0.2, "max_range": 50.0, "mount_height": 1.5}


@pytest.mark.parametrize("change, field", [
    ({"elevations_deg": {"n": 10**9, "low": -25, "high": 15}}, "sensor.elevations_deg.n"),
    ({"azimuth_step_deg": 1e-9}, "sensor.azimuth_step_deg"),
    ({"max_range": 1e308}, "sensor.max_range"),
    ({"elevations_deg": [i / 1000 for i in range(-80_000, 80_000)]}, "sensor.elevations_deg"),
    ({"elevations_deg": {"n": 32, "low": -25, "high": 15, "scale": 1e-300}}, "sensor.elevations_deg.scale"),
])
def test_the_issues_sensor_blocks_get_named_errors(change, field):
    from typ.sensors import resolve

    outcome = run_bounded(lambda: resolve({**SENSOR, **change}), seconds=SECONDS, memory=MEMORY)
    assert outcome.kind == "TypError" and outcome.seconds < SECONDS, str(outcome)
    assert outcome.text.startswith(f"params.yaml: {field}: expected "), outcome.text


SENSOR_LEAVES = list(numeric_leaves(SensorConfig))  # the elevation list's and the elevation rule's included


@pytest.mark.parametrize("path, leaf", SENSOR_LEAVES, ids=[dotted(p) for p, _ in SENSOR_LEAVES])
def test_every_number_of_a_sensor_block_is_bounded(path, leaf):
    from typ.sensors import resolve

    field, bound = "sensor." + dotted(path), bound_of(leaf)
    blocks = [put(SensorConfig, SENSOR, path, value) for value in past(leaf)]
    for text, _ in refusals(*(lambda b=b: resolve(b) for b in blocks)):
        assert_refused(text, field, bound)


def test_a_sensor_config_built_in_code_meets_the_same_bounds():
    from typ.sensors import resolve

    assert resolve(SensorConfig(elevations_deg=(-10.0, 0.0), azimuth_step_deg=0.2, max_range=50.0,
                                mount_height=1.5)).n_beams == 2
    with pytest.raises(TypError) as info:
        resolve(SensorConfig(elevations_deg=ElevationRule(n=10**9, low=-25.0, high=15.0), azimuth_step_deg=0.2,
                             max_range=50.0, mount_height=1.5), field="simulate.sources.target.sensor")
    assert info.value.field == "simulate.sources.target.sensor.elevations_deg.n"


# ---------------------------------------------------------------- saved model configs (typ.artifacts)


@pytest.fixture(scope="module")
def modules(tmp_path_factory) -> dict[str, tuple[Path, typing.Callable]]:
    """One module of every kind typ saves, at the tiny profile's sizes, saved as its stage saves it:
    folder and the builder its loader uses."""
    import torch

    from models.adapter import ZeroAdapter
    from models.discriminator import LatentDiscriminator
    from models.ldm import LatentDiffusion
    from models.lidar_features import SegmentationFeatureNet
    from models.pixel_ddpm import PixelDiffusion
    from models.vqvae import PooledBoxMap
    from models.vqvae import build_from_config as build_encoder
    from tasks import fusion_train, lidar_features, ssc_train, stage1, stage2, vqvae
    from tasks.ssc_data import model_kwargs
    from typ.artifacts import save_module
    from typ.voxel import Grid

    torch.manual_seed(0)
    cfg = config_from_dict({})
    root = tmp_path_factory.mktemp("modules")
    g = cfg.voxelize.grid
    unet = stage1.build(cfg.stage1, cfg.vqvae.x.latent_channels, 1, 16)
    u = cfg.ddpm.unet
    made = {
        "vqvae": (vqvae.build("x", cfg.vqvae.x, g.shape[2]), None, build_encoder),
        "box_pool": (PooledBoxMap(downsample=8), None, build_encoder),
        "unet": (unet, None, LatentDiffusion.from_config),
        "adapter": (stage2.build_adapter(unet, res_blocks=1, seed=0, conditions=2), None, ZeroAdapter.from_config),
        "discriminator": (LatentDiscriminator(in_channels=8, width=cfg.adapt.disc_width), None,
                          LatentDiscriminator.from_config),
        "features": (lidar_features.build("voxel", cfg.ddpm.features, Grid(g.x_range, g.y_range, g.z_range, g.shape)),
                     None, SegmentationFeatureNet.from_config),
        "ddpm": (PixelDiffusion(channels=2, height=64, width=256, patch=(4, 4), block_out_channels=u.block_out_channels,
                                layers_per_block=1, norm_num_groups=u.norm_num_groups, dropout=u.dropout,
                                time_embedding="fourier", harmonics=u.harmonics, coordinates=True), None,
                 PixelDiffusion.from_config),
    }
    for method in ("none", "v2xvit"):
        made[f"fusion_{method}"] = (fusion_train.build_model(method, cfg.fusion),
                                    fusion_train.model_config(method, cfg.fusion), fusion_train.build_from_config)
    for name in ("single", "v2xvit"):
        conf = ssc_train._network_config(name, model_kwargs(cfg.ssc), ssc_train.network_options(cfg.ssc, name))
        made[f"ssc_{name}"] = (ssc_train._build(conf), conf, ssc_train._build)
    out = {}
    for name, (module, config, build) in made.items():
        extra = {"schedule": "linear", "train_timesteps": 1000} if name == "unet" else {}
        save_module(root / name, module, module.config if config is None else config, **extra)
        out[name] = (root / name, build)
    return out


def _model_leaves(value, header, path=(), key="config", block=None, block_path=()):
    """(path in config.json, the most :func:`typ.artifacts.check_config` allows there) of every number: a
    params block's bound inside one, else an input size's, the size limit (ints) or MAX_FLOAT (floats)."""
    from typ.artifacts import INPUT_SIZES, MAX_FLOAT, params_block, size_limit

    if isinstance(value, bool) or value is None or isinstance(value, str):
        return
    if isinstance(value, (int, float)):
        if block is not None:
            yield path, _hint_bound(block, block_path).high
        else:
            yield path, MAX_FLOAT if isinstance(value, float) else INPUT_SIZES.get(key, size_limit(header))
    elif isinstance(value, dict):
        inner = block or params_block(value)
        for k, v in value.items():
            yield from _model_leaves(v, header, path + (k,), k, inner, block_path + (k,) if inner else ())
    else:
        for i, v in enumerate(value):
            yield from _model_leaves(v, header, path + (i,), key, block, block_path + (i,) if block else ())


def _hint_bound(cls, block_path) -> Bound:
    tp = typing.get_type_hints(cls, include_extras=True)[block_path[0]]
    for step in block_path[1:]:
        args = typing.get_args(unannotated(tp))
        tp = args[0] if args[-1] is Ellipsis else args[step]
    return bound_of(tp)


def _name(path) -> str:
    return "config" + "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in path)


def _set(doc, path, value):
    for step in path[:-1]:
        doc = doc[step]
    doc[path[-1]] = value


KINDS = ["vqvae", "box_pool", "unet", "adapter", "discriminator", "features", "ddpm", "fusion_none", "fusion_v2xvit",
         "ssc_single", "ssc_v2xvit"]


@pytest.mark.parametrize("kind", KINDS)
def test_every_number_of_a_model_config_past_its_bound_is_refused_by_name(kind, modules, tmp_path):
    from typ.artifacts import CONFIG, load_module, read_weights_header

    folder, build = modules[kind]
    load_module(folder, build, "stage")  # as saved: within every bound
    doc = json.loads((folder / CONFIG).read_text())
    header = read_weights_header(folder, "stage")
    leaves = list(_model_leaves(doc["config"], header))
    assert leaves
    bads = []
    for k, (path, high) in enumerate(leaves):
        for value in (10 * high, 10**15):
            bad = tmp_path / f"{k}-{value}"
            shutil.copytree(folder, bad)
            changed = json.loads(json.dumps(doc))
            _set(changed["config"], path, value)
            (bad / CONFIG).write_text(json.dumps(changed))
            bads.append((bad, path))
    texts = refusals(*(lambda b=bad: load_module(b, build, "stage") for bad, _ in bads))
    for (bad, path), (text, _) in zip(bads, texts):
        assert text.startswith(f"{bad / CONFIG}: {_name(path)}: expected "), text


def _with(folder: Path, tmp_path: Path, change) -> Path:
    from typ.artifacts import CONFIG

    bad = tmp_path / folder.name
    shutil.copytree(folder, bad)
    doc = json.loads((bad / CONFIG).read_text())
    change(doc)
    (bad / CONFIG).write_text(json.dumps(doc))
    return bad


def test_the_issues_unet_of_100000_layers_per_block_is_refused_before_building(modules, tmp_path):
    from typ.artifacts import load_module

    folder, build = modules["unet"]
    bad = _with(folder, tmp_path, lambda d: d["config"].update(layers_per_block=100_000))
    outcome = run_bounded(lambda: load_module(bad, build, "stage1"), seconds=SECONDS, memory=MEMORY)
    assert outcome.kind == "TypError" and outcome.seconds < 0.5, str(outcome)
    assert f"{bad / 'config.json'}: config.layers_per_block: expected an integer of at most" in outcome.text


@pytest.mark.parametrize("kind, key", [("unet", "layers_per_block"), ("vqvae", "layers_per_block"),
                                       ("ddpm", "layers_per_block"), ("adapter", "num_res_blocks"),
                                       ("features", "levels")])
def test_a_depth_under_the_size_limit_stops_the_build_at_the_weights_tensor_count(kind, key, modules, tmp_path):
    """A depth as large as the header's tensor count passes the per-field rule; the build on the meta device
    stops as soon as it has registered more parameters than the file holds."""
    from typ.artifacts import load_module, read_weights_header, size_limit

    folder, build = modules[kind]
    limit = size_limit(read_weights_header(folder, "stage"))
    bad = _with(folder, tmp_path, lambda d: d["config"].update({key: limit}))
    outcome = run_bounded(lambda: load_module(bad, build, "stage"), seconds=SECONDS, memory=MEMORY)
    assert outcome.kind == "TypError" and outcome.seconds < SECONDS, str(outcome)
    assert f"{bad / 'config.json'}: config: expected " in outcome.text and "a depth or count" in outcome.text


@pytest.mark.parametrize("change, field", [
    (lambda d: d.update(train_timesteps=10**15), "train_timesteps"),          # a noise schedule of 10**15 betas
    (lambda d: d["config"].update(sample_size=1 << 20), "config.sample_size"),  # coordinate channels of 12 TB
    (lambda d: d["config"].update(norm_num_groups=float("nan")), "config.norm_num_groups"),
])
def test_saved_sizes_beside_the_weights_are_bounded_too(change, field, modules, tmp_path):
    from typ.artifacts import load_module

    folder, build = modules["unet"]
    bad = _with(folder, tmp_path, change)
    outcome = run_bounded(lambda: load_module(bad, build, "stage1"), seconds=SECONDS, memory=MEMORY)
    assert outcome.kind == "TypError" and outcome.text.startswith(f"{bad / 'config.json'}: {field}: expected "), \
        str(outcome)


def test_a_detectors_params_block_meets_the_params_bounds_and_checks(modules, tmp_path):
    from typ.artifacts import load_module

    folder, build = modules["fusion_none"]
    bad = _with(folder, tmp_path, lambda d: d["config"]["detector"].update(voxel_size=1e-9))  # 10**20 pillar cells
    with pytest.raises(TypError) as info:
        load_module(bad, build, "fusion")
    assert info.value.field == "config.detector.voxel_size" and "[0.01, 10]" in info.value.expected
    wide = _with(folder, tmp_path / "wide", lambda d: d["config"]["detector"].update(
        lidar_range=[-819.2, -819.2, -3.0, 819.2, 819.2, 1.0], voxel_size=0.4))  # each number in bounds
    with pytest.raises(TypError, match="at most 4194304 pillar cells"):
        load_module(wide, build, "fusion")
