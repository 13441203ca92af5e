"""PointPillars (Lang et al., CVPR 2019) with OpenCOOD's layout, the detector of TYP §4.

Pieces and the OpenCOOD files whose conventions they keep (the code is ours):
- :func:`pillarize` — spconv's voxel generator as OpenCOOD's ``SpVoxelPreprocessor`` calls it
  (``opencood/data_utils/pre_processor/sp_voxel_preprocessor.py``): one z cell spanning the
  whole range, pillars numbered by first appearance, the first ``max_points_per_pillar`` points
  of a pillar kept, pillars past ``max_pillars`` dropped; ``voxel_coords`` rows are
  ``[batch, z, y, x]``.
- :class:`PillarFeatureNet` — ``sub_modules/pillar_vfe.py``: per point ``[x, y, z, i]`` +
  offset to the pillar's point mean + offset to the pillar centre (10 features), then
  Linear(no bias) + BatchNorm1d(eps 1e-3, momentum 0.01) + ReLU + max over the pillar.
- :func:`scatter_to_bev` — ``sub_modules/point_pillar_scatter.py``: (B, C, ny, nx), rows are y,
  columns are x, cell ``(y, x)`` covers ``[x_min + x v, x_min + (x + 1) v)``.
- :class:`BEVBackbone` — ``sub_modules/base_bev_backbone.py``: per level ZeroPad + strided conv
  + ``layer_nums`` convs, each level upsampled by a transposed conv and concatenated.
- :class:`AnchorHead` — ``point_pillar.py`` heads (1x1 convs ``psm``: A, ``rm``: 7A) plus the
  direction classifier ``dm`` (2A bins) of OpenCOOD v2 / HEAL's ``point_pillar.py``.

Output dict (OpenCOOD keys): ``psm`` (B, A, H, W) logits, ``rm`` (B, 7A, H, W) residuals with
anchor ``a`` in channels ``7a..7a+6``, ``dm`` (B, bins*A, H, W) direction logits, anchor ``a`` in
``bins*a..``; H, W = grid / ``feature_stride``. Decoding lives in ``models/box_coder.py``.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from typ.errors import TypError

OPV2V_LIDAR_RANGE = (-140.8, -40.0, -3.0, 140.8, 40.0, 1.0)


def grid_size(lidar_range: Sequence[float], voxel_size: float) -> tuple[int, int]:
    """(nx, ny) pillars covering ``lidar_range`` = [x_min, y_min, z_min, x_max, y_max, z_max]."""
    r = [float(v) for v in lidar_range]
    if len(r) != 6 or not (r[0] < r[3] and r[1] < r[4] and r[2] < r[5]):
        raise TypError(None, "lidar_range", "[x_min, y_min, z_min, x_max, y_max, z_max] with min < max", r)
    if voxel_size <= 0:
        raise TypError(None, "voxel_size", "a positive pillar size in metres", voxel_size)
    n = [(r[3] - r[0]) / voxel_size, (r[4] - r[1]) / voxel_size]
    if any(abs(v - round(v)) > 1e-6 for v in n):
        raise TypError(None, "lidar_range", f"x and y extents that are multiples of voxel_size={voxel_size}", r)
    return int(round(n[0])), int(round(n[1]))


def pillarize(clouds: Sequence, *, lidar_range: Sequence[float] = OPV2V_LIDAR_RANGE, voxel_size: float = 0.4,
              max_points_per_pillar: int = 32, max_pillars: int = 32000,
              num_point_features: int = 4) -> dict[str, torch.Tensor]:
    """Point clouds -> OpenCOOD's pillar dict; cloud ``b`` gets batch index ``b``.

    clouds: each (n, >= num_point_features) ``[x, y, z, intensity, ...]`` in its own sensor frame.
    Returns ``voxel_features`` (P, M, F) float32 (unused slots zero), ``voxel_coords`` (P, 4) long
    ``[b, 0, y, x]``, ``voxel_num_points`` (P,) long. Points outside the range are dropped.
    """
    nx, ny = grid_size(lidar_range, voxel_size)
    feats, coords, counts = [], [], []
    for b, cloud in enumerate(clouds):
        pts = torch.as_tensor(np.asarray(cloud) if not torch.is_tensor(cloud) else cloud)
        dev = pts.device
        r = torch.tensor([float(v) for v in lidar_range], dtype=torch.float64, device=dev)
        if pts.ndim != 2 or pts.shape[1] < num_point_features:
            raise TypError(None, f"clouds[{b}]", f"array of shape (n, >={num_point_features})", tuple(pts.shape))
        xyz = pts[:, :3].to(torch.float64)  # cell indices in float64: no point flips cell on a boundary
        ix = torch.floor((xyz[:, 0] - r[0]) / voxel_size).long()
        iy = torch.floor((xyz[:, 1] - r[1]) / voxel_size).long()
        keep = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny) & (xyz[:, 2] >= r[2]) & (xyz[:, 2] < r[5])
        pts, ix, iy = pts[keep, :num_point_features].float(), ix[keep], iy[keep]
        n = len(pts)
        uniq, inverse = torch.unique(iy * nx + ix, return_inverse=True)
        first = torch.full((len(uniq),), n, device=dev).scatter_reduce(0, inverse, torch.arange(n, device=dev), "amin")
        order = torch.argsort(first)                      # pillars by first appearance, as spconv
        rank = torch.empty_like(order)
        rank[order] = torch.arange(len(order), device=dev)
        pillar = rank[inverse]                            # (n,) pillar id of each point
        sorted_pillar, perm = torch.sort(pillar, stable=True)
        count = torch.bincount(pillar, minlength=len(uniq))
        start = torch.cumsum(count, 0) - count
        slot = torch.empty_like(pillar)
        slot[perm] = torch.arange(n, device=dev) - start[sorted_pillar]   # rank of the point inside its pillar
        p = min(len(uniq), max_pillars)
        sel = (slot < max_points_per_pillar) & (pillar < p)
        f = torch.zeros(p, max_points_per_pillar, num_point_features, device=dev)
        f[pillar[sel], slot[sel]] = pts[sel]
        key = uniq[order[:p]]
        c = torch.stack([torch.full((p,), b, device=dev), torch.zeros_like(key), key // nx, key % nx], 1)
        feats.append(f)
        coords.append(c)
        counts.append(count[:p].clamp(max=max_points_per_pillar))
    if not feats:
        raise TypError(None, "clouds", "at least one point cloud", 0)
    return {"voxel_features": torch.cat(feats), "voxel_coords": torch.cat(coords),
            "voxel_num_points": torch.cat(counts)}


class PillarFeatureNet(nn.Module):
    """PointNet over the points of each pillar -> one (C,) feature per pillar (PillarVFE)."""

    def __init__(self, *, lidar_range: Sequence[float] = OPV2V_LIDAR_RANGE, voxel_size: float = 0.4,
                 num_point_features: int = 4, out_channels: int = 64):
        """lidar_range: [x_min, y_min, z_min, x_max, y_max, z_max] m; voxel_size: pillar side (m);
        num_point_features: F of the raw points; out_channels: C of the pillar feature."""
        super().__init__()
        r = [float(v) for v in lidar_range]
        self.voxel_size = float(voxel_size)
        # pillar centre = index * size + offset; the z "voxel" is the whole z range
        self.register_buffer("offset", torch.tensor([voxel_size / 2 + r[0], voxel_size / 2 + r[1],
                                                     (r[5] - r[2]) / 2 + r[2]]), persistent=False)
        self.linear = nn.Linear(num_point_features + 6, out_channels, bias=False)
        self.norm = nn.BatchNorm1d(out_channels, eps=1e-3, momentum=0.01)

    def forward(self, voxel_features: torch.Tensor, voxel_num_points: torch.Tensor,
                voxel_coords: torch.Tensor) -> torch.Tensor:
        """(P, M, F), (P,), (P, 4) -> (P, C)."""
        if len(voxel_features) == 0:
            return voxel_features.new_zeros(0, self.linear.out_features)
        xyz = voxel_features[:, :, :3]
        n = voxel_num_points.clamp(min=1).to(xyz.dtype).view(-1, 1, 1)
        f_cluster = xyz - xyz.sum(1, keepdim=True) / n
        centre = torch.stack([voxel_coords[:, 3].to(xyz.dtype) * self.voxel_size + self.offset[0],
                              voxel_coords[:, 2].to(xyz.dtype) * self.voxel_size + self.offset[1],
                              self.offset[2].expand(len(xyz))], 1)
        f_center = xyz - centre[:, None, :]
        x = torch.cat([voxel_features, f_cluster, f_center], -1)
        valid = torch.arange(x.shape[1], device=x.device)[None, :] < voxel_num_points[:, None]
        x = x * valid[..., None].to(x.dtype)
        x = self.linear(x)
        # BatchNorm1d over (P * M, C) has the same statistics as OpenCOOD's over (P, C, M), without
        # transposes; max(relu(x)) = relu(max(x)) saves a pass over all points
        x = self.norm(x.reshape(-1, x.shape[-1])).view_as(x)
        return F.relu(x.max(dim=1).values)


def scatter_to_bev(pillar_features: torch.Tensor, voxel_coords: torch.Tensor, *, batch_size: int,
                   nx: int, ny: int) -> torch.Tensor:
    """(P, C) pillar features at ``[b, z, y, x]`` -> (batch_size, C, ny, nx), zeros elsewhere."""
    c = pillar_features.shape[1]
    flat = (voxel_coords[:, 0] * ny + voxel_coords[:, 2]) * nx + voxel_coords[:, 3]
    canvas = pillar_features.new_zeros(batch_size * ny * nx, c).index_copy(0, flat.long(), pillar_features)
    return canvas.view(batch_size, ny, nx, c).permute(0, 3, 1, 2).contiguous()


def pillars_to_bev(pillar_net: PillarFeatureNet, pillars: dict[str, torch.Tensor], *, batch_size: int, nx: int,
                   ny: int, keep: torch.Tensor | None = None) -> torch.Tensor:
    """Pillar dict -> (batch_size, C, ny, nx) pseudo-image. ``keep`` (batch_size,) bool: only those
    samples are encoded and returned, (keep.sum(), C, ny, nx), so the BatchNorm never sees the others."""
    coords, feats, counts = pillars["voxel_coords"], pillars["voxel_features"], pillars["voxel_num_points"]
    if keep is not None:
        sel = keep[coords[:, 0]]
        new_index = torch.cumsum(keep.long(), 0) - 1
        coords = torch.cat([new_index[coords[sel, 0]][:, None], coords[sel, 1:]], 1)
        feats, counts, batch_size = feats[sel], counts[sel], int(keep.sum())
    return scatter_to_bev(pillar_net(feats, counts, coords), coords, batch_size=batch_size, nx=nx, ny=ny)


def _conv_bn(c_in: int, c_out: int, stride: int, pad: bool) -> list[nn.Module]:
    conv = nn.Conv2d(c_in, c_out, 3, stride=stride, padding=0 if pad else 1, bias=False)
    return ([nn.ZeroPad2d(1)] if pad else []) + [conv, nn.BatchNorm2d(c_out, eps=1e-3, momentum=0.01), nn.ReLU()]


class BEVBackbone(nn.Module):
    """OpenCOOD's BaseBEVBackbone: :meth:`down` gives one map per level, :meth:`up` merges them."""

    def __init__(self, *, in_channels: int = 64, layer_nums: Sequence[int] = (3, 5, 8),
                 layer_strides: Sequence[int] = (2, 2, 2), num_filters: Sequence[int] = (64, 128, 256),
                 upsample_strides: Sequence[int] = (1, 2, 4), num_upsample_filters: Sequence[int] = (128, 128, 128)):
        """in_channels: pillar feature C; layer_nums / layer_strides / num_filters: convs after the
        strided conv, its stride and width, per level; upsample_strides / num_upsample_filters: the
        transposed conv bringing each level to the common output resolution."""
        super().__init__()
        if not len(layer_nums) == len(layer_strides) == len(num_filters) == len(upsample_strides) \
                == len(num_upsample_filters) or not layer_nums:
            raise TypError(None, "backbone", "layer_nums, layer_strides, num_filters, upsample_strides and "
                           "num_upsample_filters of one equal, non-zero length", None)
        self.level_strides = [int(np.prod(layer_strides[:i + 1])) for i in range(len(layer_nums))]
        out = {s // u for s, u in zip(self.level_strides, upsample_strides)}
        if len(out) != 1 or any(s % u for s, u in zip(self.level_strides, upsample_strides)):
            raise TypError(None, "upsample_strides", "strides bringing every level to one resolution",
                           list(upsample_strides))
        self.stride = out.pop()
        c_in = [in_channels, *num_filters[:-1]]
        self.blocks = nn.ModuleList(
            nn.Sequential(*_conv_bn(c_in[i], num_filters[i], layer_strides[i], True),
                          *[m for _ in range(layer_nums[i])
                            for m in _conv_bn(num_filters[i], num_filters[i], 1, False)])
            for i in range(len(layer_nums)))
        self.deblocks = nn.ModuleList(
            nn.Sequential(nn.ConvTranspose2d(num_filters[i], num_upsample_filters[i], upsample_strides[i],
                                             stride=upsample_strides[i], bias=False),
                          nn.BatchNorm2d(num_upsample_filters[i], eps=1e-3, momentum=0.01), nn.ReLU())
            for i in range(len(layer_nums)))
        self.level_channels = list(num_filters)
        self.out_channels = int(sum(num_upsample_filters))

    def down(self, x: torch.Tensor) -> list[torch.Tensor]:
        """(N, C, H, W) -> per level (N, C_i, H / s_i, W / s_i), s_i = ``level_strides[i]``."""
        levels = []
        for block in self.blocks:
            x = block(x)
            levels.append(x)
        return levels

    def up(self, levels: Sequence[torch.Tensor]) -> torch.Tensor:
        """Per-level maps -> (N, out_channels, H / stride, W / stride)."""
        return torch.cat([deblock(x) for deblock, x in zip(self.deblocks, levels)], 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) BEV pseudo-image -> (N, out_channels, H / stride, W / stride)."""
        return self.up(self.down(x))


class AnchorHead(nn.Module):
    """1x1 convs: classification ``psm``, box residuals ``rm``, direction bins ``dm``."""

    def __init__(self, *, in_channels: int, num_anchors: int = 2, num_dir_bins: int = 2, prior: float = 0.01):
        """in_channels: C of the fused BEV map; num_anchors: A per cell (yaws); num_dir_bins: direction
        classes (0: no direction head); prior: initial foreground probability (OpenPCDet's focal-loss init)."""
        super().__init__()
        self.cls = nn.Conv2d(in_channels, num_anchors, 1)
        self.reg = nn.Conv2d(in_channels, 7 * num_anchors, 1)
        self.dir = nn.Conv2d(in_channels, num_dir_bins * num_anchors, 1) if num_dir_bins else None
        nn.init.constant_(self.cls.bias, -float(np.log((1 - prior) / prior)))

    def like(self, *, in_channels: int, feature_stride: int) -> "AnchorHead":
        """A fresh head of the same anchors and direction bins on a ``in_channels`` map (the anchors
        are laid per cell of that map, so ``feature_stride`` changes nothing here)."""
        return AnchorHead(in_channels=in_channels, num_anchors=self.cls.out_channels,
                          num_dir_bins=0 if self.dir is None else self.dir.out_channels // self.cls.out_channels)

    def forward(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """(B, C, H, W) -> {``psm``, ``rm``[, ``dm``]}."""
        out = {"psm": self.cls(x), "rm": self.reg(x)}
        if self.dir is not None:
            out["dm"] = self.dir(x)
        return out


class PointPillars(nn.Module):
    """Single-agent PointPillars: pillars -> BEV pseudo-image -> 2-D backbone -> anchor head."""

    def __init__(self, *, lidar_range: Sequence[float] = OPV2V_LIDAR_RANGE, voxel_size: float = 0.4,
                 max_points_per_pillar: int = 32, max_pillars: int = 32000, num_point_features: int = 4,
                 pillar_channels: int = 64, layer_nums: Sequence[int] = (3, 5, 8),
                 layer_strides: Sequence[int] = (2, 2, 2), num_filters: Sequence[int] = (64, 128, 256),
                 upsample_strides: Sequence[int] = (1, 2, 4), num_upsample_filters: Sequence[int] = (128, 128, 128),
                 num_anchors: int = 2, num_dir_bins: int = 2):
        """lidar_range: [x_min, y_min, z_min, x_max, y_max, z_max] m (default OPV2V's);
        voxel_size: pillar side (m); max_points_per_pillar / max_pillars: truncation in :meth:`pillarize`;
        num_point_features: F of the raw points; pillar_channels: C of the pillar features;
        layer_nums … num_upsample_filters: :class:`BEVBackbone`; num_anchors: A; num_dir_bins: direction bins."""
        super().__init__()
        self.lidar_range = tuple(float(v) for v in lidar_range)
        self.voxel_size = float(voxel_size)
        self.nx, self.ny = grid_size(self.lidar_range, self.voxel_size)
        self.max_points_per_pillar, self.max_pillars = int(max_points_per_pillar), int(max_pillars)
        self.num_point_features = int(num_point_features)
        self.pillar_net = PillarFeatureNet(lidar_range=self.lidar_range, voxel_size=self.voxel_size,
                                           num_point_features=num_point_features, out_channels=pillar_channels)
        self.backbone = BEVBackbone(in_channels=pillar_channels, layer_nums=layer_nums, layer_strides=layer_strides,
                                    num_filters=num_filters, upsample_strides=upsample_strides,
                                    num_upsample_filters=num_upsample_filters)
        total = self.backbone.level_strides[-1]
        if self.nx % total or self.ny % total:
            raise TypError(None, "lidar_range", f"a grid ({self.nx} x {self.ny} pillars) divisible by the "
                           f"backbone's total stride {total}", self.lidar_range)
        self.head = AnchorHead(in_channels=self.backbone.out_channels, num_anchors=num_anchors,
                               num_dir_bins=num_dir_bins)
        self.feature_stride = self.backbone.stride
        self.num_anchors, self.num_dir_bins = int(num_anchors), int(num_dir_bins)

    def pillarize(self, clouds: Sequence) -> dict[str, torch.Tensor]:
        """:func:`pillarize` with this model's range, pillar size and truncation limits."""
        return pillarize(clouds, lidar_range=self.lidar_range, voxel_size=self.voxel_size,
                         max_points_per_pillar=self.max_points_per_pillar, max_pillars=self.max_pillars,
                         num_point_features=self.num_point_features)

    def bev(self, pillars: dict[str, torch.Tensor], batch_size: int,
            keep: torch.Tensor | None = None) -> torch.Tensor:
        """:func:`pillars_to_bev` with this model's pillar net and grid."""
        return pillars_to_bev(self.pillar_net, pillars, batch_size=batch_size, nx=self.nx, ny=self.ny, keep=keep)

    def forward(self, pillars: dict[str, torch.Tensor], batch_size: int) -> dict[str, torch.Tensor]:
        """Pillar dict of ``batch_size`` clouds -> {``psm``, ``rm``, ``dm``} (see module doc)."""
        return self.head(self.backbone(self.bev(pillars, batch_size)))
