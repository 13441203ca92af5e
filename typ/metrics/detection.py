"""Average precision of collaborative 3D detection, by distance band, as OpenCOOD/V2V4Real report it.

The numbers reproduce OpenCOOD's evaluation (DerrickXuNu/OpenCOOD, main branch,
``opencood/utils/eval_utils.py``: ``caluclate_tp_fp``, ``calculate_ap``, ``voc_ap``,
``eval_final_results``) and V2V4Real's range bands (ucla-mobility/V2V4Real, same file with
``left_range``/``right_range``, called from ``opencood/tools/inference.py`` with bands
0-30, 30-50 and 50-100 m plus an unbanded run). Conventions, each with its source:

1. Overlap is the BEV IoU of the box footprints (``common_utils.convert_format`` takes the
   first 4 of the 8 corners, x and y; ``compute_iou`` uses shapely). Height is ignored.
   Here: :func:`typ.boxes_bev.rotated_iou_bev`, float64 (OpenCOOD keeps float32, so an IoU
   within ~1e-7 of the threshold may be decided differently there).
2. Matching is per frame (``caluclate_tp_fp``): detections sorted by descending score; each
   in turn takes the *still unmatched* gt of highest IoU (first one on ties) and is a TP if
   that IoU is >= ``iou_thr``, else an FP. A matched gt is removed, so a duplicate of an
   already matched gt is an FP unless it overlaps another free gt enough.
3. The per-frame TP/FP lists are concatenated in frame order and *not* re-sorted
   (``calculate_ap`` with ``global_sort_detections=False``, the default of
   ``tools/inference.py``; V2V4Real has no other mode). ``global_sort=True`` is OpenCOOD's
   ``--global_sort_detections``: the concatenated lists are re-ranked by score, as VOC/COCO do.
   Ties: this module sorts stably (equal scores keep frame/detection order); OpenCOOD's
   ``np.argsort(-score)`` is numpy's default, unstable sort.
4. Precision and recall: ``recall = cumTP / n_gt``, ``precision = cumTP / (cumTP + cumFP)``
   along the ranking; ``n_gt`` is the total gt count over all frames (``result_stat['gt']``).
5. AP is VOC 2010 all-point interpolation (``voc_ap``): ``mrec = [0, recall..., 1]``,
   ``mpre = [0, precision..., 0]``, ``mpre`` replaced by its running maximum from the right,
   then ``AP = sum((mrec[i] - mrec[i-1]) * mpre[i])`` over the i where recall changes. The
   padded recall 1 carries precision 0, so recall never reached adds nothing.
6. Bands (V2V4Real ``caluclate_tp_fp``): a box is in band ``(lo, hi)`` when the planar
   distance of its footprint centroid (= the box centre ``x, y``) from the ego origin ``d``
   satisfies ``lo < d < hi`` — both bounds strict, so a box at exactly 30 m is in neither
   0-30 nor 30-50. Predictions *and* gts are filtered, then matched within the band, so a
   detection at 29 m of a car at 31 m is an FP in 0-30 and its car a miss in 30-50.
   ``"overall"`` filters nothing (V2V4Real's defaults ``-inf < d < inf``).
7. No predictions (``None`` or empty) in a frame: its gts still count, it adds no TP/FP.
   If no frame has a prediction, AP = 0 (``mrec = [0, 1]``, ``mpre = [0, 0]``), as there.

Deliberate differences, where OpenCOOD's answer is an accident rather than a convention:

- Zero gts in a band gives AP = NaN (undefined; average bands with ``np.nanmean``).
  OpenCOOD raises ZeroDivisionError when that band has a detection and reports 0.0 when
  it has none.
- V2V4Real counts *all* of a frame's gts, unfiltered by band, when that frame's
  prediction is ``None`` (the ``else: gt = gt_boxes.shape[0]`` branch). Here a frame's gts
  are always filtered by band, so ``None`` and an empty prediction give the same numbers.

``gts[i]`` are expected to be already restricted to the evaluated area (OpenCOOD's
``generate_gt_bbx`` keeps objects inside the LiDAR range); nothing is clipped here.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from typ.boxes_bev import rotated_iou_bev
from typ.errors import TypError

DEFAULT_RANGES = ((0, 30), (30, 50), (50, 100))


@dataclass(frozen=True)
class PRCurve:
    """Ranking, precision/recall and AP of one band (arrays along the detection ranking)."""

    ap: float  # VOC all-point AP; NaN without gts
    recall: np.ndarray  # (D,) cumTP / n_gt after each detection; NaN without gts
    precision: np.ndarray  # (D,) cumTP / (cumTP + cumFP)
    mrec: np.ndarray  # (D + 2,) [0, recall..., 1], as OpenCOOD dumps mrec_50
    mpre: np.ndarray  # (D + 2,) [0, precision..., 0] made non-increasing, as mpre_50
    scores: np.ndarray  # (D,) detection scores in ranking order
    tp: np.ndarray  # (D,) bool, True where the detection is a true positive
    num_gt: int


def band_name(lo: float, hi: float) -> str:
    """``(0, 30)`` -> ``"0-30"``: the key a band's AP is reported under."""
    return f"{lo:g}-{hi:g}"


