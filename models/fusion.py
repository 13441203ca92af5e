"""Collaborative fusion on one PointPillars detector: none, early, late, AttFuse, V2X-ViT (TYP §4).

Every method is a :class:`FusionModule` with one forward signature,
``module(pillars, *, agent_mask, transforms, time_delay=None, agent_types=None)``, and the hooks
the benchmark needs: ``detections`` (head -> ego-frame boxes), ``message_bytes`` and
``message_bits`` (what a cooperating agent sends, and its quantisation), ``warm_start`` (from a
trained single-agent detector). :data:`models.registry.METHODS` is the registry (torch-free, so
the config reads it): each :class:`~models.registry.FusionMethod` names its module, display name,
inputs, training targets, message and whether it runs another method's network (no fusion runs
late fusion's single-agent detector on the ego's cloud only, as OpenCOOD). Its order is the
order of the tables; ``typ.config`` takes the allowed names from it. A new method is a module
here and an entry there (plus a config block if it has options).

Batch layout: B samples of L agent slots, agent 0 the ego. ``pillars`` is ``pillarize`` of the
B*L clouds in b-major order (cloud ``b * L + l``, each in its own sensor frame; empty clouds for
unused slots); ``agent_mask`` (B, L) bool marks present agents within communication range
(``warp.communication_mask``), ``[:, 0]`` all True; ``transforms`` (B, L, 4, 4) float64
agent->ego (``typ.geometry.relative_transform(agent_pose, ego_pose)``). Early fusion's batches
have L = 1, the merged ego-frame cloud. Masked slots never reach the network, not even its
BatchNorm statistics. Outputs are the ego's head dict (``psm``, ``rm``, ``dm``); late fusion's
has a row per present agent.

Following OpenCOOD (``point_pillar_intermediate.py`` + ``att_bev_backbone.py`` + ``fuse_modules/
self_attn.py`` for AttFuse; ``point_pillar_transformer.py`` + ``fuse_modules/v2xvit_basic.py``,
``hmsa.py``, ``mswin.py``, ``sub_modules/split_attn.py`` for V2X-ViT), but agents' features are
computed in their own frames and warped into the ego frame (``models/warp.py``), as V2X-ViT's
STTF does, instead of projecting points first; cells a warped map does not cover are masked.
"""
from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from models.box_coder import AnchorBoxCoder
from models.pointpillars import PointPillars, pillars_to_bev
from models.registry import METHODS, SINGLE_AGENT, FusionMethod  # noqa: F401  (the registry, re-exported)
from models.warp import warp_bev, warp_valid_mask
from typ.errors import TypError
from typ.geometry import transform_points

BYTES_PER_POINT = 16        # x, y, z, intensity as float32
BYTES_PER_BOX = 32          # 7 box parameters and a score as float32


def merge_agent_points(clouds: Sequence, transforms, agent_mask=None) -> np.ndarray:
    """Early fusion's input: agents' (n_i, F) clouds moved into the ego frame (float64) and
    concatenated, cast to float32 once in the ego frame; transforms (L, 4, 4) agent->ego."""
    t = np.asarray(transforms, dtype=np.float64)
    keep = np.ones(len(clouds), bool) if agent_mask is None else np.asarray(agent_mask, bool)
    moved = [transform_points(t[i], np.asarray(c, dtype=np.float64)) for i, c in enumerate(clouds) if keep[i]]
    return np.concatenate(moved).astype(np.float32)


def transform_boxes(boxes: torch.Tensor, transform: torch.Tensor) -> torch.Tensor:
    """(K, 7) boxes moved by a (4, 4) rigid transform in float64 (``typ.geometry.transform_boxes``)."""
    b, t = boxes.to(torch.float64), transform.to(torch.float64)
    rot = t[:3, :3]
    heading = torch.stack([torch.cos(b[:, 6]), torch.sin(b[:, 6]), torch.zeros_like(b[:, 6])], 1) @ rot.T
    yaw = torch.remainder(torch.atan2(heading[:, 1], heading[:, 0]) + math.pi, 2 * math.pi) - math.pi
    return torch.cat([b[:, :3] @ rot.T + t[:3, 3], b[:, 3:6], yaw[:, None]], 1)


def _check(agent_mask: torch.Tensor) -> torch.Tensor:
    agent_mask = torch.as_tensor(agent_mask).bool()
    if agent_mask.ndim != 2 or not bool(agent_mask[:, 0].all()):
        raise TypError(None, "agent_mask", "(B, L) bool with the ego (column 0) present", tuple(agent_mask.shape))
    return agent_mask


