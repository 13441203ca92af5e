"""Nothing a user owns is deleted (the classes of input below).

typ deletes or replaces only what it can prove it wrote: what its record beside it says the
stage put there (``.typ/written/``: the inode and fingerprint of the tree), never a folder that
merely holds a manifest (``_typ.json``), a copy, an unpacked archive or a folder a user added to.
Anything else in an output folder is left alone and counted in the stage's metrics. One run at a
time per output folder, whatever root or name reaches it (a lock beside the folder the second run
is refused by, naming the holder's pid; a lock path that is not typ's own file is named, never
written). ``typ edit`` never writes over its own input nor through a link (its copy holds real
files), and the CLI names a path that is in the way (a file where a folder goes, a name too long,
a link out of the output) instead of a traceback.
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from typ.errors import TypError
from typ.voxel import Grid
from repo_paths import REPO, SHARED_DATA

KITTI = SHARED_DATA / "kitti_object_vis"
GRID = Grid((-51.2, 51.2), (-51.2, 51.2), (-3.0, 1.0), (64, 64, 8))


def snapshot(folder: Path) -> dict[str, bytes | str | None]:
    """Every path under ``folder``: a file's bytes, a link's target, None for a folder."""
    out = {}
    for p in sorted(folder.rglob("*")):
        rel = str(p.relative_to(folder))
        out[rel] = f"-> {os.readlink(p)}" if p.is_symlink() else p.read_bytes() if p.is_file() else None
    return out


class _GroundPipe:
    """Stands in for the trained diffusion model: ground everywhere, a car in every box of y_r."""

    conditions = 0
    grid = GRID

    @property
    def point_stats(self):
        from pipelines.typ.pipeline_typ import PointStats

        return PointStats.single()

    def occupancy(self, x_e, y_r, *, seed, resim=None):
        occ = np.zeros((len(y_r), GRID.shape[2], *GRID.shape[:2]), dtype=bool)
        occ[:, 0] = True
        occ[:, 1:4] |= y_r[:, :1].astype(bool)
        return occ

    def points(self, occupancy, grid, seed):
        from pipelines.typ.pipeline_typ import PointStats, occupancy_to_points

        return occupancy_to_points(occupancy, grid, PointStats.single(), np.random.default_rng(seed))


def write_scenario(parent: Path, name: str = "scen") -> Path:
    """A one-agent OPV2V-layout scenario ``parent/name`` with a car (id 5) and a manifest of its own."""
    from typ.formats.opv2v import write_scene
    from typ.scene import AgentView, Scene

    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-30, 30, (2000, 2)), np.full(2000, -1.7), np.zeros(2000)].astype(np.float32)
    view = AgentView("1", points, np.eye(4), np.array([[10.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0]]), ("car",),
                     np.array([5]))
    folder = write_scene(Scene(name, "000000", {"1": view}), parent)
    (folder / "_typ.json").write_text('{"key": "the user\'s", "counts": {}}\n')
    return folder


@pytest.fixture
def cli(tmp_path, monkeypatch):
    """``typ ARGS`` in this process on a tiny project whose generator is :class:`_GroundPipe`;
    returns (exit code, stderr). The environment the CLI sets up is restored afterwards."""
    import flows.generate
    from cli.main import main
    from tasks.generate import Generator

    project = tmp_path / "project"
    project.mkdir()
    (project / "params.yaml").write_text("profile: tiny\n")
    for name in ("PREFECT_HOME", "PREFECT_LOGGING_EXTRA_LOGGERS", "TYP_HASH_CACHE", "PREFECT_LOGGING_LEVEL"):
        monkeypatch.setenv(name, os.environ.get(name, ""))
    monkeypatch.setenv("PREFECT_HOME", str(tmp_path / "prefect"))
    monkeypatch.setattr(flows.generate, "load_generator",
                        lambda root, cfg: Generator(_GroundPipe(), dict(cfg.voxelize.mount_height), digest=""))

    def run(*argv: str) -> int:
        return main(["--root", str(project), *argv])

    return run


EDIT = ("--timestamp", "000000", "--remove", "5")


# --- class 1 and 2: typ edit never replaces what it did not write, nor its input ----------------

def test_edit_of_dot_from_inside_a_scenario_keeps_what_out_holds(cli, tmp_path, monkeypatch, capsys):
    scenario = write_scenario(tmp_path / "data")
    out = tmp_path / "mine"
    out.mkdir()
    (out / "thesis.tex").write_text("years of work")
    monkeypatch.chdir(scenario)
    assert cli("edit", ".", *EDIT, "--out", str(out)) == 0, capsys.readouterr().err
    assert (out / "thesis.tex").read_text() == "years of work"
    from typ.formats.opv2v import read_scene

    edited = read_scene(out / "scen", "000000").ego
    assert list(edited.box_ids) == [] and len(edited.points) > 0
    # a second edit replaces the first: that folder is typ's own (its manifest says so)
    assert cli("edit", ".", "--timestamp", "000000", "--add", "5,5,0", "--out", str(out)) == 0
    assert list(read_scene(out / "scen", "000000").ego.box_ids) == [5, 6]
    assert sorted(p.name for p in out.iterdir()) == ["scen", "scen_000000_1_edit.png", "thesis.tex"]


@pytest.mark.parametrize("where", ["parent", "inside", "itself"])
def test_edit_whose_output_is_or_holds_its_input_is_refused(cli, tmp_path, capsys, where):
    scenario = write_scenario(tmp_path / "data")
    out = {"parent": scenario.parent, "inside": scenario / "edits", "itself": scenario}[where]
    before = snapshot(tmp_path / "data")
    assert cli("edit", str(scenario), *EDIT, "--out", str(out)) == 2
    err = capsys.readouterr().err
    assert "typ: error" in err and "--out" in err and str(scenario) in err and "Traceback" not in err
    assert snapshot(tmp_path / "data") == before   # the input and its _typ.json as they were


@pytest.mark.parametrize("command", ["edit", "show"])
def test_a_picture_of_the_users_where_typ_draws_one_is_not_replaced(cli, tmp_path, capsys, command):
    scenario = write_scenario(tmp_path / "data")
    out = tmp_path / "out"
    argv = ("edit", str(scenario), *EDIT) if command == "edit" else ("show", str(scenario), "--no-resim")
    assert cli(*argv, "--out", str(out)) == 0, capsys.readouterr().err
    png = next(p for p in out.iterdir() if p.suffix == ".png")
    assert cli(*argv, "--out", str(out)) == 0, capsys.readouterr().err    # its own: replaced
    png.write_bytes(b"my drawing")                                       # now the user's
    assert cli(*argv, "--out", str(out)) == 2
    err = capsys.readouterr().err
    assert "typ: error" in err and str(png) in err and png.read_bytes() == b"my drawing"


def test_edit_does_not_replace_a_folder_it_did_not_write(cli, tmp_path, capsys):
    scenario = write_scenario(tmp_path / "data")
    out = tmp_path / "out"
    (out / "scen").mkdir(parents=True)
    (out / "scen" / "notes.txt").write_text("mine")
    assert cli("edit", str(scenario), *EDIT, "--out", str(out)) == 2
    err = capsys.readouterr().err
    assert "typ: error" in err and str(out / "scen") in err
    assert snapshot(out) == {"scen": None, "scen/notes.txt": b"mine"}


# --- class 5: a copy holds real files, never a link to write through ---------------------------------

class TookTooLong(Exception):
    """Not an OSError, which shutil.copytree would collect and carry on after."""


@contextlib.contextmanager
def time_limit(seconds: float):
    def expire(signum, frame):
        raise TookTooLong(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def test_edit_copies_links_as_real_files_and_a_loop_once(cli, tmp_path, capsys):
    scenario = write_scenario(tmp_path / "data")
    (scenario / "1" / "loop").symlink_to("..")                # loops: 1/loop/1/again/1/loop/...
    (scenario / "1" / "again").symlink_to("..")
    (scenario / "calib.txt").write_text("P0: 1 0 0")
    (scenario / "also.txt").symlink_to("calib.txt")           # a link inside the scenario
    shared = tmp_path / "shared.txt"
    shared.write_text("outside")
    (scenario / "shared.txt").symlink_to(os.path.relpath(shared, scenario))   # one that points outside
    (scenario / "gone.txt").symlink_to(tmp_path / "nowhere")                 # a dangling one
    out = tmp_path / "out"
    with time_limit(30):
        assert cli("edit", str(scenario), *EDIT, "--out", str(out)) == 0, capsys.readouterr().err
    copy = out / "scen"
    assert not any(p.is_symlink() for p in copy.rglob("*"))
    assert (copy / "also.txt").read_text() == "P0: 1 0 0" and (copy / "shared.txt").read_text() == "outside"
    assert not (copy / "gone.txt").exists() and not (copy / "1" / "loop").exists()
    assert sum(1 for _ in copy.rglob("*")) < 20
    assert shared.read_text() == "outside"


def test_edit_of_a_scenario_assembled_from_links_leaves_the_dataset_as_it_was(cli, tmp_path, capsys):
    """OPV2V / V2V4Real copies are often scenarios whose agent folders link to a dataset kept
    elsewhere: the edited .pcd and .yaml must land in the copy, not in the dataset."""
    dataset = write_scenario(tmp_path / "dataset")
    scenario = tmp_path / "data" / "scen"
    scenario.mkdir(parents=True)
    (scenario / "1").symlink_to(dataset / "1")
    before = snapshot(tmp_path / "dataset")
    out = tmp_path / "out"
    assert cli("edit", str(scenario), *EDIT, "--out", str(out)) == 0, capsys.readouterr().err
    assert snapshot(tmp_path / "dataset") == before
    from typ.formats.opv2v import read_scene

    assert not (out / "scen" / "1").is_symlink()
    assert list(read_scene(out / "scen", "000000").ego.box_ids) == []
    assert list(read_scene(dataset, "000000").ego.box_ids) == [5]


def test_a_file_written_into_a_folder_typ_builds_never_passes_a_link(tmp_path):
    from typ.io import atomic_path, write_text

    elsewhere = tmp_path / "dataset"
    elsewhere.mkdir()
    (elsewhere / "000000.pcd").write_bytes(b"the user's points")
    with pytest.raises(TypError, match="never writes through a link"):
        with atomic_path(tmp_path / "out" / "scen", stage="edit") as tmp:
            tmp.mkdir(parents=True)
            (tmp / "1").symlink_to(elsewhere)
            write_text(tmp / "1" / "000000.pcd", "typ's points")
    assert (elsewhere / "000000.pcd").read_bytes() == b"the user's points"
    assert not (tmp_path / "out" / "scen").exists()


# --- class 14: paths in the way ---------------------------------------------------------------------

@pytest.mark.parametrize("command", ["edit", "show", "generate"])
def test_out_that_is_a_file_is_named(cli, tmp_path, capsys, command):
    scenario = write_scenario(tmp_path / "data")
    blocker = tmp_path / "out.txt"
    blocker.write_text("a file")
    argv = {"edit": ("edit", str(scenario), *EDIT),
            "show": ("show", str(scenario), "--no-resim"),
            "generate": ("generate", "--format", "kitti", "--input", str(KITTI))}[command]
    if command == "generate" and not KITTI.is_dir():
        pytest.skip(f"no KITTI frames at {KITTI}")
    for out in (blocker, blocker / "sub"):
        assert cli(*argv, "--out", str(out)) == 2
        err = capsys.readouterr().err
        assert "typ: error" in err and "--out" in err and str(blocker) in err and "Traceback" not in err
    assert blocker.read_text() == "a file"


def test_a_long_scenario_name_fits_its_temporary_names(cli, tmp_path, capsys):
    """A scenario name of 240 bytes is legal; typ's temporary names beside it must still fit NAME_MAX."""
    from typ.formats.opv2v import read_scene

    name = "s" * 240
    scenario = write_scenario(tmp_path / "data", name)
    out = tmp_path / "out"
    assert cli("edit", str(scenario), *EDIT, "--out", str(out)) == 0, capsys.readouterr().err
    assert list(read_scene(out / name, "000000").ego.box_ids) == []
    png = [p for p in out.iterdir() if p.suffix == ".png"]
    assert len(png) == 1 and len(png[0].name.encode()) <= 255 and png[0].name.endswith("_edit.png")
    assert cli("show", str(scenario), "--no-resim", "--out", str(tmp_path / "shown")) == 0, capsys.readouterr().err
    shown = sorted((tmp_path / "shown").iterdir())
    assert len(shown) > 1 and all(len(p.name.encode()) <= 255 and p.suffix == ".png" for p in shown)
    records = list((tmp_path / ".typ" / "written" / "shown").iterdir())   # typ's records of the pictures, one up
    assert len(records) == len(shown) and all(len(p.name.encode()) <= 255 for p in records)


