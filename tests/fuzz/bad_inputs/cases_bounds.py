"""Bad-input cases: sizes past their bounds: params fields, sensor blocks, model configs (registered with
:func:`bad_inputs.make_corpus.case`).

Each size issue 57 found accepted (a count, an epoch, a batch, a worker pool, a seed, a sensor's beams,
a model's depth) is given past the bound declared beside its field, and must be refused by name before
any work: the dotted field, the interval and why (:class:`typ.config.Bound`), or the config.json field
against its weights (:func:`typ.artifacts.check_config`). tests/fuzz/test_bounds.py walks every field; these
are the ones a user met.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

from bad_inputs.make_corpus import PRIOR, Probe, _cli, _tiny_unet, case, load_params, params, write


def _params(d: Path, raw: dict, field: str, interval: str) -> Probe:
    probe = load_params(d, raw)
    probe.says += (field, interval)
    return probe


@case("params", "scenarios_per_split_1e15", "huge")
def _(d):
    # once accepted by typ check; typ run simulate then grew 9 MB/s and wrote nothing
    return _params(d, {"simulate": {"scenarios": {"target": {"train": 10**15}}}}, "simulate.scenarios.target.train",
                   "an integer in [0, 100000]")


@case("params", "references_per_frame_a_billion", "huge")
def _(d):
    return _params(d, {"generate": {"references_per_frame": 10**9}}, "generate.references_per_frame",
                   "an integer in [1, 64]")


@case("params", "epochs_1e18", "huge")
def _(d):
    return _params(d, {"stage1": {"epochs": 10**18}}, "stage1.epochs", "an integer in [1, 10000]")


@case("params", "batch_size_1e12", "huge")
def _(d):
    return _params(d, {"stage1": {"batch_size": 10**12}}, "stage1.batch_size", "an integer in [1, 1024]")


@case("params", "workers_a_billion", "huge")
def _(d):
    return _params(d, {"voxelize": {"workers": 10**9}}, "voxelize.workers", "an integer in [1, 256]")


@case("params", "negative_seed", "wrong units")
def _(d):
    return _params(d, {"simulate": {"seed": -1}}, "simulate.seed", "an integer in [0, 2147483647]")


@case("params", "seed_past_numpy", "overflow")
def _(d):
    return _params(d, {"fusion": {"seed": 2**32}}, "fusion.seed", "an integer in [0, 2147483647]")


@case("params", "grid_of_half_a_trillion_voxels", "huge")
def _(d):
    return _params(d, {"voxelize": {"grid": {"shape": [8192, 8192, 8192]}}}, "voxelize.grid.shape",
                   "3 numbers whose product is at most 67108864")


@case("params", "sampler_steps_inside_a_list", "huge")
def _(d):
    return _params(d, {"ddpm": {"samplers": [["ddim", 10**12]]}}, "ddpm.samplers[0][1]", "an integer in [1, 10000]")


@case("params", "ten_thousand_thresholds", "huge")
def _(d):
    # every pair of the candidates is scored on the validation split
    return _params(d, {"stage1": {"postprocess": {"candidates": [0.5] * 10_000}}}, "stage1.postprocess.candidates",
                   "1 to 32 items")


@case("params", "sensor_block_of_a_billion_beams", "huge")
def _(d):
    from typ.sensors import resolve

    block = {"elevations_deg": {"n": 10**9, "low": -25, "high": 15}, "azimuth_step_deg": 0.2, "max_range": 100,
             "mount_height": 1.8}   # a raw MemoryError before
    return Probe(says=("simulate.sources.target.sensor.elevations_deg.n", "an integer in [1, 256]"),
                 call=lambda: resolve(block, field="simulate.sources.target.sensor"))


@case("params", "sensor_block_azimuth_step_1e-9", "wrong units")
def _(d):
    from typ.sensors import resolve

    block = {"elevations_deg": [-10.0, 0.0], "azimuth_step_deg": 1e-9, "max_range": 100, "mount_height": 1.8}
    return Probe(says=("sensor.azimuth_step_deg", "a number in [0.05, 10]"), call=lambda: resolve(block))


@case("params", "sensor_block_range_1e308", "overflow")
def _(d):
    from typ.sensors import resolve

    block = {"elevations_deg": [-10.0, 0.0], "azimuth_step_deg": 0.2, "max_range": 1e308, "mount_height": 1.8}
    return Probe(says=("sensor.max_range", "a number in (0, 1000]"), call=lambda: resolve(block))


@case("cli", "check_scenarios_1e15", "huge")
def _(d):
    root = d / "proj"
    params(root, {"profile": "tiny", "simulate": {"scenarios": {"target": {"train": 10**15}}}})
    for rel, text in PRIOR.items():
        write(root / rel, text)
    return _cli(root, "check", says=("params.yaml: simulate.scenarios.target.train: expected an integer in "
                                     "[0, 100000]",))


def _unet(d: Path, **changes) -> tuple[Path, Callable]:
    """A stage-1 model folder whose config.json has ``changes``, and its loader."""
    from tasks import stage1
    from typ.config import config_from_dict

    folder = d / "seed_0"
    stage1.save_model(_tiny_unet(), config_from_dict({}).stage1, {"low": 0.5, "high": 0.5, "noise_std": 0.0}, folder)
    path = folder / "config.json"
    doc = json.loads(path.read_text())
    for key, value in changes.items():
        (doc if key == "train_timesteps" else doc["config"])[key] = value
    path.write_text(json.dumps(doc))
    return path, lambda: stage1.load_model(folder)


@case("artifact", "unet_100000_layers_per_block", "huge", needs="torch")
def _(d):
    # built for more than 300 s and 2.6 GB before any check
    path, load = _unet(d, layers_per_block=100_000)
    return Probe(says=(str(path), "config.layers_per_block", "stage1 stage"), call=load)


@case("artifact", "unet_depth_under_the_size_limit", "huge", needs="torch")
def _(d):
    # within the per-field rule (the weights' tensor count), stopped by the build's parameter budget
    path, load = _unet(d, layers_per_block=60)
    return Probe(says=(str(path), "config", "a depth or count of it is too large"), call=load)


@case("artifact", "unet_train_timesteps_1e15", "huge", needs="torch")
def _(d):
    path, load = _unet(d, train_timesteps=10**15)   # a noise schedule of 10**15 betas where it is sampled
    return Probe(says=(str(path), "train_timesteps", "an integer in [1, 10000]"), call=load)


@case("artifact", "unet_config_nan", "nan/inf", needs="torch")
def _(d):
    path, load = _unet(d, attention_head_dim=float("nan"))
    return Probe(says=(str(path), "config.attention_head_dim", "a finite number"), call=load)


@case("artifact", "detector_pillars_of_a_nanometre", "wrong units", needs="torch")
def _(d):
    from tasks import fusion_train
    from typ.artifacts import save_module
    from typ.config import config_from_dict

    cfg = config_from_dict({}).fusion
    folder = d / "none"
    save_module(folder, fusion_train.build_model("none", cfg), fusion_train.model_config("none", cfg))
    path = folder / "config.json"
    doc = json.loads(path.read_text())
    doc["config"]["detector"]["voxel_size"] = 1e-9   # 10**20 pillar cells where it detects
    path.write_text(json.dumps(doc))
    return Probe(says=(str(path), "config.detector.voxel_size", "a number in [0.01, 10]"),
                 call=lambda: fusion_train.load(folder, cfg))
