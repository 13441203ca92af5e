"""A real single-agent target domain end to end: `dvc repro generate` on the KITTI, nuScenes and
Waymo frames in ../shared/data (TYP §3.4: VQ-VAE and stage 1 on the real dataset, stage 2 on
simulated collaborative data, the collaborative dataset generated from held-out real frames).

The frames are few, so the test spends them: KITTI's ImageSets put training frame 000001
(a car and a truck: self-training's pseudo references) in train, 000000 in val and
testing frame 000002 in test; the nuScenes keyframe and the Waymo frame (labels, no range
images) are shared out to pretrain by fraction. The tiny settings of tests/e2e/test_pipeline_e2e.py.
"""
import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml

from test_pipeline_e2e import SMALL, VENV_BIN, _copy_project, _run
from repo_paths import SHARED_DATA

DATA = SHARED_DATA
KITTI, KITTI_TEST = DATA / "kitti_object_vis" / "training", DATA / "pointpillars_kitti_demo" / "testing"
NUSCENES, WAYMO = DATA / "nuscenes_mmdet3d_demo", DATA / "waymo_mmdet3d_testdata"

pytestmark = [pytest.mark.e2e,
              pytest.mark.skipif(not all(p.is_dir() for p in (KITTI, KITTI_TEST, NUSCENES, WAYMO)),
                                 reason="../shared/data (the real KITTI, nuScenes and Waymo frames) not present")]


def kitti_root(dst: Path) -> Path:
    """A KITTI object root of copies of the shared frames (4 MB; a link out of the root would be
    refused, typ.inputs.inside), with its own ImageSets split files."""
    for src, folders in ((KITTI, ("velodyne", "calib", "label_2")), (KITTI_TEST, ("velodyne_reduced", "calib"))):
        for folder in folders:
            (dst / src.name / folder).mkdir(parents=True)
            for f in (src / folder).iterdir():
                shutil.copyfile(f, dst / src.name / folder / f.name)
    (dst / "ImageSets").mkdir()
    for split, frame in (("train", "000001"), ("val", "000000"), ("test", "000002")):
        (dst / "ImageSets" / f"{split}.txt").write_text(f"{frame}\n")
    return dst