def test_atomic_path_fits_temporaries_and_names_a_name_too_long(tmp_path):
    from typ.io import atomic_path, write_text

    longest = tmp_path / ("f" * 255)
    write_text(longest, "fits")
    write_text(longest, "fits again")             # replacing it too: the old file's temporary name
    assert longest.read_text() == "fits again" and [p.name for p in tmp_path.iterdir()] == [longest.name]
    with pytest.raises(TypError, match="at most 255 bytes"):
        write_text(tmp_path / ("f" * 256), "too long")
    with pytest.raises(TypError, match="a folder"):
        with atomic_path(longest / "x.txt") as tmp:
            tmp.write_text("under a file")
    assert [p.name for p in tmp_path.iterdir()] == [longest.name]


# --- class 3: a stage deletes only its own stale outputs ---------------------------------------------

def _manifest(folder: Path, **fields) -> Path:
    """A folder a user (or an archive) made that claims to be typ's: a manifest written by hand."""
    folder.mkdir(parents=True)
    (folder / "000000.pcd").write_bytes(b"points")
    (folder / "_typ.json").write_text(json.dumps(fields))
    return folder


def _typ_wrote(folder: Path, stage: str, **fields) -> Path:
    """A folder ``stage`` wrote as typ writes it (typ.io.atomic_path: its record beside it)."""
    from typ.io import atomic_path, write_manifest

    with atomic_path(folder, stage=stage) as tmp:
        tmp.mkdir(parents=True)
        (tmp / "000000.pcd").write_bytes(b"points")
        write_manifest(tmp, stage, fields)
    return folder


