"""Stage ``fusion`` end to end on a few small simulated scenarios (tasks/fusion.py and friends)."""
from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from models.fusion import METHODS, FusionModule, LateFusion
from tasks import fusion as F
from tasks import fusion_report as R
from tasks.fusion_batch import Inputs
from tasks import fusion_score
from tasks.fusion_score import Scorer, fill_tables
from tasks.fusion_train import Trained, box_coder, build_model
from typ.config import config_from_dict
from typ.errors import TypError
from typ.formats.opv2v import list_scenarios, read_scene, write_scene
from typ.sim import simulate_scenario

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SMALL = {"methods": list(METHODS),
         "detector": {"lidar_range": [-76.8, -25.6, -3.0, 76.8, 25.6, 1.0], "voxel_size": 0.8,
                      "max_points_per_pillar": 8, "max_pillars": 6000, "pillar_channels": 8,
                      "num_filters": [8, 16], "num_upsample_filters": [8, 8]},
         "v2xvit": {"dim": 8, "heads": 1, "dim_head": 8, "window_sizes": [4], "window_heads": [1],
                    "window_dim_heads": [8], "mlp_dim": 8},
         "robustness": {"position_std": [0.0, 0.4], "heading_std_deg": [0.0, 0.8], "delay_ms": [0, 100],
                        "quantization_bits": [8, 2]},
         "steps": 2, "pretrain_steps": 2, "warm_start_steps": 1, "checkpoint_every": 1,
         "pretrain_sources": ["colwaymo", "source", "both"], "finetune_scenes": [1], "seeds": 2, "bootstrap": 50}
BAND_NAMES = ("overall", "0-30", "30-50", "50-100")


def _simulate(folder, domain: str, seed: int, agents: int, azimuth: float = 1.5, frames: int = 3) -> None:
    for scene in simulate_scenario(domain=domain, seed=seed, n_frames=frames, n_agents=agents,
                                   azimuth_step_deg=azimuth, scenario=f"{domain}_{seed:04d}"):
        write_scene(scene, folder)


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """data/sim with real_cav train (2 scenarios) / test (2), source train (1); data/generated with
    real_cav/train (cooperating clouds thinned and jittered: a stand-in for TYP's) and
    target/pretrain (ColWaymo)."""
    root = tmp_path_factory.mktemp("fusion")
    sim, gen = root / "data" / "sim", root / "data" / "generated"
    for seed in (1, 2):
        _simulate(sim / "real_cav" / "train", "real_cav", seed, 3, frames=2)
    for seed in (3, 6):
        _simulate(sim / "real_cav" / "test", "real_cav", seed, 3)
    _simulate(sim / "source" / "train", "source", 4, 2, azimuth=3.0, frames=2)
    _simulate(gen / "target" / "pretrain", "target", 5, 2, azimuth=3.0, frames=2)
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


@pytest.fixture(scope="module")
def stage(project):
    """The stage's work as the flow does it: every run trained for both seeds, every table scored."""
    root, cfg = project
    bench = F.Benchmark(cfg, F.Roots.from_config(cfg, root), root / "artifacts" / "fusion")
    bench.train_all()
    return bench, fusion_score.score_benchmark(bench)


def _numbers(cell) -> bool:
    """Every band of AP@0.5 and AP@0.7 a number in [0, 1] inside its interval."""
    return all(cell[k][b] is not None and 0.0 <= cell[k][b]["low"] <= cell[k][b]["value"] <= cell[k][b]["high"] <= 1.0
               for k in ("ap50", "ap70") for b in BAND_NAMES)


def test_the_test_split_has_vehicles_in_every_band(stage):
    _, results = stage
    assert results["test_scenarios"] == 2 and results["test_frames"] == 6
    assert all(n > 0 for n in results["test_gt_boxes_by_band"].values()), results["test_gt_boxes_by_band"]


