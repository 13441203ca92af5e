"""Evaluation metrics: generation quality (BEV JSD/MMD) and agreement with ground truth."""
from typ.metrics.bev import PRESETS, BevPreset, bev_histogram, jsd_bev, mmd_bev
from typ.metrics.truth import chamfer_distance, occupancy_iou, voxel_iou
from typ.metrics.detection import FrameMatches, PRCurve, ap_by_range, ap_of_frames, frame_matches, pr_curves
