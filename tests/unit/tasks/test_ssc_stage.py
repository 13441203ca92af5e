"""The ssc stage's tasks on small simulated scenarios: maps beside the clouds, training of every
network, prediction by every method, pooled scores and their intervals, resume, the report."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from models.fusion import NoFusion, build
from models.ssc import ssc_detector
from tasks import ssc as S
from tasks import ssc_report
from tasks import ssc_train as T
from tasks.simulate import ScenarioJob
from tasks.training import seed_everything
from typ.config import config_from_dict
from typ.errors import TypError
from typ.metrics.ssc import ssc_iou

NETWORK = {"layer_nums": [1, 1, 1], "num_filters": [8, 8, 8], "num_upsample_filters": [8, 8, 8],
           "pillar_channels": 8, "head_hidden": 8, "max_pillars": 16384}
V2XVIT = {"dim": 8, "depth": 1, "heads": 2, "dim_head": 4, "window_sizes": [4, 8], "window_heads": [1, 1],
          "window_dim_heads": [4, 4], "mlp_dim": 8, "dropout": 0.0,
          "shrink_stride": 2}    # OpenCOOD's shrink (tiny keeps stride 1: tests/unit/models/test_fusion.py covers that)
METHODS = ["none", "early", "late", "attfuse", "v2xvit"]     # every method, whatever the profile runs


def _block(tmp_path, **changes):
    over = {"ssc": {"network": NETWORK, "v2xvit": V2XVIT, "methods": METHODS, "steps": 6, "warm_start_steps": 2,
                    "bootstrap": 20, "lr": 5e-3,
                    "robustness": {"position_std": [0.0, 0.4], "heading_std_deg": [0.0], "delay_ms": [0, 100],
                                   "quantization_bits": [4]},
                    "noisy": {"position_std": 0.2, "heading_std_deg": 0.2, "delay_ms": 100}, **changes}}
    block = config_from_dict(over).ssc
    return dataclasses.replace(block, out=str(tmp_path / "artifacts" / "ssc"), reports=str(tmp_path / "reports"))


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("ssc")
    for split, seed in (("train", 11), ("test", 12)):
        job = ScenarioJob(domain="real_cav", split=split, index=0, seed=seed, n_agents=2, n_frames=2,
                          azimuth_step_deg=1.0, comm_range=70.0, dt=0.1)
        folder = root / "data" / "sim" / "real_cav" / split / job.name
        folder.mkdir(parents=True)
        job.write(folder)
    return root


@pytest.fixture(scope="module")
def trained(root, tmp_path_factory):
    block = _block(tmp_path_factory.mktemp("out"))
    data = S.TrainingSet.read(S.ssc_dataset(root / "data/sim/real_cav/train"))
    weights = S.class_weights(data.class_counts(), eps=block.class_weight_eps)
    return block, data, weights, S.train_seed(block, data, weights, 0, root / block.out, log=lambda m: None)


def test_training_set_holds_every_agent_view_and_the_ego_maps(root):
    ds = S.ssc_dataset(root / "data/sim/real_cav/train")
    data = S.TrainingSet.read(ds)
    assert len(ds) == 2 and len(data.samples) == 2 and len(data.views) == sum(len(s.clouds) for s in data.samples)
    for (cloud, labels), (c2, m2) in zip(data.views[:2], zip(ds[0].clouds, S.sample_maps(ds, 0))):
        assert cloud is c2 or np.array_equal(cloud, c2)
        assert np.array_equal(labels, m2) and labels.shape == (128, 128, 20)
    assert np.array_equal(data.ego_maps[0], S.ego_map(ds, 0, ds[0]))
    counts = data.class_counts()
    assert counts.sum() == len(data.views) * 128 * 128 * 20 and (counts[1:] > 0).sum() >= 3
    assert S.TrainingSet.read(ds).key == data.key  # a content key, the same on a second read


def test_every_network_trains_and_every_method_predicts(trained, root):
    block, data, _, nets = trained
    assert set(nets.networks) == {"single", "early", "attfuse", "v2xvit"}
    for name, losses in nets.losses.items():
        steps = block.steps if name == "single" else block.warm_start_steps
        assert len(losses) == steps and np.isfinite(losses).all(), name
    assert np.mean(nets.losses["single"][-2:]) < np.mean(nets.losses["single"][:2])
    test = S.ssc_dataset(root / "data/sim/real_cav/test")
    for method in block.methods:
        pred = S.predict(nets, test[0], method)
        assert pred.shape == (128, 128, 20) and pred.dtype == np.uint8 and pred.max() < 7, method
    # late fusion of the ego alone is no fusion
    solo = S.ssc_dataset(root / "data/sim/real_cav/test", max_agents=1)
    assert np.array_equal(S.predict(nets, solo[0], "late"), S.predict(nets, solo[0], "none"))
    with pytest.raises(TypError, match="method"):
        S.predict(nets, test[0], "cobevt")


def test_v2xvit_runs_its_configured_transformer_with_an_occupancy_head(trained, root):
    """V2X-ViT's network is the registry's module with the ``ssc.v2xvit`` block's transformer, the
    single-agent backbone copied in, and an occupancy head on the transformer's width and stride."""
    from models.fusion import V2XViT
    from models.ssc import OccupancyHead

    block, _, _, nets = trained
    module, single = nets.networks["v2xvit"], nets.networks["single"].detector
    assert type(module) is V2XViT and module.dim == V2XVIT["dim"] and len(module.layers) == V2XVIT["depth"]
    assert isinstance(module.head, OccupancyHead) and module.head.up[0].in_channels == V2XVIT["dim"]
    assert module.feature_stride == 2 * single.feature_stride and module.head.up[0].stride == (4, 4)
    test = S.ssc_dataset(root / "data/sim/real_cav/test")
    pillars, kw = T._inputs(single, "v2xvit", test[0])
    assert module(pillars, **kw)["occ"].shape == (1, 7, 128, 128, 20)
    # fine-tuned from the single-agent network, not from scratch: the backbone moved away from it
    # by a little, the fresh V2X-ViT of the same seed is far further
    fresh = build("v2xvit", ssc_detector(**S.model_kwargs(block)), S.network_options(block, "v2xvit"))
    moved = [(a - b).abs().max().item() for a, b in zip(module.backbone.parameters(), single.backbone.parameters())]
    scratch = [(a - b).abs().max().item() for a, b in zip(fresh.backbone.parameters(), single.backbone.parameters())]
    assert max(moved) < max(scratch)
    assert len(test[0].clouds) == 2
    with S.compressed(module, 2):                  # V2X-ViT sends features: its messages quantise
        coarse = module(pillars, **kw)["occ"]
    assert not torch.equal(coarse, module(pillars, **kw)["occ"])