def test_every_oracle_and_generated_cell_holds_a_number(stage, project):
    root, cfg = project
    bench, results = stage
    t1 = results["tables"]["table1"]
    assert list(t1) == list(METHODS)
    assert set(t1["none"]) == {"ego"} and all(set(t1[m]) == {"oracle", "generated"} for m in list(METHODS)[1:])
    for method, row in t1.items():
        for data, cell in row.items():
            assert _numbers(cell), (method, data, cell)
            assert len(cell["per_seed"]) == 2 and len(cell["pr"]["recall"]) == len(cell["pr"]["precision"])
            for key in ("ap50_global", "ap70_global"):      # ranked over all frames: overall only
                g = cell[key]
                assert set(g) == {"overall"} and 0.0 <= g["overall"]["low"] <= g["overall"]["value"] <= 1.0
    # each fusion method's paired difference to no fusion: its value is the two cells' difference
    assert set(results["differences"]) == set(list(METHODS)[1:])
    for method, d in results["differences"].items():
        assert set(d) == {"overall", "50-100", "overall_global"}
        for name, key, band in (("overall", "ap50", "overall"), ("50-100", "ap50", "50-100"),
                                ("overall_global", "ap50_global", "overall")):
            expected = t1[method]["oracle"][key][band]["value"] - t1["none"]["ego"][key][band]["value"]
            assert d[name]["value"] == pytest.approx(expected, abs=2e-4), (method, name)
            assert d[name]["low"] <= d[name]["value"] <= d[name]["high"]
    assert "ap50_global" not in results["tables"]["table3"]["late"]["scratch"]["1"]
    t3 = results["tables"]["table3"]
    for method in METHODS:
        assert set(t3[method]) == {"scratch", "colwaymo", "source", "both"}
        assert set(t3[method]["scratch"]) == {"1", "all"}
        assert set(t3[method]["colwaymo"]) == set(t3[method]["source"]) == set(t3[method]["both"]) == {"0", "1", "all"}
        assert all(_numbers(c) for cols in t3[method].values() for c in cols.values())
    # Table 3's paired differences: every pair whose rows were trained, each the two cells' difference
    d3 = results["table3_differences"]
    assert set(d3) == set(METHODS)
    for method, by_pair in d3.items():
        assert set(by_pair) == {"colwaymo-scratch", "source-scratch", "both-scratch", "colwaymo-source", "both-source"}
        for pair, by_column in by_pair.items():
            row, base = pair.split("-")
            assert set(by_column) == set(t3[method][row]) & set(t3[method][base]), (method, pair)
            for column, iv in by_column.items():
                expected = (t3[method][row][column]["ap50"]["overall"]["value"]
                            - t3[method][base][column]["ap50"]["overall"]["value"])
                assert iv["value"] == pytest.approx(expected, abs=2e-4), (method, pair, column)
                assert iv["low"] <= iv["value"] <= iv["high"]
    # scratch on all scenes is the oracle run itself; no and late fusion one network
    assert t3["late"]["scratch"]["all"]["ap50"] == t1["late"]["oracle"]["ap50"]
    assert "scratchall-late" not in bench.plan.runs and "oracle-none" not in bench.plan.runs
    # one pre-training per (source, network) serves every fine-tuning size
    for source in ("colwaymo", "source", "both"):
        pre = [r for r in bench.plan.runs.values() if r.name.startswith(f"pretrain-{source}-")]
        assert sorted(r.method for r in pre) == sorted(["late", "early", "attfuse", "v2xvit"])
        assert {r.data for r in pre} == {source}
    _check_table3_budgets(bench.plan, cfg)
    # warm start: AttFuse began from the single-agent detector of the same data, then trained on
    assert bench.plan.runs["oracle-attfuse"].warm == "oracle-late"
    assert [t.steps for t in bench.networks["oracle-attfuse"]] == [cfg.warm_start_steps] * 2
    assert [t.seed for t in bench.networks["oracle-late"]] == [0, 1]
    for run in bench.plan.runs:
        for seed in (0, 1):
            assert (bench.model_folder(run, seed) / "model.safetensors").is_file()
    saved = [p for p in (root / "artifacts" / "fusion" / "models").rglob("*") if p.is_file()]
    assert {p.name for p in saved} == {"model.safetensors", "config.json"}           # never a pickle


