"""Semantic scene completion metrics: geometric IoU, per-class IoU, mIoU and cIoU (V2VSSC).

The convention is SSCNet's / SemanticKITTI's (``semantic-kitti-api`` ``evaluate_completion.py``,
MonoScene's ``SSCMetrics``): a confusion matrix is accumulated over every voxel of every frame
and the ratios are taken once at the end (pooled, not averaged per frame). Class 0 is empty.
V2VSSC adds cIoU, the mean IoU of the two "critical" classes, drivable road and car.
"""
from __future__ import annotations

import numpy as np

from typ.errors import TypError

#: Class ids of V2VSSC's semantic occupancy maps, in its order; 0 is empty.
SSC_CLASSES: tuple[str, ...] = ("empty", "road", "car", "terrain", "building", "vegetation", "pole")
SSC_CODE: dict[str, int] = {name: i for i, name in enumerate(SSC_CLASSES)}
#: V2VSSC's critical objects: cIoU is the mean IoU of these classes.
CRITICAL_CLASSES: tuple[str, ...] = ("road", "car")
#: every figure of :func:`ssc_scores` that the ssc stage scores with an interval, in order: name ->
#: its header in the Table I analogue (None: in the metrics only). A new figure is its value in
#: ssc_scores' dict and an entry here; ``iou_<class>`` reads the per-class array (:func:`figure_of`).
FIGURES: dict[str, str | None] = {"iou": "IoU", "miou": "mIoU", "ciou": "cIoU", "precision": None, "recall": None,
                                  **{f"iou_{c}": c for c in SSC_CLASSES[1:]}}

_WHERE = "ssc_iou"


def _frames(value, field: str) -> list[np.ndarray]:
    """One frame, a stacked array of frames or a list of frames, as a list of integer arrays."""
    if isinstance(value, (list, tuple)):
        arrays = [np.asarray(v) for v in value]
        if not arrays:
            raise TypError(_WHERE, field, "at least one frame", "an empty list")
    else:
        arrays = [np.asarray(value)]
    for arr in arrays:
        if arr.dtype == bool or not np.issubdtype(arr.dtype, np.integer):
            raise TypError(_WHERE, field, "integer class ids", arr.dtype)
    return arrays


def ssc_confusion(pred, gt, n_classes: int, *, ignore: int = 255, mask=None) -> np.ndarray:
    """(n_classes, n_classes) int64 confusion matrix, rows truth, columns prediction, pooled over
    every voxel of every frame. Arguments as in :func:`ssc_iou`."""
    if isinstance(n_classes, bool) or not isinstance(n_classes, (int, np.integer)) or n_classes < 2:
        raise TypError(_WHERE, "n_classes", "an integer >= 2 (class 0 is empty)", n_classes)
    preds, gts = _frames(pred, "pred"), _frames(gt, "gt")
    if len(preds) != len(gts):
        raise TypError(_WHERE, "pred", f"as many frames as gt ({len(gts)})", len(preds))
    masks = [None] * len(gts) if mask is None else (
        [np.asarray(m) for m in mask] if isinstance(mask, (list, tuple)) else [np.asarray(mask)])
    if len(masks) != len(gts):
        raise TypError(_WHERE, "mask", f"as many frames as gt ({len(gts)})", len(masks))
    conf = np.zeros((n_classes, n_classes), dtype=np.int64)
    for i, (p, t, m) in enumerate(zip(preds, gts, masks)):
        if p.shape != t.shape:
            raise TypError(_WHERE, "pred", f"the shape of gt {t.shape} (frame {i})", p.shape)
        keep = t != ignore
        if m is not None:
            if m.dtype != bool or m.shape != t.shape:
                raise TypError(_WHERE, "mask", f"a bool array of shape {t.shape} (frame {i})", (m.dtype, m.shape))
            keep &= m
        t_k, p_k = t[keep].astype(np.int64), p[keep].astype(np.int64)
        for name, arr in (("gt", t_k), ("pred", p_k)):
            if arr.size and (arr.min() < 0 or arr.max() >= n_classes):
                bad = arr[(arr < 0) | (arr >= n_classes)][0]
                raise TypError(_WHERE, name, f"class ids in [0, {n_classes}) or ignore={ignore} (frame {i})", int(bad))
        conf += np.bincount(t_k * n_classes + p_k, minlength=n_classes * n_classes).reshape(n_classes, n_classes)
    return conf