def _quiet_stage_run(monkeypatch) -> dict:
    from flows import common

    finished = {}
    monkeypatch.setattr(common, "stage_run", lambda stage, cfg, root, **kw: contextlib.nullcontext(None))
    monkeypatch.setattr(common, "finish_stage", lambda stage, run, metrics, root: finished.update(metrics))
    return finished


def test_generate_stage_removes_only_scenarios_it_wrote(tmp_path, monkeypatch):
    import flows.generate

    params = {"profile": "tiny", "generate": {"input": "in", "out": "gen",
                                              "sets": [{"dataset": "target", "split": "test", "references": "vehicles"}]}}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    (tmp_path / "in" / "target" / "test").mkdir(parents=True)
    gen = tmp_path / "gen"
    fields = {"key": "k", "counts": {"frames": 1}, "generated_agents": ["12"]}
    _typ_wrote(gen / "target" / "test" / "old", "generate", **fields)
    _typ_wrote(gen / "gone" / "split" / "old", "generate", **fields)          # a set dropped from generate.sets
    _typ_wrote(gen / "target" / "test" / "noted", "generate", **fields)
    (gen / "target" / "test" / "noted" / "notes.txt").write_text("mine")     # a user's note added since
    _manifest(gen / "target" / "test" / "legacy", key="k", counts={})       # the legacy form: proves nothing
    _manifest(gen / "target" / "test" / "claims", stage="generate", **fields)  # a manifest anyone can write
    _typ_wrote(gen / "target" / "test" / "simulated", "simulate", key="k")  # another stage's
    (gen / "target" / "test" / "photos").mkdir()
    (gen / "target" / "test" / "photos" / "a.jpg").write_bytes(b"jpeg")
    (gen / "gone" / "split" / "thesis").mkdir()
    (gen / "gone" / "split" / "thesis" / "main.tex").write_text("years of work")
    (gen / "gone" / "notes.txt").write_text("mine")
    ours = ("target/test/old", "gone/split/old")
    mine = {k: v for k, v in snapshot(gen).items()
            if not any(k == o or k.startswith(o + "/") for o in ours) and ".typ" not in k}
    monkeypatch.setattr(flows.generate, "load_generator", lambda root, cfg: None)
    finished = _quiet_stage_run(monkeypatch)
    metrics = flows.generate.generate_flow.fn(params="params.yaml", root=str(tmp_path))
    assert {k: v for k, v in snapshot(gen).items() if k in mine} == mine
    assert not any((gen / o).exists() for o in ours)
    assert (metrics["removed_stale"], metrics["kept_not_written_by_typ"]) == (2, 6) and finished == metrics