def test_robustness_is_scored_on_the_same_frames_with_the_delay_applied(stage):
    _, results = stage
    rob = results["robustness"]
    assert rob["applied_delay_ms"] == [0.0, 100.0]
    assert rob["delay_frames_scored"] == 4                      # frames 1, 2 of both test scenarios
    for method, entry in rob["methods"].items():
        for sweep in rob["levels"]:
            assert len(entry[sweep]) == 2 and all(c["ap50"]["overall"] is not None for c in entry[sweep])
    quant = rob["methods"]["attfuse"]["quantization"]
    assert [q["bits"] for q in quant] == [32, 8, 2]
    assert quant[0]["bytes_per_message"] > quant[1]["bytes_per_message"] > quant[2]["bytes_per_message"] > 0
    assert rob["methods"]["none"]["bytes_per_message"] == 0
    assert rob["methods"]["early"]["bytes_per_message"] > rob["methods"]["attfuse"]["bytes_per_message"] / 100


def test_report_and_metrics(stage, project):
    root, cfg = project
    bench, results = stage
    results = {**results, "seconds_total": 1.0, "seconds_training": 0.5}
    paths = R.write_report(results, cfg, root / "reports")
    assert [p.name for p in paths] == ["fusion.md", "fusion_pr.png", "fusion_robustness.png"]
    assert all(p.stat().st_size > 0 for p in paths)
    text = paths[0].read_text()
    assert "TYP Tables 1–2" in text and "TYP Table 3" in text and "V2X-ViT" in text and "Skipped" not in text
    assert "applied" in text and "[" in text
    # the stand-in generated scenarios carry no manifest: the generator's sample alone
    assert results["generated_compose"] == ["generated"] and "`generate.compose` = generated (TYP's sample" in text
    manifest = next(iter(list_scenarios(bench.roots.generated_cavs))) / "_typ.json"
    manifest.write_text(json.dumps({"compose": "hybrid"}))
    try:
        assert F.generated_compose(bench.roots.generated_cavs) == ["generated", "hybrid"]
    finally:
        manifest.unlink()
    # the same curves as dvc plots data: PR on a recall grid, AP against each sweep, one column per method
    tables = {p.name: p.read_text().splitlines() for p in R.write_plot_data(results, root / "reports" / "plots")}
    assert sorted(tables) == sorted(["fusion_bits.csv", "fusion_delay.csv", "fusion_heading_std.csv", "fusion_pr.csv",
                                     "fusion_position_std.csv"])
    pr = [line.split(",") for line in tables["fusion_pr.csv"]]
    assert pr[0] == ["recall", *(f"{m}_{d}" for m, d in R.TABLE1_COLUMNS)] and len(pr) == 102
    for col, (m, d) in enumerate(R.TABLE1_COLUMNS, start=1):
        curve = (results["tables"]["table1"].get(m, {}).get(d) or {}).get("pr") or {"recall": [], "precision": []}
        values = [float(r[col]) for r in pr[1:] if r[col]]
        assert len(values) == sum(k / 100 <= max(curve["recall"], default=-1) + 1e-12 for k in range(101)), (m, d)
        assert values == sorted(values, reverse=True) and values[:1] == [max(curve["precision"], default=0)][:len(values)]
    # OpenCOOD's interpolation: the best precision at a recall at least as high; none past the last
    assert R._interpolated_precision({"recall": [0.2, 0.5, 0.8], "precision": [1.0, 0.6, 0.7]}, 0.3) == 0.7
    assert R._interpolated_precision({"recall": [0.2, 0.5, 0.8], "precision": [1.0, 0.6, 0.7]}, 0.9) is None
    delay = [line.split(",") for line in tables["fusion_delay.csv"]]
    assert delay[0] == ["delay_ms", *METHODS] and [float(r[0]) for r in delay[1:]] == results["robustness"]["applied_delay_ms"]
    late = [m["ap50"]["overall"]["value"] for m in results["robustness"]["methods"]["late"]["delay_ms"]]
    assert [float(r[delay[0].index("late")]) for r in delay[1:]] == late
    loss = F.write_loss_curve(bench, root / "loss.csv").read_text().splitlines()
    assert loss[0] == "step,oracle,generated"
    assert [int(r.split(",")[0]) for r in loss[1:]] == [row["step"] for row in bench.networks["oracle-late"][0].curve]
    metrics = json.loads(json.dumps(R.metrics_of(results)))
    assert metrics["table1"]["attfuse"]["generated"]["ap50"].keys() == set(BAND_NAMES)
    assert set(metrics["targets"]) >= {"no_fusion_ap50", "beats_no_fusion", "v2xvit_ge_late", "generated_over_oracle",
                                       "beats_no_fusion_global_sort", "difference_above_zero"}
    assert metrics["differences"] == results["differences"]
    assert "global_sort_detections" in text and "| Method | Δ all | Δ 50–100 m | Δ all, global |" in text
    curves = bench.curves()
    assert set(curves) == set(bench.plan.runs) and all(set(c) == {"0", "1"} for c in curves.values())


