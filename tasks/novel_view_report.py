"""``OUT/novel_view.json``, ``OUT/novel_view.md`` and the BEV pictures of one drive's novel-view
benchmark (:func:`tasks.novel_view.run_benchmark`).

The JSON holds ``{"pairs": N, "methods": {METHOD: {BAND: {METRIC: {"value", "low", "high"}}}},
"differences": {"vs_copy" | "vs_resim" | "vs_cast_no_typ": {METHOD: {BAND: {METRIC: ...}}}}}``
and beside them the ratios of F-score to the map oracle's, every pair's own figures, the
timings, the sensor, the generator each learned row used, the rules and the metric conventions.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tasks import novel_view as nvt
from typ.io import write_json, write_text
from typ.metrics import novel_view as nv
from typ.metrics.intervals import Interval, interval_cell
from typ.reporting import markdown_table

JSON_NAME, REPORT_NAME = "novel_view.json", "novel_view.md"
#: the report's main table: (metric, header)
MAIN_COLUMNS = ("fscore", "precision", "recall", "chamfer", "depth_rmse", "depth_medae", "raydrop_acc", "on_beam",
                "row_l1")
CONVENTIONS = {
    "source": "LiDAR4D (Zheng et al., CVPR 2024), ispc-lab/LiDAR4D utils/metrics.py and utils/convert.py",
    "range": f"points nearer than {nv.MAX_RANGE:g} m to the sensor only (LiDAR4D's pano max_depth)",
    "chamfer": "mean squared nearest-neighbour distance pred->true plus true->pred (m², LiDAR4D's "
               "dist1.mean() + dist2.mean() of chamfer_3DDist), on the points themselves",
    "fscore": f"at {nv.FSCORE_THRESHOLD} m² of squared distance ({nv.FSCORE_THRESHOLD ** 0.5:.3f} m): precision = "
              "share of predicted points within it of a true point, recall = share of true points within it of a "
              "predicted point, F = 2PR/(P+R), 0 when P+R = 0 (LiDAR4D's fscore)",
    "depth": "on the reference sensor's own range image (a row per beam, a column per azimuth step, nearest "
             "return per pixel): RMSE and median absolute error over the pixels where both images have a return "
             "(LiDAR4D takes every pixel, empty ones as depth 0)",
    "raydrop_acc": "share of range-image pixels on which both agree: return or no return (LiDAR4D's RaydropMeter "
                   "accuracy)",
    "on_beam": f"share of points within ±{nv.ON_BEAM_DEG}° of one of the sensor's beams, seen from the beam's origin",
    "row_l1": "mean over beam rows of |share of azimuth bins with a return, method - truth|",
    "seen_unseen": "precision over the predicted points, recall over the true points, in the BEV cells (the "
                   "generator's cell size, out to 80 m) that scan i covered (within 1 m: typ.resim.coverage_mask), "
                   "or in the others",
    "pooling": "each figure is the mean over a band's pairs of the pair's figure (LiDAR4D averages per frame); "
               "95 % percentile bootstrap intervals resampling the band's ego frames (a pair's scan i), "
               "paired differences resampled the same way",
}


def _cell(iv: Interval | None, digits: int = 3) -> str:
    return interval_cell(iv, digits)


def models(result: nvt.BenchmarkResult) -> dict[str, str]:
    """Which generator each method's row used."""
    return {m: (result.model if nvt.METHODS[m].learned else "none (no learned part)") for m in result.methods}


def seconds(result: nvt.BenchmarkResult) -> dict[str, dict[str, float]]:
    """Per method: mean seconds per pair making the view, scoring it, and both."""
    out = {}
    for m in result.methods:
        view = float(np.mean([r.seconds[m] for r in result.results]))
        score = float(np.mean([r.score_seconds[m] for r in result.results]))
        out[m] = {"view": round(view, 3), "scoring": round(score, 3), "total": round(view + score, 3)}
    return out


def to_json(result: nvt.BenchmarkResult) -> dict:
    s = result.summary
    drive = result.drive
    return {
        "pairs": len(result.pairs),
        "methods": nvt.intervals_json(s["methods"]),
        "differences": nvt.intervals_json(s["differences"]),
        "ratios_to_map_oracle": nvt.intervals_json(s["ratios_to_map_oracle"]),
        "sequence": {"root": str(drive.root), "sequence": drive.name, "scans": len(drive),
                     "sensor": result.sensor_name, "sensor_chosen": result.sensor_note,
                     "times": drive.times is not None},
        "pair_rule": pair_rule(result),
        "bands": {name: [lo, hi] for name, lo, hi in nvt.BANDS},
        "pairs_per_band": {b: sum(p.band == b for p in result.pairs) for b, _, _ in nvt.BANDS},
        "models": models(result),
        "skipped": result.skipped,
        "conventions": CONVENTIONS,
        "seconds_per_pair": seconds(result),
        "per_pair": [{"ego": r.pair.ego, "reference": r.pair.reference, "distance": round(r.pair.distance, 3),
                      "band": r.pair.band,
                      "methods": {m: {k: _rounded(v) for k, v in r.scores[m].items()} for m in result.methods}}
                     for r in result.results],
    }