def _frame_boxes(value, where: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.size == 0:
        return arr.reshape(0, 7)
    if arr.ndim != 2 or arr.shape[1] != 7:
        raise TypError(where, "boxes", "an (N, 7) array [x, y, z, l, w, h, yaw] in the ego frame", arr.shape)
    if not np.isfinite(arr).all():
        raise TypError(where, "boxes", "finite values (no NaN/Inf)", "non-finite entries")
    return arr


def _frame_pred(pred, i: int) -> tuple[np.ndarray, np.ndarray]:
    if pred is None:
        return np.zeros((0, 7)), np.zeros(0)
    if not isinstance(pred, (tuple, list)) or len(pred) != 2:
        raise TypError(f"preds[{i}]", "prediction", "None or a pair (boxes (N, 7), scores (N,))",
                       type(pred).__name__)
    boxes = _frame_boxes(pred[0], f"preds[{i}]")
    scores = np.asarray(pred[1], dtype=np.float64).reshape(-1)
    if len(scores) != len(boxes):
        raise TypError(f"preds[{i}]", "scores", f"one score per box ({len(boxes)})", len(scores))
    if not np.isfinite(scores).all():
        raise TypError(f"preds[{i}]", "scores", "finite values (no NaN/Inf)", "non-finite entries")
    return boxes, scores


def _check_args(preds, gts, iou_thr, ranges) -> list[tuple[float, float]]:
    if len(preds) != len(gts):
        raise TypError(None, "preds", f"one entry per frame of gts ({len(gts)})", len(preds))
    if not 0.0 < float(iou_thr) <= 1.0:
        raise TypError(None, "iou_thr", "a number in (0, 1]", iou_thr)
    bands = []
    for band in ranges:
        if len(band) != 2 or not float(band[0]) < float(band[1]):
            raise TypError(None, "ranges", "pairs (lo, hi) of metres with lo < hi", band)
        bands.append((float(band[0]), float(band[1])))
    if len({band_name(lo, hi) for lo, hi in bands}) != len(bands):
        raise TypError(None, "ranges", "distinct bands", ranges)
    return bands


def _match(iou: np.ndarray, iou_thr: float) -> np.ndarray:
    """(D, G) IoU, rows in descending score -> (D,) bool TP (``caluclate_tp_fp``'s greedy loop)."""
    free = np.ones(iou.shape[1], dtype=bool)
    tp = np.zeros(iou.shape[0], dtype=bool)
    for k in range(iou.shape[0]):
        if not free.any():
            break
        masked = np.where(free, iou[k], -1.0)
        j = int(np.argmax(masked))
        if masked[j] >= iou_thr:
            tp[k] = True
            free[j] = False
    return tp


def voc_ap(recall: np.ndarray, precision: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """VOC 2010 all-point AP of one ranking -> ``(ap, mrec, mpre)`` (convention 5 above)."""
    mrec = np.concatenate([[0.0], recall, [1.0]])
    mpre = np.concatenate([[0.0], precision, [0.0]])
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]
    step = np.nonzero(mrec[1:] != mrec[:-1])[0] + 1
    return float(np.sum((mrec[step] - mrec[step - 1]) * mpre[step])), mrec, mpre


def _curve(tp: np.ndarray, scores: np.ndarray, num_gt: int, global_sort: bool) -> PRCurve:
    if global_sort:
        order = np.argsort(-scores, kind="stable")
        tp, scores = tp[order], scores[order]
    cum_tp = np.cumsum(tp)
    precision = cum_tp / np.arange(1, len(tp) + 1)
    if num_gt == 0:
        recall = np.full(len(tp), np.nan)
        _, mrec, mpre = voc_ap(recall, precision)
        return PRCurve(float("nan"), recall, precision, mrec, mpre, scores, tp, 0)
    recall = cum_tp / num_gt
    ap, mrec, mpre = voc_ap(recall, precision)
    return PRCurve(ap, recall, precision, mrec, mpre, scores, tp, num_gt)


@dataclass(frozen=True)
class FrameMatches:
    """Per band, per frame: which of the frame's detections (by descending score) are true
    positives, their scores, and the frame's gt count — all AP needs, so that AP over any
    choice and order of frames (a bootstrap replicate) is :func:`ap_of_frames` without matching
    again."""

    tp: dict[str, list[np.ndarray]]         # band -> per frame (D_i,) bool
    scores: dict[str, list[np.ndarray]]     # band -> per frame (D_i,) float64
    num_gt: dict[str, np.ndarray]           # band -> (frames,) int

    @property
    def bands(self) -> list[str]:
        return list(self.tp)


def frame_matches(preds, gts, iou_thr: float = 0.5, ranges=DEFAULT_RANGES) -> FrameMatches:
    """Match every frame once, per band (conventions 1, 2, 6, 7 of the module doc); bands are
    ``"overall"`` first, then :func:`band_name` of each range."""
    bands = _check_args(preds, gts, iou_thr, ranges)
    keys = ["overall"] + [band_name(lo, hi) for lo, hi in bands]
    limits = [(-np.inf, np.inf)] + bands
    tps: dict[str, list] = {k: [] for k in keys}
    scores: dict[str, list] = {k: [] for k in keys}
    num_gt: dict[str, list] = {k: [] for k in keys}
    for i, (pred, gt) in enumerate(zip(preds, gts)):
        det, score = _frame_pred(pred, i)
        gt = _frame_boxes(gt, f"gts[{i}]")
        order = np.argsort(-score, kind="stable")
        det, score = det[order], score[order]
        iou = rotated_iou_bev(det, gt)
        det_d, gt_d = np.hypot(det[:, 0], det[:, 1]), np.hypot(gt[:, 0], gt[:, 1])
        for key, (lo, hi) in zip(keys, limits):
            d_in, g_in = (lo < det_d) & (det_d < hi), (lo < gt_d) & (gt_d < hi)
            tps[key].append(_match(iou[np.ix_(d_in, g_in)], float(iou_thr)))
            scores[key].append(score[d_in])
            num_gt[key].append(int(g_in.sum()))
    return FrameMatches(tps, scores, {k: np.asarray(v, dtype=np.int64) for k, v in num_gt.items()})


def _pooled(m: FrameMatches, band: str, frames) -> tuple[np.ndarray, np.ndarray, int]:
    frames = list(frames)
    tp = [m.tp[band][i] for i in frames]
    sc = [m.scores[band][i] for i in frames]
    return (np.concatenate(tp) if tp else np.zeros(0, bool), np.concatenate(sc) if sc else np.zeros(0),
            int(m.num_gt[band][frames].sum()) if frames else 0)


def ap_of_frames(m: FrameMatches, band: str, frames, global_sort: bool = False) -> float:
    """AP of ``band`` over ``frames`` (indices, repeats allowed) concatenated in that order, as if
    those frames were the whole evaluation set; NaN without gts."""
    tp, scores, num_gt = _pooled(m, band, frames)
    return _curve(tp, scores, num_gt, global_sort).ap


def pr_curves(preds, gts, iou_thr: float = 0.5, ranges=DEFAULT_RANGES,
              global_sort: bool = False) -> dict[str, PRCurve]:
    """Per-band :class:`PRCurve` (``"overall"`` first, then :func:`band_name` of each range).

    Same inputs and conventions as :func:`ap_by_range`; for PR plots use ``recall`` against
    ``precision`` (raw) or ``mrec`` against ``mpre`` (the interpolated envelope OpenCOOD saves).
    """
    m = frame_matches(preds, gts, iou_thr, ranges)
    return {k: _curve(*_pooled(m, k, range(len(preds))), global_sort) for k in m.bands}


def ap_by_range(preds, gts, iou_thr: float = 0.5, ranges=DEFAULT_RANGES,
                global_sort: bool = False) -> dict[str, float]:
    """AP overall and per distance band: ``{"overall": ap, "0-30": ap, "30-50": ap, "50-100": ap}``.

    preds: per frame, ``None`` or ``(boxes (N, 7), scores (N,))``; gts: per frame ``(M, 7)``;
    boxes ``[x, y, z, l, w, h, yaw]`` in the ego frame (metres, radians). ``iou_thr`` is the
    BEV IoU a match needs (OpenCOOD reports 0.3, 0.5, 0.7; V2V4Real 0.5, 0.7). ``ranges``
    are ``(lo, hi)`` metre bands, open at both ends. ``global_sort`` re-ranks detections of
    all frames by score (VOC/COCO) instead of OpenCOOD's frame-order concatenation. See the
    module docstring for every convention and where it comes from. AP is NaN for a band
    without gts.
    """
    return {k: c.ap for k, c in pr_curves(preds, gts, iou_thr, ranges, global_sort).items()}
