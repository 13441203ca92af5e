"""Training, warm start and saving of the fusion networks (tasks/fusion_train.py)."""
from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from models.fusion import METHODS, LateFusion, NoFusion
from tasks.fusion_batch import Inputs
from tasks.fusion_data import FusionDataset
from tasks.fusion_train import Trained, build_model, detector_learning_rate, load, save, train
from tasks.training import checkpoints
from typ.config import config_from_dict
from typ.errors import TypError
from typ.formats.opv2v import write_scene
from typ.sim import simulate_scenario

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SMALL = {"detector": {"lidar_range": [-51.2, -25.6, -3.0, 51.2, 25.6, 1.0], "voxel_size": 0.8,
                      "max_points_per_pillar": 8, "max_pillars": 4000, "pillar_channels": 8,
                      "num_filters": [8, 16], "num_upsample_filters": [8, 8]},
         "v2xvit": {"dim": 8, "heads": 1, "dim_head": 8, "window_sizes": [4], "window_heads": [1],
                    "window_dim_heads": [8], "mlp_dim": 8},
         "checkpoint_every": 1, "batch_size": 2}


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("fusion_train")
    for scene in simulate_scenario(domain="real_cav", seed=7, n_frames=2, n_agents=2, azimuth_step_deg=1.5,
                                   scenario="real_cav_0007"):
        write_scene(scene, root)
    cfg = config_from_dict({"fusion": SMALL}).fusion
    return cfg, Inputs(list(FusionDataset(root, lidar_range=cfg.detector.lidar_range)), cfg)



def _run_dir(folder):
    """The one run folder of checkpoints under ``folder`` (not typ's records of them, ``.typ/``)."""
    (run,) = [p for p in folder.iterdir() if not p.name.startswith(".")]
    return run

def test_learning_rate_warms_up_then_decays_to_a_hundredth():
    lrs = [detector_learning_rate(1.0, s, 100, "cosine", 0.1) for s in range(100)]
    assert lrs[0] == pytest.approx(0.1) and lrs[9] == pytest.approx(1.0)
    assert all(a >= b for a, b in zip(lrs[9:], lrs[10:]))
    assert lrs[-1] == pytest.approx(0.01) and lrs[54] == pytest.approx(0.505, abs=0.01)
    assert [detector_learning_rate(1.0, s, 100, "constant", 0.1) for s in (0, 9, 50, 99)] == [pytest.approx(0.1), 1, 1, 1]


def test_training_resumes_from_its_last_checkpoint(setup, tmp_path):
    cfg, inputs = setup
    whole = train("attfuse", cfg, inputs, steps=3, out=tmp_path, name="run")
    ckpts = checkpoints(_run_dir(tmp_path / "checkpoints" / "run"))
    assert [s for s, _ in ckpts] == [2, 3]
    ckpts[-1][1].unlink()                                        # as if killed after step 2
    resumed = train("attfuse", cfg, inputs, steps=3, out=tmp_path, name="run")
    for (k, a), b in zip(whole.model.state_dict().items(), resumed.model.state_dict().values()):
        assert torch.allclose(a.float(), b.float(), atol=1e-6), k
    assert [r["step"] for r in resumed.curve] == [0, 2] and resumed.curve == whole.curve
    other = train("attfuse", cfg, inputs, steps=3, out=tmp_path, name="run", seed=1)
    assert other.key != whole.key and other.seed == 1


def test_batchnorm_statistics_are_the_training_loops_own(setup, tmp_path):
    """Defect 2: no re-estimation after training. The returned network is exactly the last
    checkpoint's (running statistics included); re-estimating them on the training samples, as
    the stage once did, makes them differ."""
    cfg, inputs = setup
    trained = train("late", cfg, inputs, steps=3, out=tmp_path, name="bn")
    last = torch.load(checkpoints(_run_dir(tmp_path / "checkpoints" / "bn"))[-1][1], weights_only=False)
    for k, v in trained.model.state_dict().items():
        assert torch.equal(v, last["model"][k]), k
    assert any("running_mean" in k for k in last["model"])