def _rounded(v: float) -> float | None:
    return round(float(v), 5) if np.isfinite(v) else None


def write_report(result: nvt.BenchmarkResult, out: Path, *, pictures: bool = True) -> list[Path]:
    """Write the JSON, the markdown report and (``pictures``) one PNG per :func:`picture_pairs`
    pair under ``out``; the paths written."""
    out = Path(out)
    written = []
    if pictures:
        written += [draw_pair(result, r, out) for r in result.results if r.views]
    written.append(write_json(out / JSON_NAME, to_json(result)) or out / JSON_NAME)
    written.append(write_text(out / REPORT_NAME, markdown(result, [p.name for p in written])) or out / REPORT_NAME)
    return written


def markdown(result: nvt.BenchmarkResult, pictures: list[str]) -> str:
    s, drive = result.summary, result.drive
    bands = [b for b in nvt.BAND_NAMES if any(b in s["methods"][m] for m in result.methods)]
    per_band = ", ".join(f"{b} m {sum(p.band == b for p in result.pairs)}" for b, _, _ in nvt.BANDS)
    lines = [f"# Real scans at other poses: {drive.root.name} sequence {drive.name}", "",
             f"{len(drive)} scans; LiDAR `{result.sensor_name}` ({result.sensor_note}). "
             f"{len(result.pairs)} pairs: {pair_rule(result)}. Per band: {per_band}.", "",
             "Each method makes reference frame j's view from scan i and the two poses alone; the map oracle from "
             "every other scan of the drive, never j's. The drive's own car has left pose i by time j, so the "
             "reference's box map y_r holds no box (the drive has no labels).", "",
             f"Generator of the learned rows (hybrid, cast, typ): {result.model}.", ""]
    if result.skipped:
        lines += ["Not run: " + "; ".join(f"{m}: {why}" for m, why in result.skipped.items()) + ".", ""]
    conventions = "; ".join(f"**{k}**: {v}" for k, v in CONVENTIONS.items())
    lines += [f"Metrics (LiDAR4D's conventions): {conventions}.", ""]
    for band in bands:
        lines += [f"## {band} m" if band != nvt.ALL else "## all pairs", "", _figures_table(result, band), ""]
    if s["ratios_to_map_oracle"]:
        ratios = s["ratios_to_map_oracle"]
        lines += ["## F-score as a share of the map oracle's (the ceiling)", "",
                  markdown_table(["method", *bands], ([_label(m), *(_cell(ratios[m].get(b, {}).get("fscore"))
                                                                    for b in bands)] for m in ratios)), ""]
    for key, diffs in s["differences"].items():
        lines += [f"## Paired differences against {key[3:]} (method - {key[3:]}; **bold** where the interval "
                  "excludes 0 on the better side)", "", _differences_table(diffs, bands), ""]
    if "cast" in result.methods and "cast_no_typ" in result.methods:
        lines += ["## What the learned part adds: cast against cast without TYP's cells", "",
                  "In the BEV cells scan i did not cover (unseen) and those it did (seen); each cell `cast [interval]` "
                  "then the paired difference cast - cast_no_typ.", "", _learned_table(result, bands), ""]
    t = seconds(result)
    lines += ["## Seconds per pair", "",
              markdown_table(["method", "view", "scoring", "total"],
                             ([_label(m), *(f"{t[m][k]:.2f}" for k in ("view", "scoring", "total"))]
                              for m in result.methods)), "",
              "The map oracle's view depends on j alone: it is cast once per reference frame and its time "
              "counted on the first pair that needed it.", ""]
    if pictures:
        lines += ["## Pictures", "", "The first pair of each band (in (i, j) order): scan i in its own frame (the "
                  "arrow: pose j), each method's view and the real scan j in j's frame, and the error map of the "
                  f"BEV cells (0.5 m) of {_error_method(result)} against scan j.", "",
                  *(f"![{p}]({p})" for p in pictures), ""]
    lines += ["## Every pair (F-score)", "",
              markdown_table(["i", "j", "distance (m)", "band", *result.methods],
                             ([r.pair.ego, r.pair.reference, f"{r.pair.distance:.1f}", r.pair.band,
                               *(f"{r.scores[m]['fscore']:.3f}" for m in result.methods)] for r in result.results)), ""]
    return "\n".join(lines)