def test_simulate_stage_removes_only_scenarios_it_wrote(tmp_path, monkeypatch):
    from flows.common import per_scene_stage
    from tasks import simulate
    from typ.config import load_config

    zero = {"train": 0, "test": 0}
    params = {"profile": "tiny", "simulate": {"out": "sim", "scenarios": {
        "source": zero, "real_cav": zero, "target": {"train": 0, "val": 0, "test": 0, "pretrain": 0}}}}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    sim = tmp_path / "sim"
    _typ_wrote(sim / "target" / "train" / "target_train_0000", "simulate", key="k", job={}, counts={})
    (sim / "target" / "train" / "my_scan" / "1").mkdir(parents=True)
    (sim / "target" / "train" / "my_scan" / "1" / "000000.pcd").write_bytes(b"my points")
    mine = snapshot(sim / "target" / "train" / "my_scan")
    finished = _quiet_stage_run(monkeypatch)
    cfg = load_config(tmp_path / "params.yaml")
    metrics = per_scene_stage("simulate", cfg, tmp_path, simulate.scene_stage(cfg, tmp_path))
    assert snapshot(sim / "target" / "train" / "my_scan") == mine
    assert not (sim / "target" / "train" / "target_train_0000").exists()
    assert (metrics["removed_stale"], metrics["kept_not_written_by_typ"]) == (1, 1) and finished == metrics