def test_scores_pool_the_frames_and_the_interval_brackets_them(trained, root):
    _, _, _, nets = trained
    test = S.ssc_dataset(root / "data/sim/real_cav/test")
    conf, info = S.confusions(nets, test, "late")
    assert conf.shape == (1, 7, 7) and info["frames"] == len(test) == 2
    preds = [S.predict(nets, test[i], "late") for i in range(len(test))]
    truth = [S.ego_map(test, i, test[i]) for i in range(len(test))]
    reference = ssc_iou(preds, truth, 7)   # SemanticKITTI pooling, independently of the per-scene sums
    assert conf.sum() == 2 * 128 * 128 * 20 and np.array_equal(conf[0], reference["confusion"])
    figures = S.intervals(np.stack([conf, conf]), n_boot=20)   # two identical seeds: the same figure
    assert figures["iou"]["value"] == pytest.approx(reference["iou"])
    assert figures["miou"]["value"] == pytest.approx(reference["miou"])
    assert figures["iou_car"]["value"] == pytest.approx(reference["iou_per_class"][1])
    for cell in figures.values():
        assert cell["low"] <= cell["value"] + 1e-12 and cell["value"] <= cell["high"] + 1e-12


def test_a_rerun_loads_the_finished_networks_and_a_changed_budget_retrains(trained, root):
    block, data, weights, nets = trained
    said = []
    again = S.train_seed(block, data, weights, 0, root / block.out, log=said.append)
    assert len(said) == 4 and all("loaded" in s for s in said)
    test = S.ssc_dataset(root / "data/sim/real_cav/test")
    for method in block.methods:
        assert np.array_equal(S.predict(again, test[0], method), S.predict(nets, test[0], method)), method
    said.clear()
    more = dataclasses.replace(block, warm_start_steps=block.warm_start_steps + 1)
    S.train_seed(more, data, weights, 0, root / "other", log=said.append)
    assert said == []                                           # nothing stored there: all trained
    S.train_seed(more, data, weights, 0, root / block.out, log=said.append)
    assert len(said) == 1 and "single" in said[0]               # the single-agent network's key is unchanged
    said.clear()
    wider = dataclasses.replace(more, v2xvit=dataclasses.replace(block.v2xvit, mlp_dim=16))
    S.train_seed(wider, data, weights, 0, root / block.out, log=said.append)
    assert len(said) == 3 and not any("v2xvit" in s for s in said)   # only V2X-ViT's key holds its options