def _label(method: str) -> str:
    return nvt.METHODS[method].label


def _header(metric: str) -> str:
    return nvt.METRICS[metric].label + (" ↓" if nvt.METRICS[metric].lower_is_better else " ↑")


def _figures_table(result: nvt.BenchmarkResult, band: str) -> str:
    rows = result.summary["methods"]
    return markdown_table(["method", *(_header(k) for k in MAIN_COLUMNS)],
                          ([_label(m), *(_cell(rows[m][band].get(k)) for k in MAIN_COLUMNS)]
                           for m in result.methods if band in rows[m]))


def _differences_table(diffs: dict, bands: list[str]) -> str:
    return markdown_table(["method", *(f"{b}: F-score" for b in bands), *(f"{b}: Chamfer" for b in bands)],
                          ([_label(m), *(_verdict(diffs[m].get(b, {}).get("fscore"), "fscore") for b in bands),
                            *(_verdict(diffs[m].get(b, {}).get("chamfer"), "chamfer") for b in bands)]
                           for m in diffs))


def _learned_table(result: nvt.BenchmarkResult, bands: list[str]) -> str:
    cast, d = result.summary["methods"]["cast"], result.summary["differences"]["vs_cast_no_typ"]["cast"]
    keys = ("recall_unseen", "precision_unseen", "recall_seen", "precision_seen")
    return markdown_table(["band", *keys], ([b, *(f"{_cell(cast[b].get(k))}; {_verdict(d.get(b, {}).get(k), k)}"
                                                  for k in keys)] for b in bands))


def pair_rule(result: nvt.BenchmarkResult) -> str:
    return (f"every ordered (i, j) of scans {nvt.MIN_DISTANCE:g}-{nvt.MAX_DISTANCE:g} m apart, both directions" +
            (f", {result.split_rule}" if result.split_rule else ""))


def _verdict(iv: Interval | None, metric: str) -> str:
    if iv is None:
        return "–"
    text = _cell(iv)
    return f"**{text}**" if np.isfinite(iv.low) and nvt.beats(iv, metric) else text


def _error_method(result: nvt.BenchmarkResult) -> str:
    return next(m for m in ("cast", "hybrid", "resim", "copy") if m in result.methods or m == "copy")


def draw_pair(result: nvt.BenchmarkResult, r: nvt.PairResult, out: Path) -> Path:
    """One pair's pictures side by side (module doc of :func:`markdown`'s pictures section)."""
    from typ import viz
    from typ.geometry import invert
    from typ.voxel import Grid

    drive, pair = result.drive, r.pair
    half = 60.0
    window = viz.Window((-half, half), (-half, half), 0.25)
    z = (result.grid.z_range[0] - 0.5, result.grid.z_range[1] + 2.0)
    j_in_i = invert(drive.poses[pair.ego]) @ drive.poses[pair.reference]
    marker = [j_in_i[0, 3], j_in_i[1, 3], float(np.arctan2(j_in_i[1, 0], j_in_i[0, 0]))]
    panels = [viz.cloud_panel(f"scan i = {pair.ego} (ego)", drive.points(pair.ego), window=window, markers=[marker],
                              z_range=z)]
    for m in result.methods:
        panels.append(viz.cloud_panel(m, r.views[m], window=window, z_range=z,
                                      note=f"F {r.scores[m]['fscore']:.3f} · CD {r.scores[m]['chamfer']:.2f}"))
    truth = drive.points(pair.reference)
    panels.append(viz.cloud_panel(f"real scan j = {pair.reference}", truth, window=window, z_range=z))
    cells = Grid((-half, half), (-half, half), (-10.0, 10.0), (240, 240, 1))
    shown = _error_method(result)
    panels.append(viz.error_panel(viz.as_occupancy(nv.within_range(r.views[shown]).astype(np.float32), cells),
                                  viz.as_occupancy(nv.within_range(truth).astype(np.float32), cells), cells,
                                  title=f"{shown} vs scan j (BEV cells)"))
    title = (f"{drive.root.name} seq {drive.name}: scan {pair.ego} -> pose {pair.reference} "
             f"({pair.distance:.1f} m, band {pair.band})")
    fig = viz.panels_figure(panels, title=title, ncols=4, colorbar_z=z)
    return viz.save_png(fig, out / f"pair_{pair.ego:04d}_{pair.reference:04d}.png")