def test_networks_load_back_as_saved(stage, project):
    root, cfg = project
    bench, _ = stage
    loaded = F.load_networks(cfg, bench.roots, bench.out)
    batch = bench.test_inputs().batch("v2xvit", [0])
    with torch.no_grad():
        a = batch.run(bench.networks["oracle-v2xvit"][1].model)
        b = batch.run(loaded["oracle-v2xvit"][1].model)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_trainings_on_two_processes_give_the_bytes_of_one(project, tmp_path):
    # the plan's runs on two spawned workers, each started when its warm-start / pre-trained
    # network is saved, write the same networks byte for byte as the trainings one after another
    root, cfg = project
    cfg = dataclasses.replace(cfg, methods=("none", "late", "attfuse"), seeds=1, steps=3, pretrain_steps=2)
    roots = F.Roots.from_config(cfg, root)
    saved = {}
    for workers in (1, 2):
        c = dataclasses.replace(cfg, processes=workers)
        assert F.training_processes(c) == workers
        bench = F.Benchmark(c, roots, tmp_path / f"w{workers}")
        bench.train_all()
        files = sorted((bench.out / "models").rglob("model.safetensors"))
        saved[workers] = {str(p.relative_to(bench.out)): p.read_bytes() for p in files}
        assert set(bench.seconds) == set(bench.plan.runs) and len(files) == len(bench.plan.runs)
        assert all(t.curve for nets in bench.networks.values() for t in nets)
    assert any(r.warm for r in bench.plan.runs.values()) and any(r.init for r in bench.plan.runs.values())
    assert saved[1] == saved[2]


def test_the_pool_starts_the_longest_chain_first(project):
    """steps_left: a run's steps plus the longest chain of runs fine-tuned or warm-started from it,
    so tiny's Table 3 chain (pre-train 400 -> fine-tune on all scenes 2000 -> AttFuse 200) goes
    before Table 1's oracle (2000 -> 200), and a leaf counts only itself."""
    root, cfg = project
    cfg = dataclasses.replace(cfg, methods=("none", "late", "attfuse"), seeds=1, steps=2000, pretrain_steps=400,
                              warm_start_steps=200, finetune_scenes=(1,), pretrain_sources=("colwaymo",))
    roots = F.Roots.from_config(cfg, root)
    bench = F.Benchmark(cfg, roots, root / "unused")
    jobs = [F.Job(run, 0, bench.out) for run in bench.plan.runs.values()]
    left = dict(zip([j.run.name for j in jobs], F.steps_left(jobs)))
    n_all = len(list_scenarios(roots.real_train))
    one = F.subset_steps(2000, 1, n_all) + F.subset_steps(200, 1, n_all)
    assert left["oracle-attfuse"] == 200 and left["oracle-late"] == 2200
    assert left["finetuneall-colwaymo-late"] == 2200
    assert left["pretrain-colwaymo-late"] == 400 + max(2200, one, 200)
    assert left["pretrain-colwaymo-late"] > left["oracle-late"]
    assert max(left, key=left.get) == "pretrain-colwaymo-late"


def test_bad_worker_count_fails_at_load():
    with pytest.raises(TypError) as err:
        config_from_dict({"fusion": {"processes": -1}})
    assert err.value.field == "fusion.processes"


