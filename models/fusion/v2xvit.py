"""V2X-ViT (Xu et al., ECCV 2022): heterogeneous multi-agent attention and multi-scale windows."""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from models.fusion.base import FusionModule, _check, _dense_map_bytes, _regroup, _to_ego, quantize
from models.pointpillars import PointPillars, pillars_to_bev
from typ.errors import TypError


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
