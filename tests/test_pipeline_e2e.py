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
                               "real_cav": {"train": 1, "test": 1}}},
    "voxelize": {"workers": 2},
    # training stages at a few steps: the test checks wiring, outputs and resumability, not quality
    "vqvae": {"x": {"epochs": 2, "block_out_channels": [8, 16, 16, 16]},
              "y": {"epochs": 2, "block_out_channels": [8, 16, 16, 16]}, "checkpoint_every": 1},
    "stage1": {"epochs": 2, "sample_steps": 5, "eval_views": 1, "checkpoint_every": 1,
               "unet": {"block_out_channels": [16, 16, 16, 16]}},
    "adapt": {"epochs": 1, "disc_width": 8, "checkpoint_every": 1, "eval_views": 2},
    "stage2": {"epochs": 1, "checkpoint_every": 1, "eval_pairs": 2},
    "selftrain": {"epochs": 1, "checkpoint_every": 1, "eval_pairs": 2, "pseudo_references": 2, "sample_steps": 2},
    "generate": {"references_per_frame": 1, "sample_steps": 3, "max_distance": 50.0},
    "fusion": {"steps": 2, "pretrain_steps": 2, "finetune_steps": 1, "warm_start_steps": 1, "checkpoint_every": 1,
               "robustness": {"position_std": [0.0, 0.2], "heading_std_deg": [0.0, 0.4], "delay_ms": [0, 100],
                              "quantization_bits": [8]}},
    "ddpm": {"steps": 2, "checkpoint_every": 1, "eval_samples": 2, "bootstrap": 10,
             "unet": {"block_out_channels": [8, 16, 16]}, "features": {"steps": 2, "width": 4},
             "configs": [{"name": "J", "representation": "range", "schedule": "time_dependent", "embedding": "fourier",
                          "samplers": [["ddpm", 20], ["dpmsolver++", 3]]},
                         {"name": "A", "representation": "bev", "schedule": "linear", "embedding": "sinusoidal"}],
             "samplers": [["dpmsolver++", 3]], "latent": {"samplers": [["dpmsolver++", 2]], "views": 2}},
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
    # PYTHONPATH: the copy's code, not the checkout the venv's editable install points at
    env = {**os.environ, "PATH": f"{VENV_BIN}:{os.environ['PATH']}", "PYTHONPATH": str(proj),
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
    assert [s.name for s in scenarios] == ["real_cav_test_0000", "real_cav_train_0000", "source_test_0000",
                                           "source_train_0000", "target_test_0000", "target_train_0000",
                                           "target_val_0000"]
    for folder in scenarios:
        agents = list_agents(folder)
        assert len(agents) == 2
        stamps = list_timestamps(folder)
        assert len(stamps) == 2
        scene = read_scene(folder, stamps[0])
        assert all(len(v.points) > 1000 for v in scene.agents.values())
    stored = list_scenes(proj / "data" / "voxels")
    assert {(s.dataset, s.split) for s in stored} == {("real_cav", "train"), ("real_cav", "test"), ("source", "train"), ("source", "test"),
                                                      ("target", "test"), ("target", "train"), ("target", "val")}
    grid, _, records = read_scene_voxels(stored[0].path)
    assert grid.shape == (128, 128, 8) and len(records) == 4
    occupancy, boxes = next(iter(records.values()))
    assert 0 < occupancy.mean() < 0.2 and boxes.shape == (128, 128, 1)

    sim = json.loads((proj / "metrics" / "simulate.json").read_text())
    vox = json.loads((proj / "metrics" / "voxelize.json").read_text())
    assert sim["simulated"] == 7 and sim["skipped_unchanged"] == 0
    assert vox["voxelized"] == 7 and vox["views"] == 28


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


def test_selftrain_scores_every_method_and_table4_row(project):
    from tasks.selftrain import TABLE4

    proj, _, _ = project
    st = json.loads((proj / "metrics" / "selftrain.json").read_text())
    assert st["variant"] == "disc_st_dummy" and st["pseudo_references"] == 2 and st["eval_pairs"] == 2
    assert st["source_tuples"] == 4 and st["dummy_ego_tuples"] == 2
    assert {"naive_copy", "re_simulation", "stage_1_only_boxes_no_ego", "stage_2_without_adaptation",
            "stage_2_adapted_source_encoder", "self_training", "typ", "hybrid"} == set(st["accuracy"])
    for scores in st["accuracy"].values():
        assert 0.0 <= scores["iou"] <= 1.0 and "iou_0-20" in scores and "iou_seen" in scores
    report = (proj / "reports" / "generation_accuracy.md").read_text()
    assert "Table 4" in report and all(f"| {row}" in report for row in (
        "naive copy", "re-simulation", "hybrid: re-simulation where the ego saw, TYP elsewhere"))
    assert len(TABLE4) == 4 and (proj / "artifacts" / "selftrain" / "adapter.pt").exists()


def test_generated_dataset_is_opv2v_with_a_second_agent(project):
    from typ.formats.opv2v import list_agents, list_timestamps, read_scene

    proj, _, _ = project
    gen = json.loads((proj / "metrics" / "generate.json").read_text())
    # target train + target test (vehicles) + real_cav train (cavs): one scenario of 2 frames each
    assert gen["frames"] == 6 and gen["scenarios"] == 3
    assert {k: gen[k]["scenarios"] for k in ("target_train", "target_test", "real_cav_train")} == {
        "target_train": 1, "target_test": 1, "real_cav_train": 1}
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
    assert gen["target_test"]["references"] >= 1

    # cavs: the real CAVs replaced by generated clouds at their true poses, same ids (oracle drop-in)
    real = proj / "data" / "sim" / "real_cav" / "train" / "real_cav_train_0000"
    fake = proj / "data" / "generated" / "real_cav" / "train" / "real_cav_train_0000"
    generated = json.loads((fake / "_typ.json").read_text())["generated_agents"]
    assert set(list_agents(fake)) == {list_agents(real)[0], *generated} and set(generated) <= set(list_agents(real))
    for ts in list_timestamps(real):
        truth, made = read_scene(real, ts), read_scene(fake, ts)
        for agent_id in generated:
            assert np.array_equal(made.agents[agent_id].pose, truth.agents[agent_id].pose)
            assert not np.array_equal(made.agents[agent_id].points, truth.agents[agent_id].points)


def test_fusion_benchmark_trains_every_method_on_oracle_and_generated_cavs(project):
    proj, _, _ = project
    fu = json.loads((proj / "metrics" / "fusion.json").read_text())
    methods = ("early", "late", "attfuse", "v2xvit")
    assert set(fu["table2"]) == {"none", *methods}
    for m in methods:
        for variant in ("oracle", "generated"):  # generated: data/generated/real_cav/train exists now
            row = fu["table2"][m][variant]
            assert "skipped" not in row, row
            assert set(row["ap50"]) == {"overall", "0-30", "30-50", "50-100"}
            assert all(0.0 <= v <= 1.0 for v in row["ap50"].values())
        assert "skipped" not in fu["table3"][m]["colwaymo"]  # pre-training on the generated target split
        assert set(fu["robustness"][m]["position_std"]) == {"0.0", "0.2"}
    text = (proj / "reports" / "fusion.md").read_text()
    assert "oracle" in text and "generated" in text.lower()
    assert (proj / "reports" / "fusion_pr.png").stat().st_size > 10_000
    assert (proj / "reports" / "fusion_robustness.png").stat().st_size > 10_000


KITTI = REPO.parent / "shared" / "data" / "kitti_object_vis"


@pytest.mark.skipif(not KITTI.is_dir(), reason="../shared/data not present")
def test_generate_from_real_kitti_frames_through_the_cli(project, tmp_path):
    from typ.formats.opv2v import list_agents, read_scene

    proj, env, _ = project
    out = tmp_path / "kitti_collab"
    # the two KITTI frames have no car inside the 5-50 m band (a pedestrian; a car and a truck
    # beyond 60 m): a roadside unit on the observed road gives each a reference view anyway
    proc = _run([str(VENV_BIN / "typ"), "generate", "--format", "kitti", "--input", str(KITTI), "--out", str(out),
                 "--rsu", "1"], proj, env)
    assert "reference views" in proc.stdout
    folders = sorted((out / "kitti" / "frames").iterdir())
    assert [f.name for f in folders] == ["kitti_training_000000", "kitti_training_000001"]
    made = 0
    for folder in folders:
        agents = list_agents(folder)
        assert agents == ["ego", "-1"]  # the roadside unit sorts last, as OpenCOOD's RSUs do
        scene = read_scene(folder, "000000")
        rsu = scene.agents["-1"]
        assert np.isfinite(rsu.points).all() and len(rsu.points) > 0
        offset = np.linalg.inv(scene.ego.pose) @ rsu.pose
        assert 5.0 <= np.hypot(*offset[:2, 3]) <= 50.0 and abs(offset[2, 3]) < 1e-6  # at the ego's sensor height
        made += 1
    assert made == 2
    again = _run([str(VENV_BIN / "typ"), "generate", "--format", "kitti", "--input", str(KITTI), "--out", str(out),
                  "--rsu", "1"], proj, env)
    assert "(2 scenarios unchanged)" in again.stdout  # same frames, params and models: nothing regenerated
    bad = _run([str(VENV_BIN / "typ"), "generate", "--format", "lyft", "--input", str(KITTI)], proj, env, check=False)
    assert bad.returncode == 2 and "--format: expected one of" in bad.stderr


def test_edit_regenerates_only_the_edited_footprint(project, tmp_path):
    from tasks.edit import FOOTPRINT_MARGIN, _in_cells, footprint_mask
    from typ.formats.opv2v import list_agents, read_scene
    from typ.store import list_scenes, stored_grid

    proj, env, _ = project
    source = proj / "data" / "sim" / "target" / "test" / "target_test_0000"
    ego = list_agents(source)[0]
    view = read_scene(source, "000000", agents=[ego]).ego
    vid = int(view.box_ids[np.argmin(np.hypot(view.boxes[:, 0], view.boxes[:, 1]))])
    _run([str(VENV_BIN / "typ"), "edit", str(source), "--timestamp", "000000", "--remove", str(vid),
          "--add", "12,-6,90", "--out", str(tmp_path)], proj, env)
    edited = read_scene(tmp_path / source.name, "000000", agents=[ego]).ego
    assert vid not in edited.box_ids and len(edited.boxes) == len(view.boxes)
    grid = stored_grid(list_scenes(proj / "data" / "voxels")[0].path)
    touched = np.concatenate([view.boxes[view.box_ids == vid], edited.boxes[-1:]])
    cells = footprint_mask(touched, grid, FOOTPRINT_MARGIN)
    outside = view.points[~_in_cells(view.points, cells, grid)]
    kept = edited.points[~_in_cells(edited.points, cells, grid)]
    assert np.array_equal(np.sort(kept, axis=0), np.sort(outside, axis=0))
    for other in list_agents(source)[1:]:  # other agents' files are copied unchanged
        assert (tmp_path / source.name / other / "000000.pcd").read_bytes() == \
            (source / other / "000000.pcd").read_bytes()


def test_ddpm_stage_writes_its_table_models_and_report(project):
    from tasks.training import load_weights

    proj, _, _ = project
    dd = json.loads((proj / "metrics" / "ddpm.json").read_text())
    # test split: 1 scenario x 2 frames x 2 agents; every row scored on the same 4 views
    assert dd["test_scans"] == 4 and dd["train_scans"] == 4
    assert {"range full noise", "range real train views", "range J ddpm-20", "range J dpmsolver++-3",
            "bev full noise", "bev real train views", "bev A dpmsolver++-3",
            "voxel TYP stage 1 dpmsolver++-2"} == set(dd["rows"])
    for name, row in dd["rows"].items():
        for m in ("jsd", "mmd", "frid", "fpvd"):
            assert row[m]["low"] <= row[m]["high"], (name, m)
        assert 0.0 <= row["jsd"]["value"] <= 0.833  # sqrt(ln 2) at most
    assert dd["rows"]["voxel TYP stage 1 dpmsolver++-2"]["iou"] is not None
    assert dd["round_trip"]["range"]["max_error_over_bound"] <= 1.0
    assert set(dd["feature_nets"]) == {"range", "voxel"} and set(dd["models"]) == {
        "range-time_dependent-fourier-seed0", "bev-linear-sinusoidal-seed0"}
    for name in dd["models"]:
        state, config = load_weights(proj / "artifacts" / "ddpm" / "models" / name, "ddpm")
        assert config["train_timesteps"] == 1000 and state
    text = (proj / "reports" / "ddpm.md").read_text()
    assert "Table II analogue: range image" in text and "Side by side with TYP's latent route" in text
    assert "compare rows within typ only" in text and "## Targets" in text
    assert (proj / "reports" / "ddpm_pareto.png").stat().st_size > 10_000
    assert (proj / "reports" / "ddpm_samples.png").stat().st_size > 10_000


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
    assert sim.data.metrics["simulated"] == 7
    assert by_stage["voxelize"].data.metrics["views"] == 28
    # every trained network is an MLflow model of the stage run that trained it
    logged, stage_runs = {}, {}
    for m in client.search_logged_models(experiment_ids=[exp.experiment_id]):
        logged.setdefault(m.name, set()).add(m.source_run_id)
    for r in runs:
        stage_runs.setdefault(r.data.tags["typ.stage"], set()).add(r.info.run_id)
    owners = {"vqvae-x": "vqvae", "vqvae-y": "vqvae", "stage1-ldm": "stage1", "adapt-source-vq": "adapt",
              "stage2-adapter": "stage2", "selftrain-adapter": "selftrain",
              **{f"fusion-{m}": "fusion" for m in ("none", "early", "late", "attfuse", "v2xvit")},
              "ddpm-frid-net": "ddpm", "ddpm-fpvd-net": "ddpm", "ddpm-range-time_dependent-fourier-seed0": "ddpm"}
    assert set(owners) <= set(logged), set(owners) - set(logged)
    for name, stage in owners.items():
        assert logged[name] <= stage_runs[stage], name


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
    assert (sim["simulated"], sim["skipped_unchanged"]) == (1, 7)
    assert (vox["voxelized"], vox["skipped_unchanged"]) == (1, 7)
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
