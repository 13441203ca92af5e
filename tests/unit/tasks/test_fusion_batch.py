"""Batches and augmentation of collaborative samples (tasks/fusion_batch.py)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from models.fusion import METHODS, merge_agent_points
from tasks.fusion_batch import Inputs, augment, draw_similarity, map_boxes
from tasks.fusion_data import FusionSample, boxes_in_range
from typ.config import AugmentConfig, config_from_dict
from tasks.fusion_train import box_coder, build_model
from typ.geometry import invert, points_in_boxes, pose_to_matrix, relative_transform, transform_boxes

pytestmark = pytest.mark.usefixtures("one_torch_thread")

RANGE = [-51.2, -25.6, -3.0, 51.2, 25.6, 1.0]
CFG = config_from_dict({"fusion": {"detector": {"lidar_range": RANGE, "voxel_size": 0.8, "max_points_per_pillar": 8,
                                                "max_pillars": 4000, "pillar_channels": 8, "num_filters": [8, 16],
                                                "num_upsample_filters": [8, 8]}}}).fusion


def _sample(rng: np.random.Generator) -> FusionSample:
    """An ego and two agents that all see three cars: each cloud holds points inside every car
    (in its own frame) and ground clutter around it."""
    poses = [[0, 0, 1.8, 0, 0, 0], [18, -4, 1.8, 0, 150, 0], [-15, 6, 1.8, 0, -60, 0]]
    world = np.array([[10.0, 3.0, 0.75, 4.5, 1.8, 1.5, 0.4], [-8.0, -5.0, 0.75, 4.0, 1.7, 1.5, 2.0],
                      [25.0, 8.0, 0.75, 4.2, 1.8, 1.5, -1.0]])
    clouds, own = [], []
    for p in poses:
        to_agent = invert(pose_to_matrix(p))
        boxes = transform_boxes(to_agent, world)
        inside = [b[:3] + rng.uniform(-0.4, 0.4, (40, 3)) * [b[3] / 2, b[4] / 2, b[5] / 2] for b in boxes]
        clutter = np.c_[rng.uniform(-40, 40, (300, 2)), np.full(300, -1.8)]
        xyz = np.concatenate([*inside, clutter])
        clouds.append(np.c_[xyz, rng.random(len(xyz))].astype(np.float32))
        own.append(boxes[boxes_in_range(boxes, RANGE)])
    t = np.stack([relative_transform(p, poses[0]) for p in poses])
    gt = transform_boxes(invert(pose_to_matrix(poses[0])), world)
    return FusionSample("s", "000000", ("1", "2", "3"), tuple(clouds), t, t.copy(), np.zeros(3, np.int64), gt,
                        np.arange(3), tuple(own))


def test_similarity_is_a_rotation_scaling_and_maybe_a_flip():
    rng = np.random.default_rng(0)
    aug = AugmentConfig(flip=True, rotation_deg=45.0, scale=(0.95, 1.05))
    dets, scales = [], []
    for _ in range(200):
        a = draw_similarity(rng, aug)
        s = np.cbrt(abs(np.linalg.det(a[:3, :3])))
        m = a[:3, :3] / s
        np.testing.assert_allclose(m.T @ m, np.eye(3), atol=1e-12)
        assert a[2, 2] == pytest.approx(s) and (a[:3, 3] == 0).all() and (a[3] == [0, 0, 0, 1]).all()
        dets.append(np.sign(np.linalg.det(m)))
        scales.append(s)
    assert 0.3 < np.mean(np.array(dets) < 0) < 0.7                      # flipped about half the time
    assert 0.95 <= min(scales) and max(scales) <= 1.05
    off = AugmentConfig(flip=False, rotation_deg=0.0, scale=(1.0, 1.0))
    np.testing.assert_array_equal(draw_similarity(rng, off), np.eye(4))


def test_augmentation_keeps_points_in_their_boxes_and_transforms_rigid():
    """Every agent's points that fell in a car's box (its own labels, or the fused ground truth
    once moved into the ego frame) still do after augmentation; transforms stay rigid. A
    transform left as it was, or multiplied by A on one side only, moves the agents' points
    off the ego-frame boxes."""
    rng = np.random.default_rng(1)
    s = _sample(rng)
    aug = AugmentConfig(flip=True, rotation_deg=45.0, scale=(0.9, 1.1))
    for k in range(6):
        a = draw_similarity(np.random.default_rng(k), aug)
        t = augment(s, a)
        for r in t.transforms:
            np.testing.assert_allclose(r[:3, :3].T @ r[:3, :3], np.eye(3), atol=1e-9)
            assert np.linalg.det(r[:3, :3]) == pytest.approx(1.0)
        for i in range(3):
            before = points_in_boxes(s.clouds[i], s.agent_boxes[i])
            after = points_in_boxes(t.clouds[i], t.agent_boxes[i])
            np.testing.assert_array_equal(before, after)
            assert before.sum() >= 40
        merged, merged_aug = merge_agent_points(s.clouds, s.transforms), merge_agent_points(t.clouds, t.transforms)
        np.testing.assert_array_equal(points_in_boxes(merged, s.gt_boxes), points_in_boxes(merged_aug, t.gt_boxes))
        assert points_in_boxes(merged_aug, t.gt_boxes).sum() >= 3 * 40
        wrong = merge_agent_points(t.clouds, s.transforms)                  # transforms not conjugated
        assert points_in_boxes(wrong, t.gt_boxes).sum() < points_in_boxes(merged_aug, t.gt_boxes).sum()


def test_map_boxes_scales_sizes_and_turns_yaw():
    a = np.diag([2.0, -2.0, 2.0, 1.0])                                 # flip y, scale 2
    b = map_boxes(a, np.array([[1.0, 2.0, -1.0, 4.0, 2.0, 1.5, 0.5]]))
    np.testing.assert_allclose(b, [[2.0, -4.0, -2.0, 8.0, 4.0, 3.0, -0.5]], atol=1e-12)


@pytest.mark.parametrize("method", list(METHODS))
def test_batch_layout_and_target_rows_follow_the_registry(method):
    rng = np.random.default_rng(2)
    samples = [_sample(rng), _sample(rng)]
    inputs = Inputs(samples, CFG)
    batch = inputs.batch(method, [0, 1])
    m = METHODS[method]
    width = 3 if m.inputs == "agents" else 1
    assert batch.agent_mask.shape == (2, width) and bool(batch.agent_mask.all())
    assert set(batch.pillars["voxel_coords"][:, 0].tolist()) == set(range(2 * width))
    coder = box_coder(CFG, build_model(m.network, CFG))
    targets = batch.targets(coder)
    rows = 2 * width if m.targets == "own" else 2
    assert targets["pos_equal_one"].shape[0] == rows
    # each row's positives cover its own labels: an agent's in its frame, or the 3 fused cars
    labels = [s.agent_boxes[k] for s in samples for k in range(width)] if m.targets == "own" else \
        [s.gt_boxes for s in samples]
    assert all(int(targets["pos_equal_one"][r].sum()) >= len(labels[r]) > 0 for r in range(rows))
    again = inputs.batch(method, [0, 1])
    assert all(torch.equal(batch.pillars[k], again.pillars[k]) for k in batch.pillars)       # cached


def test_augmented_batches_are_drawn_fresh():
    rng = np.random.default_rng(3)
    inputs = Inputs([_sample(rng)], CFG)
    a = draw_similarity(np.random.default_rng(5), AugmentConfig(flip=True, rotation_deg=45.0, scale=(0.95, 1.05)))
    plain, turned = inputs.batch("attfuse", [0]), inputs.batch("attfuse", [0], [a])
    assert not torch.equal(plain.pillars["voxel_coords"], turned.pillars["voxel_coords"])
    np.testing.assert_allclose(turned.transforms[0].numpy(), augment(inputs.samples[0], a).transforms, atol=1e-12)
    assert torch.equal(inputs.batch("attfuse", [0]).pillars["voxel_coords"], plain.pillars["voxel_coords"])
