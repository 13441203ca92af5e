"""MLflow extras of typ.tracking: trained networks logged with signatures, DVC experiment tags,
and silent logging on torchrun ranks other than 0."""
import mlflow
import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from models.ldm import LatentDiffusion
from models.vqvae import BEVVQVAE
from typ import distributed
from typ.config import config_from_dict
from typ.tracking import NullRun, stage_run


@pytest.fixture
def store(tmp_path, monkeypatch):
    uri = f"sqlite:///{tmp_path / 'mlruns.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    return tmp_path, uri


def test_trained_networks_are_logged_with_signatures_and_load_back(store, one_torch_thread):
    tmp_path, uri = store
    torch.manual_seed(0)
    vq = BEVVQVAE(in_channels=4, latent_channels=3, block_out_channels=(8, 8), num_codes=16).eval()
    ldm = LatentDiffusion(latent_channels=3, cond_channels=2, sample_size=8, block_out_channels=(8, 8),
                          cross_attention_dim=8, attention_head_dim=4).eval()
    x = (torch.rand(2, 4, 16, 16) > 0.7).float()
    inputs = {"z_t": torch.randn(2, 3, 8, 8), "t": torch.tensor([10, 500]), "cond": torch.randn(2, 2, 8, 8)}
    cfg = config_from_dict({"profile": "tiny"})
    with stage_run("vqvae", cfg, root=tmp_path) as run:
        vq_uri = run.log_model("vqvae-x", vq, x, output="logits")
        ldm_uri = run.log_model("stage1-ldm", ldm, inputs)

    vq_model = mlflow.pyfunc.load_model(vq_uri)
    spec = vq_model.metadata.signature
    assert spec.inputs.input_names() == ["input"] and spec.inputs.inputs[0].shape == (-1, 4, 16, 16)
    assert spec.outputs.inputs[0].shape == (-1, 4, 16, 16)
    with torch.no_grad():
        expected = vq(x).logits.numpy()
    np.testing.assert_allclose(vq_model.predict({"input": x.numpy()}), expected, rtol=1e-5, atol=1e-6)

    ldm_model = mlflow.pyfunc.load_model(ldm_uri)
    assert sorted(ldm_model.metadata.signature.inputs.input_names()) == ["cond", "t", "z_t"]
    with torch.no_grad():
        expected = ldm(**inputs).numpy()
    got = ldm_model.predict({k: v.numpy() for k, v in inputs.items()})
    np.testing.assert_allclose(got, expected, rtol=1e-4, atol=1e-5)
    assert isinstance(ldm_model.unwrap_python_model().module, LatentDiffusion)


def test_dvc_experiment_runs_are_tagged_and_land_in_the_main_store(store, monkeypatch):
    tmp_path, _ = store
    monkeypatch.delenv("MLFLOW_TRACKING_URI")
    # `dvc exp run --temp` runs stage commands in a copy of the repo; DVC_ROOT names the real one
    copy = tmp_path / "exp-copy"
    copy.mkdir()
    monkeypatch.setenv("DVC_ROOT", str(tmp_path))
    monkeypatch.setenv("DVC_EXP_NAME", "quick-fox")
    monkeypatch.setenv("DVC_EXP_BASELINE_REV", "0123abcd")
    cfg = config_from_dict({"profile": "tiny", "stage1": {"epochs": 3}})
    with stage_run("stage1", cfg, root=copy) as run:
        run.metrics({"stage1.loss": 0.5}, step=0)
    assert (tmp_path / "mlruns.db").is_file() and not (copy / "mlruns.db").exists()
    tags = MlflowClient(f"sqlite:///{tmp_path / 'mlruns.db'}").get_run(run.run_id).data.tags
    assert tags["dvc.exp_name"] == "quick-fox" and tags["dvc.exp_baseline_rev"] == "0123abcd"
    assert tags["typ.stage"] == "stage1"


def test_ranks_other_than_zero_log_nothing(store, monkeypatch):
    tmp_path, _ = store
    monkeypatch.setattr(distributed, "_runtime", distributed.Runtime(torch.device("cpu"), "fp32", rank=1,
                                                                     world_size=2))
    with stage_run("vqvae", config_from_dict({"profile": "tiny"}), root=tmp_path) as run:
        assert isinstance(run, NullRun)
        run.metrics({"loss": 1.0})
    assert not (tmp_path / "mlruns.db").exists()


def test_adapter_and_fusion_detector_serve_their_named_outputs(store, one_torch_thread):
    """Multi-output networks: the T2I-Adapter's feature list and a fusion detector's head dict."""
    from diffusers import T2IAdapter

    from tasks.fusion_batch import Inputs
    from tasks.fusion_data import FusionDataset
    from tasks.fusion_serve import ServedDetector
    from tasks.fusion_train import Trained, build_model
    from typ.formats.opv2v import write_scene
    from typ.sim import simulate_scenario

    tmp_path, _ = store
    torch.manual_seed(0)
    adapter = T2IAdapter(in_channels=3, channels=[8, 8], num_res_blocks=1, downscale_factor=1,
                         adapter_type="full_adapter").eval()
    x = torch.randn(2, 3, 8, 8)
    cfg = config_from_dict({"profile": "tiny", "fusion": {
        "detector": {"lidar_range": [-51.2, -25.6, -3.0, 51.2, 25.6, 1.0], "voxel_size": 0.8,
                     "max_points_per_pillar": 8, "max_pillars": 4000, "pillar_channels": 8,
                     "num_filters": [8, 16], "num_upsample_filters": [8, 8]}}})
    for scene in simulate_scenario(domain="real_cav", seed=3, n_frames=2, n_agents=2, scenario="real_cav_0003"):
        write_scene(scene, tmp_path / "scenes")
    data = FusionDataset(tmp_path / "scenes", lidar_range=cfg.fusion.detector.lidar_range)
    inputs = Inputs(list(data), cfg.fusion)
    trained = Trained("late", build_model("late", cfg.fusion).eval(), None, "k", 0)
    served, example = ServedDetector(trained).eval(), ServedDetector.example("late", inputs)
    with stage_run("fusion", cfg, root=tmp_path) as run:
        adapter_uri = run.log_model("stage2-adapter", adapter, x)
        detector_uri = run.log_model("fusion-late", served, example)

    got = mlflow.pyfunc.load_model(adapter_uri).predict({"input": x.numpy()})
    with torch.no_grad():
        expected = adapter(x)
    assert sorted(got) == [f"level_{i}" for i in range(len(expected))]
    for i, e in enumerate(expected):
        np.testing.assert_allclose(got[f"level_{i}"], e.numpy(), rtol=1e-5, atol=1e-6)

    model = mlflow.pyfunc.load_model(detector_uri)
    assert sorted(model.metadata.signature.inputs.input_names()) == sorted(example)
    got = model.predict({k: v.numpy() for k, v in example.items()})
    with torch.no_grad():
        expected = inputs.batch("late", range(2)).run(trained.model)
    assert set(got) == set(expected)
    for k, e in expected.items():   # one row per present agent: 2 frames x 2 agents
        assert got[k].shape == tuple(e.shape) and e.shape[0] == 4
        np.testing.assert_allclose(got[k], e.numpy(), rtol=1e-5, atol=1e-6)
