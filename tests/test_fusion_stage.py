"""Stage ``fusion`` end to end on a few small simulated scenarios (tasks/fusion.py)."""
from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
import torch
from torch import nn

from tasks import fusion as F
from tasks import fusion_report as R
from tasks.fusion_data import FusionDataset
from tasks.training import checkpoints
from typ.boxes_bev import rotated_iou_bev
from typ.config import config_from_dict
from typ.errors import TypError
from typ.formats.opv2v import list_scenarios, read_scene, write_scene
from typ.geometry import invert, points_in_boxes, transform_points
from typ.sim import simulate_scenario

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SMALL = {"methods": ["none", "early", "late", "attfuse", "v2xvit"],
         "detector": {"lidar_range": [-51.2, -25.6, -3.0, 51.2, 25.6, 1.0], "voxel_size": 0.8,
                      "max_points_per_pillar": 8, "max_pillars": 4000, "pillar_channels": 8,
                      "num_filters": [8, 16], "num_upsample_filters": [8, 8]},
         "v2xvit": {"dim": 8, "heads": 1, "dim_head": 8, "window_sizes": [4], "window_heads": [1],
                    "window_dim_heads": [8], "mlp_dim": 8},
         "robustness": {"position_std": [0.0, 0.4], "heading_std_deg": [0.0, 0.8], "delay_ms": [0, 100],
                        "quantization_bits": [8, 2]},
         "steps": 2, "pretrain_steps": 2, "finetune_steps": 1, "warm_start_steps": 1, "checkpoint_every": 1,
         "finetune_scenes": [1]}


def _simulate(folder, domain: str, seed: int, agents: int, azimuth: float = 1.5) -> None:
    for scene in simulate_scenario(domain=domain, seed=seed, n_frames=2, n_agents=agents, azimuth_step_deg=azimuth,
                                   scenario=f"{domain}_{seed:04d}"):
        write_scene(scene, folder)


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """data/sim with real_cav train (2 scenarios) / test (1), source train (1); data/generated with
    real_cav/train (cooperating clouds jittered: a stand-in for TYP's) and target/pretrain (ColWaymo)."""
    root = tmp_path_factory.mktemp("fusion")
    sim, gen = root / "data" / "sim", root / "data" / "generated"
    for seed in (1, 2):
        _simulate(sim / "real_cav" / "train", "real_cav", seed, 3)
    _simulate(sim / "real_cav" / "test", "real_cav", 3, 3)
    _simulate(sim / "source" / "train", "source", 4, 2, azimuth=3.0)
    _simulate(gen / "target" / "pretrain", "target", 5, 2, azimuth=3.0)
    rng = np.random.default_rng(0)
    for folder in list_scenarios(sim / "real_cav" / "train"):
        for ts in ("000000", "000001"):
            scene = read_scene(folder, ts)
            for agent in list(scene.agents)[1:]:
                view = scene.agents[agent]
                keep = rng.random(len(view.points)) < 0.5
                view.points = (view.points[keep] + rng.normal(0, 0.05, (int(keep.sum()), 4))).astype(np.float32)
                view.points[:, 3] = view.points[:, 3].clip(0, 1)
                view.semantics = None
            write_scene(scene, gen / "real_cav" / "train")
    cfg = config_from_dict({"fusion": SMALL}).fusion
    return root, cfg


def _bench(project):
    root, cfg = project
    return F.Benchmark(cfg, F.Roots.from_config(cfg, root), root / "artifacts" / "fusion")


def _valid(cell) -> bool:
    return set(cell) >= {"ap50", "ap70"} and all(
        set(cell[k]) == {"overall", "0-30", "30-50", "50-100"} and
        all(v is None or 0.0 <= v <= 1.0 for v in cell[k].values()) for k in ("ap50", "ap70"))