def test_the_ratio_interval_pairs_the_scenarios_and_is_one_for_the_same_networks():
    rng = np.random.default_rng(0)
    conf = rng.integers(0, 50, (2, 5, 7, 7))
    same = S.ratio_interval(conf, conf, "miou", n_boot=50)
    assert same == {"value": 1.0, "low": 1.0, "high": 1.0}
    half = conf.copy()
    half[:, :, 1:, 1:] = 0            # nothing right but empty space: every class IoU 0
    assert S.ratio_interval(half, conf, "miou", n_boot=50)["high"] == 0.0
    with pytest.raises(TypError, match="den"):
        S.ratio_interval(conf, conf[:, :4], "miou", n_boot=10)


def test_the_stage_writes_table_i_the_curves_and_the_metrics(root, tmp_path):
    block = _block(tmp_path)
    said = []
    results = S.run_benchmark(block, root, log=said.append)
    assert set(results["tables"]) == {"perfect", "noisy"}      # no generated data under this root
    assert "does not exist" in results["skipped"]["generated"] and any("generated rows" in m for m in said)
    for setting, rows in results["tables"].items():
        assert list(rows) == list(block.methods)
        for method, row in rows.items():
            for f in S.FIGURES:
                cell = row["figures"][f]
                assert 0.0 <= cell["low"] <= cell["high"] <= 1.0 and np.isfinite(cell["value"]), (setting, method, f)
    assert results["tables"]["noisy"]["late"]["frames"] == 1 and results["tables"]["perfect"]["late"]["frames"] == 2
    rob = results["robustness"]
    assert rob["applied_delay_ms"] == [0.0, 100.0] and list(rob["quantization"]) == ["attfuse", "v2xvit"]
    assert all(list(per) == ["4"] for per in rob["quantization"].values())
    # no fusion reads no cooperating agent: flat along every sweep
    flat = [c["miou"]["value"] for c in rob["methods"]["none"]["position_std"]]
    assert flat[0] == flat[1]
    metrics = S.metrics_of(results, 1.0)
    assert set(metrics["targets"]) >= {"none_iou_ge_0.50", "late_beats_none_miou", "attfuse_beats_none_iou"}
    test = S.ssc_dataset(root / "data/sim/real_cav/test")
    preds = {m: S.predict(results["networks"][0], test[0], m) for m in block.methods}
    paths = ssc_report.write_report(results, block, tmp_path / "reports", (S.ego_map(test, 0, test[0]), preds, "t"))
    md = paths[0].read_text()
    for method in block.methods:
        assert md.count(f"| {S.DISPLAY[method]} |") == 2 + 3 + (method in ssc_report.PAPER)
    assert all(p.stat().st_size > 0 for p in paths)


def test_top_class_is_the_highest_occupied_voxel():
    labels = np.zeros((2, 2, 4), np.uint8)
    labels[0, 0, [0, 2]] = [1, 4]      # road under a building: the building
    labels[1, 1, 3] = 6
    assert ssc_report.top_class(labels).tolist() == [[4, 0], [0, 6]]


def test_bad_ssc_params_are_named():
    with pytest.raises(TypError, match="ssc.methods"):
        config_from_dict({"ssc": {"methods": ["cobevt"]}})
    with pytest.raises(TypError, match="ssc.v2xvit"):
        config_from_dict({"ssc": {"v2xvit": {"dim": 7}}})
    with pytest.raises(TypError, match="class_weight_eps"):
        config_from_dict({"ssc": {"class_weight_eps": 1.0}})
    with pytest.raises(TypError, match="ssc.noisy.delay_ms"):
        config_from_dict({"ssc": {"noisy": {"delay_ms": 50}}})