def test_voxelize_stage_removes_only_voxel_files_it_wrote(tmp_path, monkeypatch):
    from flows.common import per_scene_stage
    from tasks import voxelize
    from typ.config import load_config
    from typ.store import scene_path, write_scene_voxels

    params = {"profile": "tiny", "voxelize": {"input": "sim", "out": "vox"}}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    (tmp_path / "sim").mkdir()
    grid = Grid((-8.0, 8.0), (-8.0, 8.0), (-2.0, 2.0), (16, 16, 4))
    ours = scene_path(tmp_path / "vox", "target", "train", "gone")
    write_scene_voxels(ours, {("1", "000000"): (np.zeros(grid.shape, bool), np.zeros((*grid.shape[:2], 1), bool))},
                       grid=grid, input_hash="h", stage="voxelize")
    forged = scene_path(tmp_path / "vox", "target", "train", "copied")   # typ's file, copied by a user
    forged.write_bytes(ours.read_bytes())
    theirs = scene_path(tmp_path / "vox", "target", "train", "mine")
    theirs.write_bytes(b"PAR1 a parquet file of the user's")
    finished = _quiet_stage_run(monkeypatch)
    cfg = load_config(tmp_path / "params.yaml")
    metrics = per_scene_stage("voxelize", cfg, tmp_path, voxelize.scene_stage(cfg, tmp_path))
    assert not ours.exists() and theirs.read_bytes() == b"PAR1 a parquet file of the user's" and forged.is_file()
    assert (metrics["removed_stale"], metrics["kept_not_written_by_typ"]) == (1, 2) and finished == metrics


def test_a_new_training_run_removes_only_checkpoints_typ_wrote(tmp_path):
    from tasks.training import run_checkpoint_dir, save_checkpoint, save_torch

    root = tmp_path / "checkpoints"
    save_checkpoint(root / "0123456789abcdef", 2, {})
    save_checkpoint(root / "0123456789abcdef", 3, {})
    save_checkpoint(root / "00000000aaaaaaaa", 1, {})
    (root / "00000000aaaaaaaa" / "notes.md").write_text("mine")               # a note beside typ's checkpoint
    save_torch(root / "copied" / "step_00000001.pt", {"step": 1})             # a checkpoint typ did not write
    (root / "notes").mkdir(parents=True)
    (root / "notes" / "step_00000001.pt.txt").write_text("mine")
    (root / "readme.md").write_text("mine")
    assert run_checkpoint_dir(root, "fedcba9876543210") == root / "fedcba9876543210"
    assert sorted(p.name for p in root.iterdir()) == ["00000000aaaaaaaa", "copied", "notes", "readme.md"]
    assert [p.name for p in (root / "00000000aaaaaaaa").iterdir()] == ["notes.md"]
    assert (root / "copied" / "step_00000001.pt").is_file()
    assert (root / "notes" / "step_00000001.pt.txt").read_text() == "mine"


# --- class 4: one run of a stage at a time per output --------------------------------------------------

#: ``typ run simulate`` whose scenario, once written to its temporary folder, waits for a file
HELD_RUN = """
import sys, time
from pathlib import Path
import tasks.simulate as simulate
root, started, release = (Path(a) for a in sys.argv[1:4])
write = simulate.ScenarioJob.write
def write_then_wait(self, tmp):
    counts = write(self, tmp)
    started.write_text(str(tmp))
    deadline = time.monotonic() + 300
    while not release.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    return counts
simulate.ScenarioJob.write = write_then_wait
from cli.main import main
sys.exit(main(["--root", str(root), "run", "simulate"]))
"""


def test_a_second_run_of_a_stage_is_refused_while_the_first_runs(tmp_path, request, tmp_path_factory):
    from stage_processes import make_project, stage_env

    env = stage_env(request.config, tmp_path_factory)
    zero = {"train": 0, "test": 0}
    root = make_project(tmp_path / "project", {
        "profile": "tiny", "simulate": {"frames": 1, "agents_min": 1, "agents_max": 1, "workers": 1,
                                        "scenarios": {"source": zero, "real_cav": zero,
                                                      "target": {"train": 1, "val": 0, "test": 0, "pretrain": 0}}}})
    started, release = tmp_path / "started", tmp_path / "release"
    first = subprocess.Popen([sys.executable, "-c", HELD_RUN, str(root), str(started), str(release)], cwd=root,
                             env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 300
        while not started.exists() and first.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert started.exists(), first.communicate()[0][-3000:]
        in_flight = Path(started.read_text())
        second = subprocess.run([sys.executable, "-m", "cli", "--root", str(root), "run", "simulate"], cwd=root,
                                env=env, capture_output=True, text=True, timeout=300)
        assert second.returncode == 2, second.stderr[-3000:]
        assert "typ: error" in second.stderr and "simulate" in second.stderr and f"pid {first.pid}" in second.stderr
        assert in_flight.is_dir() and any(in_flight.rglob("*.pcd")), "the second run touched the first's temporary"
        release.write_text("")
        assert first.wait(300) == 0, first.communicate()[0][-3000:]
    finally:
        release.write_text("")
        if first.poll() is None:
            first.kill()
            first.wait()
    from typ.formats.opv2v import read_scene

    assert len(read_scene(root / "data" / "sim" / "target" / "train" / "target_train_0000", "000000").ego.points)


HOLDER = """
import sys, time
from pathlib import Path
from typ.io import output_lock
with output_lock("voxelize", Path(sys.argv[2])):
    print("held", flush=True)
    time.sleep(300)
"""


def test_the_lock_of_a_killed_run_is_released(tmp_path):
    from typ.io import OutputBusy, output_lock

    out = tmp_path / "data" / "voxels"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path), str(out)], env=env,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(OutputBusy, match=f"pid {holder.pid} \\(voxelize\\)"):
            with output_lock("voxelize", out):
                pass
        with output_lock("voxelize", tmp_path / "elsewhere"):   # another output: not locked
            pass
    finally:
        holder.kill()
        holder.wait()
    with output_lock("voxelize", out):    # the kernel dropped the dead holder's lock
        with pytest.raises(OutputBusy):   # and a second holder in this process waits its turn
            with output_lock("voxelize", out):
                pass


