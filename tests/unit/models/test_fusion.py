"""BEV warping, communication range, and the fusion modules (none, early, late, AttFuse, V2X-ViT)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from models.box_coder import AnchorBoxCoder
from models.fusion import (METHODS, AttFuse, EarlyFusion, FusionModule, HeteroAgentAttention, LateFusion, NoFusion,
                           V2XViT, build, compressed, merge_agent_points, method_of, quantize, transform_boxes)
from models.pointpillars import PointPillars, pillarize
from models.warp import communication_mask, warp_bev
from typ.geometry import pose_to_matrix, relative_transform, transform_boxes as np_transform_boxes, transform_points


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _translation(x: float, y: float) -> np.ndarray:
    t = np.eye(4)
    t[0, 3], t[1, 3] = x, y
    return t[None]


# ------------------------------------------------------------------ warp_bev


def test_identity_warp_leaves_features_unchanged():
    f = torch.randn(2, 3, 6, 8)
    out = warp_bev(f, np.stack([np.eye(4)] * 2), voxel_size=0.5)
    assert out.dtype == f.dtype and torch.allclose(out, f, atol=1e-6)


def test_one_cell_translation_shifts_by_one_cell():
    f = torch.arange(24.0).view(1, 1, 4, 6)
    along_x = warp_bev(f, _translation(0.5, 0.0), voxel_size=0.25, downsample_rate=2)   # one 0.5 m cell in +x
    assert torch.allclose(along_x[..., 1:], f[..., :-1], atol=1e-6) and (along_x[..., 0] == 0).all()
    along_y = warp_bev(f, _translation(0.0, -0.5), voxel_size=0.5)                     # one cell in -y (rows)
    assert torch.allclose(along_y[..., :-1, :], f[..., 1:, :], atol=1e-6) and (along_y[..., -1, :] == 0).all()


def test_quarter_turn_matches_rot90():
    f = torch.randn(1, 2, 6, 6)
    t = pose_to_matrix([0, 0, 0, 0, 90, 0])[None]                       # agent frame turned +90 deg (CCW)
    # rows are y, columns x: a CCW turn carries the x axis (dim -1) onto the y axis (dim -2)
    assert torch.allclose(warp_bev(f, t, voxel_size=1.0), torch.rot90(f, 1, dims=(-1, -2)), atol=1e-5)


def test_warp_follows_relative_transform():
    """A blob where agent B sees a world point lands where the ego sees the same point."""
    ego_pose, agent_pose = [10.0, 5.0, 0.0, 0.0, 20.0, 0.0], [13.0, 7.0, 0.3, 0.0, 75.0, 0.0]
    world = pose_to_matrix(ego_pose) @ np.array([2.0, -1.5, 0.0, 1.0])
    p_ego = np.linalg.inv(pose_to_matrix(ego_pose)) @ world
    p_agent = np.linalg.inv(pose_to_matrix(agent_pose)) @ world
    cell, n = 0.25, 64                                                   # 16 m x 16 m map centred on the sensor
    centres = (np.arange(n) + 0.5) * cell - n * cell / 2
    assert np.abs(p_agent[:2]).max() < 6
    yy, xx = np.meshgrid(centres, centres, indexing="ij")
    blob = np.exp(-((xx - p_agent[0]) ** 2 + (yy - p_agent[1]) ** 2) / (2 * 0.5 ** 2))
    warped = warp_bev(torch.from_numpy(blob)[None, None], relative_transform(agent_pose, ego_pose)[None],
                      voxel_size=cell)[0, 0].numpy()
    centroid = np.array([(warped * xx).sum(), (warped * yy).sum()]) / warped.sum()
    np.testing.assert_allclose(centroid, p_ego[:2], atol=0.02)
    i, j = np.unravel_index(np.argmax(warped), warped.shape)
    assert abs(centres[j] - p_ego[0]) <= cell and abs(centres[i] - p_ego[1]) <= cell


def test_communication_mask_uses_the_70_m_range():
    poses = np.array([[0, 0, 0, 0, 0, 0], [80, 0, 0, 0, 0, 0], [0, 50, 1, 0, 30, 0], [42, 56, 0, 0, 0, 0]], float)
    assert communication_mask(poses, poses[0]).tolist() == [True, False, True, True]     # 70 m exactly is in
    matrices = np.stack([pose_to_matrix(p) for p in poses])
    assert communication_mask(matrices, matrices[0], comm_range=60.0).tolist() == [True, False, True, False]


# ------------------------------------------------------------- fusion modules
RANGE = (-12.8, -6.4, -3.0, 12.8, 6.4, 1.0)
B, L = 2, 3
POSES = np.array([[[0, 0, 0, 0, 0, 0], [6, 2, 0, 0, 30, 0], [-5, 1, 0, 0, -90, 0]],
                  [[3, 3, 0, 0, 10, 0], [0, 0, 0, 0, 180, 0], [1, 2, 0, 0, 0, 0]]], float)
MASK = torch.tensor([[True, True, True], [True, True, False]])


def _detector() -> PointPillars:
    torch.manual_seed(0)
    return PointPillars(lidar_range=RANGE, voxel_size=0.4, pillar_channels=8, layer_nums=(1, 1), layer_strides=(2, 2),
                        num_filters=(8, 16), upsample_strides=(1, 2), num_upsample_filters=(8, 8), max_pillars=2000)


def _v2xvit(detector, **kw) -> V2XViT:
    args = dict(dim=16, depth=1, heads=2, dim_head=8, window_sizes=(2, 4), window_heads=(2, 2),
                window_dim_heads=(8, 8), mlp_dim=16, dropout=0.0)
    return V2XViT(detector=detector, **{**args, **kw})


def _clouds(seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [np.c_[rng.uniform(-12, 12, 1500), rng.uniform(-6, 6, 1500), rng.uniform(-2.5, 0.5, 1500),
                  rng.uniform(0, 1, 1500)].astype(np.float32) for _ in range(B * L)]


def _transforms(poses=POSES) -> np.ndarray:
    return np.stack([[relative_transform(p, s[0]) for p in s] for s in poses])


def _run(module, clouds, transforms=None, mask=MASK, **kw):
    pillars = pillarize(clouds, lidar_range=RANGE, voxel_size=0.4, max_pillars=2000)
    return module(pillars, agent_mask=mask, transforms=_transforms() if transforms is None else transforms, **kw)


INTERMEDIATE = {"none": lambda d: NoFusion(detector=d), "attfuse": lambda d: AttFuse(detector=d), "v2xvit": _v2xvit}


@pytest.mark.parametrize("name", INTERMEDIATE)
def test_shapes_and_where_gradients_flow(name):
    det = _detector()
    module = INTERMEDIATE[name](det).train()
    pillars = det.pillarize(_clouds())
    pillars["voxel_features"].requires_grad_(True)
    out = module(pillars, agent_mask=MASK, transforms=_transforms())
    h, w = det.ny // module.feature_stride, det.nx // module.feature_stride
    assert {k: tuple(v.shape) for k, v in out.items()} == {"psm": (B, 2, h, w), "rm": (B, 14, h, w), "dm": (B, 4, h, w)}
    sum((v ** 2).mean() for v in out.values()).backward()
    assert det.pillar_net.linear.weight.grad.abs().sum() > 0
    grad = pillars["voxel_features"].grad.abs().sum((1, 2))
    slot = pillars["voxel_coords"][:, 0]
    per_slot = torch.stack([grad[slot == s].sum() for s in range(B * L)]).view(B, L)
    assert (per_slot[:, 0] > 0).all() and per_slot[1, 2] == 0          # the masked agent gets nothing
    assert (per_slot[:, 1] > 0).all() == (name != "none")              # other agents reach the ego only if fused
    if name == "v2xvit":
        att = module.layers[0][1]
        assert att.relation_att.grad.abs().sum() > 0 and att.relation_msg.grad.abs().sum() > 0


def test_attfuse_over_one_agent_returns_its_features():
    x = torch.randn(2, 1, 5, 4, 3)
    assert torch.equal(AttFuse.attend(x, torch.ones(2, 1, 4, 3, dtype=torch.bool)), x[:, 0])
    det = _detector().eval()
    ego_only = torch.tensor([[True, False, False]] * B)
    fused = _run(AttFuse(detector=det), _clouds(), mask=ego_only)
    alone = _run(NoFusion(detector=det), _clouds(), mask=ego_only)
    assert all(torch.allclose(fused[k], alone[k], atol=1e-6) for k in fused)


@pytest.mark.parametrize("name", ["attfuse", "v2xvit"])
def test_ego_output_ignores_the_order_of_other_agents(name):
    module = INTERMEDIATE[name](_detector()).eval()
    types = torch.tensor([[0, 1, 0], [0, 0, 0]])
    delay = torch.tensor([[0, 1, 2], [0, 3, 0]])
    kw = {"agent_types": types, "time_delay": delay} if name == "v2xvit" else {}
    base = _run(module, _clouds(), **kw)
    order = [0, 2, 1, 3, 4, 5]                                          # swap agents 1 and 2 of sample 0
    clouds = [_clouds()[i] for i in order]
    poses = POSES.copy()
    poses[0] = poses[0, [0, 2, 1]]
    if kw:
        kw = {"agent_types": torch.tensor([[0, 0, 1], [0, 0, 0]]), "time_delay": torch.tensor([[0, 2, 1], [0, 3, 0]])}
    swapped = _run(module, clouds, transforms=_transforms(poses), **kw)
    assert all(torch.allclose(base[k], swapped[k], atol=1e-5) for k in base)


@pytest.mark.parametrize("name", list(INTERMEDIATE) + ["late"])
def test_masked_agents_do_not_change_the_output(name):
    det = _detector()
    module = LateFusion(detector=det) if name == "late" else INTERMEDIATE[name](det)
    module.train()                                                      # BatchNorm must not see them either
    other_clouds, other_t = _clouds(), _transforms()
    other_clouds[5] = _clouds(seed=7)[5] * 0.5                          # sample 1, slot 2 is masked
    other_t[1, 2] = 0.0
    if name == "late":
        a = module(det.pillarize(_clouds()), agent_mask=MASK)
        b = module(det.pillarize(other_clouds), agent_mask=MASK)
    else:
        a, b = _run(module, _clouds()), _run(module, other_clouds, transforms=other_t)
    assert all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("name", ["attfuse", "v2xvit"])
def test_masked_slot_or_agent_out_of_view_is_no_agent(name):
    module = INTERMEDIATE[name](_detector()).eval()
    clouds, t = _clouds(), _transforms()
    mask = torch.tensor([[True, True, False], [True, True, False]])
    with_slot = _run(module, clouds, mask=mask)
    two = [c for i, c in enumerate(clouds) if i % L < 2]
    without = _run(module, two, transforms=t[:, :2], mask=mask[:, :2])
    assert all(torch.allclose(with_slot[k], without[k], atol=1e-6) for k in with_slot)
    far = t.copy()
    far[0, 1] = _translation(200.0, 0.0)[0]                             # its map misses the ego's entirely
    out_of_view = _run(module, clouds, transforms=far, mask=mask)
    ego_only = _run(module, clouds, mask=torch.tensor([[True, False, False], [True, True, False]]))
    assert all(torch.allclose(out_of_view[k][0], ego_only[k][0], atol=1e-6) for k in ego_only)


def test_v2xvit_depends_on_agent_type_and_delay():
    module = _v2xvit(_detector()).eval()
    base = _run(module, _clouds())["psm"]
    rsu = _run(module, _clouds(), agent_types=torch.tensor([[0, 1, 0], [0, 0, 0]]))["psm"]
    late = _run(module, _clouds(), time_delay=torch.tensor([[0, 2, 0], [0, 0, 0]]))["psm"]
    assert not torch.allclose(base[0], rsu[0]) and torch.equal(base[1], rsu[1])
    assert not torch.allclose(base[0], late[0])


def test_hetero_attention_matches_its_pairwise_definition():
    torch.manual_seed(0)
    att = HeteroAgentAttention(dim=6, heads=2, dim_head=3, num_types=2).eval()
    x, types = torch.randn(2, 3, 2, 2, 6), torch.tensor([[0, 1, 1], [1, 0, 0]])
    mask = torch.ones(2, 3, 2, 2, dtype=torch.bool)
    mask[0, 2, 0, 1] = False
    out = att(x, mask, types)
    q, k, v = (proj(x, types).view(2, 3, 2, 2, 2, 3) for proj in (att.q, att.k, att.v))
    expected = torch.zeros(2, 3, 2, 2, 2, 3)
    for b in range(2):
        for i in range(3):
            rel = [types[b, i] * 2 + types[b, j] for j in range(3)]
            for y in range(2):
                for z in range(2):
                    for m in range(2):
                        logits = torch.stack([q[b, i, y, z, m] @ att.relation_att[rel[j], m] @ k[b, j, y, z, m]
                                              for j in range(3)]) * 3 ** -0.5
                        logits[~mask[b, :, y, z]] = float("-inf")
                        msgs = torch.stack([att.relation_msg[rel[j], m].T @ v[b, j, y, z, m] for j in range(3)])
                        expected[b, i, y, z, m] = logits.softmax(0) @ msgs
    assert torch.allclose(out, att.out(expected.reshape(2, 3, 2, 2, 6), types), atol=1e-5)


def test_v2xvit_warm_started_on_the_single_map_starts_as_no_fusion_and_learns():
    """With the shrink keeping the backbone map's width and stride, a warm-started V2X-ViT is the
    single-agent detector on the ego's cloud, whatever the others send; its zeroed residual branches
    get gradients. On OpenCOOD's stride-2 shrink the head stays fresh."""
    det = _detector().eval()
    module = _v2xvit(det, dim=det.backbone.out_channels, shrink_stride=1)
    assert module.keeps_single_map(det)
    module.warm_start(det)
    module.eval()
    fused, alone = _run(module, _clouds()), _run(NoFusion(detector=det), _clouds())
    for key in ("psm", "rm", "dm"):
        torch.testing.assert_close(fused[key], alone[key], atol=1e-5, rtol=1e-5)
    module.train()
    sum((v ** 2).mean() for v in _run(module, _clouds()).values()).backward()
    _, agent_att, _, window_att, _, mlp = module.layers[0]
    for layer in (agent_att.out.layers[0], window_att.branches[0].out[0], mlp[3], module.rte):
        assert layer.weight.grad.abs().sum() > 0
    fresh = _v2xvit(det)                           # stride 2, width 16 of a 16-wide map: not the single map
    assert not fresh.keeps_single_map(det)
    head = {k: v.clone() for k, v in fresh.head.state_dict().items()}
    fresh.warm_start(det)
    assert all(torch.equal(v, fresh.head.state_dict()[k]) for k, v in head.items())