def _regroup(x: torch.Tensor, keep: torch.Tensor, b: int, l: int) -> torch.Tensor:
    """(V, ...) features of the kept slots -> (B, L, ...), zeros in the others."""
    out = x.new_zeros(b * l, *x.shape[1:]).index_put((keep.nonzero()[:, 0],), x)
    return out.view(b, l, *x.shape[1:])


def _to_ego(x: torch.Tensor, agent_mask: torch.Tensor, transforms, *, voxel_size: float, stride: int,
            lidar_range: Sequence[float]) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, L, C, h, w) agents' maps -> the same warped into the ego frame, and (B, L, h, w) bool
    validity (agent present and the cell inside its map). The ego is not resampled."""
    b, l, c, h, w = x.shape
    others = agent_mask.clone()
    others[:, 0] = False
    sel = others.flatten().nonzero()[:, 0]
    mask = agent_mask[:, :, None, None].expand(b, l, h, w).reshape(b * l, h, w)
    if len(sel) == 0:
        return x, mask.view(b, l, h, w)
    t = torch.as_tensor(transforms, dtype=torch.float64).reshape(b * l, 4, 4)[sel.cpu()]
    kw = dict(voxel_size=voxel_size, downsample_rate=stride, lidar_range=lidar_range)
    flat = x.reshape(b * l, c, h, w)
    flat = flat.index_put((sel,), warp_bev(flat[sel], t, **kw))
    mask = mask.index_put((sel,), warp_valid_mask(t, shape=(h, w), device=x.device, **kw))
    return flat.view(b, l, c, h, w), mask.view(b, l, h, w)


def quantize(x: torch.Tensor, bits: int, dims: tuple[int, ...]) -> torch.Tensor:
    """Uniform min/max quantisation to ``2**bits`` levels and back, one (min, step) per slice
    reduced over ``dims`` (the spatial dims: one pair per channel)."""
    lo, hi = x.amin(dims, keepdim=True), x.amax(dims, keepdim=True)
    step = (hi - lo).clamp(min=1e-12) / (2 ** bits - 1)
    return torch.round((x - lo) / step) * step + lo


def _dense_map_bytes(maps: Sequence[tuple[int, int, int]], bits: int | None) -> float:
    """Bytes of dense (C, h, w) maps at ``bits`` per value (None: float32), plus a float32
    (min, step) pair per channel when quantised."""
    value_bits = 32 if bits is None else bits
    return float(sum(c * h * w * value_bits / 8 + (0 if bits is None else 8 * c) for c, h, w in maps))


class FusionModule(nn.Module):
    """What every fusion method's module offers the benchmark (defaults for a one-map detector).

    ``forward(pillars, *, agent_mask, transforms, time_delay=None, agent_types=None)`` -> head dict
    (module doc's batch layout); :meth:`detections` decodes it into ego-frame boxes per sample;
    :meth:`message_bytes` is what one cooperating agent sends per frame; ``message_bits`` (None:
    float32) quantises the cooperating agents' features where a method sends features
    (:func:`compressed`); :meth:`warm_start` copies a trained single-agent detector in."""

    #: quantisation of the features cooperating agents send (None: float32; features only)
    message_bits: int | None = None

    def __init__(self, *, detector: PointPillars | None = None):
        """detector: the PointPillars whose pillar net, backbone and head the method uses (None: the
        subclass keeps the parts it uses itself)."""
        super().__init__()
        if detector is not None:
            self.detector = detector
            self.feature_stride = detector.feature_stride

    def detections(self, output: dict[str, torch.Tensor], coder: AnchorBoxCoder, *, agent_mask: torch.Tensor,
                   transforms, score_threshold: float, max_boxes: int | None) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Per sample (boxes (K, 7) in the ego frame, scores (K,)) above ``score_threshold``, before NMS."""
        return coder.decode_predictions(output, score_threshold=score_threshold, max_boxes=max_boxes)

    def message_bytes(self, *, points: float, boxes: float) -> float:
        """Bytes one cooperating agent sends the ego per frame, given its mean cloud size ``points``
        and mean boxes above the score threshold ``boxes`` (nothing here: no fusion)."""
        return 0.0

    def warm_start(self, single: PointPillars) -> None:
        """Start from a trained single-agent detector: its weights where this module has them."""
        self.detector.load_state_dict(single.state_dict())


class NoFusion(FusionModule):
    """The ego's own detector on the ego's own points ("No Fusion" rows of TYP Tables 1–3).

    It is :class:`LateFusion`'s detector (the same state dict): OpenCOOD's no fusion runs the
    single-agent detector on the ego's cloud only."""

    def forward(self, pillars: dict, *, agent_mask: torch.Tensor, transforms=None, time_delay=None,
                agent_types=None) -> dict[str, torch.Tensor]:
        """Batch layout of the module doc; only the ego slots are encoded."""
        agent_mask = _check(agent_mask)
        b, l = agent_mask.shape
        ego = torch.zeros_like(agent_mask)
        ego[:, 0] = True
        d = self.detector
        return d.head(d.backbone(d.bev(pillars, b * l, keep=ego.flatten())))


class EarlyFusion(FusionModule):
    """Early fusion (Cooper): the plain detector on :func:`merge_agent_points` of each sample;
    its batches have one slot per sample, the merged ego-frame cloud."""

    merge_points = staticmethod(merge_agent_points)

    def forward(self, pillars: dict, *, agent_mask: torch.Tensor, transforms=None, time_delay=None,
                agent_types=None) -> dict[str, torch.Tensor]:
        """``pillarize`` of the B merged, ego-frame clouds (agent_mask (B, 1)) -> the ego's head dict."""
        agent_mask = _check(agent_mask)
        return self.detector(pillars, agent_mask.shape[0] * agent_mask.shape[1])

    def message_bytes(self, *, points: float, boxes: float) -> float:
        return float(points * BYTES_PER_POINT)


class LateFusion(FusionModule):
    """Late fusion: every agent detects in its own frame; boxes meet in the ego frame for NMS."""

    def forward(self, pillars: dict, *, agent_mask: torch.Tensor, transforms=None, time_delay=None,
                agent_types=None) -> dict[str, torch.Tensor]:
        """Head dicts of the present agents, (V, ...) with V = agent_mask.sum() in b-major order;
        train them with each agent's own labels (OpenCOOD's LateFusionDataset)."""
        agent_mask = _check(agent_mask)
        b, l = agent_mask.shape
        d = self.detector
        return d.head(d.backbone(d.bev(pillars, b * l, keep=agent_mask.flatten())))

    def detections(self, output, coder, *, agent_mask, transforms, score_threshold, max_boxes):
        return self.boxes_in_ego(output, coder, agent_mask=agent_mask, transforms=transforms,
                                 score_threshold=score_threshold, max_boxes_per_agent=max_boxes)

    def message_bytes(self, *, points: float, boxes: float) -> float:
        return float(boxes * BYTES_PER_BOX)

    @staticmethod
    def boxes_in_ego(output: dict[str, torch.Tensor], box_coder: AnchorBoxCoder, *, agent_mask: torch.Tensor,
                     transforms, score_threshold: float = 0.2,
                     max_boxes_per_agent: int | None = None) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Per sample: every present agent's decoded boxes (score > threshold) moved into the ego
        frame in float64 and concatenated -> (boxes (K, 7) float64, scores (K,)), before NMS."""
        agent_mask = _check(agent_mask)
        b, l = agent_mask.shape
        t = torch.as_tensor(transforms, dtype=torch.float64).reshape(b * l, 4, 4)
        slots = agent_mask.flatten().nonzero()[:, 0].tolist()
        per_agent = box_coder.decode_predictions(output, score_threshold=score_threshold, max_boxes=max_boxes_per_agent)
        merged: list[list] = [[] for _ in range(b)]
        for slot, (boxes, scores) in zip(slots, per_agent):
            merged[slot // l].append((transform_boxes(boxes, t[slot].to(boxes.device)), scores))
        return [(torch.cat([m[0] for m in ms]), torch.cat([m[1] for m in ms])) for ms in merged]


class AttFuse(FusionModule):
    """OPV2V's AttFuse: at every backbone level, per BEV cell, the ego's feature attends (scaled
    dot product, no projections) over all agents' features at that cell; then upsample + head.
    Messages are the cooperating agents' level maps, quantised as the ego receives them (after
    the warp, which interpolates, so the value range is the sent one)."""

    @staticmethod
    def attend(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """(B, L, C, h, w) ego-frame maps, (B, L, h, w) validity -> (B, C, h, w) fused ego map."""
        x = x.masked_fill(~mask[:, :, None], 0.0)
        score = (x * x[:, :1]).sum(2) / math.sqrt(x.shape[2])
        weight = torch.softmax(score.masked_fill(~mask, float("-inf")), dim=1)
        return (weight[:, :, None] * x).sum(1)

    def forward(self, pillars: dict, *, agent_mask: torch.Tensor, transforms, time_delay=None,
                agent_types=None) -> dict[str, torch.Tensor]:
        """Batch layout of the module doc -> the ego's head dict."""
        agent_mask = _check(agent_mask)
        b, l = agent_mask.shape
        d, keep = self.detector, agent_mask.flatten()
        fused = []
        for feat, stride in zip(d.backbone.down(d.bev(pillars, b * l, keep=keep)), d.backbone.level_strides):
            x, mask = _to_ego(_regroup(feat, keep, b, l), agent_mask, transforms, voxel_size=d.voxel_size,
                              stride=stride, lidar_range=d.lidar_range)
            if self.message_bits is not None:
                x = torch.cat([x[:, :1], quantize(x[:, 1:], self.message_bits, (3, 4))], 1)
            fused.append(self.attend(x, mask))
        return d.head(d.backbone.up(fused))

    def message_bytes(self, *, points: float, boxes: float) -> float:
        d = self.detector
        return _dense_map_bytes([(c, d.ny // s, d.nx // s) for c, s in
                                 zip(d.backbone.level_channels, d.backbone.level_strides)], self.message_bits)


class _TypedLinear(nn.Module):
    """One Linear per agent type (V2X-ViT's heterogeneous projections); x (B, L, ..., C), types (B, L)."""

    def __init__(self, c_in: int, c_out: int, num_types: int):
        super().__init__()
        self.layers = nn.ModuleList(nn.Linear(c_in, c_out) for _ in range(num_types))

    def forward(self, x: torch.Tensor, types: torch.Tensor) -> torch.Tensor:
        sel = types.view(*types.shape, *[1] * (x.ndim - 2))
        return sum(layer(x) * (sel == t) for t, layer in enumerate(self.layers))


class HeteroAgentAttention(nn.Module):
    """V2X-ViT's HMSA (``hmsa.HGTCavAttention``): per cell, attention across agents with
    type-specific q/k/v/out projections and per type-pair (ego type, other type) edge matrices."""

    def __init__(self, *, dim: int, heads: int, dim_head: int, num_types: int = 2, dropout: float = 0.0):
        """dim: feature width; heads / dim_head: attention heads and their width; num_types: agent
        types (vehicle, RSU); dropout: on the output."""
        super().__init__()
        inner, self.heads, self.dim_head, self.num_types = heads * dim_head, heads, dim_head, num_types
        self.scale = dim_head ** -0.5
        self.q, self.k, self.v = (_TypedLinear(dim, inner, num_types) for _ in range(3))
        self.out = _TypedLinear(inner, dim, num_types)
        self.relation_att = nn.Parameter(torch.empty(num_types ** 2, heads, dim_head, dim_head))
        self.relation_msg = nn.Parameter(torch.empty(num_types ** 2, heads, dim_head, dim_head))
        nn.init.xavier_uniform_(self.relation_att), nn.init.xavier_uniform_(self.relation_msg)
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, mask: torch.Tensor, types: torch.Tensor) -> torch.Tensor:
        """x (B, L, H, W, C), mask (B, L, H, W) bool (which keys exist), types (B, L) -> (B, L, H, W, C).

        ``att_ij = q_i W_att[t_i, t_j] k_j``, ``out_i = sum_j softmax_j(att_ij) W_msg[t_i, t_j]^T v_j``;
        keys and values are transformed once per query type instead of once per (i, j) pair.
        """
        b, l, h, w, _ = x.shape
        t = self.num_types
        q, k, v = (proj(x, types).view(b, l, h, w, self.heads, self.dim_head) for proj in (self.q, self.k, self.v))
        query_type = F.one_hot(types, t).to(x.dtype)                                  # (B, L_i, T)
        w_att = self.relation_att.view(t, t, *self.relation_att.shape[1:])[:, types]  # (T_i, B, L_j, M, P, Q)
        w_msg = self.relation_msg.view(t, t, *self.relation_msg.shape[1:])[:, types]
        k_t = torch.einsum("tbjmpq,bjhwmq->tbjhwmp", w_att, k)
        att = torch.einsum("bihwmp,tbjhwmp,bit->bhwmij", q, k_t, query_type) * self.scale
        att = att.masked_fill(~mask.permute(0, 2, 3, 1)[:, :, :, None, None, :], float("-inf")).softmax(-1)
        v_t = torch.einsum("tbjmpc,bjhwmp->tbjhwmc", w_msg, v)
        out = torch.einsum("bhwmij,tbjhwmc,bit->bihwmc", att, v_t, query_type)
        return self.drop(self.out(out.reshape(b, l, h, w, -1), types))