def test_no_and_late_fusion_share_one_single_agent_detector(setup, tmp_path):
    """Defect 4: one training run serves both; no fusion is that detector on the ego's cloud."""
    cfg, inputs = setup
    assert METHODS["none"].network == "late" and METHODS["late"].network == "late"
    with pytest.raises(TypError, match="late"):
        train("none", cfg, inputs, steps=1, out=tmp_path, name="none")
    single = train("late", cfg, inputs, steps=1, out=tmp_path, name="single")
    ego = single.as_method("none")
    assert isinstance(ego.model, NoFusion) and isinstance(single.model, LateFusion)
    assert ego.model.detector is single.model.detector
    batch_all, batch_ego = inputs.batch("late", [0]), inputs.batch("none", [0])
    with torch.no_grad():
        heads_all, heads_ego = batch_all.run(single.model), batch_ego.run(ego.model)
    assert heads_all["psm"].shape[0] == 2 and heads_ego["psm"].shape[0] == 1
    assert torch.allclose(heads_all["psm"][:1], heads_ego["psm"], atol=1e-6)      # the ego's row


@pytest.mark.parametrize("method", ["early", "attfuse", "v2xvit"])
def test_warm_start_copies_the_single_agent_detector(setup, method):
    cfg, _ = setup
    torch.manual_seed(1)
    single = build_model("late", cfg)
    model = build_model(method, cfg)
    model.warm_start(single.detector)
    own = model.state_dict()
    for k, v in single.detector.state_dict().items():
        name = k if method == "v2xvit" else f"detector.{k}"
        if method == "v2xvit" and k.startswith("head."):
            continue                                   # V2X-ViT's head sits on the transformer: fresh
        assert torch.equal(own[name], v), name


def test_saved_networks_load_back_and_damage_names_the_file(setup, tmp_path):
    cfg, inputs = setup
    torch.manual_seed(0)
    model = build_model("v2xvit", cfg).eval()
    trained = Trained("v2xvit", model, None, "k1", 5, 2, [{"step": 0, "loss": 1.0}])
    folder = save(trained, tmp_path / "v2xvit", cfg)
    assert sorted(p.name for p in folder.iterdir()) == ["config.json", "model.safetensors"]
    back = load(folder, cfg)
    assert (back.method, back.key, back.steps, back.seed, back.curve) == ("v2xvit", "k1", 5, 2, trained.curve)
    batch = inputs.batch("v2xvit", [0, 1])
    with torch.no_grad():
        a, b = batch.run(model), batch.run(back.model)
    assert all(torch.equal(a[k], b[k]) for k in a)
    (folder / "model.safetensors").write_bytes((folder / "model.safetensors").read_bytes()[:100])
    with pytest.raises(TypError) as err:
        load(folder, cfg)
    assert "model.safetensors" in str(err.value.where) and "fusion" in err.value.expected
    meta = json.loads((folder / "config.json").read_text())
    meta["config"]["method"] = "cobevt"
    (folder / "config.json").write_text(json.dumps(meta))
    with pytest.raises(TypError):
        load(folder, cfg)
    with pytest.raises(TypError, match="fusion"):
        load(tmp_path / "missing", cfg)


def test_fine_tuning_needs_the_same_method(setup, tmp_path):
    cfg, inputs = setup
    single = Trained("late", build_model("late", cfg), None, "k", 0)
    with pytest.raises(TypError, match="init"):
        train("attfuse", dataclasses.replace(cfg), inputs, steps=1, out=tmp_path, name="x", init=single)


@pytest.mark.parametrize("profile", ["tiny", "small"])
def test_the_profiles_v2xvit_starts_as_the_single_agent_detector(profile):
    """tiny's V2X-ViT (small keeps tiny's fusion) keeps the backbone map's width and stride: warm-started, the
    whole module (head included) starts from the single-agent detector, not from a fresh head."""
    cfg = config_from_dict({"profile": profile}).fusion
    single = build_model("late", cfg).detector
    v2x = build_model("v2xvit", cfg)
    assert v2x.keeps_single_map(single)
    v2x.warm_start(single)
    assert all(torch.equal(a, b) for a, b in zip(v2x.head.state_dict().values(), single.head.state_dict().values()))
