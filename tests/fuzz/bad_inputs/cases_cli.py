"""Bad-input cases: the CLI (typ ...): exit code 2, the message on stderr (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

from pathlib import Path

from typ import geometry
from typ.formats.opv2v import write_scene
from typ.scene import AgentView, Scene
from typ.store import scene_path, write_scene_voxels

from bad_inputs.make_corpus import (GRID, PRIOR, Probe, _cli, case, cloud, params, pcd_text, store_records, unreadable, write)


def project(d: Path, raw: dict | str | None = None) -> Path:
    """A project folder: params.yaml and outputs of an earlier run, which no failing command may touch."""
    root = d / "proj"
    params(root, {"profile": "tiny"} if raw is None else raw)
    for rel, text in PRIOR.items():
        write(root / rel, text)
    return root




@case("cli", "run_unknown_stage", "unknown")
def _(d):
    root = project(d)
    return _cli(root, "run", "voxelise", says=("typ run", "stage", "one of ['all', 'simulate'", "'voxelise'"))


@case("cli", "unknown_command", "unknown")
def _(d):
    root = project(d)
    return _cli(root, "frobnicate", says=("invalid choice", "frobnicate"))


@case("cli", "run_without_stage", "missing keys")
def _(d):
    root = project(d)
    return _cli(root, "run", says=("the following arguments are required: stage",))


@case("cli", "params_missing", "missing keys")
def _(d):
    root = project(d)
    return _cli(root, "--params", "nope.yaml", "run", "simulate", says=(str(root / "nope.yaml"), "file"))


@case("cli", "params_is_a_directory", "unreadable")
def _(d):
    root = project(d)
    (root / "conf").mkdir()
    return _cli(root, "--params", "conf", "run", "simulate",
                says=(str(root / "conf"), "file", "a readable UTF-8 params.yaml"))


@case("cli", "params_no_permission", "unreadable", needs_non_root=True)
def _(d):
    root = project(d)
    unreadable(root / "params.yaml")
    return _cli(root, "run", "simulate", says=(str(root / "params.yaml"), "PermissionError"))


@case("cli", "params_unknown_profile", "unknown")
def _(d):
    root = project(d, {"profile": "huge"})
    return _cli(root, "run", "voxelize", says=("params.yaml: profile", "one of ['tiny', 'small', 'paper']"))


@case("cli", "params_wrong_type", "wrong dtype")
def _(d):
    root = project(d, {"profile": "tiny", "simulate": {"frames": "two"}})
    return _cli(root, "run", "simulate", says=("params.yaml: simulate.frames: expected an integer, got 'two'",))


@case("cli", "check_params_nan", "nan/inf")
def _(d):
    root = project(d, "profile: tiny\nvoxelize:\n  grid: {z_range: [-3.0, .inf]}\n")
    return _cli(root, "check", says=("voxelize.grid.z_range[1]", "a finite number"))


def _stage_process(root: Path, stage: str, says: tuple[str, ...]) -> Probe:
    return Probe(says=says, process=["--root", str(root), "run", stage], cwd=root, watch=root)


@case("cli", "voxelize_nan_intensity_in_a_scan", "nan/inf")
def _(d):
    """Through the whole stage: the scene's earlier voxels and the other outputs stay as they were."""
    root = d / "proj"
    params(root, {"profile": "tiny", "voxelize": {"workers": 1}})
    scene = root / "data" / "sim" / "target" / "train" / "target_train_0000"
    pts = cloud()
    good = Scene("target_train_0000", "000000", {"1": AgentView("1", pts, geometry.pose_to_matrix([0] * 6))})
    write_scene(good, scene.parent)
    write_scene_voxels(scene_path(root / "data" / "voxels", "target", "train", scene.name),
                       store_records(), grid=GRID, input_hash="an earlier run")
    write(root / "metrics" / "voxelize.json", '{"voxelized": 1}\n')
    bad = scene / "1" / "000000.pcd"
    bad.write_bytes(pcd_text(body="1 2 3 0.5\n4 5 6 nan\n7 8 9 0.5\n"))
    return _stage_process(root, "voxelize", says=(str(bad), "intensity", "finite values"))