class _PerfectAgents(FusionModule):
    """A stand-in network that outputs exactly what its method learns from: for ``own`` targets
    every agent's own labels in its own frame, for ``fused`` the fused ground truth; the sample
    is recognised by the pillars of its first cloud."""

    def __init__(self, method: str, inputs: Inputs, coder):
        super().__init__()
        self.method, self.samples, self.coder = method, inputs.samples, coder
        self.feature_stride = 2
        self.index = {self._key(inputs.batch(method, [i]).pillars, 0): i for i in range(len(inputs))}

    @staticmethod
    def _key(pillars, b: int) -> bytes:
        sel = pillars["voxel_coords"][:, 0] == b
        return pillars["voxel_coords"][sel, 2:].numpy().tobytes()

    def _heads(self, boxes) -> dict:
        t = self.coder.assign_targets(boxes)
        h, w, a = t["pos_equal_one"].shape
        return {"psm": (t["pos_equal_one"] * 20 - 10).permute(2, 0, 1), "rm": t["targets"].permute(2, 0, 1),
                "dm": torch.nn.functional.one_hot(t["dir_targets"], 2).float().view(h, w, 2 * a).permute(2, 0, 1) * 10}

    def forward(self, pillars, *, agent_mask, transforms=None, time_delay=None, agent_types=None):
        b, width = agent_mask.shape
        rows = []
        for k in range(b):
            s = self.samples[self.index[self._key(pillars, k * width)]]
            if METHODS[self.method].targets == "own":
                rows += [self._heads(s.agent_boxes[slot]) for slot in range(width) if agent_mask[k, slot]]
            else:
                rows.append(self._heads(s.gt_boxes))
        return {key: torch.stack([r[key] for r in rows]) for key in rows[0]}

    def detections(self, output, coder, *, agent_mask, transforms, score_threshold, max_boxes):
        if METHODS[self.method].targets == "own":
            return LateFusion.boxes_in_ego(output, coder, agent_mask=agent_mask, transforms=transforms,
                                           score_threshold=score_threshold, max_boxes_per_agent=max_boxes)
        return super().detections(output, coder, agent_mask=agent_mask, transforms=transforms,
                                  score_threshold=score_threshold, max_boxes=max_boxes)


class _PerfectTrained(Trained):
    def as_method(self, method: str) -> Trained:
        return Trained(method, _PerfectAgents(method, self.inputs, self.coder), self.coder, "perfect", 0)


def test_the_tables_of_perfect_agents_score_one(stage, project):
    """Run the stage's tables with networks that output their labels: AP@0.5 and AP@0.7 overall
    must be 1 in every cell of a method that hears the other agents. Ground truth in the wrong
    frame, boxes moved the wrong way, a cell scored on the wrong run or frames dropped would not
    give 1. No fusion's labels are the ego's, which never hold its own car: the fused ground
    truth does wherever another agent labels it (OpenCOOD's convention), so its AP is exactly
    the share of the other vehicles (precision 1 throughout)."""
    root, cfg = project
    bench, _ = stage
    test = bench.test_inputs()
    coder = box_coder(cfg, build_model("late", cfg))
    perfect = _PerfectTrained("late", None, coder, "perfect", 0)
    perfect.inputs = test
    scorer = Scorer(cfg, bench.test, {run: [perfect] * 2 for run in bench.plan.runs})
    tables = fill_tables(scorer, bench.plan.cells)
    cells = [(t, m, r, c) for t, rows in tables.items() for m, row in rows.items() for r, c in row.items()]
    assert len(cells) == len(list(METHODS)) * (1 + 1 + 4) - 1    # table1: ego/oracle + generated; table3: 4 rows
    gts = [s.gt_boxes for s in test.samples]
    own_car = sum(int((np.abs(g[:, :2]).max(1) < 1.0).sum()) for g in gts)
    assert own_car > 0
    ego_only = 1.0 - own_car / sum(len(g) for g in gts)
    for table, method, row, cell in cells:
        for c in ([cell] if table == "table1" else cell.values()):
            expected = round(ego_only, 4) if method == "none" else 1.0
            assert c["ap50"]["overall"]["value"] == expected and c["ap70"]["overall"]["value"] == expected, \
                (table, method, row)
            assert method == "none" or c["ap50"]["overall"]["low"] == 1.0
            if table == "table1":     # precision 1 everywhere: the ranking cannot matter
                assert c["ap50_global"]["overall"]["value"] == expected, (method, row)


