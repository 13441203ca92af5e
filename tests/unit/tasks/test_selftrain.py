"""Target-domain enhancement (TYP §3.4): Table 4 switches, pseudo references, dummy ego, cav references."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from tasks import generate
from tasks.genscore import BANDS, band_label, cell_distance
from tasks.selftrain import (TABLE4, dummy_ego_tuples, encode_kinds, pseudo_references, resim_variant, target_frames,
                             training_fields, variant_of, variants_to_run)
from tasks.voxel_data import ViewSet
from typ.config import config_from_dict
from typ.errors import TypError
from typ.formats.opv2v import write_scene
from typ.geometry import invert
from typ.sim import simulate_scenario
from typ.voxel import Grid, box_map, voxelize

GRID = Grid((-51.2, 51.2), (-51.2, 51.2), (-3.0, 1.0), (64, 64, 8))


def _cfg(**selftrain):
    return config_from_dict({"selftrain": selftrain})


@pytest.fixture(scope="module")
def scenes():
    return simulate_scenario(domain="target", seed=3, n_frames=2, n_agents=3, azimuth_step_deg=1.6,
                             scenario="target_train_0000", split="train")


def test_switches_pick_the_table4_row_and_ablation_runs_every_row():
    assert variant_of(_cfg().selftrain).name == "disc_st_dummy"
    off = _cfg(discriminator=False, self_training=False, dummy_ego=False, ablation=False).selftrain
    assert variants_to_run(off, resim=False) == [TABLE4[0]] and TABLE4[0].name == "no_adaptation"
    odd = _cfg(discriminator=False, self_training=True, dummy_ego=True, ablation=True).selftrain
    names = [v.name for v in variants_to_run(odd, resim=True)]
    assert names == ["no_adaptation", "disc", "disc_st", "disc_st_dummy", "st_dummy", "typ_resim"]
    resim = resim_variant(odd)  # the switches' recipe, on the adapter that also sees the re-simulated view
    assert (resim.self_training, resim.dummy_ego, resim.conditions) == (True, True, 2) and resim.discriminator
    assert [(v.discriminator, v.self_training, v.dummy_ego) for v in TABLE4] == [
        (False, False, False), (True, False, False), (True, True, False), (True, True, True)]


def test_the_adapter_scale_is_a_sampling_setting_not_part_of_the_training_key():
    tiny, scaled = _cfg().selftrain, _cfg(adapter_scale=9.0).selftrain
    assert tiny.adapter_scale == 1.5 and scaled.adapter_scale == 9.0
    assert training_fields(tiny) == training_fields(scaled)          # same checkpoints: no retraining
    assert "adapter_scale" not in training_fields(tiny) and training_fields(tiny)["epochs"] == tiny.epochs
    assert training_fields(_cfg(epochs=7).selftrain) != training_fields(tiny)


def test_pseudo_references_sit_on_labelled_vehicles_inside_the_band(tmp_path, scenes):
    for scene in scenes:
        write_scene(scene, tmp_path)
    cfg = _cfg(pseudo_references=3, min_distance=5.0, max_distance=40.0)
    frames = target_frames(tmp_path)
    assert [f.agent_id for f in frames] == [scenes[0].ego.agent_id] * 2  # the ego's view, nobody else's
    refs = pseudo_references(frames, cfg.selftrain, GRID, np.random.default_rng(0))
    again = pseudo_references(frames, cfg.selftrain, GRID, np.random.default_rng(0))
    assert len(refs) == 2  # one per frame, two frames
    assert [r.agent_id for r in refs] == [r.agent_id for r in again]
    ego_id = scenes[0].ego.agent_id
    for ref, scene in zip(refs, scenes):
        ego = scene.ego
        assert ref.agent_id.startswith(ego_id)
        vid = int(ref.agent_id[len(ego_id):])
        box = ego.boxes[list(ego.box_ids).index(vid)]
        offset = invert(ego.pose) @ ref.pose
        assert np.allclose(offset[:2, 3], box[:2], atol=1e-6)
        assert 5.0 <= np.hypot(*box[:2]) <= 40.0
        assert vid not in ref.ids and int(ego_id) in ref.ids  # own vehicle out, the ego car in
        assert ref.x_e.any() and ref.y_r.any()
    narrow = _cfg(min_distance=60.0, max_distance=61.0).selftrain
    with pytest.raises(TypError, match="distance band"):
        pseudo_references(frames, narrow, GRID, np.random.default_rng(0))


def test_dummy_ego_tuples_condition_on_an_empty_grid():
    rng = np.random.default_rng(0)
    records = []
    for _ in range(3):
        occ = rng.random(GRID.shape) < 0.02
        boxes = np.array([[rng.uniform(-20, 20), rng.uniform(-20, 20), -1.0, 4.5, 1.9, 1.5, 0.3]])
        records.append((np.argwhere(occ), np.argwhere(box_map(boxes, GRID)[:, :, 0])))
    views = ViewSet(GRID, [("s", "1", f"{i:06d}") for i in range(3)], records)
    t = dummy_ego_tuples(views)
    assert len(t) == 3
    assert np.array_equal(t.x_r, views.occupancy([0, 1, 2])) and np.array_equal(t.y_r, views.box_maps([0, 1, 2]))
    assert t.x_r.any() and not t.x_e.any() and not t.resim.any()  # the targets are the views, the egos empty
    assert t.x_e.shape == t.resim.shape == t.x_r.shape


def test_cav_references_use_true_poses_and_only_the_egos_cloud(scenes):
    scene = scenes[0]
    refs = generate.cav_references(scene, GRID)
    cavs = [a for a in scene.agents if a != scene.ego.agent_id]
    assert [r.agent_id for r in refs] == cavs  # every CAV, whatever its distance: a drop-in for the real split
    for ref in refs:
        assert np.array_equal(ref.pose, scene.agents[ref.agent_id].pose)
        assert int(ref.agent_id) not in ref.ids
    # the CAVs' own clouds are never read: replacing them changes nothing
    blanked = dataclasses.replace(scene, agents={a: (v if a == scene.ego.agent_id else dataclasses.replace(
        v, points=np.zeros((0, 4), np.float32), semantics=None)) for a, v in scene.agents.items()})
    again = generate.cav_references(blanked, GRID)
    assert all(np.array_equal(a.x_e, b.x_e) and np.array_equal(a.y_r, b.y_r) for a, b in zip(refs, again))


def test_range_bands_cover_the_grid_by_cell_centre_distance():
    dist = cell_distance(GRID)
    assert dist.shape == GRID.shape[:2] and np.isclose(dist.min(), np.hypot(0.8, 0.8))
    assert np.isclose(dist.max(), np.hypot(51.2 - 0.8, 51.2 - 0.8))
    assert [band_label(*b) for b in BANDS] == ["0-20", "20-40", "40-80"]
    covered = sum(((dist >= lo) & (dist < hi)).sum() for lo, hi in BANDS)
    assert covered == dist.size  # every cell in exactly one band


def test_adapter_training_does_not_depend_on_the_global_torch_seed(tmp_path):
    from tasks import stage1, stage2

    cfg = config_from_dict({"stage1": {"unet": {"block_out_channels": [8, 8], "norm_num_groups": 4,
                                                 "cross_attention_dim": 8, "attention_head_dim": 4}},
                            "stage2": {"epochs": 1, "batch_size": 2, "checkpoint_every": 10}})
    torch.manual_seed(0)
    ldm = stage1.build(cfg.stage1, 4, 3, 8)
    gen = torch.Generator().manual_seed(1)
    data = stage2.Latents(*(torch.randn(4, c, 8, 8, generator=gen) for c in (4, 3, 4)))
    settings = stage2.settings_of(cfg.stage2, seed=7, min_snr=5.0)
    adapters = []
    for k in range(2):
        torch.manual_seed(100 + k)  # whatever the process's state, the stage's seed decides
        adapter = stage2.build_adapter(ldm, res_blocks=1, seed=7)
        adapters.append(stage2.fit_adapter(adapter, ldm, "linear", 1000, data, name="adapter", settings=settings,
                                           views=4, key_extra={}, out=tmp_path / str(k),
                                           log_fn=lambda values, step: None))
    assert all(torch.equal(p, q) for p, q in zip(adapters[0].parameters(), adapters[1].parameters()))
    fresh = stage2.build_adapter(ldm, res_blocks=1, seed=7)  # it did train: the zero convolutions moved
    assert any(not torch.equal(p, q) for p, q in zip(adapters[0].parameters(), fresh.parameters()))


class OffsetEncoder(torch.nn.Module):
    """A stand-in x encoder that marks its latents: the 2x2 average of each channel, plus ``offset``."""

    def __init__(self, offset: float):
        super().__init__()
        self.offset = offset

    def encode_pre_quant(self, x):
        return torch.nn.functional.avg_pool2d(x, 2) + self.offset


def test_each_kind_of_tuple_is_encoded_by_its_domains_encoder():
    """TYP §3.4: source CAV tuples through the adapted E_src (E_tgt when there is no adaptation),
    pseudo references and dummy egos, both target-domain data, through E_tgt; x_r and x_e' of a
    tuple through the same encoder."""
    from models.vqvae import PooledBoxMap
    from tasks import stage1
    from tasks.stage2 import Tuples

    rng = np.random.default_rng(0)

    def tuples(n):
        grids = [(rng.random((n, 4, 8, 8)) < 0.3).astype(np.float32) for _ in range(3)]
        return Tuples(grids[0], grids[1][:, :1], grids[2], (rng.random((n, 4, 8, 8)) < 0.3).astype(np.float32))

    kinds = {"source": tuples(3), "pseudo": tuples(2), "dummy": tuples(1)}
    e_src, e_tgt, box = OffsetEncoder(10.0), OffsetEncoder(-10.0), PooledBoxMap(downsample=2)
    cfg = config_from_dict({"stage1": {"unet": {"block_out_channels": [8, 8], "norm_num_groups": 4,
                                                 "cross_attention_dim": 8, "attention_head_dim": 4}}})
    torch.manual_seed(0)
    ldm = stage1.build(cfg.stage1, 4, 1, 4)
    for v in (*TABLE4, resim_variant(_cfg().selftrain)):
        expected = {"source": e_src if v.discriminator else e_tgt, "pseudo": e_tgt, "dummy": e_tgt}
        parts = encode_kinds(v, kinds, e_src, e_tgt, box, ldm, augment=1)
        assert len(parts) == 3
        for part, (kind, t) in zip(parts, kinds.items()):
            enc = expected[kind]
            x_r, x_e = torch.from_numpy(t.x_r), torch.from_numpy(t.x_e)
            torch.testing.assert_close(part.z0, ldm.normalize(enc.encode_pre_quant(x_r)), msg=f"{v.name} {kind}")
            ego = [ldm.normalize(enc.encode_pre_quant(x_e))]
            if v.conditions == 2:  # the re-simulated view beside x_e', through the same encoder
                ego.append(ldm.normalize(enc.encode_pre_quant(torch.from_numpy(t.resim))))
            torch.testing.assert_close(part.ego, torch.cat(ego, dim=1), msg=f"{v.name} {kind}")


def test_enhance_fine_tunes_stage_2s_adapter_as_stage_2_hands_it_over(tmp_path):
    """fit_adapter returns its EMA copy, frozen: self-training in the same process (bench/gpu.py)
    fine-tunes it all the same, and leaves stage 2's adapter as it was."""
    from models.vqvae import PooledBoxMap
    from tasks import selftrain, stage1, stage2, vqvae
    from pipelines.typ.pipeline_typ import PointStats, TYPPipeline

    unet = {"block_out_channels": [8, 8], "norm_num_groups": 4, "cross_attention_dim": 8, "attention_head_dim": 4}
    ae = {"latent_channels": 4, "block_out_channels": [8, 8], "num_codes": 16, "norm_num_groups": 4, "quantizer": "vq"}
    cfg = config_from_dict({"stage1": {"unet": unet}, "vqvae": {"x": ae, "y": ae},
                            "stage2": {"epochs": 1, "batch_size": 2, "augment": 1},
                            "selftrain": {"epochs": 1, "batch_size": 2}})
    grid = Grid((-16.0, 16.0), (-16.0, 16.0), (-3.0, 1.0), (32, 32, 4))
    torch.manual_seed(0)
    x_vq = vqvae.build("x", cfg.vqvae.x, 4)
    ldm = stage1.build(cfg.stage1, 4, 1, 16)
    rng = np.random.default_rng(0)
    views = ViewSet(grid, [("s", str(i), "0") for i in range(2)],
                    [(np.argwhere(rng.random(grid.shape) < 0.1), np.argwhere(rng.random(grid.shape[:2]) < 0.1))
                     for _ in range(2)])
    x, y = views.occupancy([0, 1]) > 0.5, views.box_maps([0, 1]) > 0.5
    tuples = stage2.Tuples(x, y, x[::-1].copy())
    latents = stage2.encode(tuples, x_vq, PooledBoxMap(downsample=2), ldm)
    handed = stage2.fit_adapter(stage2.build_adapter(ldm, res_blocks=1, seed=0), ldm, "linear", 1000, latents,
                                name="adapter", settings=stage2.settings_of(cfg.stage2, 0, 0.0), views=2,
                                key_extra={}, out=tmp_path / "s2", log_fn=lambda v, s: None)
    assert not any(p.requires_grad for p in handed.parameters())   # the EMA copy, as stage 2 returns it
    before = [p.clone() for p in handed.parameters()]
    base = TYPPipeline(x_vq, PooledBoxMap(downsample=2), ldm, None, grid, "linear", 1000, "ddim", 2,
                       {"low": 0.5, "high": 0.5, "noise_std": 0.0})
    data = selftrain.Inputs(tuples, selftrain.References(x, y), dummy_ego_tuples(views), PointStats.single())
    adapter, _ = selftrain.enhance(TABLE4[-1], cfg, data, selftrain.Encoders(x_vq, x_vq, base.box_encoder), base,
                                   handed, seed=0, out=tmp_path / "st", log_fn=lambda v, s: None)
    assert any(not torch.equal(p, q) for p, q in zip(adapter.parameters(), before))
    assert all(torch.equal(p, q) for p, q in zip(handed.parameters(), before))