# --- class 15: what decides a delete is typ's record, which a copy or an archive does not carry ------------

def _stage_wrote_and_cleaned(tmp_path, monkeypatch, arrange) -> tuple[dict, dict]:
    """generate's stage with nothing to generate, after ``arrange(gen)`` placed what lies in its output:
    (the snapshot of the output before, after)."""
    import flows.generate

    params = {"profile": "tiny", "generate": {"input": "in", "out": "gen",
                                              "sets": [{"dataset": "target", "split": "test", "references": "vehicles"}]}}
    (tmp_path / "in" / "target" / "test").mkdir(parents=True, exist_ok=True)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    gen = tmp_path / "gen"
    arrange(gen)
    before = snapshot(gen)
    monkeypatch.setattr(flows.generate, "load_generator", lambda root, cfg: None)
    _quiet_stage_run(monkeypatch)
    flows.generate.generate_flow.fn(params="params.yaml", root=str(tmp_path))
    return before, snapshot(gen)


@pytest.mark.parametrize("how", ["same place", "another root"])
def test_an_unpacked_archive_of_typ_outputs_and_records_is_left_alone(tmp_path, monkeypatch, how):
    import shutil
    import tarfile

    origin = tmp_path / "origin" / "gen" / "target" / "test"
    _typ_wrote(origin / "old", "generate", key="k")
    archive = tmp_path / "outputs.tar"
    with tarfile.open(archive, "w") as tar:   # the folder and typ's records beside it: .typ/ travels too
        tar.add(tmp_path / "origin" / "gen", arcname="gen")
    if how == "same place":
        shutil.rmtree(tmp_path / "origin" / "gen")
    root = tmp_path / ("origin" if how == "same place" else "other")

    def unpack(gen):
        gen.parent.mkdir(parents=True, exist_ok=True)
        with tarfile.open(archive) as tar:
            tar.extractall(gen.parent, filter="tar")
        assert (gen / "target" / ".typ" / "written" / "test" / "old.json").is_file()

    before, after = _stage_wrote_and_cleaned(root, monkeypatch, unpack)
    assert after == before


def test_a_copy_of_a_typ_output_folder_with_notes_is_left_alone(tmp_path, monkeypatch):
    import shutil

    def arrange(gen):
        split = gen / "target" / "test"
        _typ_wrote(split / "old", "generate", key="k")
        shutil.copytree(split / "old", split / "my_copy")           # cp -r: the manifest comes along
        (split / "my_copy" / "notes.txt").write_text("mine")
        shutil.copytree(split / "old", split / "exact_copy", copy_function=shutil.copy2)
        shutil.rmtree(split / "old")
        shutil.copytree(split / "exact_copy", split / "old", copy_function=shutil.copy2)   # same path, a copy

    before, after = _stage_wrote_and_cleaned(tmp_path, monkeypatch, arrange)
    assert after == before


def test_a_forged_record_beside_a_users_folder_proves_nothing(tmp_path, monkeypatch):
    from typ.io import record_path

    def arrange(gen):
        mine = _manifest(gen / "target" / "test" / "mine", stage="generate", key="k")
        record = record_path(mine)
        record.parent.mkdir(parents=True)
        record.write_text(json.dumps({"stage": "generate", "ino": 1, "tree": "0" * 64}))

    before, after = _stage_wrote_and_cleaned(tmp_path, monkeypatch, arrange)
    assert after == before


