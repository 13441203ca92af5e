"""The tiny pipeline end to end: `dvc repro` in a throwaway copy of the project.

Checks what a user relies on: the stages run through the CLI, Prefect and MLflow; outputs
open with typ's own readers; a second `dvc repro` does nothing; adding one scenario
recomputes only that scenario; bad params stop the run before anything is touched.
"""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent

pytestmark = pytest.mark.e2e

SMALL = {
    "profile": "tiny",
    "simulate": {"frames": 2, "azimuth_step_deg": 1.0, "agents_min": 2, "agents_max": 2,
                 "scenarios": {"source": {"train": 1, "test": 1}, "target": {"train": 1, "val": 1, "test": 1},
                               "real_cav": {"train": 1, "test": 0}}},
    "voxelize": {"workers": 2},
    # training stages at a few steps: the test checks wiring, outputs and resumability, not quality
    "vqvae": {"x": {"epochs": 2, "block_out_channels": [8, 16, 16, 16]},
              "y": {"epochs": 2, "block_out_channels": [8, 16, 16, 16]}, "checkpoint_every": 1},
    "stage1": {"epochs": 2, "sample_steps": 5, "eval_views": 1, "checkpoint_every": 1,
               "unet": {"block_out_channels": [16, 16, 16, 16]}},
    "adapt": {"epochs": 1, "disc_width": 8, "checkpoint_every": 1, "eval_views": 2},
    "stage2": {"epochs": 1, "checkpoint_every": 1, "eval_pairs": 2},
    "generate": {"references_per_frame": 1, "sample_steps": 3},
}


def _copy_project(dst: Path) -> None:
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, capture_output=True,
                           text=True, check=True).stdout.split()
    for rel in files:
        src = REPO / rel
        if src.is_file():
            (dst / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / rel)
    (dst / ".venv").symlink_to(VENV_BIN.parent)


