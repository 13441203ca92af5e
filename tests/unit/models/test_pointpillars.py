"""PointPillars detector: pillarisation, scatter, box coding, assignment, loss, and that it learns."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from models.box_coder import AnchorBoxCoder, axis_aligned_iou, standup_boxes
from models.detection_loss import DetectionLoss
from models.pointpillars import PillarFeatureNet, PointPillars, pillarize, scatter_to_bev
from typ.errors import TypError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


RANGE = (-4.0, -2.0, -3.0, 4.0, 2.0, 1.0)          # 8 x 4 m, 1 m pillars -> nx = 8, ny = 4


def _pillarize(points, **kw):
    args = dict(lidar_range=RANGE, voxel_size=1.0, max_points_per_pillar=3, max_pillars=100)
    return pillarize([np.asarray(points, dtype=np.float32)], **{**args, **kw})


def test_pillarize_groups_points_and_orders_pillars_by_first_appearance():
    pts = [[0.5, 0.5, 0.0, 0.1],      # pillar A: x cell 4, y cell 2
           [-3.5, -1.5, 0.0, 0.2],    # pillar B: x cell 0, y cell 0
           [0.9, 0.1, -1.0, 0.3],     # pillar A again
           [3.99, 1.99, 0.0, 0.4],    # pillar C: last cell (7, 3)
           [-4.0, -2.0, 0.0, 0.5],    # on the lower range edge: kept, pillar B
           [4.0, 0.0, 0.0, 0.6],      # x_max is excluded
           [0.0, 0.0, 1.0, 0.7],      # z_max is excluded
           [0.0, 0.0, -3.5, 0.8]]     # below z_min
    p = _pillarize(pts)
    assert p["voxel_coords"].tolist() == [[0, 0, 2, 4], [0, 0, 0, 0], [0, 0, 3, 7]]
    assert p["voxel_num_points"].tolist() == [2, 2, 1]
    f = p["voxel_features"]
    assert f.shape == (3, 3, 4)
    np.testing.assert_allclose(f[0, :2].numpy(), np.array([pts[0], pts[2]], np.float32))
    np.testing.assert_allclose(f[1, :2].numpy(), np.array([pts[1], pts[4]], np.float32))
    assert (f[0, 2] == 0).all() and (f[2, 1:] == 0).all()           # unused slots are zero


def test_pillarize_truncation_keeps_first_points_and_first_pillars():
    pts = [[0.1 * i, 0.2, 0.0, float(i)] for i in range(5)]        # 5 points, one pillar
    pts += [[-3.5, -1.5, 0.0, 10.0], [2.5, 1.5, 0.0, 11.0]]          # two more pillars
    p = _pillarize(pts, max_pillars=2)
    assert p["voxel_num_points"].tolist() == [3, 1]                  # capped at 3; third pillar dropped
    assert p["voxel_features"][0, :, 3].tolist() == [0.0, 1.0, 2.0]
    assert p["voxel_coords"][:, 2:].tolist() == [[2, 4], [0, 0]]
    again = _pillarize(pts, max_pillars=2)
    assert all(torch.equal(p[k], again[k]) for k in p)


def test_pillarize_batches_clouds_and_rejects_bad_input():
    clouds = [np.zeros((1, 4), np.float32), np.zeros((0, 4), np.float32), np.array([[1.5, 1.5, 0.0, 1.0]], np.float32)]
    p = pillarize(clouds, lidar_range=RANGE, voxel_size=1.0)
    assert p["voxel_coords"][:, 0].tolist() == [0, 2]
    with pytest.raises(TypError, match="clouds"):
        pillarize([np.zeros((3, 2))], lidar_range=RANGE, voxel_size=1.0)
    with pytest.raises(TypError, match="lidar_range"):
        pillarize([np.zeros((3, 4))], lidar_range=RANGE, voxel_size=0.3)


def test_pillar_feature_net_decorates_points_like_pillar_vfe():
    net = PillarFeatureNet(lidar_range=RANGE, voxel_size=1.0, out_channels=10).eval()
    with torch.no_grad():
        net.linear.weight.copy_(torch.eye(10))   # features pass through; eval BN is x / sqrt(1 + 1e-3)
    p = _pillarize([[0.75, 0.5, 0.25, 0.5], [0.25, 0.5, -0.75, 0.0]])   # pillar centre (0.5, 0.5, -1.0)
    with torch.no_grad():
        out = net(p["voxel_features"], p["voxel_num_points"], p["voxel_coords"])[0] * math.sqrt(1 + 1e-3)
    # [x, y, z, i], offset to the mean (0.5, 0.5, -0.25), offset to the pillar centre; max over points, relu
    expected = [0.75, 0.5, 0.25, 0.5, 0.25, 0.0, 0.5, 0.25, 0.0, 1.25]
    np.testing.assert_allclose(out.numpy(), expected, atol=1e-5)


def test_scatter_puts_each_pillar_at_its_bev_cell():
    feats = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    coords = torch.tensor([[1, 0, 2, 3], [0, 0, 0, 5]])
    bev = scatter_to_bev(feats, coords, batch_size=2, nx=6, ny=4)
    assert bev.shape == (2, 2, 4, 6)
    assert bev[1, :, 2, 3].tolist() == [1.0, 2.0] and bev[0, :, 0, 5].tolist() == [3.0, 4.0]
    assert bev.abs().sum() == 10.0


def test_point_lands_in_the_bev_cell_its_anchor_covers():
    torch.manual_seed(0)
    model = PointPillars(lidar_range=RANGE, voxel_size=1.0, layer_nums=(0,), layer_strides=(1,), num_filters=(4,),
                         upsample_strides=(1,), num_upsample_filters=(4,), pillar_channels=16).eval()
    bev = model.bev(_pillarize([[2.7, -1.2, 0.0, 1.0]]), 1)
    ys, xs = torch.nonzero(bev[0].abs().sum(0), as_tuple=True)
    coder = AnchorBoxCoder(lidar_range=RANGE, voxel_size=1.0, feature_stride=1)
    centre = coder.anchors[ys[0], xs[0], 0, :2]
    assert (ys.tolist(), xs.tolist()) == ([0], [6]) and centre.tolist() == [2.5, -1.5]


boxes_st = st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-3, 1), st.floats(0.5, 10),
                     st.floats(0.5, 5), st.floats(0.5, 4), st.floats(-math.pi, math.pi))


@settings(max_examples=60, deadline=None)
@given(box=boxes_st, anchor=boxes_st)
def test_encode_decode_round_trip(box, anchor):
    b = torch.tensor(box, dtype=torch.float64)
    a = torch.tensor(anchor, dtype=torch.float64)
    np.testing.assert_allclose(AnchorBoxCoder.decode(AnchorBoxCoder.encode(b, a), a).numpy(), b.numpy(),
                               rtol=1e-9, atol=1e-9)


def test_axis_aligned_iou_hand_cases():
    a = torch.tensor([[0.0, 0.0, 2.0, 2.0]])
    b = torch.tensor([[1.0, 0.0, 3.0, 2.0], [5.0, 5.0, 6.0, 6.0]])
    np.testing.assert_allclose(axis_aligned_iou(a, b, pixel_offset=0.0).numpy(), [[2 / 6, 0.0]])
    np.testing.assert_allclose(axis_aligned_iou(a, b).numpy(), [[6 / 12, 0.0]])   # OpenCOOD's +1 widths
    rotated = standup_boxes(torch.tensor([[0.0, 0.0, 0.0, 4.0, 2.0, 1.0, math.pi / 2]]))
    np.testing.assert_allclose(rotated.numpy(), [[-1.0, -2.0, 1.0, 2.0]], atol=1e-6)


def test_assignment_marks_the_anchor_under_a_box_positive():
    coder = AnchorBoxCoder(lidar_range=(-8, -8, -3, 8, 8, 1), voxel_size=0.5, feature_stride=2)
    assert coder.anchors.shape == (16, 16, 2, 7)
    anchor = coder.anchors[5, 9, 1]                              # the 90-degree anchor of cell (5, 9)
    labels = coder.assign_targets(anchor[None].numpy())
    pos, neg = labels["pos_equal_one"], labels["neg_equal_one"]
    assert pos[5, 9, 1] == 1 and neg[5, 9, 1] == 0
    assert pos[5, 9, 0] == 0                                      # the 0-degree anchor overlaps < 0.6
    assert torch.all(pos * neg == 0)
    assert torch.allclose(labels["targets"][5, 9, 7:], torch.zeros(7), atol=1e-6)
    assert labels["dir_targets"][5, 9, 1] == coder.direction_bin(anchor[6:7])[0]
    far = labels["neg_equal_one"][0, 0]
    assert far.tolist() == [1.0, 1.0]
    empty = coder.assign_targets(np.zeros((0, 7)))
    assert empty["pos_equal_one"].sum() == 0 and empty["neg_equal_one"].all()


def test_decode_head_applies_direction_bins():
    coder = AnchorBoxCoder(lidar_range=(-4, -4, -3, 4, 4, 1), voxel_size=1.0, feature_stride=4)   # 2 x 2 cells
    a = coder.num_anchors
    rm = torch.zeros(1, 7 * a, 2, 2)
    rm[:, 6::7] = 0.1                                                  # yaw residual 0.1 on every anchor
    dm = torch.zeros(1, 2 * a, 2, 2)
    dm[:, 0::2] = 5.0                                                  # every anchor picks bin 0
    boxes, scores = coder.decode_head({"psm": torch.zeros(1, a, 2, 2), "rm": rm, "dm": dm})
    assert boxes.shape == (1, 8, 7) and torch.allclose(scores, torch.full((1, 8), 0.5))
    # bin 0 is [pi/4, 5pi/4): yaw 0.1 (bin 1) turns by pi, pi/2 + 0.1 (bin 0) stays; then wrap to [-pi, pi)
    yaws = boxes[0, :, 6].view(4, 2)
    expected = [0.1 - math.pi, math.pi / 2 + 0.1]
    np.testing.assert_allclose(yaws.numpy(), np.tile(expected, (4, 1)), atol=1e-5)
    assert (coder.direction_bin(yaws.flatten()) == 0).all()


def test_regression_loss_is_blind_to_a_half_turn():
    loss = DetectionLoss()
    target = torch.tensor([0.1, 0, 0, 0, 0, 0, 0.3]).view(1, 1, 1, 7)
    labels = {"pos_equal_one": torch.ones(1, 1, 1, 1), "targets": target}
    same = loss({"psm": torch.zeros(1, 1, 1, 1), "rm": labels["targets"].permute(0, 3, 1, 2).clone()}, labels)
    flipped = labels["targets"].clone()
    flipped[..., 6] += math.pi
    turned = loss({"psm": torch.zeros(1, 1, 1, 1), "rm": flipped.permute(0, 3, 1, 2)}, labels)
    assert same["reg_loss"] < 1e-10 and turned["reg_loss"] < 1e-6 and same["dir_loss"] == 0


SMALL_RANGE = (-19.2, -9.6, -3.0, 19.2, 9.6, 1.0)
GT = np.array([[8.0, 4.0, -1.0, 4.0, 1.8, 1.6, 0.2], [-10.0, -5.0, -1.0, 4.5, 1.9, 1.5, 1.7],
               [12.0, -5.0, -1.0, 3.8, 1.7, 1.5, -2.8]])


def _synthetic_frame(rng: np.random.Generator) -> np.ndarray:
    """Points filling each gt box, plus a flat ground, in the sensor frame."""
    parts = []
    for x, y, z, l, w, h, yaw in GT:
        local = rng.uniform(-0.5, 0.5, (300, 3)) * [l, w, h]
        c, s = np.cos(yaw), np.sin(yaw)
        xy = local[:, :2] @ np.array([[c, s], [-s, c]]) + [x, y]
        parts.append(np.c_[xy, local[:, 2] + z, rng.uniform(0.2, 1.0, 300)])
    n = 2000
    parts.append(np.c_[rng.uniform(-19.2, 19.2, n), rng.uniform(-9.6, 9.6, n), rng.normal(-1.8, 0.02, n),
                       rng.uniform(0.0, 0.3, n)])
    return np.concatenate(parts).astype(np.float32)


def test_detector_overfits_one_frame():
    torch.manual_seed(0)
    model = PointPillars(lidar_range=SMALL_RANGE, voxel_size=0.4, pillar_channels=16, layer_nums=(1, 1),
                         layer_strides=(2, 2), num_filters=(16, 32), upsample_strides=(1, 2),
                         num_upsample_filters=(32, 32), max_pillars=4000)
    coder = AnchorBoxCoder(lidar_range=SMALL_RANGE, voxel_size=0.4, feature_stride=model.feature_stride)
    pillars = model.pillarize([_synthetic_frame(np.random.default_rng(0))])
    labels = coder.assign_batch([GT])
    criterion, opt = DetectionLoss(), torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(60):
        loss = criterion(model(pillars, 1), labels)["total_loss"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[39] < 0.5 * losses[0] and losses[-1] < 0.1 * losses[0]
    with torch.no_grad():   # train-mode BatchNorm: running stats (momentum 0.01) lag after 60 steps
        boxes, scores = coder.decode_head(model(pillars, 1))
    boxes, scores = boxes[0].double(), scores[0]
    dist = torch.cdist(boxes[:, :2], torch.from_numpy(GT[:, :2]))
    for g, gt in enumerate(GT):                   # the best box near each gt is on it, heading included
        best = torch.argmax(torch.where(dist[:, g] < 2.0, scores, -1.0))
        yaw_err = (boxes[best, 6].item() - gt[6] + math.pi) % (2 * math.pi) - math.pi
        assert scores[best] > 0.3 and dist[best, g] < 0.5 and abs(yaw_err) < 0.2
    confident = scores > 0.5                      # and no confident box is off every gt
    assert (dist[confident].min(1).values < 0.5).all()