def ssc_iou(pred, gt, n_classes: int, ignore: int = 255, mask=None) -> dict:
    """Completion and semantic IoU of predicted semantic occupancy maps against the truth.

    pred, gt: integer class ids, one frame (e.g. (X, Y, Z)), a stack (F, X, Y, Z) or a list of
    frames (shapes may differ between frames but pred and gt must match frame by frame); class 0
    is empty, ``1 .. n_classes-1`` are semantic classes (:data:`SSC_CLASSES` for V2VSSC).
    Voxels whose truth is ``ignore`` or where ``mask`` (bool, same shape / list) is False are left
    out of every count. Counts are pooled over all kept voxels of all frames (SemanticKITTI), not
    averaged per frame.

    Returns a dict:

    - ``iou``, ``precision``, ``recall``: geometric completion, occupied (class != 0) vs empty:
      ``TP / (TP + FP + FN)``, ``TP / (TP + FP)``, ``TP / (TP + FN)``; NaN when the denominator is 0.
    - ``iou_per_class``: (n_classes - 1,) float64 IoU of classes 1 .. n_classes-1 (empty is not a
      semantic class). A class absent from both prediction and truth has ``TP + FP + FN = 0``;
      its IoU is set to **0**, not NaN, as SemanticKITTI's and MonoScene's evaluators do
      (they divide by ``union + 1e-15``), so it still counts in the mean below.
    - ``miou``: the plain mean of ``iou_per_class``, absent classes included as 0.
    - ``ciou``: V2VSSC's critical-object IoU, the mean of road's and car's IoU; only when
      ``n_classes`` is V2VSSC's 7, NaN otherwise.
    - ``confusion``: the pooled (n_classes, n_classes) int64 matrix, rows truth, columns prediction.
    """
    return ssc_scores(ssc_confusion(pred, gt, n_classes, ignore=ignore, mask=mask))


def ssc_scores(conf: np.ndarray) -> dict:
    """:func:`ssc_iou`'s figures from a pooled (n_classes, n_classes) confusion matrix (rows truth,
    columns prediction), e.g. the sum of per-scene matrices a scene bootstrap draws."""
    conf = np.asarray(conf)
    n_classes = conf.shape[0]
    if conf.ndim != 2 or conf.shape[1] != n_classes or n_classes < 2:
        raise TypError(_WHERE, "confusion", "a square (n_classes, n_classes) matrix, n_classes >= 2", conf.shape)
    occ_t, occ_p = conf[1:, :].sum(), conf[:, 1:].sum()
    tp_geo = conf[1:, 1:].sum()
    fp_geo, fn_geo = occ_p - tp_geo, occ_t - tp_geo

    def ratio(num, den) -> float:
        return float(num / den) if den else float("nan")

    tp = np.diag(conf)[1:].astype(np.float64)
    union = conf[1:, :].sum(axis=1) + conf[:, 1:].sum(axis=0) - np.diag(conf)[1:]
    per_class = np.where(union > 0, tp / np.maximum(union, 1), 0.0)
    ciou = float("nan")
    if n_classes == len(SSC_CLASSES):
        ciou = float(np.mean([per_class[SSC_CODE[c] - 1] for c in CRITICAL_CLASSES]))
    return {"iou": ratio(tp_geo, tp_geo + fp_geo + fn_geo), "precision": ratio(tp_geo, tp_geo + fp_geo),
            "recall": ratio(tp_geo, tp_geo + fn_geo), "iou_per_class": per_class,
            "miou": float(per_class.mean()), "ciou": ciou, "confusion": conf}


def figure_of(scores: dict, name: str) -> float:
    """One of :data:`FIGURES` from :func:`ssc_scores`' dict."""
    if name.startswith("iou_"):
        return float(scores["iou_per_class"][SSC_CLASSES.index(name[4:]) - 1])
    return float(scores[name])