@pytest.mark.parametrize("command", ["edit", "generate"])
def test_a_folder_claiming_to_be_typs_is_not_replaced(cli, tmp_path, capsys, command):
    scenario = write_scenario(tmp_path / "data")
    out = tmp_path / "out"
    if command == "edit":
        argv, claimed = ("edit", str(scenario), *EDIT), out / "scen"
        _manifest(claimed, stage="edit", source=str(scenario))
    else:
        if not KITTI.is_dir():
            pytest.skip(f"no KITTI frames at {KITTI}")
        from tasks.ingest import read_frames

        first = read_frames("kitti", KITTI)[0].name
        argv, claimed = ("generate", "--format", "kitti", "--input", str(KITTI)), out / "single_agent" / "kitti" / first
        _manifest(claimed, stage="ingest", frames=1)
    (claimed / "thesis.tex").write_text("years of work")
    before = snapshot(out)
    assert cli(*argv, "--out", str(out)) == 2
    err = capsys.readouterr().err
    assert "typ: error" in err and str(claimed) in err and "did not write" in err and "Traceback" not in err
    assert {k: v for k, v in snapshot(out).items() if ".typ" not in k} == {k: v for k, v in before.items()}


def test_generate_through_a_link_in_its_output_is_refused(cli, tmp_path, capsys):
    if not KITTI.is_dir():
        pytest.skip(f"no KITTI frames at {KITTI}")
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "000000").mkdir()
    (mine / "000000" / "thesis.tex").write_text("years of work")
    out = tmp_path / "out"
    (out / "single_agent").mkdir(parents=True)
    (out / "single_agent" / "kitti").symlink_to(mine)            # an archive or a careless link
    before = snapshot(mine)
    assert cli("generate", "--format", "kitti", "--input", str(KITTI), "--out", str(out)) == 2
    err = capsys.readouterr().err
    assert "typ: error" in err and "never writes through a link" in err and "Traceback" not in err
    assert snapshot(mine) == before


# --- class 16: a lock is a file typ made, one per output folder whatever names it ---------------------------

def _lock_in_the_way(tmp_path: Path, kind: str) -> tuple[Path, Path]:
    """An output folder, and a user's file that what lies at its lock path would let typ write."""
    from typ.io import lock_path

    out = tmp_path / "project" / "data" / "gen"
    precious = tmp_path / "precious.txt"
    precious.write_text("years of work")
    path = lock_path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    if kind == "link":
        path.symlink_to(precious)
    elif kind == "hard link":
        os.link(precious, path)
    elif kind == "a user's file":
        path.write_text("my lock notes, not typ's")
    elif kind == "folder":
        path.mkdir()
        (path / "inside.txt").write_text("mine")
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "state folder is a file":
        path.parent.rmdir()
        path.parent.write_text("mine")
    elif kind == "state folder is a link":
        path.parent.rmdir()
        (tmp_path / "elsewhere").mkdir()
        (tmp_path / "elsewhere" / path.name).write_text("mine")
        path.parent.symlink_to(tmp_path / "elsewhere")
    return out, precious


LOCK_CASES = ["link", "hard link", "a user's file", "folder", "fifo", "state folder is a file", "state folder is a link"]


@pytest.mark.parametrize("kind", LOCK_CASES)
def test_a_lock_path_that_is_not_typs_file_is_named_and_left_alone(tmp_path, kind):
    from typ.io import lock_path, output_lock

    out, precious = _lock_in_the_way(tmp_path, kind)
    before = snapshot(tmp_path)
    with pytest.raises(TypError) as err:
        with output_lock("generate", out):
            pass
    assert str(lock_path(out).parent if kind.startswith("state") else lock_path(out)) in str(err.value)
    assert "lock" in err.value.field
    assert snapshot(tmp_path) == before and precious.read_text() == "years of work"


@pytest.mark.parametrize("kind", ["link", "hard link"])
def test_typ_generate_with_a_planted_lock_link_loses_no_file(cli, tmp_path, capsys, kind):
    if not KITTI.is_dir():
        pytest.skip(f"no KITTI frames at {KITTI}")
    out, precious = _lock_in_the_way(tmp_path, kind)
    assert cli("generate", "--format", "kitti", "--input", str(KITTI), "--out", str(out)) == 2
    err = capsys.readouterr().err
    assert "typ: error" in err and "lock" in err and "Traceback" not in err
    assert precious.read_text() == "years of work" and not out.exists()


def test_every_name_of_one_output_folder_shares_its_lock(tmp_path, monkeypatch):
    from typ.io import OutputBusy, lock_path, output_lock

    out = tmp_path / "a" / "data" / "gen"
    out.mkdir(parents=True)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "link").symlink_to(out)
    monkeypatch.chdir(tmp_path / "a")
    names = [Path("data/gen"), Path("data/../data/gen"), tmp_path / "b" / "link", tmp_path / "b" / ".." / "a" / "data" / "gen"]
    assert len({lock_path(n) for n in names}) == 1 and lock_path(out).parent == out.parent / ".typ"
    with output_lock("generate", out):
        for name in names:
            with pytest.raises(OutputBusy, match=str(out)):
                with output_lock("simulate", name):   # another stage, another root: the same folder
                    pass
    with output_lock("generate", names[1]):   # released
        pass