def test_generated_cooperators_identical_to_the_true_ones_give_a_ratio_of_one(root, tmp_path):
    """With "generated" clouds that are byte copies of the true ones, the generated networks are the
    oracle ones retrained from the same seed: the same scores, a ratio of exactly 1."""
    import shutil

    proj = tmp_path / "proj"
    shutil.copytree(root / "data" / "sim", proj / "data" / "sim")
    shutil.copytree(root / "data" / "sim" / "real_cav" / "train", proj / "data" / "generated" / "real_cav" / "train")
    block = _block(tmp_path, generated_views="all",   # every view: the generated arm sees the oracle's data
                   robustness={"position_std": [0.0], "heading_std_deg": [0.0], "delay_ms": [0],
                               "quantization_bits": []})
    logged = []
    results = S.run_benchmark(block, proj, log=lambda m: None, log_fn=lambda values, step: logged.append(values))
    assert sorted(k for d in logged for k in d) == [f"loss_{n}_seed0_last"
                                                    for n in ("attfuse", "early", "single", "v2xvit")]
    gen = results["tables"]["generated"]
    assert list(gen) == ["early", "late", "attfuse", "v2xvit"] and results["skipped"] == {}
    for method, row in gen.items():
        assert row["ratio_miou"]["value"] == 1.0 and row["ratio_iou"]["value"] == 1.0, method
        assert row["figures"]["miou"] == results["tables"]["perfect"][method]["figures"]["miou"], method
    assert (proj / block.out / "models" / "generated" / "attfuse" / "seed_0" / "model.safetensors").is_file()
    metrics = S.metrics_of(results, 1.0)
    assert metrics["targets"]["late_generated_ge_0.85_oracle_miou"] is True
    md = ssc_report.report_markdown(results, block)
    assert "TYP Table 1 for SSC" in md and "| Late Fusion |" in md


def test_the_footprint_is_the_columns_near_the_points():
    one = S.footprint(np.array([[0.1, 0.1, 0.0, 0.5]]))           # column (64, 64), a disc of radius 2
    assert one.sum() == 13 and one[64, 62] and one[65, 65] and not one[66, 65]
    corner = S.footprint(np.array([[-49.9, -49.9, 0.0, 0.5], [60.0, 0.0, 0.0, 0.5]]))   # the second: off the grid
    assert corner.sum() == 6 and corner[0, 2] and corner[1, 1] and not corner[2, 1]
    assert not S.footprint(np.zeros((0, 4))).any()


def test_generated_views_modes_keep_the_ego_views_and_mask_or_drop_the_others(root):
    data = S.TrainingSet.read(S.ssc_dataset(root / "data/sim/real_cav/train"))
    assert data.ego == [j == 0 for s in data.samples for j in range(len(s.clouds))] and not all(data.ego)
    assert data.with_generated_views("all") is data
    ego = data.with_generated_views("ego")
    assert len(ego.views) == len(data.samples) and ego.samples is data.samples
    assert all(c is s.clouds[0] for (c, _), s in zip(ego.views, data.samples))
    fp = data.with_generated_views("footprint")
    assert len(fp.views) == len(data.views) and fp.ego == data.ego
    for (c, m), (c0, m0), e in zip(fp.views, data.views, data.ego):
        assert c is c0
        if e:
            assert m is m0
        else:
            seen = S.footprint(c)
            assert 0 < seen.sum() < seen.size
            assert np.array_equal(m[seen], m0[seen]) and (m[~seen] == S.IGNORE).all()
    assert np.array_equal(fp.class_counts()[1:] <= data.class_counts()[1:], np.ones(6, bool))
    assert len({data.key, ego.key, fp.key}) == 3
    with pytest.raises(TypError, match="generated_views"):
        data.with_generated_views("half")


