"""A real collaborative dataset in OPV2V layout as a domain's data source (``simulate.sources``).

The test writes a small OPV2V-layout root with typ's own writer (typ/formats/opv2v.py) and makes
it look like OPV2V's files: yaml with OPV2V's other keys (cameras, speeds, trajectory, RSU
flag), ``lidar_pose`` as ``[x, y, z, roll, yaw, pitch]``, one agent's clouds as OPV2V's ASCII
PCDs with an ``intensity`` field (the other's as typ's binary ones, intensity in ``rgb``),
camera images and a protocol file that typ leaves alone. Then:

- the pipeline's first stages run on it as the target domain: simulate takes the scenarios in
  (hard links, byte-identical), voxelize reads them, vqvae and stage1 train on them; a rerun
  takes nothing again, a changed file takes its scenario again;
- bad folders stop the stage before anything is written, naming the first bad file.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from tasks.simulate import plan_jobs, run_job
from stage_processes import run_stages, stage_env
from typ.config import SourceConfig, config_from_dict
from typ.errors import TypError
from typ.formats.opv2v import list_agents, list_timestamps, read_scene, write_scene
from typ.formats.pcd import read_pcd
from typ.sim import simulate_scenario

SPLITS = {"train": 2, "val": 1, "test": 1}


def write_ascii_pcd(path: Path, points: np.ndarray) -> None:
    """A cloud as OPV2V ships it: ASCII, fields x y z intensity."""
    n = len(points)
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\n"
              f"TYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA ascii\n")
    rows = "\n".join(" ".join(f"{v:.5f}" for v in row) for row in points.astype(np.float64))
    path.write_text(header + rows + "\n")


def opv2v_extras(rng: np.random.Generator, doc: dict) -> dict:
    """The keys an OPV2V yaml has beside lidar_pose and vehicles."""
    x, y, z, roll, yaw, pitch = doc["lidar_pose"]
    cams = {f"camera{k}": {"cords": [x, y, z - 0.3, 0.0, yaw + 90.0 * k, 0.0],
                           "extrinsic": np.eye(4).tolist(),
                           "intrinsic": [[335.6, 0.0, 400.0], [0.0, 335.6, 300.0], [0.0, 0.0, 1.0]]} for k in range(4)}
    return {"RSU": False, **cams, "ego_speed": float(rng.uniform(0, 30)),
            "plan_trajectory": [[x + 2.0 * t, y, 18.0] for t in range(3)],
            "predicted_ego_pos": [x, y, z - 1.9, roll, yaw, pitch], "true_ego_pos": [x, y, z - 1.9, roll, yaw, pitch]}


def make_real_root(root: Path, *, seed: int = 0) -> Path:
    """``root/<split>/<scenario>/<agent>/<timestamp>.pcd|.yaml`` (+ camera pngs) for :data:`SPLITS`."""
    rng = np.random.default_rng(seed)
    for split, count in SPLITS.items():
        for i in range(count):
            name = f"2021_08_{16 + i:02d}_22_26_54_{split}"      # OPV2V names scenarios by recording time
            scenes = simulate_scenario(domain="target", seed=seed * 100 + len(split) * 10 + i, n_frames=2,
                                       n_agents=2, azimuth_step_deg=1.5, scenario=name, split=split)
            for scene in scenes:
                folder = write_scene(scene, root / split)
                for k, agent in enumerate(scene.agents):
                    stem = folder / agent / scene.timestamp
                    doc = yaml.safe_load(stem.with_suffix(".yaml").read_text())
                    doc.update(opv2v_extras(rng, doc))
                    stem.with_suffix(".yaml").write_text(yaml.safe_dump(doc, sort_keys=True, default_flow_style=None))
                    if k == 0:   # the ego's clouds as OPV2V's raw files; the other agent's as typ writes them
                        write_ascii_pcd(stem.with_suffix(".pcd"), scene.agents[agent].points)
                    for cam in range(4):
                        (folder / agent / f"{scene.timestamp}_camera{cam}.png").write_bytes(b"\x89PNG fake")
            (folder / "data_protocol.yaml").write_text("description: fake\n")
    return root


@pytest.fixture(scope="module")
def real_root(tmp_path_factory) -> Path:
    return make_real_root(tmp_path_factory.mktemp("opv2v") / "OPV2V")


def params(data_root: str, **blocks) -> dict:
    out = {"profile": "tiny",
           "simulate": {"sources": {"target": data_root}, "workers": 1,
                        "scenarios": {"source": {"train": 0, "test": 0}, "target": {**SPLITS, "pretrain": 0},
                                      "real_cav": {"train": 0, "test": 0}}},
           "voxelize": {"workers": 1},
           "vqvae": {"x": {"epochs": 1, "block_out_channels": [8, 16]}, "y": {"epochs": 1, "block_out_channels": [8, 16]},
                     "checkpoint_every": 1},
           "stage1": {"epochs": 1, "sample_steps": 2, "eval_views": 1, "checkpoint_every": 1,
                      "unet": {"block_out_channels": [16, 16, 16, 16]}}}
    for name, block in blocks.items():
        out[name] = {**out.get(name, {}), **block}
    return out


def files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_the_first_stages_run_on_a_real_layout_folder(real_root, tmp_path, request, tmp_path_factory):
    project = tmp_path / "project"
    project.mkdir()
    (project / "params.yaml").write_text(yaml.safe_dump(params(str(real_root))))
    env = stage_env(request.config, tmp_path_factory)
    run_stages(project, env, "simulate", "voxelize", "vqvae", "stage1")

    sim = json.loads((project / "metrics" / "simulate.json").read_text())
    assert (sim["imported"], sim["simulated"], sim["skipped_unchanged"]) == (4, 0, 0)
    for split, count in SPLITS.items():
        taken = project / "data" / "sim" / "target" / split
        sources = sorted((real_root / split).iterdir())
        assert [p.name for p in sorted(taken.iterdir())] == [p.name for p in sources]
        for src in sources:
            want = {k: v for k, v in files(src).items() if k.endswith((".pcd", ".yaml")) and "/" in k}
            got = files(taken / src.name)
            assert got.pop("_typ.json") and got == want          # pcd + yaml as they are, nothing else
            pcd = next(src.rglob("*.pcd"))
            assert (taken / src.name / pcd.relative_to(src)).stat().st_ino == pcd.stat().st_ino   # linked
        # the stage's counts, against the folder read with typ's reader
        scenes = [read_scene(src, ts) for src in sources for ts in list_timestamps(src)]
        group = sim[f"target_{split}"]
        assert group["scenarios"] == count and group["frames"] == len(scenes)
        assert group["views"] == sum(len(s.agents) for s in scenes)
        assert group["points"] == sum(len(a.points) for s in scenes for a in s.agents.values())
        assert group["boxes"] == sum(len(a.boxes) for s in scenes for a in s.agents.values())

    # voxelize read the real clouds: the ASCII cloud's occupancy equals voxelizing it directly
    from tasks.voxelize import to_grid
    from typ.store import read_scene_voxels, scene_path
    from typ.voxel import voxelize

    cfg = config_from_dict(params(str(real_root)))
    grid = cfg.voxelize.sensor_grid("target")  # the configured grid, lifted to the target sensor's height
    assert grid.z_range[0] == pytest.approx(to_grid(cfg.voxelize.grid).z_range[0] - 2.2)
    src = sorted((real_root / "train").iterdir())[0]
    ego, ts = list_agents(src)[0], list_timestamps(src)[0]
    _, _, stored = read_scene_voxels(scene_path(project / "data" / "voxels", "target", "train", src.name))
    direct = voxelize(read_pcd(src / ego / f"{ts}.pcd")[0], grid)
    assert direct.any() and np.array_equal(stored[(ego, ts)][0], direct)
    vox = json.loads((project / "metrics" / "voxelize.json").read_text())
    assert vox["voxelized"] == 4 and vox["empty_views"] == 0

    # and the models trained on them
    for path in ("artifacts/vqvae/x/model.safetensors", "artifacts/vqvae/y/config.json",
                 "artifacts/stage1/seed_0/model.safetensors", "metrics/vqvae.json", "metrics/stage1.json"):
        assert (project / path).is_file(), path

    # a rerun takes nothing again; a changed file takes its scenario again
    run_stages(project, env, "simulate")
    sim = json.loads((project / "metrics" / "simulate.json").read_text())
    assert (sim["imported"], sim["skipped_unchanged"]) == (0, 4)
    changed = next((real_root / "test").glob("*/*/*.yaml"))     # an agent's yaml, which typ reads
    changed.write_text(changed.read_text() + "# edited\n")
    run_stages(project, env, "simulate")
    sim = json.loads((project / "metrics" / "simulate.json").read_text())
    assert (sim["imported"], sim["skipped_unchanged"]) == (1, 3)


# --- bad folders: the first bad file is named, nothing is written -------------------------------

def _first_yaml(root: Path, split: str = "train") -> Path:
    scenario = sorted((root / split).iterdir())[0]
    return scenario / list_agents(scenario)[0] / f"{list_timestamps(scenario)[0]}.yaml"


def _edit_yaml(path: Path, change) -> None:
    doc = yaml.safe_load(path.read_text())
    change(doc)
    path.write_text(yaml.safe_dump(doc))


def _second_agent_yaml(root: Path) -> Path:
    scenario = sorted((root / "val").iterdir())[0]
    return scenario / list_agents(scenario)[1] / f"{list_timestamps(scenario)[-1]}.yaml"


BAD = {
    "no root": (lambda r: shutil.rmtree(r), lambda r: (r, "root")),
    "no split folder": (lambda r: shutil.rmtree(r / "val"), lambda r: (r / "val", "split")),
    "empty split": (lambda r: [shutil.rmtree(p) for p in (r / "test").iterdir()], lambda r: (r / "test", "split")),
    "scenario without agents": (
        lambda r: [shutil.rmtree(p) for p in sorted((r / "val").iterdir())[0].iterdir() if p.is_dir()],
        lambda r: (sorted((r / "val").iterdir())[0], "agents")),
    "no lidar_pose": (lambda r: _edit_yaml(_first_yaml(r), lambda d: d.pop("lidar_pose")),
                      lambda r: (_first_yaml(r), "lidar_pose")),
    "pose as a quaternion": (lambda r: _edit_yaml(_first_yaml(r), lambda d: d.update(lidar_pose=[1, 2, 3, 0, 0, 0, 1])),
                             lambda r: (_first_yaml(r), "lidar_pose")),
    "vehicle without extent": (
        lambda r: _edit_yaml(_first_yaml(r), lambda d: next(iter(d["vehicles"].values())).pop("extent")),
        lambda r: (_first_yaml(r), "vehicles.")),
    "an agent misses a frame": (lambda r: _second_agent_yaml(r).unlink(), lambda r: (_second_agent_yaml(r), "yaml")),
    "no cloud beside the yaml": (lambda r: _second_agent_yaml(r).with_suffix(".pcd").unlink(),
                                 lambda r: (_second_agent_yaml(r).with_suffix(".pcd"), "file")),
    "truncated binary cloud": (
        lambda r: _second_agent_yaml(r).with_suffix(".pcd").write_bytes(
            _second_agent_yaml(r).with_suffix(".pcd").read_bytes()[:-100]),
        lambda r: (_second_agent_yaml(r).with_suffix(".pcd"), "DATA")),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_bad_folder_is_named_before_anything_is_written(real_root, tmp_path, case):
    root = tmp_path / "OPV2V"
    shutil.copytree(real_root, root)
    damage, names = BAD[case]
    damage(root)
    where, field = names(root)
    cfg = config_from_dict(params(str(root)))
    out = tmp_path / "data" / "sim"
    with pytest.raises(TypError) as info:
        plan_jobs(cfg.simulate, root=tmp_path, out=out)
    assert info.value.where == str(where) and info.value.field.startswith(field), str(info.value)
    assert not out.exists()


def test_the_first_bad_file_in_order_is_the_one_named(real_root, tmp_path):
    root = tmp_path / "OPV2V"
    shutil.copytree(real_root, root)
    first, later = (sorted((root / "train").iterdir())[k] for k in (0, 1))
    for scenario in (later, first):   # both bad; the error names the one read first
        path = scenario / list_agents(scenario)[1] / f"{list_timestamps(scenario)[0]}.yaml"
        _edit_yaml(path, lambda d: d.update(lidar_pose="0 0 0"))
    with pytest.raises(TypError) as info:
        plan_jobs(config_from_dict(params(str(root))).simulate, root=tmp_path)
    assert info.value.where.startswith(str(first)) and info.value.field == "lidar_pose"


def test_a_split_asked_for_more_scenarios_than_it_has(real_root, tmp_path):
    raw = params(str(real_root))
    raw["simulate"]["scenarios"]["target"]["train"] = 5
    with pytest.raises(TypError) as info:
        plan_jobs(config_from_dict(raw).simulate, where="my-params.yaml")
    assert str(info.value).startswith("my-params.yaml: simulate.scenarios.target.train: expected at most 2")


def test_sources_are_checked_with_the_params(real_root):
    for sources, field in (({"lidar": str(real_root)}, "simulate.sources.lidar"), ({"target": " "}, "simulate.sources.target")):
        raw = params(str(real_root))
        raw["simulate"]["sources"] = sources
        with pytest.raises(TypError, match=field):
            config_from_dict(raw)
    cfg = config_from_dict(params("relative/opv2v")).simulate
    assert cfg.source_blocks("target") == (SourceConfig(format="opv2v", root="relative/opv2v"),)
    assert cfg.source_blocks("source") == ()


def test_a_changed_scenario_is_checked_again_and_taken_again(real_root, tmp_path):
    """In-process: the unchanged scenarios are neither checked nor copied again."""
    root = tmp_path / "OPV2V"
    shutil.copytree(real_root, root)
    cfg = config_from_dict(params(str(root))).simulate
    out = tmp_path / "out"
    jobs = plan_jobs(cfg, root=tmp_path, out=out)
    assert all(job.counts for job in jobs)                     # all new: all checked
    assert [run_job(job, out)["skipped"] for job in jobs] == [None] * 4
    again = plan_jobs(cfg, root=tmp_path, out=out)
    assert not any(job.counts for job in again)                # unchanged: not checked again
    assert [run_job(job, out)["skipped"] for job in again] == ["unchanged"] * 4
    bad = _first_yaml(root)
    _edit_yaml(bad, lambda d: d.pop("vehicles"))               # the changed one is checked again
    with pytest.raises(TypError, match="vehicles"):
        plan_jobs(cfg, root=tmp_path, out=out)