def _check_table3_budgets(plan: F.Plan, cfg) -> None:
    """Table 3's arms differ only in where they start (TYP §4.5): each fine-tuned run trains the steps
    its scratch run on the same scenes trains; the single-agent detector starts from its own
    pre-training, the warm-started methods from the fine-tuned detector, as scratch's from scratch's."""
    runs = plan.runs
    tuned = [r for r in runs.values() if r.name.startswith("finetune")]
    assert tuned
    for run in tuned:
        ft, source, network = run.name[len("finetune"):].split("-")
        twin = runs["oracle-" + network if ft == "all" else f"scratch{ft}-{network}"]
        assert (run.steps, run.data) == (twin.steps, twin.data), run.name
        if twin.warm is None:
            assert (run.init, run.warm) == (f"pretrain-{source}-{network}", None), run.name
        else:
            assert (run.init, run.warm) == (None, f"finetune{ft}-{source}-{runs[twin.warm].method}"), run.name
    assert {r.init for r in tuned} - {None} <= {r.name for r in runs.values() if r.name.startswith("pretrain")}


def test_table3_fine_tunes_with_scratch_budget_on_the_same_scenes(monkeypatch):
    """tiny's plan on 12 training scenarios: on n of them every run trains n / 12 of its full steps,
    fine-tuned or from scratch (a fine-tuning budget of 1/20 of scratch's left every pre-trained
    detector near AP 0, all scenes included)."""
    cfg = config_from_dict({"profile": "tiny"}).fusion
    monkeypatch.setattr(F, "list_scenarios", lambda folder: [f"s{i}" for i in range(12)])
    monkeypatch.setattr(F, "unavailable", lambda folder: None)
    plan = F.plan(cfg, F.Roots.from_config(cfg, Path("/nonexistent")))
    assert plan.finetune_sets == {"0": 0, "1": 1, "5": 5, "all": None}
    _check_table3_budgets(plan, cfg)
    steps = {name: run.steps for name, run in plan.runs.items()}
    assert steps["finetune1-colwaymo-late"] == steps["scratch1-late"] == round(cfg.steps / 12)
    assert steps["finetune5-source-late"] == steps["scratch5-late"] == round(cfg.steps * 5 / 12)
    assert steps["finetuneall-colwaymo-late"] == steps["oracle-late"] == cfg.steps
    assert steps["finetune5-colwaymo-attfuse"] == steps["scratch5-attfuse"] == round(cfg.warm_start_steps * 5 / 12)
    assert steps["pretrain-colwaymo-late"] == cfg.pretrain_steps
    assert [F.subset_steps(100, n, 7) for n in (None, 7, 1, 0)] == [100, 100, 14, 1]


def test_both_pretrains_on_the_generated_target_and_the_source_together(project):
    # one training set of the generated target's frames (cooperating labels cut to the generated
    # extent, as when it is read alone) followed by the source's, each sample as read on its own
    root, cfg = project
    roots = F.Roots.from_config(cfg, root)
    parts = [F.read_inputs(cfg, roots, data).samples for data in ("colwaymo", "source")]
    both = F.read_inputs(cfg, roots, "both").samples
    assert len(both) == sum(map(len, parts)) and min(map(len, parts)) > 0
    for a, b in zip(both, parts[0] + parts[1]):
        assert (a.scenario, a.timestamp, a.agent_ids) == (b.scenario, b.timestamp, b.agent_ids)
        assert np.array_equal(a.gt_boxes, b.gt_boxes) and all(np.array_equal(x, y) for x, y in zip(a.clouds, b.clouds))
    assert {s.scenario.split("_")[0] for s in both} == {"target", "source"}