def test_every_table_and_report_on_tiny_data(project):
    root, cfg = project
    bench = _bench(project)
    table2 = F.oracle_vs_generated(bench)
    assert set(table2) == set(cfg.methods)
    assert set(table2["none"]) == {"ego"} and all(set(table2[m]) == {"oracle", "generated"} for m in F.METHODS[1:])
    assert all(_valid(c) and len(c["pr"]["recall"]) == len(c["pr"]["precision"])
               for row in table2.values() for c in row.values())
    table3 = F.pretrain_finetune(bench)
    assert set(table3["none"]) == {"scratch"} and table3["none"]["scratch"]["0"] is None
    for method in F.METHODS[1:]:
        assert set(table3[method]) == {"scratch", "colwaymo", "source"}
        assert all(set(row) == {"0", "1", "all"} for row in table3[method].values())
        assert _valid(table3[method]["source"]["0"]) and _valid(table3[method]["colwaymo"]["1"])
    # scratch on all scenes is the oracle run itself, not a second training
    assert table3["late"]["scratch"]["all"] == {k: table2["late"]["oracle"][k] for k in ("ap50", "ap70")}
    assert "finetune1-source-v2xvit" in bench.models and "scratchall-late" not in bench.models
    # warm start: AttFuse began from the late-fusion detector of the same data, then trained on
    assert bench.models["oracle-attfuse"].steps == cfg.warm_start_steps and bench.models["oracle-late"].steps == 2
    curves = F.robustness(bench)
    for method, entry in curves["methods"].items():
        assert all(len(entry[s]) == 2 and all(_valid(c) for c in entry[s]) for s in curves["levels"])
    quant = curves["methods"]["attfuse"]["quantization"]
    assert [q["bits"] for q in quant] == [32, 8, 2]
    assert quant[0]["bytes_per_message"] > quant[1]["bytes_per_message"] > quant[2]["bytes_per_message"] > 0
    assert curves["methods"]["none"]["bytes_per_message"] == 0
    assert curves["methods"]["early"]["bytes_per_message"] > curves["methods"]["attfuse"]["bytes_per_message"] / 100

    results = {**F.summarize(bench, table2, table3, curves), "seconds_total": 1.0, "seconds_training": 0.5}
    paths = R.write_report(results, cfg, root / "reports")
    assert [p.name for p in paths] == ["fusion.md", "fusion_pr.png", "fusion_robustness.png"]
    assert all(p.stat().st_size > 0 for p in paths)
    text = paths[0].read_text()
    assert "TYP Tables 1–2" in text and "TYP Table 3" in text and "V2X-ViT" in text and "skipped" not in text
    metrics = json.loads(json.dumps(R.metrics_of(results)))
    assert metrics["table2"]["attfuse"]["generated"]["ap50"].keys() == {"overall", "0-30", "30-50", "50-100"}
    assert (root / "artifacts" / "fusion" / "models" / "oracle-v2xvit.pt").is_file()


def test_generated_rows_are_skipped_without_generated_data(project, tmp_path):
    root, cfg = project
    shutil.copytree(root / "data" / "sim", tmp_path / "data" / "sim")
    cfg = dataclasses.replace(cfg, methods=("none", "early"))
    bench = F.Benchmark(cfg, F.Roots.from_config(cfg, tmp_path), tmp_path / "out")
    table2 = F.oracle_vs_generated(bench)
    assert "does not exist" in table2["early"]["generated"]["skipped"]
    table3 = F.pretrain_finetune(bench)
    assert "skipped" in table3["early"]["colwaymo"] and _valid(table3["early"]["source"]["all"])
    results = {**F.summarize(bench, table2, table3, F.robustness(bench)), "seconds_total": 1.0,
               "seconds_training": 0.5}
    assert "## Skipped" in R.report_markdown(results, cfg)


