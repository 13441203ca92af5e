"""The generator as one object: what conditions it, reproducibility, the zero-initialised adapter,
save/load round trips with named errors, and turning occupancy back into a realistic cloud."""
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from models.adapter import ZeroAdapter
from models.ldm import LatentDiffusion
from models.vqvae import BEVVQVAE, PooledBoxMap
from pipelines.typ.pipeline_typ import PointStats, TYPPipeline, occupancy_to_points, point_statistics
from typ.errors import TypError
from typ.voxel import Grid, voxelize
from tiny_pipeline import TINY_GRID, tiny_pipeline
from repo_paths import REPO

GRID = TINY_GRID
_pipeline = tiny_pipeline


def _inputs(n=2, seed=0):
    rng = np.random.default_rng(seed)
    x_e = (rng.random((n, 8, 32, 32)) < 0.05).astype(np.float32)
    y_r = np.zeros((n, 1, 32, 32), np.float32)
    y_r[:, :, 10:14, 6:9] = 1
    return x_e, y_r


def test_same_seed_same_bytes_other_seed_other_sample():
    pipe = _pipeline()
    x_e, y_r = _inputs()
    a = pipe.logits(x_e, y_r, seed=3)
    assert torch.equal(a, pipe.logits(x_e, y_r, seed=3))
    assert not torch.equal(a, pipe.logits(x_e, y_r, seed=4))


def test_a_fresh_zero_initialised_adapter_leaves_stage_one_unchanged():
    pipe = _pipeline()
    x_e, y_r = _inputs()
    assert all(float(f.abs().max()) == 0 for f in pipe.adapter(torch.randn(2, 4, 16, 16)))
    assert torch.equal(pipe.logits(x_e, y_r, seed=1), pipe.with_adapter(None).logits(x_e, y_r, seed=1))


def test_condition_is_the_normalised_box_latent_and_the_adapter_sees_x_e():
    pipe = _pipeline()
    x_e, y_r = _inputs()
    seen = {"cond": [], "adapter": []}
    unet_forward, adapter_forward = pipe.unet.forward, pipe.adapter.forward

    def unet_spy(z_t, t, cond, adapter_features=None):
        seen["cond"].append(cond.clone())
        return unet_forward(z_t, t, cond, adapter_features)

    def adapter_spy(condition):
        seen["adapter"].append(condition.clone())
        return adapter_forward(condition)

    pipe.unet.forward, pipe.adapter.forward = unet_spy, adapter_spy
    pipe.logits(x_e, y_r, seed=0)
    expected_cond = pipe.unet.normalize_cond(pipe.box_encoder.encode_pre_quant(torch.from_numpy(y_r)))
    assert len(seen["cond"]) == 3 and all(torch.equal(c, expected_cond) for c in seen["cond"])  # every step
    with torch.no_grad():
        expected_ego = pipe.unet.normalize(pipe.x_vqvae.encode_pre_quant(torch.from_numpy(x_e)))
    assert len(seen["adapter"]) == 1 and torch.allclose(seen["adapter"][0], expected_ego)  # once per sample


def test_samples_are_decoded_de_standardised_and_x_e_is_standardised_for_the_adapter(monkeypatch):
    """The UNet works on standardised latents (x^f - mean) / std: with statistics that are not
    (0, 1), G decodes the sample moved back, z·std + mean, and F_AD gets E(x_e') standardised."""
    import pipelines.typ.pipeline_typ as pipeline_module

    pipe = _pipeline()
    with torch.no_grad():
        pipe.unet.latent_mean.copy_(torch.tensor([0.5, -1.0, 2.0, 0.25]).view(1, 4, 1, 1))
        pipe.unet.latent_std.copy_(torch.tensor([2.0, 0.5, 3.0, 1.5]).view(1, 4, 1, 1))
    x_e, y_r = _inputs()
    seen = {}
    real_sample, decode, adapter_forward = pipeline_module.sample, pipe.x_vqvae.decode_latents, pipe.adapter.forward

    def sample_spy(*args, **kwargs):
        seen["sample"] = real_sample(*args, **kwargs)
        return seen["sample"]

    def decode_spy(latents):
        seen["decoded"] = latents.clone()
        return decode(latents)

    def adapter_spy(condition):
        seen["adapter"] = condition.clone()
        return adapter_forward(condition)

    monkeypatch.setattr(pipeline_module, "sample", sample_spy)
    pipe.x_vqvae.decode_latents, pipe.adapter.forward = decode_spy, adapter_spy
    logits = pipe.logits(x_e, y_r, seed=0)
    mean, std = pipe.unet.latent_mean, pipe.unet.latent_std
    torch.testing.assert_close(seen["decoded"], seen["sample"] * std + mean)
    with torch.no_grad():
        torch.testing.assert_close(logits, decode(seen["sample"] * std + mean))
        assert not torch.allclose(logits, decode(seen["sample"]))  # (the statistics do matter here)
        ego = pipe.x_vqvae.encode_pre_quant(torch.from_numpy(x_e))
    torch.testing.assert_close(seen["adapter"], (ego - mean) / std)