def test_generated_rows_are_skipped_without_generated_data(project, tmp_path):
    root, cfg = project
    shutil.copytree(root / "data" / "sim", tmp_path / "data" / "sim")
    cfg = dataclasses.replace(cfg, methods=("none", "early"), seeds=1)
    plan = F.plan(cfg, F.Roots.from_config(cfg, tmp_path))
    assert "does not exist" in plan.skipped["table1/generated"] and "table3/colwaymo" in plan.skipped
    assert plan.skipped["table3/both"].startswith("colwaymo: ") and "does not exist" in plan.skipped["table3/both"]
    assert {c.row for c in plan.cells if c.table == "table3"} == {"source", "scratch"}
    assert {c.row for c in plan.cells if c.table == "table1"} == {"ego", "oracle"}
    text = R.report_markdown({"tables": {}, "robustness": {"levels": {}, "methods": {}, "applied_delay_ms": [],
                                                            "delay_frames_scored": 0},
                              "skipped": plan.skipped, "finetune_sets": {}, "test_frames": 1, "test_scenarios": 1,
                              "test_gt_boxes": 1, "test_gt_boxes_by_band": {}, "train_frames": 1,
                              "train_scenarios": 1, "runs": 1, "seeds": 1, "trainings": 1, "seconds_total": 1,
                              "seconds_training": 1}, cfg)
    assert "## Skipped" in text and "does not exist" in text


@pytest.mark.parametrize("override, field", [
    ({"methods": ["late", "late"]}, "fusion.methods"),
    ({"methods": ["cobevt"]}, "fusion.methods[0]"),
    ({"detector": {"lidar_range": [-50.0, -25.6, -3.0, 51.2, 25.6, 1.0]}}, "fusion.detector.lidar_range"),
    ({"robustness": {"delay_ms": [0, 150]}}, "fusion.robustness.delay_ms"),
    ({"finetune_scenes": [0]}, "fusion.finetune_scenes[0]"),
    ({"score_threshold": 1.5}, "fusion.score_threshold"),
    ({"pretrain_sources": ["both", "both"]}, "fusion.pretrain_sources"),
    ({"pretrain_sources": ["opv2v"]}, "fusion.pretrain_sources[0]"),
    ({"augment": {"scale": [1.1, 0.9]}}, "fusion.augment.scale"),
    ({"seeds": 0}, "fusion.seeds"),
    ({"lr_schedule": "step"}, "fusion.lr_schedule"),
])
def test_bad_fusion_params_fail_at_load(override, field):
    with pytest.raises(TypError) as err:
        config_from_dict({"fusion": override})
    assert err.value.field == field


def test_config_names_come_from_the_registry():
    # paper runs every registered method, in the registry's order; tiny (and small, which keeps tiny's fusion) a subset of it
    for profile in ("paper",):
        assert config_from_dict({"profile": profile}).fusion.methods == tuple(METHODS)
    tiny = config_from_dict({}).fusion.methods
    assert list(tiny) == [m for m in METHODS if m in tiny] and {"none", "late"} <= set(tiny)
    assert [m.display for m in METHODS.values()] == ["No Fusion", "Early Fusion", "Late Fusion", "AttFuse", "V2X-ViT"]


def test_a_listed_fine_tuning_size_equal_to_the_whole_set_is_the_all_column(monkeypatch):
    """finetune_scenes [1, 12] on 12 training scenarios: 12 of 12 is "all" (Table 1's oracle for
    scratch, the full budget), not a second column of the same runs on ``real-12``; a size past
    the set is no column either."""
    cfg = config_from_dict({"profile": "tiny", "fusion": {"finetune_scenes": [1, 12, 30]}}).fusion
    monkeypatch.setattr(F, "list_scenarios", lambda folder: [f"s{i}" for i in range(12)])
    monkeypatch.setattr(F, "unavailable", lambda folder: None)
    plan = F.plan(cfg, F.Roots.from_config(cfg, Path("/nonexistent")))
    assert plan.finetune_sets == {"0": 0, "1": 1, "all": None}
    assert {r.data for r in plan.runs.values()} == {"real", "real-1", *cfg.pretrain_sources, "generated"}
    assert {c.column for c in plan.cells if c.table == "table3"} == {"0", "1", "all"}
    _check_table3_budgets(plan, cfg)
    steps = {name: run.steps for name, run in plan.runs.items()}
    assert steps["finetuneall-colwaymo-late"] == steps["oracle-late"] == cfg.steps
