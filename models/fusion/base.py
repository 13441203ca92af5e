"""What every fusion method shares: :class:`FusionModule` (the hooks the benchmark calls), the
batch helpers (ego check, regrouping, warping into the ego frame, quantisation, message sizes)
and the registry's lookups (:func:`build`, :func:`get_method`, :func:`method_of`,
:func:`compressed`). The batch layout is :mod:`models.fusion`'s."""
from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import nn

from models.box_coder import AnchorBoxCoder
from models.pointpillars import PointPillars
from models.warp import warp_bev, warp_valid_mask
from typ.errors import TypError
from typ.geometry import transform_points
from typ.registry import METHODS, FusionMethod

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