def test_adapter_scale_multiplies_every_residual_the_unet_gets():
    pipe = _pipeline()
    with torch.no_grad():
        for p in pipe.adapter.parameters():
            p.add_(0.01)
    x_e, y_r = _inputs()
    got = {}
    unet_forward = pipe.unet.forward

    def unet_spy(z_t, t, cond, adapter_features=None):
        got.setdefault("features", [f.clone() for f in adapter_features])
        return unet_forward(z_t, t, cond, adapter_features)

    pipe.unet.forward = unet_spy
    with torch.no_grad():
        raw = pipe.adapter(pipe.unet.normalize(pipe.x_vqvae.encode_pre_quant(torch.from_numpy(x_e))))
    assert all(float(r.abs().max()) > 0 for r in raw)
    for scale in (3.0, 1.0):
        got.clear()
        dataclasses.replace(pipe, adapter_scale=scale).logits(x_e, y_r, seed=0)
        assert len(got["features"]) == len(raw)
        for f, r in zip(got["features"], raw):
            torch.testing.assert_close(f, scale * r)
    # scale 1 (the default) is the adapter as trained: its residuals reach the UNet bit for bit
    assert pipe.adapter_scale == 1.0 and all(torch.equal(f, r) for f, r in zip(got["features"], raw))
    # a larger scale moves the sample further from stage 1's
    pipe.unet.forward = unet_forward
    stage1 = pipe.with_adapter(None).logits(x_e, y_r, seed=0)
    moved = [float((dataclasses.replace(pipe, adapter_scale=s).logits(x_e, y_r, seed=0) - stage1).abs().mean())
             for s in (1.0, 4.0)]
    assert 0 < moved[0] < moved[1]


def test_a_resimulation_conditioned_adapter_needs_the_resimulated_view():
    pipe = _pipeline(conditions=2)
    x_e, y_r = _inputs()
    with pytest.raises(TypError, match="resim"):
        pipe.logits(x_e, y_r, seed=0)
    assert pipe.logits(x_e, y_r, seed=0, resim=x_e).shape == (2, 8, 32, 32)


def test_save_and_load_give_the_same_samples(tmp_path):
    pipe = _pipeline()
    with torch.no_grad():
        for p in pipe.adapter.parameters():
            p.add_(0.01)
    pipe.save_pretrained(tmp_path / "gen")
    assert sorted(p.name for p in (tmp_path / "gen").iterdir()) == [
        "adapter", "box_encoder", "pipeline.json", "unet", "x_vqvae"]
    assert not list((tmp_path / "gen").rglob("*.pt"))  # weights in safetensors, configs in JSON
    back = TYPPipeline.from_pretrained(tmp_path / "gen")
    x_e, y_r = _inputs()
    assert torch.equal(pipe.logits(x_e, y_r, seed=5), back.logits(x_e, y_r, seed=5))
    assert back.point_stats == pipe.point_stats and back.grid == GRID
    # the conditioning scale travels with the weights; a folder written before it existed samples at 1
    dataclasses.replace(pipe, adapter_scale=2.5).save_pretrained(tmp_path / "scaled")
    assert TYPPipeline.from_pretrained(tmp_path / "scaled").adapter_scale == 2.5
    meta = json.loads((tmp_path / "scaled" / "pipeline.json").read_text())
    del meta["adapter_scale"]
    (tmp_path / "scaled" / "pipeline.json").write_text(json.dumps(meta))
    assert TYPPipeline.from_pretrained(tmp_path / "scaled").adapter_scale == 1.0


