"""Adaptation stage (Eq. 8–10): frozen target parts, shared frozen codebook, divergence stop."""
import numpy as np
import pytest
import torch

from models.vqvae import BEVVQVAE
from tasks import adapt
from tasks.training import TrainingDiverged
from tasks.voxel_data import ViewSet
from typ.config import config_from_dict
from typ.voxel import Grid

GRID = Grid((-16.0, 16.0), (-16.0, 16.0), (-3.0, 1.0), (32, 32, 4))


def _views(seed, density):
    rng = np.random.default_rng(seed)
    records = []
    for _ in range(4):
        occ = np.argwhere(rng.random(GRID.shape) < density)
        records.append((occ, np.zeros((0, 2), dtype=np.intp)))
    return ViewSet(GRID, [("s", str(i), "000000") for i in range(4)], records)


def _target():
    torch.manual_seed(0)
    return BEVVQVAE(in_channels=4, latent_channels=3, block_out_channels=(8, 8, 8), num_codes=16, norm_num_groups=4)


def _cfg(**kw):
    return config_from_dict({"adapt": {"epochs": 1, "batch_size": 2, "checkpoint_every": 1, "disc_width": 8, **kw}}).adapt


def test_only_source_encoder_decoder_learn(tmp_path):
    target = _target()
    before_target = {k: v.clone() for k, v in target.state_dict().items()}
    source, disc = adapt.train(_cfg(), target, _views(1, 0.15), _views(2, 0.03), out=tmp_path,
                               log_fn=lambda values, step: None)
    for k, v in target.state_dict().items():  # E_tgt, Q_tgt, G_tgt frozen
        assert torch.equal(v, before_target[k]), k
    # the codebook is Q_tgt, shared and unchanged; encoder and decoder moved
    assert torch.equal(source.codebook, target.codebook)
    assert not torch.equal(source.net.encoder.conv_in.weight, target.net.encoder.conv_in.weight)
    assert not torch.equal(source.net.decoder.conv_out.weight, target.net.decoder.conv_out.weight)
    scores = adapt.translation_scores(source, target, _views(3, 0.15), _views(4, 0.03), n=4)
    assert np.isfinite(scores["jsd_r2dm"]) and 0 <= scores["rec_iou_source"] <= 1
    assert 0 <= adapt.discriminator_accuracy(disc, source, target, _views(3, 0.15), _views(4, 0.03), n=4) <= 1


def test_exploding_discriminator_stops_without_a_model(tmp_path):
    with pytest.raises(TrainingDiverged, match="discriminator loss .* > max_disc_loss"):
        adapt.train(_cfg(max_disc_loss=1e-6), _target(), _views(1, 0.15), _views(2, 0.03), out=tmp_path,
                    log_fn=lambda values, step: None)
    assert not (tmp_path / "source_vq").exists() and not (tmp_path / "discriminator").exists()