def test_ignored_voxels_are_left_out_of_the_loss(root):
    """The first logged loss (before any update) equals the class-weighted cross-entropy over the
    voxels not ignored, computed here from a network built the same way."""
    import torch.nn.functional as F

    data = S.TrainingSet.read(S.ssc_dataset(root / "data/sim/real_cav/train"))
    cloud, labels = data.views[1]
    masked = labels.copy()
    masked[:64] = S.IGNORE
    one = S.TrainingSet([(cloud, masked)], data.samples[:1], data.ego_maps[:1], "k", [False])
    weights = np.linspace(0.5, 2.0, 7)
    kw = S.model_kwargs(_block(root))
    _, losses = S.train_single(one, steps=1, seed=3, lr=1e-3, model_kw=kw, weights=weights)
    seed_everything(3)
    model = NoFusion(detector=ssc_detector(**kw)).train()
    with torch.no_grad():
        logits = model(model.detector.pillarize([cloud]), agent_mask=torch.ones(1, 1, dtype=torch.bool))["occ"][0]
    keep = torch.from_numpy(masked != S.IGNORE)
    y = torch.from_numpy(masked.astype(np.int64))[keep]
    nll = -F.log_softmax(logits, 0).permute(1, 2, 3, 0)[keep].gather(1, y[:, None])[:, 0]
    w = torch.tensor(weights, dtype=torch.float32)[y]
    assert losses[0] == pytest.approx(float((w * nll).sum() / w.sum()), rel=1e-5)


def test_arms_trained_on_spawned_processes_are_the_bytes_of_one_thread_in_process(root, tmp_path):
    """train_arms' (arm, seed) pairs on two spawned one-thread workers write the networks that
    train_seed writes in this process, byte for byte (it trains on one thread too)."""
    import shutil

    proj = tmp_path / "proj"
    shutil.copytree(root / "data" / "sim", proj / "data" / "sim")
    shutil.copytree(root / "data" / "sim" / "real_cav" / "train", proj / "data" / "generated" / "real_cav" / "train")
    block = _block(tmp_path, methods=["none", "attfuse"], steps=3, warm_start_steps=1)
    data = S.training_set(block, proj, "oracle")
    weights = S.class_weights(data.class_counts(), eps=block.class_weight_eps)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        said = []
        S.train_arms(block, proj, ["oracle", "generated"], weights, log=said.append)
    finally:
        torch.set_num_threads(threads)
    assert sorted(said) == ["ssc: the networks of generated seed 0 are trained",
                            "ssc: the networks of oracle seed 0 are trained"]
    pooled = proj / block.out / "models"
    here = tmp_path / "here"
    for arm in ("oracle", "generated"):
        S.train_seed(block, S.training_set(block, proj, arm), weights, 0, here, log=lambda m: None, data_name=arm)
        for net in ("single/seed_0", "attfuse/seed_0"):
            a, b = (pooled / arm / net / "model.safetensors").read_bytes(), (here / "models" / arm / net /
                                                                          "model.safetensors").read_bytes()
            assert a == b, (arm, net)
    # the generated arm learns from the ego views only (tiny's generated_views): its own network
    assert (pooled / "generated" / "single" / "seed_0" / "model.safetensors").read_bytes() != \
        (pooled / "oracle" / "single" / "seed_0" / "model.safetensors").read_bytes()


def test_one_thread_arms_train_here_from_the_sets_the_caller_read(root, tmp_path, monkeypatch):
    """On one thread train_arms trains each (arm, seed) here, as one named training, reading an
    arm's training set only when the caller has not read it already (ssc's run reads the oracle's)."""
    import shutil

    from tasks.training import Trainings

    proj = tmp_path / "proj"
    shutil.copytree(root / "data" / "sim", proj / "data" / "sim")
    shutil.copytree(root / "data" / "sim" / "real_cav" / "train", proj / "data" / "generated" / "real_cav" / "train")
    block = _block(tmp_path, methods=["none"], steps=2, warm_start_steps=1)
    oracle = S.training_set(block, proj, "oracle")
    weights = S.class_weights(oracle.class_counts(), eps=block.class_weight_eps)
    read, names = [], []
    real_read = T.training_set
    monkeypatch.setattr(T, "training_set", lambda b, r, arm: read.append(arm) or real_read(b, r, arm))

    class Named(Trainings):
        def run(self, name, fn):
            names.append(name)
            return fn()

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        S.train_arms(block, proj, ["oracle", "generated"], weights, log=lambda m: None, trainings=Named(),
                     sets={"oracle": oracle})
    finally:
        torch.set_num_threads(threads)
    assert read == ["generated"]
    assert names == ["train-oracle-seed0", "train-generated-seed0"]
    for arm in ("oracle", "generated"):
        assert (proj / block.out / "models" / arm / "single" / "seed_0" / "model.safetensors").is_file()
