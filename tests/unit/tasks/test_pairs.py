"""(ego, reference) pairs of TYP §3.3 and what stage 2 feeds its adapter: x_e', never x_r.

A two-agent scene with hand-placed points, written in the OPV2V layout: the ego "1" at world
(100, 50) facing +x, the reference "2" at world (104, 50) facing +y (yaw 90°). A point at
(x, y) in the ego's frame is at (100 + x, 50 + y) in the world: 4 - x behind the reference's
sensor along the world x, which is the reference's -y, and y along its +x, so at (y, 4 - x).
"""
import numpy as np
import pytest
import torch

from models.vqvae import PooledBoxMap
from tasks import stage1, stage2
from tasks.pairs import iter_pairs
from typ.config import config_from_dict
from typ.formats.opv2v import write_scene
from typ.geometry import pose_to_matrix
from typ.scene import AgentView, Scene
from typ.voxel import Grid, box_map, points_to_reference, voxelize

GRID = Grid((-8.0, 8.0), (-8.0, 8.0), (-2.0, 2.0), (16, 16, 4))  # 1 m voxels, centres at .5
EGO_POSE = pose_to_matrix([100.0, 50.0, 0.0, 0.0, 0.0, 0.0])
REF_POSE = pose_to_matrix([104.0, 50.0, 0.0, 0.0, 90.0, 0.0])
#: the ego's points in its frame [x, y, z, intensity] and, by hand, the same points in the reference's
EGO_POINTS = np.array([[3.5, 3.5, 0.5, 0.2], [-2.5, 0.5, -1.5, 0.4], [6.5, -1.5, 1.5, 0.6]], np.float32)
EGO_IN_REF = np.array([[3.5, 0.5, 0.5], [0.5, 6.5, -1.5], [-1.5, -2.5, 1.5]])
#: the reference's own points in its frame and, by hand, in the ego's: (x, y) -> (4 - y, x)
REF_POINTS = np.array([[-3.5, -3.5, 0.5, 0.8], [0.5, 0.5, -1.5, 1.0]], np.float32)
REF_IN_EGO = np.array([[7.5, -3.5, 0.5], [3.5, 0.5, -1.5]])
#: the ego in the reference's frame: rotated by -90°, at (0, 4)
EGO_POSE_IN_REF = np.array([[0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 4.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
#: the reference's labels, in its frame: a car ahead-right and a pedestrian (not a vehicle)
REF_BOXES = np.array([[5.0, -5.0, 0.0, 4.0, 2.0, 1.5, 0.0], [-5.0, 5.0, 0.0, 0.8, 0.8, 1.8, 0.0]])
EGO_BOXES = np.array([[-4.0, -4.0, 0.0, 4.0, 2.0, 1.5, 0.3]])


def _cells(points) -> set:
    return {tuple(int(v) for v in np.floor((p[:3] - GRID.lower) / GRID.voxel_size)) for p in points}


def _occupied(grid_chw) -> set:
    return {(i, j, k) for k, i, j in zip(*np.nonzero(grid_chw))}


@pytest.fixture(scope="module")
def scene():
    return Scene("source_train_0000", "000000", {
        "1": AgentView("1", EGO_POINTS, EGO_POSE, EGO_BOXES, ("car",), np.array([9])),
        "2": AgentView("2", REF_POINTS, REF_POSE, REF_BOXES, ("car", "pedestrian"), np.array([7, 8]))})


@pytest.fixture(scope="module")
def split_root(tmp_path_factory, scene):
    root = tmp_path_factory.mktemp("source") / "train"
    write_scene(scene, root)
    return root


def test_iter_pairs_moves_the_ego_cloud_to_the_reference_pose(split_root):
    pairs = {(p.ego, p.reference): p for p in iter_pairs(split_root, GRID)}
    assert sorted(pairs) == [("1", "2"), ("2", "1")]  # every ordered pair of agents
    p = pairs["1", "2"]
    assert (p.scenario, p.timestamp) == ("source_train_0000", "000000")
    np.testing.assert_allclose(p.ego_points[:, :3], EGO_IN_REF, atol=1e-5)     # x_e' before voxelization
    np.testing.assert_allclose(p.ego_points[:, 3], EGO_POINTS[:, 3], atol=1e-6)  # intensity kept (k/255 survive the pcd)
    np.testing.assert_allclose(p.ego_pose_in_ref, EGO_POSE_IN_REF, atol=1e-9)
    assert p.x_e.shape == (4, 16, 16) and _occupied(p.x_e) == _cells(EGO_IN_REF)  # x_e': the moved ego cloud
    assert _occupied(p.x_r) == _cells(REF_POINTS)                               # x_r: the reference's own cloud
    np.testing.assert_allclose(p.ref_points, REF_POINTS, atol=1e-6)
    np.testing.assert_allclose(p.ref_boxes, REF_BOXES[:1], atol=1e-6)           # its vehicles only
    np.testing.assert_array_equal(p.y_r, box_map(REF_BOXES, GRID).transpose(2, 0, 1))  # y_r: the reference's boxes
    back = pairs["2", "1"]
    np.testing.assert_allclose(back.ego_points[:, :3], REF_IN_EGO, atol=1e-5)
    assert _occupied(back.x_e) == _cells(REF_IN_EGO) and _occupied(back.x_r) == _cells(EGO_POINTS)
    # single-agent target data: only the scenario's ego is an ego
    assert [(q.ego, q.reference) for q in iter_pairs(split_root, GRID, ego_only=True)] == [("1", "2")]


class PooledOccupancy(torch.nn.Module):
    """A stand-in E_src: x^f = the 2x2 average of each height channel (C = c_x = 4)."""

    def encode_pre_quant(self, x):
        return torch.nn.functional.avg_pool2d(x, 2)


def test_the_stage2_adapter_is_fed_x_e_prime_never_x_r(split_root, scene, tmp_path):
    """From the scenario folder to the adapter's input: every condition F_AD trains on is the
    standardised E(x_e') of a pair, x_e' computed here independently from the ego's cloud."""
    tuples = stage2.collect(iter_pairs(split_root, GRID), grid=GRID)
    cfg = config_from_dict({"stage1": {"unet": {"block_out_channels": [8, 8], "norm_num_groups": 4,
                                                 "cross_attention_dim": 8, "attention_head_dim": 4}},
                            "stage2": {"epochs": 1, "batch_size": 2, "checkpoint_every": 10}})
    torch.manual_seed(0)
    ldm = stage1.build(cfg.stage1, 4, 1, 8)
    encoder, box_encoder = PooledOccupancy(), PooledBoxMap(downsample=2)
    with torch.no_grad():  # statistics that are not (0, 1): what the adapter sees is standardised
        ldm.latent_mean.copy_(torch.tensor([0.01, 0.02, -0.03, 0.04]).view(1, 4, 1, 1))
        ldm.latent_std.copy_(torch.tensor([0.1, 0.2, 0.3, 0.05]).view(1, 4, 1, 1))
    data = stage2.encode(tuples, encoder, box_encoder, ldm)

    def standardised(points):
        grid = torch.from_numpy(voxelize(points, GRID).transpose(2, 0, 1)[None].astype(np.float32))
        return ldm.normalize(encoder.encode_pre_quant(grid))[0]

    x_e_prime = {("1", "2"): points_to_reference(scene.agents["1"].points, EGO_POSE, REF_POSE),
                 ("2", "1"): points_to_reference(scene.agents["2"].points, REF_POSE, EGO_POSE)}
    x_r = {("1", "2"): scene.agents["2"].points, ("2", "1"): scene.agents["1"].points}
    order = [(p.ego, p.reference) for p in iter_pairs(split_root, GRID)]
    for row, pair in enumerate(order):
        torch.testing.assert_close(data.ego[row], standardised(x_e_prime[pair]))
        torch.testing.assert_close(data.z0[row], standardised(x_r[pair]))  # the target of Eq. 7
        assert not torch.allclose(data.ego[row], standardised(x_r[pair]))
    seen = []
    adapter = stage2.build_adapter(ldm, res_blocks=1, seed=0)
    adapter.register_forward_pre_hook(lambda module, args: seen.append(args[0].detach().clone()))
    stage2.fit_adapter(adapter, ldm, "linear", 1000, data, name="adapter", settings=stage2.settings_of(
        cfg.stage2, seed=0, min_snr=0.0), views=len(tuples), key_extra={}, out=tmp_path, log_fn=lambda v, s: None)
    fed = torch.cat(seen)
    assert len(fed) == 2  # one step of batch 2
    for condition in fed:
        assert any(torch.equal(condition, e) for e in data.ego)
        assert not any(torch.allclose(condition, z) for z in data.z0)