def test_training_resumes_from_its_last_checkpoint(project, tmp_path):
    root, cfg = project
    cfg = dataclasses.replace(cfg, batch_size=2)
    inputs = F.Inputs(list(FusionDataset(root / "data" / "sim" / "real_cav" / "train",
                                         lidar_range=cfg.detector.lidar_range)), cfg)
    whole = F.train("attfuse", cfg, inputs, steps=3, out=tmp_path, name="run")
    ckpts = checkpoints(next((tmp_path / "checkpoints" / "run").iterdir()))
    assert [s for s, _ in ckpts] == [2, 3]
    ckpts[-1][1].unlink()                                        # as if killed after step 2
    resumed = F.train("attfuse", cfg, inputs, steps=3, out=tmp_path, name="run")
    for (k, a), b in zip(whole.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.allclose(a.float(), b.float(), atol=1e-6), k
    other = F.train("attfuse", dataclasses.replace(cfg, seed=1), inputs, steps=3, out=tmp_path, name="run")
    assert other.key != whole.key


@pytest.mark.parametrize("method", ["early", "attfuse", "v2xvit"])
def test_warm_start_copies_the_single_agent_detector(project, method):
    _, cfg = project
    torch.manual_seed(1)
    single = F.Trained("late", F.build_model("late", cfg), None, "k", 0)
    model = F.build_model(method, cfg)
    F.warm_start(model, single)
    own = model.state_dict()
    for k, v in single.model.detector.state_dict().items():
        name = k if method == "v2xvit" else f"detector.{k}"
        if method == "v2xvit" and k.startswith("head."):
            continue                                   # V2X-ViT's head sits on the transformer: fresh
        assert torch.equal(own[name], v), name


class _PerfectAgents(nn.Module):
    """A 'detector' that outputs, for every agent, exactly its own labels (one sample per batch)."""

    def __init__(self, heads: list[dict]):
        super().__init__()
        self.heads = heads

    def forward(self, pillars, *, agent_mask):
        return self.heads.pop(0)


def _perfect_heads(inputs: F.Inputs, coder) -> list[dict]:
    heads = []
    for s in inputs.samples:
        t = [coder.assign_targets(b) for b in s.agent_boxes]
        h, w, a = t[0]["pos_equal_one"].shape
        heads.append({"psm": torch.stack([(x["pos_equal_one"] * 20 - 10).permute(2, 0, 1) for x in t]),
                      "rm": torch.stack([x["targets"].permute(2, 0, 1) for x in t]),
                      "dm": torch.stack([torch.nn.functional.one_hot(x["dir_targets"], 2).float().view(h, w, 2 * a)
                                         .permute(2, 0, 1) * 10 for x in t])})
    return heads


def test_late_fusion_of_perfect_agents_recovers_the_ego_frame_ground_truth(project):
    """Each agent reports its own labels in its own frame; moved by the sample's transforms they
    must be the fused ground truth. Inverted transforms, or ground truth not in the ego frame,
    break this."""
    root, cfg = project
    samples = list(FusionDataset(root / "data" / "sim" / "real_cav" / "test", lidar_range=cfg.detector.lidar_range))
    assert all(s.num_agents > 1 for s in samples)
    model = F.build_model("late", cfg)
    coder = F.box_coder(cfg, model)

    def predict(samples):
        inputs = F.Inputs(samples, cfg)
        trained = F.Trained("late", _PerfectAgents(_perfect_heads(inputs, coder)), coder, "k", 0)
        return F.predict(trained, inputs, cfg, batch_size=1), inputs

    preds, inputs = predict(samples)
    for (boxes, _), s in zip(preds, samples):              # one box on each gt, nothing else
        iou = rotated_iou_bev(boxes, s.gt_boxes)
        assert len(boxes) == len(s.gt_boxes) and (iou.max(1) > 0.99).all() and (iou.max(0) > 0.99).all()
    assert F.evaluate(preds, inputs)["ap70"]["overall"] > 0.99
    inverted = [dataclasses.replace(s, transforms=np.stack([invert(t) for t in s.transforms])) for s in samples]
    assert F.evaluate(*predict(inverted))["ap50"]["overall"] < 0.8


def test_early_fusion_points_of_other_agents_fall_in_ego_frame_boxes(project):
    root, cfg = project
    inputs = F.Inputs(list(FusionDataset(root / "data" / "sim" / "real_cav" / "test",
                                         lidar_range=cfg.detector.lidar_range)), cfg)
    hits, misses = 0, 0
    for i, s in enumerate(inputs.samples):
        merged = F.merge_agent_points(s.clouds, s.transforms)
        assert len(inputs.pillars(i, -1)["voxel_coords"]) > len(inputs.pillars(i, 0)["voxel_coords"])
        start = len(s.clouds[0])
        grown = s.gt_boxes + [0, 0, 0, 0.2, 0.2, 0.2, 0]
        for k in range(1, s.num_agents):
            part = merged[start:start + len(s.clouds[k])]
            start += len(s.clouds[k])
            hits += int(points_in_boxes(part, grown).any(1).sum())
            wrong = transform_points(invert(s.transforms[k]), s.clouds[k])
            misses += int(points_in_boxes(wrong, grown).any(1).sum())
    assert hits > 200 and hits > 10 * misses


def test_quantization_is_exact_at_high_bit_widths_and_coarse_at_low():
    x = torch.randn(2, 3, 5, 6)
    fine = F.quantize(x, 16, (2, 3))
    assert (fine - x).abs().max() <= (x.amax((2, 3)) - x.amin((2, 3))).max() / (2 ** 16 - 1)
    coarse = F.quantize(x, 2, (2, 3))
    assert all(len(torch.unique(coarse[b, c])) <= 4 for b in range(2) for c in range(3))
    assert torch.allclose(coarse.amin((2, 3)), x.amin((2, 3))) and torch.allclose(coarse.amax((2, 3)), x.amax((2, 3)))


@pytest.mark.parametrize("override, field", [
    ({"methods": ["late", "late"]}, "fusion.methods"),
    ({"methods": ["cobevt"]}, "fusion.methods[0]"),
    ({"detector": {"lidar_range": [-50.0, -25.6, -3.0, 51.2, 25.6, 1.0]}}, "fusion.detector.lidar_range"),
    ({"robustness": {"delay_ms": [0, 150]}}, "fusion.robustness.delay_ms"),
    ({"finetune_scenes": [0]}, "fusion.finetune_scenes"),
    ({"score_threshold": 1.5}, "fusion.score_threshold"),
])
def test_bad_fusion_params_fail_at_load(override, field):
    with pytest.raises(TypError) as err:
        config_from_dict({"fusion": override})
    assert err.value.field == field