def test_v2xvit_pads_maps_that_windows_do_not_tile():
    det = _detector()
    module = _v2xvit(det, window_sizes=(3,), window_heads=(2,), window_dim_heads=(8,)).eval()
    out = _run(module, _clouds())
    assert out["psm"].shape == (B, 2, det.ny // 4, det.nx // 4) and torch.isfinite(out["psm"]).all()


def test_early_fusion_merges_points_in_the_ego_frame():
    clouds = _clouds()[:3]
    t = _transforms()[0]
    merged = merge_agent_points(clouds, t, agent_mask=[True, True, False])
    assert merged.dtype == np.float32 and len(merged) == len(clouds[0]) + len(clouds[1])
    np.testing.assert_allclose(merged[len(clouds[0]):], transform_points(t[1], clouds[1].astype(np.float64)),
                               atol=1e-5)
    np.testing.assert_array_equal(merged[:len(clouds[0])], clouds[0])
    det = _detector()
    out = EarlyFusion(detector=det)(det.pillarize([merged, merged]), agent_mask=torch.ones(2, 1, dtype=torch.bool),
                                    transforms=np.eye(4)[None, None].repeat(2, 0))
    assert out["psm"].shape == (2, 2, det.ny // 2, det.nx // 2)


def test_late_fusion_moves_each_agents_boxes_into_the_ego_frame():
    det = _detector().eval()
    module = LateFusion(detector=det)
    with torch.no_grad():
        out = module(det.pillarize(_clouds()), agent_mask=MASK)
    assert out["psm"].shape[0] == int(MASK.sum())
    coder = AnchorBoxCoder(lidar_range=RANGE, voxel_size=0.4, feature_stride=module.feature_stride)
    merged = module.boxes_in_ego(out, coder, agent_mask=MASK, transforms=_transforms(), score_threshold=0.0,
                                 max_boxes_per_agent=4)
    own = coder.decode_predictions(out, score_threshold=0.0, max_boxes=4)          # per agent, own frames
    t = _transforms()
    boxes, scores = merged[0]
    assert boxes.dtype == torch.float64 and boxes.shape == (12, 7) and scores.shape == (12,)
    assert torch.allclose(boxes[:4], own[0][0].double())                          # the ego's are not moved
    np.testing.assert_allclose(boxes[4:8].numpy(), np_transform_boxes(t[0, 1], own[1][0].double().numpy()),
                               atol=1e-9)
    assert merged[1][0].shape == (8, 7)                                             # sample 1: two agents
    turned = transform_boxes(torch.tensor([[1.0, 0, 0, 4, 2, 1.5, 3.0]]), torch.from_numpy(pose_to_matrix(
        [0, 0, 0, 0, 90, 0])))
    assert turned[0, 6].item() == pytest.approx(3.0 + math.pi / 2 - 2 * math.pi)


# ------------------------------------------------------------------ registry


def test_every_registered_method_builds_and_runs_with_one_signature():
    clouds = _clouds()
    for name, m in METHODS.items():
        det = _detector()
        options = {"dim": 16, "depth": 1, "heads": 2, "dim_head": 8, "window_sizes": (2, 4), "window_heads": (2, 2),
                   "window_dim_heads": (8, 8), "mlp_dim": 16, "dropout": 0.0} if m.options else None
        module = build(name, det, options).eval()
        assert method_of(module) == name and isinstance(module, m.module)
        if m.inputs == "merged":
            merged = [merge_agent_points(clouds[b * L:(b + 1) * L], _transforms()[b], MASK[b].numpy()) for b in range(B)]
            out = module(det.pillarize(merged), agent_mask=torch.ones(B, 1, dtype=torch.bool),
                         transforms=np.eye(4)[None, None].repeat(B, 0))
        else:
            out = _run(module, clouds)
        rows = int(MASK.sum()) if m.targets == "own" and m.inputs == "agents" else B
        assert out["psm"].shape[0] == rows, name


def test_no_and_late_fusion_are_one_network():
    det = _detector()
    none, late = NoFusion(detector=det), LateFusion(detector=det)
    assert none.state_dict().keys() == late.state_dict().keys()
    assert METHODS["none"].network == METHODS["late"].network == "late"


@pytest.mark.parametrize("name", ["attfuse", "v2xvit"])
def test_compressed_messages_change_only_with_few_bits_and_shrink_the_message(name):
    module = INTERMEDIATE[name](_detector()).eval()
    with torch.no_grad():
        exact = _run(module, _clouds())["psm"]
        with compressed(module, 16):
            fine = _run(module, _clouds())["psm"]
            fine_bytes = module.message_bytes(points=0, boxes=0)
        with compressed(module, 2):
            coarse = _run(module, _clouds())["psm"]
            coarse_bytes = module.message_bytes(points=0, boxes=0)
        ego_only = _run(module, _clouds(), mask=torch.tensor([[True, False, False]] * B))["psm"]
        with compressed(module, 2):
            ego_only_2 = _run(module, _clouds(), mask=torch.tensor([[True, False, False]] * B))["psm"]
    assert module.message_bits is None
    d_fine, d_coarse = (exact - fine).abs().max(), (exact - coarse).abs().max()
    assert d_fine < d_coarse / 10 and d_coarse > 0
    assert torch.equal(ego_only, ego_only_2)                          # the ego's own features are never quantised
    full = module.message_bytes(points=0, boxes=0)
    assert full > fine_bytes > coarse_bytes > 0 and full / coarse_bytes > 10


def test_messages_of_points_and_boxes_and_nothing():
    det = _detector()
    assert NoFusion(detector=det).message_bytes(points=1000, boxes=5) == 0
    assert EarlyFusion(detector=det).message_bytes(points=1000, boxes=5) == 16_000
    assert LateFusion(detector=det).message_bytes(points=1000, boxes=5) == 160
    with pytest.raises(Exception, match="features"):
        with compressed(LateFusion(detector=det), 8):
            pass


def test_quantization_is_exact_at_high_bit_widths_and_coarse_at_low():
    x = torch.randn(2, 3, 5, 6)
    fine = quantize(x, 16, (2, 3))
    assert (fine - x).abs().max() <= (x.amax((2, 3)) - x.amin((2, 3))).max() / (2 ** 16 - 1)
    coarse = quantize(x, 2, (2, 3))
    assert all(len(torch.unique(coarse[b, c])) <= 4 for b in range(2) for c in range(3))
    assert torch.allclose(coarse.amin((2, 3)), x.amin((2, 3))) and torch.allclose(coarse.amax((2, 3)), x.amax((2, 3)))


def test_params_checking_reads_the_registry_without_torch():
    """The config offers the registry's fusion methods and samplers in its order, and reading them
    imports neither torch nor diffusers (``typ check`` and ``typ --help`` stay fast)."""
    import subprocess
    import sys

    code = ("import sys, typing, typ.config as c; from typ.registry import METHODS, SAMPLERS; "
            "assert c.FUSION_METHODS == c.SSC_METHODS == tuple(METHODS); "
            "assert typing.get_args(c.Sampler) == tuple(SAMPLERS); "
            "assert not {'torch', 'diffusers'} & set(sys.modules), sorted(m for m in sys.modules if 'torch' in m)[:5]")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)
    for m in METHODS.values():   # every entry names a module of models.fusion
        assert issubclass(m.module, FusionModule) and m.module.__name__ == m.module_name
