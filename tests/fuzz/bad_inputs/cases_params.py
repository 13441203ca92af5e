"""Bad-input cases: params.yaml (typ.config.load_config) (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

from pathlib import Path

from bad_inputs.make_corpus import Probe, case, load_params, unreadable


@case("params", "missing_file", "missing keys")
def _(d):
    from typ.config import load_config

    p = d / "params.yaml"
    return Probe(says=(str(p), "file", "a params.yaml"), call=lambda: load_config(p))


@case("params", "invalid_yaml", "wrong dtype")
def _(d):
    probe = load_params(d, "profile: tiny\nsimulate: {frames: 2\n")
    probe.says += ("yaml", "well-formed YAML")
    return probe


@case("params", "top_level_list", "wrong dtype")
def _(d):
    probe = load_params(d, "- profile\n- tiny\n")
    probe.says += ("<top level>", "a mapping of stage blocks")
    return probe


@case("params", "not_utf8", "wrong dtype")
def _(d):
    probe = load_params(d, "")
    Path(probe.says[0]).write_bytes(b"profile: tiny\nsimulate: {seed: \xff\xfe}\n")
    probe.says += ("file", "a readable UTF-8 params.yaml")
    return probe


@case("params", "is_a_directory", "unreadable")
def _(d):
    from typ.config import load_config

    p = d / "params.yaml"
    p.mkdir()
    return Probe(says=(str(p), "file", "a readable UTF-8 params.yaml"), call=lambda: load_config(p))


@case("params", "no_permission", "unreadable", needs_non_root=True)
def _(d):
    probe = load_params(d, {"profile": "tiny"})
    unreadable(Path(probe.says[0]))
    probe.says += ("file", "PermissionError")
    return probe


@case("params", "unknown_profile", "unknown")
def _(d):
    probe = load_params(d, {"profile": "huge"})
    probe.says += ("profile", "one of ['tiny', 'small', 'paper']", "'huge'")
    return probe


@case("params", "unknown_stage_block", "unknown")
def _(d):
    probe = load_params(d, {"profile": "tiny", "voxelise": {"workers": 2}})
    probe.says += ("voxelise", "one of the known keys")
    return probe


@case("params", "unknown_key_in_block", "unknown")
def _(d):
    probe = load_params(d, {"voxelize": {"grid": {"shape": [128, 128, 8], "voxel_size": 0.8}}})
    probe.says += ("voxelize.grid.voxel_size", "one of the known keys")
    return probe


@case("params", "string_for_integer", "wrong dtype")
def _(d):
    probe = load_params(d, {"simulate": {"frames": "two"}})
    probe.says += ("simulate.frames", "an integer", "'two'")
    return probe


@case("params", "float_for_integer", "wrong dtype")
def _(d):
    probe = load_params(d, {"vqvae": {"batch_size": 4.5}})
    probe.says += ("vqvae.batch_size", "an integer")
    return probe


@case("params", "grid_shape_two_numbers", "misaligned")
def _(d):
    probe = load_params(d, {"voxelize": {"grid": {"shape": [128, 128]}}})
    probe.says += ("voxelize.grid.shape", "a list of 3")
    return probe


@case("params", "nan_learning_rate", "nan/inf")
def _(d):
    probe = load_params(d, "vqvae:\n  lr: .nan\n")
    probe.says += ("vqvae.lr", "a finite number")
    return probe


@case("params", "inf_distance", "nan/inf")
def _(d):
    probe = load_params(d, "generate:\n  max_distance: .inf\n")
    probe.says += ("generate.max_distance", "a finite number")
    return probe


@case("params", "grid_range_reversed", "wrong units")
def _(d):
    probe = load_params(d, {"voxelize": {"grid": {"x_range": [51.2, -51.2]}}})
    probe.says += ("voxelize.grid.x_range", "min < max")
    return probe


@case("params", "threshold_in_percent", "wrong units")
def _(d):
    probe = load_params(d, {"vqvae": {"threshold": 50}})
    probe.says += ("vqvae.threshold", "a probability in (0, 1)")
    return probe


@case("params", "postprocess_candidates_in_percent", "wrong units")
def _(d):
    probe = load_params(d, {"stage1": {"postprocess": {"candidates": [10, 20, 30]}}})
    probe.says += ("stage1.postprocess.candidates[0]", "a probability in (0, 1)")
    return probe


@case("params", "negative_scenario_count", "wrong units")
def _(d):
    probe = load_params(d, {"simulate": {"scenarios": {"target": {"train": -1}}}})
    probe.says += ("simulate.scenarios.target.train", "an integer in [0, 100000]")
    return probe


@case("params", "huge_sample_steps", "huge")
def _(d):
    probe = load_params(d, {"stage1": {"sample_steps": 10**9}})
    probe.says += ("stage1.sample_steps", "an integer in [1, 10000]")
    return probe


@case("params", "block_is_a_number", "wrong dtype")
def _(d):
    probe = load_params(d, {"simulate": 3})
    probe.says += ("simulate", "a mapping for SimulateConfig")
    return probe


@case("params", "unknown_schedule", "unknown")
def _(d):
    probe = load_params(d, {"stage1": {"schedule": "cosine2"}})
    probe.says += ("stage1.schedule", "one of [")
    return probe
