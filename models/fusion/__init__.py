"""Collaborative fusion on one PointPillars detector: none, early, late, AttFuse, V2X-ViT (TYP §4).

Every method is a :class:`FusionModule` with one forward signature,
``module(pillars, *, agent_mask, transforms, time_delay=None, agent_types=None)``, and the hooks
the benchmark needs: ``detections`` (head -> ego-frame boxes), ``message_bytes`` and
``message_bits`` (what a cooperating agent sends, and its quantisation), ``warm_start`` (from a
trained single-agent detector). :data:`typ.registry.METHODS` is the registry (torch-free, so
the config reads it): each :class:`~typ.registry.FusionMethod` names its module, display name,
inputs, training targets, message and whether it runs another method's network (no fusion runs
late fusion's single-agent detector on the ego's cloud only, as OpenCOOD). Its order is the
order of the tables; ``typ.config`` takes the allowed names from it. A new method is a file
``models/fusion/<name>.py`` holding its module class and an entry there (plus a config block if it
has options); the registry imports the file by the method's name.

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

from models.fusion.attfuse import AttFuse
from models.fusion.base import (BYTES_PER_BOX, BYTES_PER_POINT, FusionModule, build, compressed, get_method,
                                merge_agent_points, method_of, quantize, transform_boxes)
from models.fusion.early import EarlyFusion
from models.fusion.late import LateFusion
from models.fusion.none import NoFusion
from models.fusion.v2xvit import HeteroAgentAttention, PyramidWindowAttention, V2XViT, WindowAttention
from typ.registry import METHODS, SINGLE_AGENT, FusionMethod

__all__ = ["AttFuse", "BYTES_PER_BOX", "BYTES_PER_POINT", "EarlyFusion", "FusionMethod", "FusionModule",
           "HeteroAgentAttention", "LateFusion", "METHODS", "NoFusion", "PyramidWindowAttention", "SINGLE_AGENT",
           "V2XViT", "WindowAttention", "build", "compressed", "get_method", "merge_agent_points", "method_of",
           "quantize", "transform_boxes"]
