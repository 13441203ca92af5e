"""Evaluation metrics: generation quality (BEV JSD/MMD), agreement with ground truth, detection AP,
semantic scene completion IoU/mIoU,
the evaluation-only generation figures and bootstrap intervals.

Names are re-exported lazily (PEP 562), so importing one submodule does not import the others:
a stage that only needs ``occupancy_iou`` does not depend on, or load, the detection metrics.
"""
from importlib import import_module

_EXPORTS = {
    "PRESETS": "bev", "BevPreset": "bev", "bev_histogram": "bev", "jsd_bev": "bev", "mmd_bev": "bev",
    "chamfer_distance": "truth", "occupancy_iou": "truth", "voxel_iou": "truth",
    "PRCurve": "detection", "ap_by_range": "detection", "pr_curves": "detection",
    "FrameMatches": "detection", "ap_of_frames": "detection", "frame_matches": "detection",
    "SSC_CLASSES": "ssc", "SSC_CODE": "ssc", "ssc_confusion": "ssc", "ssc_iou": "ssc", "ssc_scores": "ssc",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(f"typ.metrics.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'typ.metrics' has no attribute {name!r}")
