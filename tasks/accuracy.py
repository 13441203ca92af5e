"""Accuracy of generated reference views where the truth exists (simulated target scenes).

Every method is scored on the same held-out (ego, reference) pairs against the true
reference view: IoU / precision / recall of the occupancy, JSD and MMD (r2dm BEV preset) and
Chamfer distance of the occupied voxel centres — overall, per range band (planar distance of
the BEV cell from the reference sensor), and split into cells the ego observed and cells it
did not (:func:`typ.resim.coverage_mask`), since copying or re-simulating the ego's cloud can
only be right where the ego saw the surface.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tasks.stage1 import generation_metrics
from typ.io import atomic_path
from typ.metrics.truth import chamfer_distance, occupancy_iou
from typ.voxel import Grid, voxel_centers

#: range bands (metres from the reference sensor) inside the ±51.2 m grid; its corners reach 72 m
BANDS = ((0.0, 20.0), (20.0, 40.0), (40.0, 80.0))


def band_label(lo: float, hi: float) -> str:
    return f"{lo:g}-{hi:g}"


def cell_distance(grid: Grid) -> np.ndarray:
    """(H, W) planar distance of each BEV cell centre from the sensor at the grid's origin."""
    return np.hypot(grid.centers(0)[:, None], grid.centers(1)[None, :])


def _masked_iou(occ: np.ndarray, truth: np.ndarray, columns: np.ndarray) -> float:
    """IoU over the voxels of the (N, H, W) ``columns`` (every height), pooled over the set."""
    cols = np.broadcast_to(columns[:, None], occ.shape)
    return occupancy_iou(occ[cols], truth[cols])["iou"]


def _band_chamfer(occ: np.ndarray, truth: np.ndarray, grid: Grid, near: np.ndarray) -> float:
    """Mean Chamfer (m) over the views where both clouds have points inside the (H, W) band."""
    values = []
    for o, t in zip(occ, truth):
        a = voxel_centers((o & near[None]).transpose(1, 2, 0), grid)
        b = voxel_centers((t & near[None]).transpose(1, 2, 0), grid)
        if len(a) and len(b):
            values.append(chamfer_distance(a, b))
    return float(np.mean(values)) if values else float("nan")


def score(occupancy: np.ndarray, truth: np.ndarray, grid: Grid, seen: np.ndarray,
          bands=BANDS) -> dict[str, float]:
    """All metrics of one method. occupancy, truth: (N, C, H, W) bool; seen: (N, H, W) bool."""
    scores = generation_metrics(occupancy, truth, grid)
    dist = cell_distance(grid)
    for lo, hi in bands:
        near = (dist >= lo) & (dist < hi)
        label = band_label(lo, hi)
        scores[f"iou_{label}"] = _masked_iou(occupancy, truth, np.broadcast_to(near, seen.shape))
        scores[f"chamfer_{label}"] = _band_chamfer(occupancy, truth, grid, near)
    scores["iou_seen"] = _masked_iou(occupancy, truth, seen)
    scores["iou_unseen"] = _masked_iou(occupancy, truth, ~seen)
    return scores


def _fmt(v) -> str:
    if v is None or v != v:
        return "–"
    if isinstance(v, bool):
        return "✓" if v else ""
    if isinstance(v, (int, np.integer)):
        return str(v)
    return f"{v:.2e}" if abs(v) < 1e-2 and v != 0 else f"{v:.3f}"


def markdown_table(rows: dict[str, dict], columns: list[tuple[str, str]]) -> str:
    """| method | col... | with ``columns = [(key, header)]``."""
    lines = ["| method | " + " | ".join(h for _, h in columns) + " |",
             "|---|" + "---|" * len(columns)]
    for name, values in rows.items():
        lines.append(f"| {name} | " + " | ".join(_fmt(values.get(k)) for k, _ in columns) + " |")
    return "\n".join(lines)


ACCURACY_COLUMNS = [("iou", "IoU"), *((f"iou_{band_label(*b)}", f"IoU {band_label(*b)} m") for b in BANDS),
                    ("iou_seen", "IoU seen"), ("iou_unseen", "IoU unseen"), ("chamfer_m", "Chamfer m"),
                    *((f"chamfer_{band_label(*b)}", f"CD {band_label(*b)}") for b in BANDS),
                    ("jsd_r2dm", "JSD"), ("mmd_r2dm", "MMD")]
TABLE4_COLUMNS = [("discriminator", "Disc."), ("self_training", "ST."), ("dummy_ego", "Dum."),
                  ("jsd_r2dm", "JSD ↓"), ("mmd_r2dm", "MMD ↓"), ("iou", "IoU ↑")]


def write_report(path: Path, accuracy: dict[str, dict], table4: dict[str, dict], *, pairs: int,
                 seconds: dict[str, float], notes: list[str]) -> Path:
    """reports/generation_accuracy.md: the accuracy table by range and TYP Table 4's analogue."""
    text = [
        "# Generated reference views against the truth (held-out simulated target scenes)",
        "",
        f"{pairs} (ego, reference) pairs; the reference view is hidden from every method and scored against "
        "its true occupancy. IoU is pooled over all voxels of the set (per band: over the BEV cells at that "
        "distance from the reference sensor; seen/unseen: cells the ego's cloud did / did not cover). "
        "Chamfer (m) over occupied voxel centres, JSD/MMD with the r2dm BEV preset.",
        "",
        markdown_table(accuracy, ACCURACY_COLUMNS),
        "",
        "Seconds per reference view: " + ", ".join(f"{k} {v:.3f}" for k, v in seconds.items()) + ".",
        "",
        "## TYP Table 4 analogue: adaptation ablation (JSD/MMD against the true reference views)",
        "",
        markdown_table(table4, TABLE4_COLUMNS),
        "",
        *notes,
        "",
    ]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(text))
    return path
