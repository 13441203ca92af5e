"""The tiny pipeline end to end: `dvc repro` in a throwaway copy of the project.

Checks what a user relies on: the stages run through the CLI, Prefect and MLflow; outputs
open with typ's own readers; a second `dvc repro` does nothing; adding one scenario
recomputes only that scenario; bad params stop the run before anything is touched.
"""
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from repo_paths import REPO

VENV_BIN = Path(sys.executable).parent

pytestmark = pytest.mark.e2e

SMALL = {
    "profile": "tiny",
    "simulate": {"frames": 2, "azimuth_step_deg": 1.0, "agents_min": 2, "agents_max": 2, "domains": {},
                 "scenarios": {"source": {"train": 1, "test": 1},
                               "target": {"train": 1, "val": 1, "test": 1, "pretrain": 1},
                               "real_cav": {"train": 1, "test": 1}}},
    "voxelize": {"workers": 2},
    # training stages at a few steps: the test checks wiring, outputs and resumability, and quality only
    # against trivial baselines (an empty or an all-occupied view), which a broken model would not beat
    "vqvae": {"x": {"epochs": 2, "block_out_channels": [8, 16, 16]}, "checkpoint_every": 1},
    "stage1": {"epochs": 2, "sample_steps": 3, "eval_views": 1, "checkpoint_every": 1, "warmup_steps": 1,
               "unet": {"block_out_channels": [16, 16, 16]}},
    # adapt: 10 steps, enough for D to separate the unadapted source features and for E_src to confuse it
    "adapt": {"epochs": 5, "disc_width": 8, "checkpoint_every": 1, "eval_views": 2},
    "stage2": {"epochs": 1, "checkpoint_every": 1, "warmup_steps": 1, "resim": True, "one_stage": True},
    # every Table 4 row and every fusion method (tiny trains fewer, for make run's budget): wiring
    "selftrain": {"epochs": 1, "checkpoint_every": 1, "pseudo_references": 2, "sample_steps": 2, "warmup_steps": 1,
                  "ablation": True},
    "generate": {"references_per_frame": 1, "sample_steps": 3, "max_distance": 50.0},
    "fusion": {"methods": ["none", "early", "late", "attfuse", "v2xvit"],
               "steps": 2, "pretrain_steps": 2, "warm_start_steps": 1, "checkpoint_every": 1,
               "seeds": 1, "bootstrap": 20,
               "robustness": {"position_std": [0.0, 0.2], "heading_std_deg": [0.0, 0.4], "delay_ms": [0, 100],
                              "quantization_bits": [8]}},
    "ssc": {"steps": 2, "warm_start_steps": 1, "bootstrap": 20,
            "network": {"layer_nums": [1, 1, 1], "num_filters": [8, 8, 8], "num_upsample_filters": [8, 8, 8],
                        "pillar_channels": 8, "head_hidden": 8},
            "v2xvit": {"dim": 24, "shrink_stride": 1, "heads": 1, "dim_head": 8, "window_heads": [1, 1],
                       "window_dim_heads": [8, 8], "mlp_dim": 8},
            "robustness": {"position_std": [0.0, 0.2], "heading_std_deg": [0.0], "delay_ms": [0, 100],
                           "quantization_bits": [8]}},
    "evaluate": {"n_boot": 20, "max_pairs": 2, "gallery": 1},
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
    # no TYP_HASH_CACHE that an in-process CLI call of another test left: the CLI's default, <proj>/.typ
    env = {**{k: v for k, v in os.environ.items() if k != "TYP_HASH_CACHE"},
           "PATH": f"{VENV_BIN}:{os.environ['PATH']}", "PYTHONPATH": str(proj),
           "MLFLOW_TRACKING_URI": f"sqlite:///{proj / 'mlruns.db'}", "PREFECT_HOME": str(proj / ".prefect"),
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "DVC_NO_ANALYTICS": "1", "DO_NOT_TRACK": "1",
           "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t"}
    _run(["git", "init", "-q"], proj, env)
    _run(["git", "add", "-A"], proj, env)
    _run(["git", "commit", "-qm", "snapshot"], proj, env)
    # as `make run` does: one Prefect server for every stage of the run
    first = _run([str(VENV_BIN / "typ"), "with-server", "dvc", "repro"], proj, env)
    return proj, env, first


def test_repro_writes_readable_outputs(project):
    from typ.formats.opv2v import list_agents, list_timestamps, read_scene
    from typ.store import list_scenes, read_scene_voxels

    proj, env, _ = project
    scenarios = sorted(p for p in (proj / "data" / "sim").glob("*/*/*")   # not typ's records, <domain>/.typ/
                       if not any(part.startswith(".") for part in p.relative_to(proj / "data" / "sim").parts))
    assert [s.name for s in scenarios] == ["real_cav_test_0000", "real_cav_train_0000", "source_test_0000",
                                           "source_train_0000", "target_pretrain_0000", "target_test_0000",
                                           "target_train_0000", "target_val_0000"]
    for folder in scenarios:
        agents = list_agents(folder)
        assert len(agents) == 2
        stamps = list_timestamps(folder)
        assert len(stamps) == 2
        scene = read_scene(folder, stamps[0])
        assert all(len(v.points) > 1000 for v in scene.agents.values())
    stored = list_scenes(proj / "data" / "voxels")
    assert {(s.dataset, s.split) for s in stored} == {("real_cav", "train"), ("real_cav", "test"), ("source", "train"), ("source", "test"),
                                                      ("target", "test"), ("target", "train"), ("target", "val"),
                                                      ("target", "pretrain")}
    grid, _, records = read_scene_voxels(stored[0].path)
    assert grid.shape == (128, 128, 8) and len(records) == 4
    # the grid's z is relative to each domain's sensor height: the ground falls in the same channel
    heights = {"real_cav": 1.8, "source": 1.9, "target": 2.2}
    for scene in stored:
        g = read_scene_voxels(scene.path)[0]
        assert g.z_range == pytest.approx((-0.75 - heights[scene.dataset], 3.25 - heights[scene.dataset]))
        occupancy = np.stack([o for o, _ in read_scene_voxels(scene.path)[2].values()])
        assert occupancy[..., 1].sum() > occupancy[..., 0].sum() + occupancy[..., 2].sum()  # ground: channel 1
    occupancy, boxes = next(iter(records.values()))
    assert 0 < occupancy.mean() < 0.2 and boxes.shape == (128, 128, 1)

    sim = json.loads((proj / "metrics" / "simulate.json").read_text())
    vox = json.loads((proj / "metrics" / "voxelize.json").read_text())
    assert sim["simulated"] == 8 and sim["skipped_unchanged"] == 0
    assert vox["voxelized"] == 8 and vox["views"] == 32


def _all_occupied_iou(occupancy: np.ndarray) -> float:
    """IoU of an all-occupied view with the truth ``occupancy`` (an empty view's is 0): its density."""
    return float(np.mean(occupancy))


def test_training_stages_write_models_and_metrics(project):
    import torch

    from pipelines.typ.pipeline_typ import TYPPipeline
    from pipelines.typ.pipeline_typ import generator_dir
    from tasks.selftrain import TABLE4
    from tasks.stage1 import load_model as load_stage1
    from tasks.stage2 import load_adapter
    from tasks.voxel_data import load_views
    from tasks.vqvae import load_model as load_vqvae

    proj, _, _ = project
    vq = json.loads((proj / "metrics" / "vqvae.json").read_text())
    assert vq["train_views"] == 2 and vq["eval_views"] == 2  # ego views only: 1 scenario x 2 frames
    assert 0.0 <= vq["x"]["recall"] <= 1.0 and 0.0 < vq["x"]["codes_used"] <= 1.0 and vq["x"]["perplexity"] >= 1
    assert vq["y"] == {"encoding": "pool"}
    val = load_views(proj / "data" / "voxels", dataset="target", split="val")
    trivial = _all_occupied_iou(val.occupancy(np.arange(len(val))))  # about 0.035 (the ground channel)
    assert vq["x"]["iou"] > 1.5 * trivial  # G(Q(E(x))) reconstructs where x is (0.076 at 2 epochs)
    assert load_vqvae(proj / "artifacts" / "vqvae" / "x").config["in_channels"] == 8
    assert load_vqvae(proj / "artifacts" / "vqvae" / "y").config == {"kind": "pool", "downsample": 4}
    # weights: safetensors, never a pickle (resume checkpoints aside)
    pickles = [p for p in (proj / "artifacts").rglob("*.pt") if "checkpoints" not in p.parts]
    assert pickles == [] or all("fusion" in p.parts for p in pickles), pickles
    s1 = json.loads((proj / "metrics" / "stage1.json").read_text())
    thresholds = s1["seed_0"]["postprocess"]
    assert 0.0 < thresholds["low"] <= thresholds["high"] < 1.0
    assert s1["seed_0"]["val_iou"] > 2 * trivial  # samples of P(x | y) overlap the val views (0.10)
    model, saved = load_stage1(proj / "artifacts" / "stage1" / "seed_0")
    assert saved["schedule"] == "linear" and saved["postprocess"] == thresholds
    with torch.no_grad():
        eps = model(torch.zeros(1, 8, 32, 32), torch.tensor([1]), torch.zeros(1, 1, 32, 32))
    assert torch.isfinite(eps).all()
    ad = json.loads((proj / "metrics" / "adapt.json").read_text())
    assert ad["source_views"] == 4 and set(ad["before"]) == set(ad["after"])  # 1 scenario x 2 frames x 2 agents
    # Eq. 8-10 at work: the final D tells the unadapted source features (E_tgt) from the target's, not the
    # adapted ones (E_src): 1.0 -> 0.5; a flipped L_src sign gives 0.75 -> 1.0, swapped hinge sides 0.5 -> 0.5.
    # L_rec reaches E_src, G_src: they reconstruct the source views better than E_tgt, G_tgt (0.045 -> 0.097)
    assert abs(ad["after"]["disc_accuracy"] - 0.5) < abs(ad["before"]["disc_accuracy"] - 0.5)
    assert ad["after"]["rec_iou_source"] > ad["before"]["rec_iou_source"]
    source_vq = load_vqvae(proj / "artifacts" / "adapt" / "source_vq", "adapt")
    target_vq = load_vqvae(proj / "artifacts" / "vqvae" / "x")
    assert torch.equal(source_vq.codebook, target_vq.codebook)  # Q_tgt shared and frozen
    s2 = json.loads((proj / "metrics" / "stage2.json").read_text())
    assert s2["train_pairs"] == 4  # source: 1 scenario x 2 frames x 2 ordered pairs
    for name in ("adapter", "adapter_resim", "one_stage/adapter"):
        assert load_adapter(proj / "artifacts" / "stage2" / "seed_0" / name).config["conditions"] == \
            (2 if name == "adapter_resim" else 1)
    st = json.loads((proj / "metrics" / "selftrain.json").read_text())
    assert st["variants"] == [v.name for v in TABLE4] + ["typ_resim"]
    assert st["pseudo_references"] == 2 and st["source_tuples"] == 4 and st["dummy_ego_tuples"] == 2
    pipe = TYPPipeline.from_pretrained(generator_dir(proj / "artifacts" / "selftrain", 0))
    assert pipe.conditions == 1 and pipe.num_inference_steps == 2 and pipe.point_stats.points_per_voxel


def test_evaluate_scores_every_method_with_intervals_and_renders_a_gallery(project):
    from tasks.evaluate_generation import METHODS
    from tasks.pairs import iter_pairs
    from typ.config import load_config
    from typ.sim.sensor import domain_spec

    proj, _, _ = project
    ev = json.loads((proj / "metrics" / "evaluate.json").read_text())
    assert ev["pairs"] == 2 and ev["scenes"] == 1 and ev["seeds"] == [0]
    assert set(ev["generation"]) == set(METHODS)
    for method, figures in ev["generation"].items():
        for fig in ("iou", "iou_0-20", "iou_seen", "iou_unseen", "iou_above_ground", "object_hit_rate", "jsd_r2dm"):
            iv = figures[fig]
            assert iv["value"] is None or iv["low"] <= iv["value"] <= iv["high"], (method, fig, iv)
    assert ev["generation"]["naive_copy"]["iou"]["value"] > 0.1
    grid = load_config(proj / "params.yaml").voxelize.sensor_grid("target")
    truth = np.stack([p.x_r for p in iter_pairs(proj / "data" / "sim" / "target" / "test", grid, ego_only=True)])
    assert len(truth) == ev["pairs"]
    trivial = _all_occupied_iou(truth)  # about 0.04
    for method in sorted(set(METHODS) - {"naive_copy", "resim", "hybrid", "cast"}):  # the learned generators
        figures = ev["generation"][method]
        # above an empty view's IoU (0) and an all-occupied view's, and far above its precision (the
        # density): at this budget the generators learn the ground layer (IoU 0.13, precision 0.25)
        assert figures["iou"]["value"] > 2 * trivial and figures["precision"]["value"] > 3 * trivial, method
    assert ev["adaptation"]["before"]["jsd_r2dm"] > 0 and "jsd_change" in ev["adaptation"]
    # scan-pattern realism of every method against the true scans, FRID / FPVD with the ddpm stage's networks
    real = ev["realism"]
    assert set(real) == {"truth", *METHODS}
    assert real["truth"]["on_beam"]["value"] > 0.99 and real["cast"]["on_beam"]["value"] > 0.99
    assert real["stage1_only"]["on_beam"]["value"] < 0.9          # voxel-sampled points are off the beams
    assert real["truth"]["frid"]["value"] < 1e-9 < real["stage1_only"]["frid"]["value"]
    assert real["cast"]["row_profile_l1"]["value"] < real["stage1_only"]["row_profile_l1"]["value"]
    profile = (proj / "reports" / "plots" / "row_profile.csv").read_text().splitlines()
    assert profile[0].startswith("elevation_deg,truth,naive_copy") and len(profile) == 1 + domain_spec("target").sensor.n_beams
    report = (proj / "reports" / "generation_accuracy.md").read_text()
    assert "Table 4" in report and "Table 5" in report and all(f"| {row}" in report for row in METHODS.values())
    assert "](gallery/" in report
    pngs = list((proj / "reports" / "gallery").glob("*.png"))
    assert len(pngs) == 1 and pngs[0].stat().st_size > 50_000
    band = (proj / "reports" / "plots" / "iou_by_band.csv").read_text().splitlines()
    assert band[0].startswith("range_m,band,naive_copy") and len(band) == 4
    shown = _run([str(VENV_BIN / "dvc"), "plots", "show", "--json"], proj, project[1])
    rendered = json.loads(shown.stdout)
    for plot in ("iou_by_band", "row_profile", "fusion_loss", "fusion_pr", "fusion_position_std", "fusion_heading_std",
                 "fusion_delay", "fusion_bits"):     # every declared plot has its data
        assert plot in shown.stdout and not rendered.get("errors", {}).get(plot), plot
    # every trained network's loss curve (a folder per stage in dvc.yaml: one plot per file)
    for stage in ("vqvae", "stage1", "adapt", "stage2", "selftrain", "ddpm"):
        curves = sorted((proj / "artifacts" / stage / "loss").glob("*.csv"))
        assert curves, stage
        for curve in curves:
            key = str(curve.relative_to(proj))
            assert key in rendered["data"] and not rendered.get("errors", {}).get(key), key
            head, *rows = curve.read_text().splitlines()
            assert head.startswith("step,loss") and [int(r.split(",")[0]) for r in rows] == list(range(len(rows)))
    assert "reports/bench_sampling.csv" in rendered["data"]


def test_ssc_stage_scores_every_method_and_saves_its_networks(project):
    from typ.artifacts import read_config, read_weights

    proj, _, _ = project
    ssc = json.loads((proj / "metrics" / "ssc.json").read_text())
    methods = ["none", "early", "late", "attfuse", "v2xvit"]
    for setting in ("perfect", "noisy"):
        assert sorted(ssc["tables"][setting]) == sorted(methods)
        for method, row in ssc["tables"][setting].items():
            for fig in ("iou", "miou", "ciou", "iou_road", "iou_car"):
                assert 0.0 <= row[fig]["low"] <= row[fig]["high"] <= 1.0, (setting, method, fig)
    assert ssc["tables"]["perfect"]["late"]["frames"] == 2 and ssc["test"] == {"samples": 2, "scenarios": 1}
    assert ssc["applied_delay_ms"] == [0.0, 100.0] and set(ssc["robustness_miou"]) == set(methods)
    for data in ("oracle", "generated"):
        for name in ("single", "early", "attfuse", "v2xvit"):
            folder = proj / "artifacts" / "ssc" / "models" / data / name / "seed_0"
            assert read_config(folder, "ssc")["config"]["network"] == name and read_weights(folder, "ssc")
    assert sorted(ssc["tables"]["generated"]) == ["attfuse", "early", "late", "v2xvit"] and ssc["skipped"] == {}
    for row in ssc["tables"]["generated"].values():
        assert row["ratio_miou"]["low"] <= row["ratio_miou"]["value"] <= row["ratio_miou"]["high"]
    report = (proj / "reports" / "ssc.md").read_text()
    assert "Table I analogue" in report and "| Intermediate (AttFuse) |" in report
    for png in ("ssc_robustness.png", "ssc_gallery.png"):
        assert (proj / "reports" / png).stat().st_size > 10_000, png


def test_generated_dataset_is_opv2v_with_a_second_agent(project):
    from typ.formats.opv2v import list_agents, list_timestamps, read_scene

    proj, _, _ = project
    gen = json.loads((proj / "metrics" / "generate.json").read_text())
    # target pretrain (vehicles, held out from training) + real_cav train (cavs): one scenario of 2 frames each
    assert gen["frames"] == 4 and gen["scenarios"] == 2
    assert {k: gen[k]["scenarios"] for k in ("target_pretrain", "real_cav_train")} == {
        "target_pretrain": 1, "real_cav_train": 1}
    source = proj / "data" / "sim" / "target" / "pretrain" / "target_pretrain_0000"
    folder = proj / "data" / "generated" / "target" / "pretrain" / "target_pretrain_0000"
    assert list_timestamps(folder) == list_timestamps(source)
    ego_id = list_agents(source)[0]
    assert list_agents(folder)[0] == ego_id  # OpenCOOD still picks the real ego
    for ts in list_timestamps(folder):
        scene = read_scene(folder, ts)
        original = read_scene(source, ts, agents=[ego_id])
        assert np.array_equal(scene.agents[ego_id].points, original.ego.points)  # the real ego, untouched
        for agent_id, view in scene.agents.items():
            if agent_id != ego_id:
                pts = view.points
                assert len(pts) > 0 and np.isfinite(pts).all()
                # the reference stands on a labelled vehicle of the ego's frame
                assert agent_id.startswith(ego_id)
                assert int(agent_id[len(ego_id):]) in set(original.ego.box_ids.tolist())
                # a cast view (tiny's generate.compose): one scan of the reference sensor (the
                # target domain's, 2.2 m up) in its own frame, every point on one of its beams, off
                # the 0.8 m voxel centres, with the domain's intensities
                from typ.sensors import SENSORS, on_beam_fractions

                assert on_beam_fractions(pts, SENSORS["target"], (0.05,), min_range=1.0)[0.05] > 0.999
                assert len(np.unique(np.round(pts[:, 0] / 0.8 - 0.5, 6) % 1.0)) > 10
                assert pts[:, 3].std() > 0
    assert gen["target_pretrain"]["references"] >= 1

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
            # a scan of real_cav's own LiDAR (1.8 m up) from the CAV's pose
            assert on_beam_fractions(made.agents[agent_id].points, SENSORS["real_cav"], (0.05,),
                                     min_range=1.0)[0.05] > 0.999


def test_fusion_benchmark_trains_every_method_on_oracle_and_generated_cavs(project):
    proj, _, _ = project
    trained = json.loads((proj / "metrics" / "fusion.json").read_text())   # the fusion stage trains ...
    assert trained["trainings"] == trained["runs"] and set(trained["final_losses"]) == set(trained["seconds_per_run"])
    fu = json.loads((proj / "metrics" / "evaluate.json").read_text())["fusion"]   # ... evaluate scores
    methods = ("early", "late", "attfuse", "v2xvit")
    assert set(fu["table1"]) == {"none", *methods} and set(fu["table1"]["none"]) == {"ego"}
    for m in methods:
        for variant in ("oracle", "generated"):  # generated: data/generated/real_cav/train exists now
            cell = fu["table1"][m][variant]
            assert cell is not None and set(cell["ap50"]) == {"overall", "0-30", "30-50", "50-100"}
            overall = cell["ap50"]["overall"]            # a number, inside its interval
            assert overall is not None and 0.0 <= overall["low"] <= overall["value"] <= overall["high"] <= 1.0
        assert set(fu["table3"][m]) == {"scratch", "colwaymo", "source"}  # colwaymo: the generated target split
        assert set(fu["robustness"][m]["position_std"]) == {"0.0", "0.2"}
    assert fu["applied_delay_ms"] == [0.0, 100.0]
    text = (proj / "reports" / "fusion.md").read_text()
    assert "oracle" in text and "generated" in text.lower() and "Skipped" not in text
    assert (proj / "reports" / "fusion_pr.png").stat().st_size > 10_000
    assert (proj / "reports" / "fusion_robustness.png").stat().st_size > 10_000
    models = proj / "artifacts" / "fusion" / "models"
    assert (models / "oracle-late" / "seed_0" / "model.safetensors").is_file()
    assert (models / "oracle-v2xvit" / "seed_0" / "config.json").is_file()


def _task_runs(proj: Path, flow: str) -> dict[str, set[str]]:
    """Task run name -> its states, over every run of flow ``flow``, from the Prefect database."""
    import contextlib
    import sqlite3

    found: dict[str, set[str]] = {}
    with contextlib.closing(sqlite3.connect(proj / ".prefect" / "prefect.db")) as db:
        for name, state in db.execute("SELECT t.name, t.state_type FROM task_run t JOIN flow_run r ON "
                                      "t.flow_run_id = r.id JOIN flow f ON r.flow_id = f.id WHERE f.name = ?", (flow,)):
            found.setdefault(name, set()).add(state)
    return found


def test_each_training_is_one_prefect_task_run(project):
    """The training flows report every network they train as its own task run, named after it (the
    UI's progress and failures per network), not one opaque task for the stage."""
    proj, _, _ = project
    metrics = {stage: json.loads((proj / "metrics" / f"{stage}.json").read_text())
               for stage in ("fusion", "selftrain", "ddpm")}
    expected = {
        "vqvae": {"train-x-seed0", "train-y-seed0"},
        "stage1": {"train-ldm-seed0"},
        "adapt": {"train-source_vq-seed0"},
        "fusion": {f"train-{run}-seed0" for run in metrics["fusion"]["seconds_per_run"]},
        "ssc": {"train-oracle-seed0", "train-generated-seed0"},
        "stage2": {"train-adapter-seed0", "train-adapter_resim-seed0", "train-one-stage-seed0"},
        "selftrain": {f"train-{variant}-seed0" for variant in metrics["selftrain"]["variants"]},
        "ddpm": {f"train-{name}" for name in metrics["ddpm"]["models"]},
    }
    assert len(expected["fusion"]) > 10 and len(expected["selftrain"]) > 3 and len(expected["ddpm"]) == 2
    for flow, names in expected.items():
        found = {name: states for name, states in _task_runs(proj, flow).items() if name.startswith("train-")}
        assert set(found) == names, (flow, set(found) ^ names)
        assert all(states == {"COMPLETED"} for states in found.values()), (flow, found)


PROBE = """
import concurrent.futures, threading, time
from prefect import flow
from prefect.task_runners import ThreadPoolTaskRunner
from flows.common import PrefectTrainings

diverged = threading.Event()

def training():
    diverged.wait(60)
    time.sleep(2)            # still training well after the other one failed
    return 1.5

def diverging():
    diverged.set()
    raise ValueError("loss is NaN")

@flow(name="trainings-probe", task_runner=ThreadPoolTaskRunner(max_workers=1))   # as run_stage gives training flows
def probe():
    with concurrent.futures.ThreadPoolExecutor(2) as pool, PrefectTrainings() as trainings:
        trainings.started("train-pooled-seed0", pool.submit(training))
        trainings.started("train-diverged-seed0", pool.submit(diverging))
        assert trainings.run("train-here-seed0", lambda: 2.0) == 2.0

probe()
"""


def test_a_pool_training_is_a_task_run_that_ends_in_its_state(project):
    """Trainings on a process pool (the fusion and ssc stages on 2+ threads): each is a task run
    that runs while its training runs, and completes with it or fails with it."""
    import contextlib
    import sqlite3

    proj, env, _ = project
    _run([str(VENV_BIN / "typ"), "with-server", sys.executable, "-c", PROBE], proj, env)
    assert _task_runs(proj, "trainings-probe") == {"train-pooled-seed0": {"COMPLETED"},
                                                   "train-diverged-seed0": {"FAILED"},
                                                   "train-here-seed0": {"COMPLETED"}}
    with contextlib.closing(sqlite3.connect(proj / ".prefect" / "prefect.db")) as db:
        times = {name: (start, end) for name, start, end in db.execute(
            "SELECT name, start_time, end_time FROM task_run WHERE name IN (?, ?)",
            ("train-pooled-seed0", "train-diverged-seed0"))}
    assert times["train-diverged-seed0"][0] < times["train-pooled-seed0"][1]   # at once, not one after the other


KITTI = REPO.parent / "shared" / "data" / "kitti_object_vis"


@pytest.mark.skipif(not KITTI.is_dir(), reason="../shared/data not present")
def test_generate_from_real_kitti_frames_through_the_cli(project, tmp_path):
    from typ.formats.opv2v import list_agents, read_scene
    from typ.sensors import SENSORS, on_beam_fractions

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
        # tiny composes cast views: a scan of KITTI's own HDL-64E from the roadside unit's pose
        assert on_beam_fractions(rsu.points, SENSORS["kitti"], (0.05,), min_range=1.0)[0.05] > 0.999
        offset = np.linalg.inv(scene.ego.pose) @ rsu.pose
        assert 5.0 <= np.hypot(*offset[:2, 3]) <= 50.0 and abs(offset[2, 3]) < 1e-6  # at the ego's sensor height
        made += 1
    assert made == 2
    again = _run([str(VENV_BIN / "typ"), "generate", "--format", "kitti", "--input", str(KITTI), "--out", str(out),
                  "--rsu", "1"], proj, env)
    assert "(2 scenarios unchanged)" in again.stdout  # same frames, params and models: nothing regenerated
    bad = _run([str(VENV_BIN / "typ"), "generate", "--format", "lyft", "--input", str(KITTI)], proj, env, check=False)
    assert bad.returncode == 2 and "--format: expected one of" in bad.stderr
    bad = _run([str(VENV_BIN / "typ"), "generate", "--format", "kitti", "--input", str(KITTI), "--out", str(out),
                "--compose", "mixed"], proj, env, check=False)
    assert bad.returncode == 2 and "--compose: expected one of" in bad.stderr


def test_edit_regenerates_only_the_edited_footprint(project, tmp_path):
    from tasks.edit import FOOTPRINT_MARGIN, behind_boxes, footprint_mask
    from typ.config import load_config
    from typ.formats.opv2v import list_agents, read_scene
    from typ.resim import in_mask
    from typ.sensors import on_beam_fractions
    from typ.sim.sensor import domain_spec
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
    grid = stored_grid(list_scenes(proj / "data" / "voxels", dataset="target")[0].path)
    touched = np.concatenate([view.boxes[view.box_ids == vid], edited.boxes[-1:]])
    cells = footprint_mask(touched, grid, FOOTPRINT_MARGIN)
    outside = view.points[~in_mask(view.points, cells, grid)]
    kept = edited.points[~in_mask(edited.points, cells, grid)]
    # tiny's generate.compose is cast, so the edit is too: the footprints are a scan of the view's
    # LiDAR, and the real points the added car hides are gone; every other real point is kept as it was
    manifest = json.loads((tmp_path / source.name / "_typ.json").read_text())
    assert manifest["compose"] == "cast"
    scaled = edited.boxes[-1] * np.r_[1, 1, 1, [load_config(proj / "params.yaml").generate.cast.label_boxes] * 3, 1]
    hidden = behind_boxes(outside, scaled[None])
    assert np.array_equal(np.sort(kept, axis=0), np.sort(outside[~hidden], axis=0))
    regenerated = edited.points[in_mask(edited.points, cells, grid)]
    assert on_beam_fractions(regenerated, domain_spec("target").sensor, (0.05,), min_range=1.0)[0.05] > 0.99
    for other in list_agents(source)[1:]:  # other agents' files are copied unchanged
        assert (tmp_path / source.name / other / "000000.pcd").read_bytes() == \
            (source / other / "000000.pcd").read_bytes()
    render = tmp_path / f"{source.name}_000000_{ego}_edit.png"  # before / after / changed cells
    assert render.stat().st_size > 50_000


def test_show_renders_generated_agents_beside_their_true_views(project, tmp_path):
    from typ.formats.opv2v import list_agents

    proj, env, _ = project
    for split in ("target/pretrain", "real_cav/train"):  # vehicles: truth cast again; cavs: the simulated files
        folder = proj / "data" / "generated" / split / f"{split.replace('/', '_')}_0000"
        generated = json.loads((folder / "_typ.json").read_text())["generated_agents"]
        shown = _run([str(VENV_BIN / "typ"), "show", str(folder), "--timestamp", "000001", "--out", str(tmp_path)],
                     proj, env)
        names = {Path(line.split()[-1]).name for line in shown.stdout.splitlines()}
        prefix = f"{folder.name}_000001"
        assert names == {f"{prefix}_agents.png", *(f"{prefix}_{a}.png" for a in list_agents(folder)),
                         *(f"{prefix}_{a}_range.png" for a in list_agents(folder)),
                         *(f"{prefix}_{a}_sample.png" for a in generated)}
        assert all((tmp_path / n).stat().st_size > 20_000 for n in names)


def test_ddpm_stage_writes_its_table_models_and_report(project):
    from typ.artifacts import read_config, read_weights

    proj, _, _ = project
    dd = json.loads((proj / "metrics" / "ddpm.json").read_text())
    # test split: 1 scenario x 2 frames x 2 agents; every row scored on the same 4 views
    assert dd["test_scans"] == 4 and dd["train_scans"] == 4
    assert {"range full noise", "range real train views", "range J ddpm-20", "range J dpmsolver++-3",
            "bev full noise", "bev real train views", "bev A dpmsolver++-3",
            "voxel random occupancy", "voxel TYP stage 1 dpmsolver++-2"} == set(dd["rows"])
    for name, row in dd["rows"].items():
        blind = ("frid",) if name.startswith("voxel ") else ()  # the range network cannot rank voxel clouds
        for m in ("jsd", "mmd", "frid", "fpvd"):
            assert (row[m] is None) if m in blind else row[m]["low"] <= row[m]["high"], (name, m)
        assert 0.0 <= row["jsd"]["value"] <= 0.833  # sqrt(ln 2) at most
    assert dd["rows"]["voxel TYP stage 1 dpmsolver++-2"]["iou"] is not None
    assert dd["round_trip"]["range"]["max_error_over_bound"] <= 1.0
    assert set(dd["feature_nets"]) == {"range", "voxel"} and set(dd["models"]) == {
        "range-time_dependent-fourier-v-seed0", "bev-linear-sinusoidal-v-seed0"}
    for name in dd["models"]:
        network, seed = name.rsplit("-seed", 1)       # a model's name; its folder: <network>/seed_<k>
        folder = proj / "artifacts" / "ddpm" / "models" / network / f"seed_{seed}"
        saved = read_config(folder, "ddpm")
        assert saved["train_timesteps"] == 1000 and saved["prediction"] == "v_prediction" and read_weights(folder, "ddpm")
    text = (proj / "reports" / "ddpm.md").read_text()
    assert "Table II analogue: range image" in text and "Side by side with TYP's latent route" in text
    assert "compare rows within typ only" in text and "## Against the paper" in text
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
    assert sim.data.metrics["simulated"] == 8
    assert by_stage["voxelize"].data.metrics["views"] == 32
    # every trained network is an MLflow model of the stage run that trained it
    logged, stage_runs = {}, {}
    for m in client.search_logged_models(experiment_ids=[exp.experiment_id]):
        logged.setdefault(m.name, set()).add(m.source_run_id)
    for r in runs:
        stage_runs.setdefault(r.data.tags["typ.stage"], set()).add(r.info.run_id)
    owners = {"vqvae-x": "vqvae", "stage1-ldm": "stage1", "adapt-source-vq": "adapt",
              "stage2-adapter": "stage2", "selftrain-adapter": "selftrain",
              **{f"fusion-{m}": "fusion" for m in ("none", "early", "late", "attfuse", "v2xvit")},
              "ddpm-frid-net": "ddpm", "ddpm-fpvd-net": "ddpm", "ddpm-range-time_dependent-fourier-v-seed0": "ddpm"}
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


def test_a_stage_with_nothing_to_do_is_settled_before_prefect_is_imported(project):
    """`typ run voxelize` with every scene unchanged: no Prefect import and no flow run, the MLflow
    run and metrics the flow would log, no output touched. One input rewritten with the same
    bytes has a new stat: the hash cache misses, the file is read again and found unchanged."""
    import mlflow

    from typ.config import load_config

    proj, env, _ = project
    cfg = load_config(proj / "params.yaml")
    pcd = sorted((proj / cfg.voxelize.input).rglob("*.pcd"))[0]
    pcd.write_bytes(pcd.read_bytes())
    out = proj / cfg.voxelize.out
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")}
    code = "import sys; from cli.main import main; rc = main(['run', 'voxelize']); print(rc, 'prefect' in sys.modules)"
    ran = _run([str(VENV_BIN / "python"), "-c", code], proj, env)
    assert ran.stdout.split()[-2:] == ["0", "False"], ran.stdout
    vox = json.loads((proj / "metrics" / "voxelize.json").read_text())
    assert (vox["scenarios"], vox["voxelized"], vox["skipped_unchanged"], vox["removed_stale"]) == (8, 0, 8, 0)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before
    assert (proj / ".typ" / "hashes.sqlite").is_file()
    client = mlflow.MlflowClient(tracking_uri=env["MLFLOW_TRACKING_URI"])
    exp = client.get_experiment_by_name("typ")
    run = client.search_runs([exp.experiment_id], "tags.`typ.stage` = 'voxelize'", order_by=["attributes.start_time DESC"],
                             max_results=1)[0]
    assert run.info.status == "FINISHED" and run.data.tags["typ.prefect"] == "not started: every scene unchanged"
    assert run.data.metrics["skipped_unchanged"] == 8 and run.data.params["voxelize.workers"] == "2"


def test_adding_a_scenario_recomputes_only_that_one(project):
    proj, env, _ = project
    params = yaml.safe_load((proj / "params.yaml").read_text())
    params["simulate"]["scenarios"]["target"]["test"] = 2
    (proj / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    old = proj / "data" / "sim" / "target" / "test" / "target_test_0000"
    old_bytes = {p: p.read_bytes() for p in old.rglob("*") if p.is_file()}
    ran = _run([str(VENV_BIN / "typ"), "with-server", "dvc", "repro", "voxelize"], proj, env)
    assert re.findall(r"Running stage '(\w+)'", ran.stdout) == ["simulate", "voxelize"]
    # a held-out target scene: what `dvc repro` would run next is the stages that read target/test
    # (or all of data/sim), no training stage, no fusion. Asked of DVC rather than run: scoring
    # ddpm and evaluate again took 90 s of the suite and shows nothing about what reruns
    stale = json.loads(_run([str(VENV_BIN / "dvc"), "status", "--json"], proj, env).stdout)
    assert sorted(stale) == ["ddpm", "evaluate"], stale
    sim = json.loads((proj / "metrics" / "simulate.json").read_text())
    vox = json.loads((proj / "metrics" / "voxelize.json").read_text())
    assert (sim["simulated"], sim["skipped_unchanged"]) == (1, 8)
    assert (vox["voxelized"], vox["skipped_unchanged"]) == (1, 8)
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