def _run(cmd, cwd, env, check=True):
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=900)
    if check and proc.returncode != 0:
        raise AssertionError(f"{cmd} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}")
    return proc


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    proj = tmp_path_factory.mktemp("proj")
    _copy_project(proj)
    (proj / "params.yaml").write_text(yaml.safe_dump(SMALL, sort_keys=False))
    env = {**os.environ, "PATH": f"{VENV_BIN}:{os.environ['PATH']}",
           "MLFLOW_TRACKING_URI": f"sqlite:///{proj / 'mlruns.db'}", "PREFECT_HOME": str(proj / ".prefect"),
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DVC_NO_ANALYTICS": "1", "DO_NOT_TRACK": "1",
           "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}
    _run(["git", "init", "-q"], proj, env)
    _run(["git", "add", "-A"], proj, env)
    _run(["git", "commit", "-qm", "snapshot"], proj, env)
    first = _run(["dvc", "repro"], proj, env)
    return proj, env, first


def test_repro_writes_readable_outputs(project):
    from typ.formats.opv2v import list_agents, list_timestamps, read_scene
    from typ.store import list_scenes, read_scene_voxels

    proj, env, _ = project
    scenarios = sorted((proj / "data" / "sim").glob("*/*/*"))
    assert [s.name for s in scenarios] == ["real_cav_train_0000", "source_test_0000", "source_train_0000",
                                           "target_test_0000", "target_train_0000", "target_val_0000"]
    for folder in scenarios:
        agents = list_agents(folder)
        assert len(agents) == 2
        stamps = list_timestamps(folder)
        assert len(stamps) == 2
        scene = read_scene(folder, stamps[0])
        assert all(len(v.points) > 1000 for v in scene.agents.values())
    stored = list_scenes(proj / "data" / "voxels")
    assert {(s.dataset, s.split) for s in stored} == {("real_cav", "train"), ("source", "train"), ("source", "test"),
                                                      ("target", "test"), ("target", "train"), ("target", "val")}
    grid, _, records = read_scene_voxels(stored[0].path)
    assert grid.shape == (128, 128, 8) and len(records) == 4
    occupancy, boxes = next(iter(records.values()))
    assert 0 < occupancy.mean() < 0.2 and boxes.shape == (128, 128, 1)

    sim = json.loads((proj / "metrics" / "simulate.json").read_text())
    vox = json.loads((proj / "metrics" / "voxelize.json").read_text())
    assert sim["simulated"] == 6 and sim["skipped_unchanged"] == 0
    assert vox["voxelized"] == 6 and vox["views"] == 24


def test_training_stages_write_models_and_metrics(project):
    import torch

    from tasks.stage1 import load_model as load_stage1
    from tasks.vqvae import load_model as load_vqvae

    proj, _, _ = project
    vq = json.loads((proj / "metrics" / "vqvae.json").read_text())
    assert vq["train_views"] == 2 and vq["eval_views"] == 2  # ego views only: 1 scenario x 2 frames
    for kind in ("x", "y"):
        assert 0.0 <= vq[kind]["recall"] <= 1.0
        model = load_vqvae(proj / "artifacts" / "vqvae" / kind)
        assert model.config["in_channels"] == (8 if kind == "x" else 1)
    s1 = json.loads((proj / "metrics" / "stage1.json").read_text())
    assert s1["generated"]["empty_generated"] in (0, 1)
    assert 0.0 < s1["postprocess"]["low"] <= s1["postprocess"]["high"] < 1.0
    model, saved = load_stage1(proj / "artifacts" / "stage1")
    assert saved["schedule"] == "linear" and saved["postprocess"] == s1["postprocess"]
    with torch.no_grad():
        eps = model(torch.zeros(1, 8, 16, 16), torch.tensor([1]), torch.zeros(1, 3, 16, 16))
    assert torch.isfinite(eps).all()
    ad = json.loads((proj / "metrics" / "adapt.json").read_text())
    assert ad["source_views"] == 4 and set(ad["before"]) == set(ad["after"])  # 1 scenario x 2 frames x 2 agents
    source_vq = load_vqvae(proj / "artifacts" / "adapt" / "source_vq")
    target_vq = load_vqvae(proj / "artifacts" / "vqvae" / "x")
    assert torch.equal(source_vq.net.quantize.embedding.weight, target_vq.net.quantize.embedding.weight)
    s2 = json.loads((proj / "metrics" / "stage2.json").read_text())
    # source: 1 scenario x 2 frames x 2 ordered pairs; target test: ego -> the other agent, 2 frames
    assert (s2["train_pairs"], s2["eval_pairs"]) == (4, 2)
    for method in ("naive_copy", "stage1_only", "typ"):
        assert 0.0 <= s2[method]["iou"] <= 1.0
    assert (proj / "artifacts" / "stage2" / "adapter.pt").exists()


def test_generated_dataset_is_opv2v_with_a_second_agent(project):
    from typ.formats.opv2v import list_agents, list_timestamps, read_scene

    proj, _, _ = project
    gen = json.loads((proj / "metrics" / "generate.json").read_text())
    assert gen["frames"] == 2 and gen["references"] + gen["scenario_without_candidate_vehicle"] >= 1
    source = proj / "data" / "sim" / "target" / "test" / "target_test_0000"
    folder = proj / "data" / "generated" / "target" / "test" / "target_test_0000"
    assert list_timestamps(folder) == list_timestamps(source)
    ego_id = list_agents(source)[0]
    assert list_agents(folder)[0] == ego_id  # OpenCOOD still picks the real ego
    for ts in list_timestamps(folder):
        scene = read_scene(folder, ts)
        original = read_scene(source, ts, agents=[ego_id])
        assert np.array_equal(scene.agents[ego_id].points, original.ego.points)  # the real ego, untouched
        for agent_id, view in scene.agents.items():
            if agent_id != ego_id:
                assert len(view.points) > 0 and np.isfinite(view.points).all()
                # the reference stands on a labelled vehicle of the ego's frame
                assert agent_id.startswith(ego_id)
                assert int(agent_id[len(ego_id):]) in set(original.ego.box_ids.tolist())
    assert gen["references"] >= 1


def test_stage_runs_are_in_mlflow_with_params_and_commit(project):
    import mlflow

    proj, env, _ = project
    client = mlflow.MlflowClient(tracking_uri=env["MLFLOW_TRACKING_URI"])
    exp = client.get_experiment_by_name("typ")
    runs = client.search_runs([exp.experiment_id])
    by_stage = {r.data.tags["typ.stage"]: r for r in runs}
    assert {"simulate", "voxelize"} <= set(by_stage)
    sim = by_stage["simulate"]
    assert sim.info.status == "FINISHED"
    assert sim.data.params["simulate.frames"] == "2"
    assert sim.data.params["profile"] == "tiny"
    commit = _run(["git", "rev-parse", "HEAD"], proj, env).stdout.strip()
    assert sim.data.tags["mlflow.source.git.commit"].startswith(commit)
    assert sim.data.metrics["simulated"] == 6
    assert by_stage["voxelize"].data.metrics["views"] == 24


def test_second_repro_does_nothing(project):
    proj, env, _ = project
    before = {p: p.stat().st_mtime_ns for p in (proj / "data").rglob("*") if p.is_file()}
    again = _run(["dvc", "repro"], proj, env)
    assert "didn't change, skipping" in again.stdout
    assert "Running stage" not in again.stdout
    after = {p: p.stat().st_mtime_ns for p in (proj / "data").rglob("*") if p.is_file()}
    assert before == after


def test_adding_a_scenario_recomputes_only_that_one(project):
    proj, env, _ = project
    params = yaml.safe_load((proj / "params.yaml").read_text())
    params["simulate"]["scenarios"]["target"]["test"] = 2
    (proj / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    old = proj / "data" / "sim" / "target" / "test" / "target_test_0000"
    old_bytes = {p: p.read_bytes() for p in old.rglob("*") if p.is_file()}
    _run(["dvc", "repro"], proj, env)
    sim = json.loads((proj / "metrics" / "simulate.json").read_text())
    vox = json.loads((proj / "metrics" / "voxelize.json").read_text())
    assert (sim["simulated"], sim["skipped_unchanged"]) == (1, 6)
    assert (vox["voxelized"], vox["skipped_unchanged"]) == (1, 6)
    assert {p: p.read_bytes() for p in old.rglob("*") if p.is_file()} == old_bytes


def test_bad_params_fail_at_start_and_touch_nothing(project):
    proj, env, _ = project
    good = (proj / "params.yaml").read_text()
    before = {p: p.stat().st_mtime_ns for p in (proj / "data").rglob("*")}
    try:
        (proj / "params.yaml").write_text(good.replace("frames: 2", "frames: two"))
        proc = _run([str(VENV_BIN / "typ"), "run", "simulate"], proj, env, check=False)
        assert proc.returncode == 2
        assert "params.yaml: simulate.frames: expected an integer, got 'two'" in proc.stderr
        assert "Traceback" not in proc.stderr
        proc = _run([str(VENV_BIN / "typ"), "run", "nonsense"], proj, env, check=False)
        assert proc.returncode == 2 and "stage: expected one of" in proc.stderr
    finally:
        (proj / "params.yaml").write_text(good)
    assert {p: p.stat().st_mtime_ns for p in (proj / "data").rglob("*")} == before
