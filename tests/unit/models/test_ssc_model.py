"""models/ssc.py: occupancy head layout, class weights, late fusion's warp and max-confidence merge,
and the head riding on the fusion modules of models/fusion/."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from models.fusion import LateFusion, NoFusion
from models.ssc import (SSC_LIDAR_RANGE, OccupancyHead, class_argmax, class_weights, merge_max_confidence, ssc_detector,
                        warp_to_ego)
from typ.errors import TypError
from typ.ssc import SSC_GRID

SMALL = dict(layer_nums=(1, 1, 1), num_filters=(8, 8, 8), num_upsample_filters=(8, 8, 8), pillar_channels=8,
             head_hidden=8)


class _Fixed(nn.Module):
    def __init__(self, t):
        super().__init__()
        self.t = t

    def forward(self, x):
        return self.t


def test_head_output_is_indexed_class_x_y_z():
    z, k, h, w = 3, 2, 4, 5
    head = OccupancyHead(in_channels=1, num_classes=k, num_heights=z, feature_stride=1)
    # logit of (height iz, class ik) at BEV row y, column x = 1000 iz + 100 ik + 10 y + x
    iz, ik, y, x = np.meshgrid(range(z), range(k), range(h), range(w), indexing="ij")
    t = torch.tensor(1000 * iz + 100 * ik + 10 * y + x, dtype=torch.float32).reshape(1, z * k, h, w)
    head.up, head.out = nn.Identity(), _Fixed(t)
    occ = head(torch.zeros(1, 1, h, w))["occ"]
    assert occ.shape == (1, k, w, h, z)
    assert occ[0, 1, 4, 2, 2].item() == 1000 * 2 + 100 * 1 + 10 * 2 + 4


def test_class_weights_by_hand():
    w = class_weights([90, 10])
    raw = np.array([1 / np.log(1.92), 1 / np.log(1.12)])  # 1.5325, 8.8236
    assert w == pytest.approx(raw / raw.mean())
    assert class_weights([5, 0, 5])[1] == pytest.approx(class_weights([5, 0, 5]).max())
    with pytest.raises(TypError):
        class_weights([0, 0])


def _grid_kw():
    return dict(lower=SSC_GRID.lower, voxel=SSC_GRID.voxel.tolist())


def test_warp_identity_shift_and_rotation():
    gen = torch.Generator().manual_seed(0)
    labels = torch.randint(0, 7, SSC_GRID.shape, generator=gen)
    conf = torch.rand(SSC_GRID.shape, generator=gen)
    same_l, same_c = warp_to_ego(labels, conf, np.eye(4), **_grid_kw())
    assert torch.equal(same_l, labels) and torch.equal(same_c, conf)
    # the agent sits one voxel ahead of the ego along x: ego voxel ix holds the agent's ix - 1
    t = np.eye(4)
    t[0, 3] = 0.78125
    l2, c2 = warp_to_ego(labels, conf, t, **_grid_kw())
    assert torch.equal(l2[1:], labels[:-1]) and torch.equal(c2[1:], conf[:-1])
    assert (l2[0] == 0).all() and (c2[0] == -1).all()  # outside the agent's grid: no vote
    # agent turned 90 deg left of the ego: its +x is the ego's +y; agent voxel (ix, iy) -> ego (127 - iy, ix)
    r = np.eye(4)
    r[:2, :2] = [[0, -1], [1, 0]]
    l3, _ = warp_to_ego(labels, conf, r, **_grid_kw())
    assert l3[127 - 40, 90, 5] == labels[90, 40, 5] and l3[127 - 3, 0, 19] == labels[0, 3, 19]


def test_merge_keeps_the_most_confident_agent():
    labels = torch.tensor([[1, 2, 0, 5], [3, 4, 6, 2], [0, 1, 1, 1]]).reshape(3, 1, 1, 4)
    conf = torch.tensor([[0.9, 0.2, 0.5, 0.7], [0.8, 0.6, 0.5, -1.0], [0.1, 0.7, 0.4, 0.7]]).reshape(3, 1, 1, 4)
    lab, c = merge_max_confidence(labels, conf)
    # voxel 0: ego 0.9; 1: agent 2 0.7; 2: tie 0.5 -> ego (0); 3: tie ego/agent 2 0.7 -> ego (5)
    assert lab.flatten().tolist() == [1, 1, 0, 5]
    assert c.flatten().tolist() == pytest.approx([0.9, 0.7, 0.5, 0.7])
    with pytest.raises(TypError):
        merge_max_confidence(labels[0], conf[0])


def _clouds(n_agents, seed=0):
    rng = np.random.default_rng(seed)
    return [np.c_[rng.uniform(-45, 45, (800, 2)), rng.uniform(-2.5, 1, 800), rng.random(800)].astype(np.float32)
            for _ in range(n_agents)]


def test_the_head_rides_on_the_fusion_modules():
    torch.manual_seed(0)
    det = ssc_detector(**SMALL)
    assert det.lidar_range == SSC_LIDAR_RANGE and (det.nx, det.ny) == (128, 128)
    pillars = det.pillarize(_clouds(4))
    mask = torch.tensor([[True, True], [True, False]])
    occ = NoFusion(detector=det)(pillars, agent_mask=mask)["occ"]
    assert occ.shape == (2, 7, 128, 128, 20)
    late = LateFusion(detector=det)(pillars, agent_mask=mask)["occ"]
    assert late.shape == (3, 7, 128, 128, 20)


def test_a_few_steps_of_weighted_cross_entropy_fit_one_map():
    torch.manual_seed(0)
    det = ssc_detector(**SMALL)
    model = NoFusion(detector=det)
    pillars = det.pillarize(_clouds(1))
    target = torch.zeros(1, 128, 128, 20, dtype=torch.long)
    target[:, :, :, 2] = 1          # a road layer
    target[:, 60:70, 60:64, 3:7] = 2  # a car
    w = torch.tensor(class_weights(np.bincount(target.flatten().numpy(), minlength=7)), dtype=torch.float32)
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(40):
        loss = nn.functional.cross_entropy(model(pillars, agent_mask=torch.ones(1, 1, dtype=torch.bool))["occ"],
                                           target, weight=w)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


def test_class_argmax_is_torch_argmax_over_the_class_axis_ties_included():
    torch.manual_seed(0)
    logits = torch.randn(7, 12, 10, 5)
    logits[:, 0, 0, 0] = 1.0                      # a seven-way tie: class 0, as torch.argmax
    logits[3, 1, 1, 1] = logits[5, 1, 1, 1] = 9.0  # a tie between 3 and 5: 3
    labels = class_argmax(logits)
    assert labels.shape == (12, 10, 5)
    assert torch.equal(labels, logits.argmax(0))
    assert labels[0, 0, 0] == 0 and labels[1, 1, 1] == 3