def test_two_roots_writing_one_output_never_delete_each_others_temporaries(tmp_path):
    """The lock is the output folder's, not a project's: while one root's run holds it, another root's
    run is refused before it cleans up temporaries (which would be the first run's files in flight)."""
    from typ.io import OutputBusy, output_lock, remove_stale_temporaries

    shared = tmp_path / "shared_out"
    in_flight = shared / "target" / ".tmp-scen.abcd1234"
    in_flight.mkdir(parents=True)
    (in_flight / "000000.pcd").write_bytes(b"being written")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path / "root_a"), str(shared)], env=env,
                              stdout=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(OutputBusy):
            with output_lock("voxelize", tmp_path / "root_b" / ".." / "shared_out"):
                remove_stale_temporaries(shared)
    finally:
        holder.kill()
        holder.wait()
    assert (in_flight / "000000.pcd").read_bytes() == b"being written"


def test_typs_records_are_never_taken_for_scenarios_or_splits(tmp_path):
    """typ's records of what simulate wrote sit in ``<domain>/.typ/written/<split>/``: the stages that
    list ``<root>/<domain>/<split>/<scenario>`` (voxelize's inputs, simulate's stale outputs) and OPV2V
    readers of a split folder see the scenarios alone."""
    from tasks.simulate import stale_scenarios
    from tasks.voxelize import plan_inputs
    from typ.formats.opv2v import list_scenarios
    from typ.io import atomic_path, record_path, write_manifest

    sim = tmp_path / "sim"
    for name in ("target_train_0000", "target_train_0001"):
        with atomic_path(sim / "target" / "train" / name, stage="simulate") as tmp:
            tmp.mkdir()
            write_manifest(tmp, "simulate", {"key": name})
    assert record_path(sim / "target" / "train" / "target_train_0000").is_file()
    assert (sim / "target" / ".typ" / "written" / "train").is_dir()
    assert [(i.dataset, i.split, i.folder.name) for i in plan_inputs(sim)] == [
        ("target", "train", "target_train_0000"), ("target", "train", "target_train_0001")]
    assert [p.name for p in list_scenarios(sim / "target" / "train")] == ["target_train_0000", "target_train_0001"]
    assert stale_scenarios([], sim) == [sim / "target" / "train" / "target_train_0000",
                                        sim / "target" / "train" / "target_train_0001"]


def test_a_hard_link_to_a_users_file_in_what_typ_wrote_follows_the_users_edits(tmp_path):
    """simulate imports a real scenario's files as hard links: the user editing their file (one inode,
    two names) does not make typ's folder someone else's, and deleting typ's folder keeps the user's
    file with its edits. A file whose every name is inside typ's folder is typ's to fingerprint whole."""
    from typ.io import atomic_path, remove_written, write_manifest, written_by

    theirs = tmp_path / "dataset" / "000000.pcd"
    theirs.parent.mkdir()
    theirs.write_bytes(b"the user's points")
    folder = tmp_path / "sim" / "target" / "train" / "scen"
    with atomic_path(folder, stage="simulate") as tmp:
        (tmp / "1").mkdir(parents=True)
        os.link(theirs, tmp / "1" / "000000.pcd")
        (tmp / "1" / "000000.yaml").write_text("lidar_pose: [0, 0, 0, 0, 0, 0]\n")
        os.link(tmp / "1" / "000000.yaml", tmp / "1" / "copy.yaml")   # both names inside typ's folder
        write_manifest(tmp, "simulate", {})
    assert written_by(folder, "simulate")
    with open(theirs, "r+b") as f:    # edited in place where the user keeps it: the same inode
        f.write(b"THE")
    assert written_by(folder, "simulate")
    with open(folder / "1" / "copy.yaml", "a") as f:   # typ's own file changed: no longer provably typ's
        f.write("# mine now\n")
    assert not written_by(folder, "simulate") and not remove_written(folder, "simulate")
    assert folder.is_dir() and theirs.read_bytes() == b"THE user's points"
    with atomic_path(tmp_path / "sim" / "target" / "train" / "scen2", stage="simulate") as tmp:
        tmp.mkdir()
        os.link(theirs, tmp / "000000.pcd")
        write_manifest(tmp, "simulate", {})
    theirs.write_bytes(b"rewritten in place")   # truncated and written: still one inode
    assert remove_written(tmp_path / "sim" / "target" / "train" / "scen2", "simulate")
    assert theirs.read_bytes() == b"rewritten in place"