class WindowAttention(nn.Module):
    """``mswin.BaseWindowAttention``: self-attention inside ws x ws windows of each agent's map,
    with a learned relative-position bias shared by the heads."""

    def __init__(self, *, dim: int, heads: int, dim_head: int, window_size: int, dropout: float = 0.0):
        """dim: feature width; heads / dim_head: attention heads and their width; window_size: side
        of the square windows (cells); dropout: on the output."""
        super().__init__()
        self.heads, self.dim_head, self.ws, self.scale = heads, dim_head, window_size, dim_head ** -0.5
        self.qkv = nn.Linear(dim, 3 * heads * dim_head, bias=False)
        self.pos_embedding = nn.Parameter(torch.randn(2 * window_size - 1, 2 * window_size - 1))
        idx = torch.stack(torch.meshgrid(torch.arange(window_size), torch.arange(window_size), indexing="ij"), -1)
        idx = idx.reshape(-1, 2)
        self.register_buffer("rel", idx[None, :, :] - idx[:, None, :] + window_size - 1, persistent=False)
        self.out = nn.Sequential(nn.Linear(heads * dim_head, dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, L, H, W, C), H and W multiples of the window -> (B, L, H, W, C)."""
        b, l, h, w, _ = x.shape
        s, m, c = self.ws, self.heads, self.dim_head
        qkv = self.qkv(x).view(b, l, h // s, s, w // s, s, 3, m, c).permute(6, 0, 1, 7, 2, 4, 3, 5, 8)
        q, k, v = qkv.reshape(3, b, l, m, (h // s) * (w // s), s * s, c)
        dots = q @ k.transpose(-1, -2) * self.scale + self.pos_embedding[self.rel[..., 0], self.rel[..., 1]]
        out = (dots.softmax(-1) @ v).view(b, l, m, h // s, w // s, s, s, c)
        return self.out(out.permute(0, 1, 3, 5, 4, 6, 2, 7).reshape(b, l, h, w, m * c))


class PyramidWindowAttention(nn.Module):
    """``mswin.PyramidWindowAttention`` with split-attention fusion (``split_attn.SplitAttn``, for
    any number of windows): per agent, a softmax over window sizes gates each branch channel-wise."""

    def __init__(self, *, dim: int, heads: Sequence[int], dim_heads: Sequence[int], window_sizes: Sequence[int],
                 dropout: float = 0.0):
        """dim: feature width; heads, dim_heads, window_sizes: one entry per branch; dropout: on the outputs."""
        super().__init__()
        self.branches = nn.ModuleList(WindowAttention(dim=dim, heads=m, dim_head=c, window_size=s, dropout=dropout)
                                      for m, c, s in zip(heads, dim_heads, window_sizes))
        self.gate = nn.Sequential(nn.Linear(dim, dim, bias=False), nn.LayerNorm(dim), nn.ReLU(),
                                  nn.Linear(dim, dim * len(self.branches), bias=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, L, H, W, C) -> (B, L, H, W, C)."""
        outs = [branch(x) for branch in self.branches]
        b, l, _, _, c = x.shape
        gate = self.gate(sum(outs).mean((2, 3))).view(b, l, len(outs), c).softmax(2)
        return sum(o * gate[:, :, i, None, None, :] for i, o in enumerate(outs))


class V2XViT(FusionModule):
    """V2X-ViT (Xu et al., ECCV 2022): backbone -> shrink conv -> per-agent delay encoding (RTE)
    -> warp into the ego frame (STTF) -> ``depth`` x [HMSA, multi-scale window attention, MLP],
    pre-norm residuals -> the ego's map -> head. Defaults: OpenCOOD's ``point_pillar_v2xvit.yaml``."""

    def __init__(self, *, detector: PointPillars, dim: int = 256, shrink_stride: int = 2, depth: int = 3,
                 heads: int = 8, dim_head: int = 32, window_sizes: Sequence[int] = (4, 8, 16),
                 window_heads: Sequence[int] = (16, 8, 4), window_dim_heads: Sequence[int] = (16, 32, 64),
                 mlp_dim: int = 256, dropout: float = 0.3, num_agent_types: int = 2, rte_ratio: int = 2,
                 max_delay: int = 100):
        """detector: supplies the pillar net, the backbone and its head's kind (``head.like``); dim: width (even);
        shrink_stride: stride of the shrink conv; depth: encoder layers; heads / dim_head: HMSA;
        window_sizes / window_heads / window_dim_heads: one window-attention branch each; mlp_dim: MLP width;
        dropout: in attention and MLP; num_agent_types: 2 = vehicle (0) / RSU (1);
        rte_ratio: RTE steps per ``time_delay`` unit; max_delay: RTE table length (steps)."""
        super().__init__()
        if not len(window_sizes) == len(window_heads) == len(window_dim_heads) or dim % 2:
            raise TypError(None, "V2XViT", "equal-length window lists and an even dim", (window_sizes, dim))
        self.pillar_net, self.backbone = detector.pillar_net, detector.backbone
        self.nx, self.ny = detector.nx, detector.ny
        self.voxel_size, self.lidar_range = detector.voxel_size, detector.lidar_range
        self.feature_stride = detector.feature_stride * shrink_stride
        self.dim = dim
        self.pad_to = int(np.lcm.reduce([int(s) for s in window_sizes]))
        self.shrink = nn.Sequential(nn.Conv2d(detector.backbone.out_channels, dim, 3, stride=shrink_stride, padding=1),
                                    nn.ReLU(), nn.Conv2d(dim, dim, 3, padding=1), nn.ReLU())
        pos, div = torch.arange(max_delay)[:, None], torch.exp(torch.arange(0, dim, 2) * (-math.log(10000.0) / dim))
        table = torch.stack([torch.sin(pos * div), torch.cos(pos * div)], -1).reshape(max_delay, dim) / math.sqrt(dim)
        self.register_buffer("rte_table", table, persistent=False)
        self.rte, self.rte_ratio = nn.Linear(dim, dim), rte_ratio
        self.layers = nn.ModuleList(nn.ModuleList([
            nn.LayerNorm(dim), HeteroAgentAttention(dim=dim, heads=heads, dim_head=dim_head,
                                                    num_types=num_agent_types, dropout=dropout),
            nn.LayerNorm(dim), PyramidWindowAttention(dim=dim, heads=window_heads, dim_heads=window_dim_heads,
                                                      window_sizes=window_sizes, dropout=dropout),
            nn.LayerNorm(dim), nn.Sequential(nn.Linear(dim, mlp_dim), nn.GELU(), nn.Dropout(dropout),
                                             nn.Linear(mlp_dim, dim), nn.Dropout(dropout))]) for _ in range(depth))
        # the detector head's kind (anchors, or models.ssc's occupancy) on the transformer's width and stride
        self.head = detector.head.like(in_channels=dim, feature_stride=self.feature_stride)

    def forward(self, pillars: dict, *, agent_mask: torch.Tensor, transforms, agent_types: torch.Tensor | None = None,
                time_delay: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Batch layout of the module doc; agent_types (B, L) long 0 vehicle / 1 RSU (default all
        vehicles); time_delay (B, L) long delay per agent in 100 ms steps (default 0)."""
        agent_mask = _check(agent_mask)
        b, l = agent_mask.shape
        keep = agent_mask.flatten()
        bev = pillars_to_bev(self.pillar_net, pillars, batch_size=b * l, nx=self.nx, ny=self.ny, keep=keep)
        feat = self.shrink(self.backbone(bev))
        if self.message_bits is not None:          # rows: present slots, b-major; the egos keep float32
            ego = torch.zeros_like(agent_mask)
            ego[:, 0] = True
            sent = ~ego[agent_mask]
            feat = torch.where(sent[:, None, None, None], quantize(feat, self.message_bits, (2, 3)), feat)
        x = _regroup(feat, keep, b, l)                                              # (B, L, C, h, w)
        types = torch.zeros_like(agent_mask, dtype=torch.long) if agent_types is None else agent_types.long()
        dt = (torch.zeros_like(types) if time_delay is None else time_delay.long()) * self.rte_ratio
        if bool((dt < 0).any() or (dt >= len(self.rte_table)).any()):
            raise TypError(None, "time_delay", f"steps in [0, {len(self.rte_table) // self.rte_ratio})",
                           dt.max().item())
        x = x + self.rte(self.rte_table[dt])[..., None, None]
        x, mask = _to_ego(x, agent_mask, transforms, voxel_size=self.voxel_size, stride=self.feature_stride,
                          lidar_range=self.lidar_range)
        h, w = x.shape[-2:]
        ph, pw = -h % self.pad_to, -w % self.pad_to                               # windows need multiples
        x = F.pad(x, (0, pw, 0, ph)).permute(0, 1, 3, 4, 2)                       # (B, L, H, W, C)
        mask = F.pad(mask.float(), (0, pw, 0, ph)) > 0.5
        mask[:, 0] = True                          # padding: the ego attends to itself, never to nothing
        for norm_a, agent_att, norm_w, window_att, norm_f, mlp in self.layers:
            x = agent_att(norm_a(x), mask, types) + x
            x = window_att(norm_w(x)) + x
            x = mlp(norm_f(x)) + x
        return self.head(x[:, 0, :h, :w].permute(0, 3, 1, 2))

    def message_bytes(self, *, points: float, boxes: float) -> float:
        """The shrunk map (dim, h, w) the agent sends before the warp."""
        return _dense_map_bytes([(self.dim, self.ny // self.feature_stride, self.nx // self.feature_stride)],
                                self.message_bits)

    def keeps_single_map(self, single: PointPillars) -> bool:
        """Whether the shrunk map has the single-agent backbone map's width and stride, so that the
        single-agent head fits on the transformer's output."""
        return (self.feature_stride == single.feature_stride and self.dim == single.backbone.out_channels
                and all(a.shape == b.shape for a, b in zip(self.head.state_dict().values(),
                                                           single.head.state_dict().values())))

    def warm_start(self, single: PointPillars) -> None:
        """The pillar net and backbone. Where the shrunk map keeps the single-agent map's width and
        stride (:meth:`keeps_single_map`), the module starts as the single-agent network on the ego:
        its head copied, the shrink convs the identity (the backbone map is >= 0, after a ReLU), the
        delay encoding and every residual branch's last layer zero (ReZero / ControlNet's zero
        init: the transformer starts as the identity and learns the fusion). Otherwise the shrink
        convs, the transformer and the head (on the transformer's width) stay fresh, as OpenCOOD's."""
        self.pillar_net.load_state_dict(single.pillar_net.state_dict())
        self.backbone.load_state_dict(single.backbone.state_dict())
        if not self.keeps_single_map(single):
            return
        self.head.load_state_dict(single.head.state_dict())
        with torch.no_grad():
            for conv in (self.shrink[0], self.shrink[2]):
                conv.weight.zero_()
                conv.weight[:, :, 1, 1] = torch.eye(self.dim)
                conv.bias.zero_()
            last = [self.rte]
            for _, agent_att, _, window_att, _, mlp in self.layers:
                last += [*agent_att.out.layers, *(branch.out[0] for branch in window_att.branches), mlp[3]]
            for layer in last:
                layer.weight.zero_()
                layer.bias.zero_()


# ------------------------------------------------------------------ registry


@contextlib.contextmanager
def compressed(module: FusionModule, bits: int | None):
    """``module`` with the cooperating agents' features quantised to ``bits`` while inside."""
    if bits is not None and METHODS[method_of(module)].message != "features":
        raise TypError("fusion", "compression", "a method whose agents send features "
                       f"({[m.name for m in METHODS.values() if m.message == 'features']})", method_of(module))
    saved = module.message_bits
    module.message_bits = bits
    try:
        yield module
    finally:
        module.message_bits = saved


def method_of(module: nn.Module) -> str:
    """The registry name of a fusion module's class."""
    for m in METHODS.values():
        if type(module) is m.module:
            return m.name
    raise TypError("fusion", "module", f"a module of {[m.name for m in METHODS.values()]}", type(module).__name__)


def get_method(name: str) -> FusionMethod:
    if name not in METHODS:
        raise TypError("fusion", "method", f"one of {list(METHODS)}", name)
    return METHODS[name]


def build(name: str, detector: PointPillars, options: dict | None = None) -> FusionModule:
    """Method ``name``'s module around ``detector`` (``options``: its config block's fields)."""
    m = get_method(name)
    return m.module(detector=detector, **(options or {}))