def real_target(kitti: Path) -> dict:
    return {**SMALL["simulate"],
            "scenarios": {**SMALL["simulate"]["scenarios"], "target": {"train": 1, "val": 1, "test": 1, "pretrain": 2}},
            "sources": {"target": [{"format": "kitti", "root": str(kitti)},
                                   {"format": "nuscenes", "root": str(NUSCENES), "splits": {"pretrain": 1.0}},
                                   {"format": "waymo", "root": str(WAYMO), "splits": {"pretrain": 1.0}}]}}


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    proj = tmp_path_factory.mktemp("proj")
    _copy_project(proj)
    params = {**SMALL, "simulate": real_target(kitti_root(tmp_path_factory.mktemp("kitti"))),
              # KITTI 000001's car and truck are 61 and 70 m away: self-training's pseudo references stand on
              # them; one model per stage (the ablations' wiring is test_pipeline_e2e's)
              "stage2": {**SMALL["stage2"], "one_stage": False},
              "selftrain": {**SMALL["selftrain"], "max_distance": 72.0, "ablation": False}}
    (proj / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    env = {**{k: v for k, v in os.environ.items() if k != "TYP_HASH_CACHE"},
           "PATH": f"{VENV_BIN}:{os.environ['PATH']}", "PYTHONPATH": str(proj),
           "MLFLOW_TRACKING_URI": f"sqlite:///{proj / 'mlruns.db'}", "PREFECT_HOME": str(proj / ".prefect"),
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DVC_NO_ANALYTICS": "1", "DO_NOT_TRACK": "1",
           "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}
    for cmd in (["git", "init", "-q"], ["git", "add", "-A"], ["git", "commit", "-qm", "snapshot"]):
        _run(cmd, proj, env)
    ran = _run([str(VENV_BIN / "typ"), "with-server", "dvc", "repro", "generate"], proj, env)
    return proj, env, ran


def test_the_real_frames_become_one_agent_scenarios_in_their_lidar_frames(project):
    from typ.formats.kitti import read_kitti_frame
    from typ.formats.opv2v import list_agents, list_timestamps, read_scene
    from typ.formats.waymo import read_waymo_frames

    proj, _, ran = project
    sim = json.loads((proj / "metrics" / "simulate.json").read_text())
    assert (sim["imported"], sim["simulated"]) == (5, 4)
    target = proj / "data" / "sim" / "target"
    taken = {split: sorted(p.name for p in (target / split).iterdir()) for split in ("train", "val", "test", "pretrain")}
    assert taken == {"train": ["kitti_training_000001"], "val": ["kitti_training_000000"],
                     "test": ["kitti_testing_000002"],
                     "pretrain": ["n015-2018-07-24-11-22-45_0800__LIDAR_TOP__1532402927647951", "val"]}
    rules = sim["splits"]["target"]
    assert rules["train"] == ["kitti split train"] and rules["test"] == ["kitti split test"]
    assert len(rules["pretrain"]) == 2 and all("sha256(scenario name) in [0, 1)" in r for r in rules["pretrain"])
    # KITTI: the Velodyne frame as it is (the LiDAR's own), labels in it
    kitti = read_scene(target / "train" / "kitti_training_000001", "000000")
    truth = read_kitti_frame(DATA / "kitti_object_vis", "000001")
    assert list(kitti.agents) == ["ego"] and np.array_equal(kitti.ego.points[:, :3], truth.ego.points[:, :3])
    assert np.abs(kitti.ego.points[:, 3] - truth.ego.points[:, 3]).max() < 0.5 / 255 + 1e-6   # OpenCOOD's 8-bit colour
    assert np.allclose(kitti.ego.boxes, truth.ego.boxes, atol=1e-5) and kitti.ego.box_labels == truth.ego.box_labels
    # Waymo: from the vehicle frame (origin on the road) to the top LiDAR's, 2.184 m up
    waymo = target / "pretrain" / "val"
    assert list_agents(waymo) == ["ego"] and list_timestamps(waymo) == ["000000"]
    frame, = read_waymo_frames(WAYMO / "val.tfrecord")
    moved = read_scene(waymo, "000000").ego
    assert np.allclose(moved.boxes[:, 2], frame.ego.boxes[:, 2] - 2.184, atol=1e-5)
    assert np.allclose(moved.pose[:3, 3], frame.ego.pose[:3, :3] @ [0, 0, 2.184] + frame.ego.pose[:3, 3], atol=1e-6)
    assert "Running stage 'generate'" in ran.stdout and "Running stage 'evaluate'" not in ran.stdout


def test_each_real_frame_is_voxelized_at_its_own_lidars_height(project):
    from typ.store import list_scenes, read_scene_voxels

    proj, _, _ = project
    heights = {"kitti": 1.76, "n015": 1.84, "val": 2.184}      # the presets' (typ.sensors.presets)
    stored = [s for s in list_scenes(proj / "data" / "voxels") if s.dataset == "target"]
    assert len(stored) == 5
    for scene in stored:
        grid, _, records = read_scene_voxels(scene.path)
        h = next(v for k, v in heights.items() if scene.scene.startswith(k))
        assert grid.z_range == pytest.approx((-0.75 - h, 3.25 - h))
        occupancy = np.stack([o for o, _ in records.values()])
        if occupancy.any():   # the Waymo frame has labels but no points
            # the road fills the grid's ground channel (the target domain's 2.2 m would put it in channel 2)
            assert occupancy.sum(axis=(0, 1, 2)).argmax() == 1, scene.scene


def test_the_generator_trains_on_the_real_target_and_generates_from_held_out_frames(project):
    from typ.formats.opv2v import list_agents, read_scene

    proj, _, _ = project
    vq = json.loads((proj / "metrics" / "vqvae.json").read_text())
    assert (vq["train_views"], vq["eval_views"]) == (1, 1)     # KITTI train and val: the ego views
    st = json.loads((proj / "metrics" / "selftrain.json").read_text())
    assert st["pseudo_references"] >= 1 and st["dummy_ego_tuples"] == 1
    gen = json.loads((proj / "metrics" / "generate.json").read_text())
    assert gen["target_pretrain"]["scenarios"] == 2
    assert gen["scenario_without_candidate_vehicle"] >= 1      # Waymo's one car is 77 m away
    nuscenes = next((proj / "data" / "generated" / "target" / "pretrain").glob("n015*"))
    agents = list_agents(nuscenes)
    assert agents[0] == "ego" and len(agents) == 2              # SMALL: one reference per frame
    scene = read_scene(nuscenes, "000000")
    ref = scene.agents[agents[1]]
    assert len(ref.points) > 0 and np.isfinite(ref.points).all()
    # the reference stands on a labelled vehicle; its view (tiny composes cast views) is a scan of
    # nuScenes' own LiDAR in the reference's sensor frame: every point on one of its beams
    from typ.sensors import SENSORS, on_beam_fractions

    assert on_beam_fractions(ref.points, SENSORS["nuscenes"], (0.05,), min_range=1.0)[0.05] > 0.999


def test_a_bad_real_input_stops_simulate_with_its_name_and_touches_nothing(project, tmp_path):
    proj, env, _ = project
    good = (proj / "params.yaml").read_text()
    before = {p: p.stat().st_mtime_ns for p in (proj / "data").rglob("*")}
    kitti = kitti_root(tmp_path / "kitti")
    (kitti / "ImageSets" / "val.txt").write_text("000000\n000007\n")
    params = yaml.safe_load(good)
    params["simulate"]["sources"]["target"][0]["root"] = str(kitti)
    try:
        (proj / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
        proc = _run([str(VENV_BIN / "typ"), "run", "simulate"], proj, env, check=False)
    finally:
        (proj / "params.yaml").write_text(good)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert f"{kitti / 'ImageSets' / 'val.txt'}: line 2: expected a frame id of training/velodyne" in proc.stderr
    assert {p: p.stat().st_mtime_ns for p in (proj / "data").rglob("*")} == before
    assert subprocess.run(["git", "diff", "--quiet", "params.yaml"], cwd=proj).returncode == 0
