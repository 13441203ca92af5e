"""Moving agents' BEV feature maps into the ego frame, and who is in communication range.

OpenCOOD (``opencood/models/sub_modules/torch_transformation_utils.py``: ``get_discretized_
transformation_matrix``, ``get_transformation_matrix``, ``warp_affine``; used by V2X-ViT's STTF)
takes the x/y block of the agent->ego ``x1_to_x2`` matrix, divides the translation by
``voxel_size * downsample_rate`` to get cells, and resamples with ``F.affine_grid`` /
``F.grid_sample`` so that output cell = ego-frame cell. We do the same resampling but build the
affine map from metric cell centres in float64: an ego cell with centre ``p`` (metres) reads the
agent's map at ``T⁻¹ p``, where cell ``(row i, col j)`` of a map covering ``[x_min, x_max) x
[y_min, y_max)`` has centre ``(x_min + (j + ½) c, y_min + (i + ½) c)``, ``c = voxel_size *
downsample_rate`` (rows are y, columns x, as the PointPillars scatter lays them out). OpenCOOD
rotates about ``(W/2, H/2)`` in ``align_corners=True`` pixels, half a cell off the true centre;
we rotate about the sensor origin exactly.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from typ.errors import TypError
from typ.geometry import pose_to_matrix


def _metric_to_normalised(h: int, w: int, cell: float, x_min: float, y_min: float) -> torch.Tensor:
    """3x3 float64 taking metres ``(x, y, 1)`` to grid_sample's ``align_corners=False`` coords."""
    return torch.tensor([[2.0 / (w * cell), 0.0, -2.0 * x_min / (w * cell) - 1.0],
                         [0.0, 2.0 / (h * cell), -2.0 * y_min / (h * cell) - 1.0],
                         [0.0, 0.0, 1.0]], dtype=torch.float64)


def warp_bev(features: torch.Tensor, transforms, *, voxel_size: float, downsample_rate: int = 1,
             lidar_range: Sequence[float] | None = None, mode: str = "bilinear") -> torch.Tensor:
    """Resample each agent's BEV map into the ego frame.

    features: (N, C, H, W), agent n's sensor frame, rows y, columns x.
    transforms: (N, 4, 4) float64 agent->ego (``typ.geometry.relative_transform(agent_pose,
    ego_pose)``, OpenCOOD ``x1_to_x2``); only the x/y block is used (BEV).
    voxel_size, downsample_rate: one cell is ``voxel_size * downsample_rate`` metres.
    lidar_range: [x_min, y_min, ...] of the map; None: the map is centred on the sensor.
    mode: ``bilinear`` or ``nearest``. Cells reading outside the agent's map get zeros.
    Returns (N, C, H, W) in the ego frame, dtype of ``features`` (sampled in float64).
    """
    if features.ndim != 4:
        raise TypError(None, "features", "tensor of shape (N, C, H, W)", tuple(features.shape))
    n, c, h, w = features.shape
    t = torch.as_tensor(transforms, dtype=torch.float64).to(features.device)
    if t.shape != (n, 4, 4):
        raise TypError(None, "transforms", f"tensor of shape ({n}, 4, 4)", tuple(t.shape))
    cell = float(voxel_size) * int(downsample_rate)
    if lidar_range is None:
        x_min, y_min = -w * cell / 2, -h * cell / 2
    else:
        x_min, y_min = float(lidar_range[0]), float(lidar_range[1])
    to_norm = _metric_to_normalised(h, w, cell, x_min, y_min).to(features.device)
    affine = torch.eye(3, dtype=torch.float64, device=features.device).repeat(n, 1, 1)
    affine[:, :2, :2], affine[:, :2, 2] = t[:, :2, :2], t[:, :2, 3]
    # output (ego) normalised -> ego metres -> agent metres -> agent normalised
    theta = to_norm @ torch.linalg.inv(affine) @ torch.linalg.inv(to_norm)
    grid = F.affine_grid(theta[:, :2], [n, c, h, w], align_corners=False)
    out = F.grid_sample(features.to(torch.float64), grid, mode=mode, padding_mode="zeros", align_corners=False)
    return out.to(features.dtype)


def warp_valid_mask(transforms, *, shape: tuple[int, int], voxel_size: float, downsample_rate: int = 1,
                    lidar_range: Sequence[float] | None = None, device=None) -> torch.Tensor:
    """(N, H, W) bool: ego cells whose centre falls inside agent n's map (V2X-ViT's ROI mask)."""
    t = torch.as_tensor(transforms, dtype=torch.float64)
    ones = torch.ones(t.shape[0], 1, *shape, dtype=torch.float64, device=device)
    return warp_bev(ones, t.to(ones.device), voxel_size=voxel_size, downsample_rate=downsample_rate,
                    lidar_range=lidar_range, mode="nearest")[:, 0] > 0.5


def communication_mask(poses, ego_pose, comm_range: float = 70.0) -> torch.Tensor:
    """(N,) bool: agent within ``comm_range`` metres (x/y distance) of the ego, OpenCOOD's ``COM_RANGE``.

    poses: (N, 6) ``[x, y, z, roll, yaw, pitch]`` or (N, 4, 4) frame-to-world; ego_pose: (6,) or (4, 4).
    As OpenCOOD, an agent at exactly ``comm_range`` is kept (it drops ``distance > COM_RANGE``).
    """
    p = np.asarray(poses, dtype=np.float64)
    e = np.asarray(ego_pose, dtype=np.float64)
    if p.ndim == 2 and p.shape[1] == 6:
        xy = p[:, :2]
    elif p.ndim == 3 and p.shape[1:] == (4, 4):
        xy = p[:, :2, 3]
    else:
        raise TypError(None, "poses", "array of shape (N, 6) or (N, 4, 4)", p.shape)
    exy = pose_to_matrix(e)[:2, 3] if e.shape == (6,) else e[:2, 3]
    return torch.from_numpy(np.hypot(*(xy - exy).T) <= comm_range)