def test_damaged_artifacts_are_named(tmp_path):
    pipe = _pipeline()
    pipe.save_pretrained(tmp_path / "gen")
    weights = tmp_path / "gen" / "unet" / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: len(weights.read_bytes()) // 2])
    with pytest.raises(TypError, match=r"unet/model.safetensors.*safetensors file written by the selftrain stage"):
        TYPPipeline.from_pretrained(tmp_path / "gen")
    with pytest.raises(TypError, match="pipeline.json.*run the selftrain stage"):
        TYPPipeline.from_pretrained(tmp_path / "missing")


def test_points_fill_their_voxels_with_the_domain_density_and_intensity():
    occ = np.zeros((8, 32, 32), bool)
    occ[1, 16, 16] = True      # ~0.4 m from the sensor: band 0 (1 or 2 points)
    occ[3, 31, 0] = True       # ~17 m: band 1 (exactly 1 point, intensity 0.2)
    pts = occupancy_to_points(occ, GRID, _pipeline().point_stats, np.random.default_rng(0))
    assert pts.dtype == np.float32 and pts.shape[1] == 4
    back = voxelize(pts, GRID).transpose(2, 0, 1)
    assert np.array_equal(back, occ)                       # every point inside its own voxel
    near = np.hypot(pts[:, 0], pts[:, 1]) < 5
    assert 1 <= near.sum() <= 2 and (~near).sum() == 1
    assert np.allclose(pts[~near, 3], 0.2) and (0 <= pts[near, 3]).all() and (pts[near, 3] <= 0.5).all()
    centres = GRID.lower + (np.array([16, 16, 1]) + 0.5) * GRID.voxel_size
    assert not np.allclose(pts[near, :3], centres)          # spread inside the voxel, not on its centre


def test_point_statistics_of_a_cloud():
    rng = np.random.default_rng(0)
    near = np.concatenate([np.full((3, 3), [2.1, 2.1, 0.1]) + rng.random((3, 3)) * 0.01, np.full((3, 1), 0.7)], axis=1)
    far = np.array([[12.0, 0.1, 0.1, 0.3]])
    outside = np.array([[15.0, 0.1, 0.1, 0.9]])       # beyond the ±12.8 m grid: not counted
    stats = point_statistics([np.concatenate([near, far, outside]).astype(np.float32)], GRID)
    assert stats.points_per_voxel[0][:3] == (0.0, 0.0, 1.0)   # band 0-10 m: one voxel holding 3 points
    assert stats.points_per_voxel[1][:2] == (1.0, 0.0)        # band 10-20 m: one voxel holding 1 point
    assert stats.intensity[0] == pytest.approx((0.7,) * 21) and stats.intensity[1] == pytest.approx((0.3,) * 21)
    # bands no point reaches take the pooled statistics: 2 voxels (1 and 3 points), intensities 0.7 x3, 0.3
    assert stats.points_per_voxel[2][:3] == (0.5, 0.0, 0.5)
    assert stats.intensity[2][0] == pytest.approx(0.3) and stats.intensity[2][-1] == pytest.approx(0.7)
    assert point_statistics([np.zeros((0, 4), np.float32)], GRID) == PointStats.single()


def test_the_readme_example_makes_the_view_generate_makes(tmp_path, monkeypatch):
    """README.md's Python block runs as written (a saved generator at make run's path, an ego
    scan, a pose) and gives what the generate stage's call gives for that reference."""
    import re

    from pipelines import reference_at
    from typ.geometry import pose_to_matrix
    from typ.sim import simulate_scenario

    readme = (REPO / "README.md").read_text()
    code = re.search(r"```python\n(.*?)```", readme, re.S).group(1)
    _pipeline().save_pretrained(tmp_path / "artifacts" / "selftrain" / "generator" / "seed_0")
    monkeypatch.chdir(tmp_path)
    ego = simulate_scenario(domain="target", seed=2, n_frames=1, n_agents=1)[0].ego
    pose = pose_to_matrix([12.0, -3.0, 0.0, 0.0, 150.0, 0.0])
    scope = {"ego": ego, "pose": pose}
    exec(code, scope)
    cloud, pipe = scope["cloud"], scope["pipe"]
    grid = pipe.grid.for_sensor(2.2)
    again, = pipe.generate([reference_at(ego, ego.pose @ pose, "rsu", None, grid)], grid, seed=0)
    assert cloud.dtype == np.float32 and cloud.shape[1] == 4 and len(cloud) > 0
    np.testing.assert_array_equal(cloud, again)
