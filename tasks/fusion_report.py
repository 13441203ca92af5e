"""The fusion benchmark's reports: ``reports/fusion.md`` + plots, and ``metrics/fusion.json``.

Pure functions of the results dict (:func:`tasks.fusion_score.score` plus what the stage adds):
TYP Tables 1–3 as AP@0.5 / AP@0.7 by range with 95 % bootstrap intervals, the comparisons the
paper's claims rest on ("beats" only where intervals do not overlap), PR curves and robustness
curves. :func:`write_report` is the one entry point (the ``evaluate`` stage can call it too).
"""
from __future__ import annotations

from pathlib import Path

from tasks.fusion import TABLE3_PAIRS
from tasks.fusion_score import BANDS as SCORED_BANDS, IOU_THRESHOLDS
from typ.config import FusionConfig
from typ.io import atomic_path, write_text
from typ.registry import COMPOSE_MODES, METHODS
from typ.metrics.intervals import interval_cell
from typ.reporting import markdown_table

#: the range bands and AP figures the scorer declares (tasks.fusion_score), with their headers
BANDS = tuple((band, "all" if band == "overall" else band.replace("-", "–")) for band in SCORED_BANDS)
KEYS = tuple((key, f"AP@{threshold:g}") for key, threshold in IOU_THRESHOLDS.items())
TABLE1_ROWS = {"ego": "ego's gt only", "oracle": "gt (oracle)", "generated": "TYP (generated)"}
#: ``generate.compose`` values, as the report explains them
COMPOSE_TEXT = {name: mode.text for name, mode in COMPOSE_MODES.items()}
PRETRAIN = {"scratch": "scratch", "colwaymo": "generated target (ColWaymo)", "source": "source sim (OPV2V)",
            "both": "generated target + source sim"}


def _iv(c: dict | None) -> str:
    return interval_cell(c, 2, missing="—")


def _value(cell: dict | None, key: str = "ap50", band: str = "overall") -> dict | None:
    return None if cell is None else cell[key][band]


def _ap_only(cell: dict | None) -> dict | None:
    """A cell without its PR curve."""
    return None if cell is None else {k: v for k, v in cell.items() if k != "pr"}


def metrics_of(results: dict) -> dict:
    """``metrics/fusion.json``: tables (value, low, high per band), robustness at AP@0.5, bytes per
    message, applied delays, the target comparisons and what was run."""
    t = results["tables"]
    rob = results["robustness"]
    curves = {}
    for method, entry in rob["methods"].items():
        c = {sweep: {str(level): {b: v["ap50"][b] for b in ("overall", "50-100")}
                     for level, v in zip(rob["levels"][sweep], entry[sweep])} for sweep in rob["levels"]}
        c["bytes_per_message"] = round(entry["bytes_per_message"], 1)
        if "quantization" in entry:
            c["quantization"] = {str(q["bits"]): {"overall": q["ap50"]["overall"], "50-100": q["ap50"]["50-100"],
                                                  "bytes_per_message": round(q["bytes_per_message"], 1)}
                                 for q in entry["quantization"]}
        curves[method] = c
    return {"test_frames": results["test_frames"], "test_scenarios": results["test_scenarios"],
            "test_gt_boxes": results["test_gt_boxes"], "train_frames": results["train_frames"],
            "seeds": results["seeds"], "runs": results["runs"], "trainings": results["trainings"],
            "table1": {m: {r: _ap_only(c) for r, c in row.items()} for m, row in t.get("table1", {}).items()},
            "table3": {m: {p: {ft: _ap_only(c) for ft, c in cols.items()} for p, cols in rows.items()}
                       for m, rows in t.get("table3", {}).items()},
            "differences": results.get("differences", {}),
            "table3_differences": results.get("table3_differences", {}),
            "robustness": curves, "applied_delay_ms": rob["applied_delay_ms"],
            "delay_frames_scored": rob["delay_frames_scored"], "targets": targets(results)}


def _above(a: dict | None, b: dict | None) -> bool | None:
    """A's interval wholly above B's (None: either missing)."""
    if a is None or b is None or a.get("low") is None or b.get("high") is None:
        return None
    return a["low"] > b["high"]


def targets(results: dict) -> dict:
    """The figures the paper's claims rest on, measured: no fusion's AP@0.5; each fusion method against no
    fusion (overall and 50–100 m, intervals apart); V2X-ViT against late fusion; generated /
    oracle AP@0.5 per method; pre-training on ColWaymo against scratch at the smallest
    fine-tuning set; robustness falling with noise and delay."""
    t1, t3 = results["tables"].get("table1", {}), results["tables"].get("table3", {})
    out: dict = {}
    none = t1.get("none", {}).get("ego")
    out["no_fusion_ap50"] = _value(none)
    out["beats_no_fusion"] = {m: {b: _above(_value(row.get("oracle"), band=b), _value(none, band=b))
                                  for b in ("overall", "50-100")}
                              for m, row in t1.items() if m != "none"}
    if none and "ap50_global" in none:
        out["beats_no_fusion_global_sort"] = {
            m: _above(_value(row.get("oracle"), "ap50_global"), _value(none, "ap50_global"))
            for m, row in t1.items() if m != "none"}
    out["difference_above_zero"] = {m: {k: None if iv is None else iv["low"] > 0 for k, iv in d.items()}
                                    for m, d in results.get("differences", {}).items()}
    if "v2xvit" in t1 and "late" in t1:
        v, late = _value(t1["v2xvit"].get("oracle")), _value(t1["late"].get("oracle"))
        out["v2xvit_ge_late"] = None if v is None or late is None else v["value"] >= late["value"]
    out["generated_over_oracle"] = {
        m: round(row["generated"]["ap50"]["overall"]["value"] / row["oracle"]["ap50"]["overall"]["value"], 3)
        for m, row in t1.items() if row.get("generated") and row.get("oracle")
        and row["oracle"]["ap50"]["overall"] and row["oracle"]["ap50"]["overall"]["value"] > 0
        and row["generated"]["ap50"]["overall"]}
    d3 = results.get("table3_differences", {})
    for pair in (f"{row}-{base}" for row, base in TABLE3_PAIRS):
        by_set = {ft: {m: None if (d3.get(m, {}).get(pair) or {}).get(ft) is None else d3[m][pair][ft]["low"] > 0
                       for m in t3} for ft in results.get("finetune_sets", {}) if ft != "0"}
        if any(v is not None for row in by_set.values() for v in row.values()):
            out[f"{pair.replace('-', '_beats_')}_paired"] = by_set
    all_tuned = {m: (_value(rows.get("colwaymo", {}).get("all")), _value(rows.get("scratch", {}).get("all")))
                 for m, rows in t3.items()}
    out["colwaymo_ft_all_ge_scratch_minus_0.02"] = {
        m: None if a is None or b is None else a["value"] >= b["value"] - 0.02 for m, (a, b) in all_tuned.items()}
    rob = results["robustness"]
    out["falls_with"] = {sweep: {m: (lambda v: None if None in v else v[-1] < v[0])(
        [None if c["ap50"]["overall"] is None else c["ap50"]["overall"]["value"] for c in e[sweep]])
        for m, e in rob["methods"].items() if m != "none"} for sweep in rob["levels"]}
    return out


def _row(label: str, name: str, cell: dict | None) -> list[str]:
    cells = [_iv(_value(cell, k, b)) for k, _ in KEYS for b, _ in BANDS] if cell else ["—"] * (len(KEYS) * len(BANDS))
    return [label, name, *cells]


def _first(method: str, i: int) -> str:
    """A method's name on its first row, blank on the rows below it."""
    return METHODS[method].display if i == 0 else ""


def _signed(c: dict | None) -> str:
    return "—" if c is None else f"{c['value']:+.2f} [{c['low']:+.2f}, {c['high']:+.2f}]"


def _global_and_paired(results: dict) -> list[str]:
    """Table 1 ranked over all frames, and each method's paired difference to no fusion."""
    t1 = results["tables"].get("table1", {})
    lines: list[str] = []
    if any("ap50_global" in (cell or {}) for row in t1.values() for cell in row.values()):
        lines += ["", "The same networks with the detections of all test frames ranked by score (OpenCOOD's "
                  "`--global_sort_detections`, the mainstream AP; frame order, above, is OpenCOOD's default and "
                  "what the OPV2V, V2V4Real and TYP tables use):", "",
                  markdown_table(["Method", "Train data", "AP@0.5 all, global", "AP@0.7 all, global"],
                                 ([_first(method, i), TABLE1_ROWS[data], _iv(_value(cell, "ap50_global")),
                                   _iv(_value(cell, "ap70_global"))]
                                  for method, row in t1.items() for i, (data, cell) in enumerate(row.items())))]
    diffs = results.get("differences", {})
    if diffs:
        lines += ["", "Each method's oracle row minus no fusion, AP@0.5, paired: both scored on the same "
                  "resampled test scenarios and seeds, so the scenarios' shared difficulty cancels (an "
                  "interval above 0: the gain is not the luck of the test scenarios):", "",
                  markdown_table(["Method", "Δ all", "Δ 50–100 m", "Δ all, global"],
                                 ([METHODS[method].display, _signed(d["overall"]), _signed(d["50-100"]),
                                   _signed(d["overall_global"])] for method, d in diffs.items()))]
    return lines


def report_markdown(results: dict, cfg: FusionConfig) -> str:
    d = cfg.detector
    t = results["tables"]
    by_band = ", ".join(f"{k} m: {v}" for k, v in results["test_gt_boxes_by_band"].items())
    lines = ["# Collaborative detection benchmark (trained by stage `fusion`, scored by `evaluate`)", "",
             f"PointPillars ({d.voxel_size} m pillars over x {d.lidar_range[0]:g}..{d.lidar_range[3]:g} m, "
             f"y {d.lidar_range[1]:g}..{d.lidar_range[4]:g} m) with each fusion method; AP by range with "
             "OpenCOOD's conventions (BEV IoU, frame-order ranking, VOC all-point AP). "
             f"Test: real_cav/{cfg.test_split}, {results['test_frames']} frames of {results['test_scenarios']} "
             f"scenarios, {results['test_gt_boxes']} vehicles ({by_band}); training: real_cav/{cfg.train_split}, "
             f"{results['train_frames']} frames of {results['train_scenarios']} scenarios. "
             f"{results['runs']} runs × {results['seeds']} seeds = {results['trainings']} trainings: the "
             f"single-agent detector {cfg.steps} steps ({cfg.pretrain_steps} pre-training), fusion methods "
             + (f"{cfg.warm_start_steps} steps from it" if cfg.warm_start else "as many from scratch")
             + "; fine-tuning a pre-trained network on n of the N real_cav scenarios trains as many steps "
             "as scratch on the same n (n / N of the budget, the same epochs)"
             + f"; batch {cfg.batch_size}, {cfg.lr_schedule} learning rate, "
             f"augmentation (flip {cfg.augment.flip}, ±{cfg.augment.rotation_deg:g}°, scale "
             f"{cfg.augment.scale[0]:g}–{cfg.augment.scale[1]:g}). Training stage: {results['seconds_total']:.0f} s "
             f"wall, {results['seconds_training']:.0f} s of training summed over the runs (several run at once).", "",
             f"Every cell: mean over {results['seeds']} training seeds [95 % bootstrap interval over test scenarios "
             "and seeds]. \"A beats B\" only where the intervals do not overlap.", "",
             "## Oracle vs generated cooperating views (TYP Tables 1–2)", "",
             *([f"Generated cooperating views: `generate.compose` = {', '.join(results['generated_compose'])} "
                f"({'; '.join(COMPOSE_TEXT.get(c, c) for c in results['generated_compose'])}).", ""]
               if results.get("generated_compose") else []),
             markdown_table(["Method", "Train data", *(f"{k} {b}" for _, k in KEYS for _, b in BANDS)],
                            (_row(_first(method, i), TABLE1_ROWS[data], cell)
                             for method, row in t.get("table1", {}).items()
                             for i, (data, cell) in enumerate(row.items())))]
    lines += _global_and_paired(results)
    sets = results["finetune_sets"]
    for key, title in KEYS:
        rows3 = []
        for method, rows in t.get("table3", {}).items():
            ordered = sorted(rows.items(), key=lambda kv: list(PRETRAIN).index(kv[0]))
            rows3 += [[_first(method, i), PRETRAIN[source],
                       *(_iv(_value(cols.get(ft), key, b)) for ft in sets for b in ("overall", "50-100"))]
                      for i, (source, cols) in enumerate(ordered)]
        lines += ["", f"## Pre-training and fine-tuning on real_cav (TYP Table 3), {title}", "",
                  markdown_table(["Method", "Pre-train", *(f"FT {n} sc. {b}" for n in sets.values()
                                                           for _, b in (BANDS[0], BANDS[3]))], rows3)]
    d3 = results.get("table3_differences", {})
    if d3:
        short = {**PRETRAIN, "colwaymo": "generated target", "source": "source sim"}
        pairs = {f"{row}-{base}": f"{short[row]} − {short[base]}" for row, base in TABLE3_PAIRS}
        cols = [ft for ft in sets if ft != "0"]
        lines += ["", "Paired differences, AP@0.5 overall (the same resampled test scenarios and seeds on both "
                  "sides; \"A beats B\" where the interval is above 0):", "",
                  markdown_table(["Method", "Pair", *(f"FT {sets[ft]} sc." for ft in cols)],
                                 ([_first(method, i), label, *(_signed(by_pair[pair].get(ft)) for ft in cols)]
                                  for method, by_pair in d3.items()
                                  for i, (pair, label) in enumerate((k, v) for k, v in pairs.items()
                                                                    if k in by_pair)))]
    lines += ["", "## Targets, measured", ""] + [f"- {k}: {v}" for k, v in targets(results).items()]
    rob = results["robustness"]
    lines += ["", "## Robustness (V2VSSC §IV), AP@0.5 overall / 50–100 m, oracle networks", "",
              f"Delays are scored on the {rob['delay_frames_scored']} test frames with t ≥ the largest delay; "
              f"delay applied (mean message age): {', '.join(f'{v:g} ms' for v in rob['applied_delay_ms'])}.", ""]
    names = {"position_std": "position σ (m)", "heading_std_deg": "heading σ (°)", "delay_ms": "delay (ms)"}
    for sweep, levels in rob["levels"].items():
        lines += [markdown_table(["Method", *(f"{names[sweep]} {v:g}" for v in levels)],
                                 ([METHODS[method].display,
                                   *(f"{_iv(c['ap50']['overall'])} / {_iv(c['ap50']['50-100'])}" for c in entry[sweep])]
                                  for method, entry in rob["methods"].items())), ""]
    messages = []
    for method, entry in rob["methods"].items():
        if "quantization" not in entry:
            c = entry["position_std"][0]["ap50"]
            messages.append([METHODS[method].display, METHODS[method].message, f"{entry['bytes_per_message']:,.0f}",
                             f"{_iv(c['overall'])} / {_iv(c['50-100'])}"])
        messages += [[METHODS[method].display, f"features, {q['bits']} bit", f"{q['bytes_per_message']:,.0f}",
                      f"{_iv(q['ap50']['overall'])} / {_iv(q['ap50']['50-100'])}"]
                     for q in entry.get("quantization", [])]
    lines.append(markdown_table(["Method", "message", "bytes per message", "AP@0.5 overall / 50–100 m"], messages))
    if results.get("skipped"):
        lines += ["", "## Skipped", ""] + [f"- {k}: {v}" for k, v in results["skipped"].items()]
    lines += ["", "Plots: [PR curves](fusion_pr.png), [robustness](fusion_robustness.png). "
              "All numbers: `metrics/evaluate.json` (`fusion`); plot data: `reports/plots/fusion_*.csv` "
              "(`dvc plots show`); training: `metrics/fusion.json`, `artifacts/fusion/curves.json`, "
              "`artifacts/fusion/loss.csv`.", ""]
    return "\n".join(lines)


def _savefig(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")


def write_report(results: dict, cfg: FusionConfig, folder: Path) -> list[Path]:
    """``fusion.md``, ``fusion_pr.png`` and ``fusion_robustness.png`` under ``folder``."""
    from typ.reporting import subplots

    md, pr_png, rob_png = folder / "fusion.md", folder / "fusion_pr.png", folder / "fusion_robustness.png"
    write_text(md, report_markdown(results, cfg))
    colors = {m: f"C{i}" for i, m in enumerate(METHODS)}

    fig, ax = subplots(figsize=(6, 4.5))
    for method, row in results["tables"].get("table1", {}).items():
        for data, cell in row.items():
            if cell and "pr" in cell:
                ax.plot(cell["pr"]["recall"], cell["pr"]["precision"], color=colors[method],
                        linestyle="--" if data == "generated" else "-",
                        label=f"{METHODS[method].display}, {TABLE1_ROWS[data]} "
                              f"(AP {_iv(_value(cell))})")
    ax.set(xlabel="recall", ylabel="precision (interpolated)", xlim=(0, 1), ylim=(0, 1.02),
           title="PR curves on real_cav/test, AP@0.5, all ranges (first seed)")
    ax.legend(fontsize=6, loc="upper right")
    _savefig(fig, pr_png)

    rob = results["robustness"]
    fig, axes = subplots(1, 4, figsize=(17, 4))
    labels = {"position_std": "position noise σ (m)", "heading_std_deg": "heading noise σ (°)",
              "delay_ms": "time delay applied (ms)"}

    def ys(cells, band="overall"):
        vals = [c["ap50"][band] or {"value": 0.0, "low": 0.0, "high": 0.0} for c in cells]
        return ([v["value"] for v in vals], [v["low"] if v["low"] is not None else v["value"] for v in vals],
                [v["high"] if v["high"] is not None else v["value"] for v in vals])

    for ax, (sweep, levels) in zip(axes, rob["levels"].items()):
        xs = rob["applied_delay_ms"] if sweep == "delay_ms" else levels
        for method, entry in rob["methods"].items():
            y, lo, hi = ys(entry[sweep])
            ax.plot(xs, y, "o-", color=colors[method], label=f"{METHODS[method].display} all")
            ax.fill_between(xs, lo, hi, color=colors[method], alpha=0.12)
            ax.plot(xs, ys(entry[sweep], "50-100")[0], "x:", color=colors[method],
                    label=f"{METHODS[method].display} 50–100 m")
        ax.set(xlabel=labels[sweep], ylabel="AP@0.5", title=f"AP vs {labels[sweep].split(' (')[0]}")
    ax = axes[3]
    for method, entry in rob["methods"].items():
        if "quantization" in entry:
            q = entry["quantization"]
            ax.plot([c["bytes_per_message"] for c in q], ys(q)[0], "o-", color=colors[method],
                    label=f"{METHODS[method].display} ({'/'.join(str(c['bits']) for c in q)} bit)")
        elif METHODS[method].message != "nothing":
            ax.plot([entry["bytes_per_message"]], ys(entry["position_std"][:1])[0], "s", color=colors[method],
                    label=METHODS[method].display)
    if "none" in rob["methods"]:
        ax.axhline(ys(rob["methods"]["none"]["position_std"][:1])[0][0], color=colors["none"], linestyle="--",
                   label="No Fusion")
    ax.set(xscale="log", xlabel="bytes per message (cooperating agent, frame)", ylabel="AP@0.5",
           title="AP vs message size (compression)")
    axes[0].legend(fontsize=6, ncol=2)
    ax.legend(fontsize=7)
    fig.tight_layout()
    _savefig(fig, rob_png)
    return [md, pr_png, rob_png]


#: the (method, training data) columns of Table 1 in the plot data, for every registered method
#: (a column of a method or row not run stays empty, so dvc.yaml can declare them all)
TABLE1_COLUMNS = tuple((m, d) for m in METHODS for d in (("ego",) if METHODS[m].inputs == "ego"
                                                          else ("oracle", "generated")))
#: recall grid of the PR table (the interpolated precision is a step function of recall)
PR_RECALL = tuple(round(0.01 * k, 2) for k in range(101))


def _interpolated_precision(curve: dict, recall: float) -> float | None:
    """OpenCOOD's interpolated precision at ``recall``: the best precision at any recall >= it."""
    ps = [p for r, p in zip(curve["recall"], curve["precision"]) if r >= recall - 1e-12]
    return max(ps) if ps else None


def write_plot_data(results: dict, folder: Path) -> list[Path]:
    """The curves of the report as tables for ``dvc plots`` (:mod:`typ.plots`): ``fusion_pr.csv``
    (interpolated precision of each Table 1 cell's first seed on a 0.01 recall grid, one column
    ``<method>_<data>``), and AP@0.5 overall against each robustness sweep, one column per method:
    ``fusion_position_std.csv``, ``fusion_heading_std.csv``, ``fusion_delay.csv`` (x: the delay
    actually applied, ms) and ``fusion_bits.csv`` (x: feature bits)."""
    from typ import plots

    t1 = results["tables"].get("table1", {})
    pr = {f"{m}_{d}": [None] * len(PR_RECALL) for m, d in TABLE1_COLUMNS}
    for (m, d) in TABLE1_COLUMNS:
        cell = t1.get(m, {}).get(d)
        if cell and cell.get("pr"):
            pr[f"{m}_{d}"] = [_interpolated_precision(cell["pr"], r) for r in PR_RECALL]
    paths = [plots.write_table(folder / "fusion_pr.csv", {"recall": list(PR_RECALL), **pr})]
    rob = results["robustness"]

    def overall(cells):
        return [(c["ap50"]["overall"] or {}).get("value") for c in cells]

    for sweep, name, x in (("position_std", "fusion_position_std.csv", "position_std_m"),
                           ("heading_std_deg", "fusion_heading_std.csv", "heading_std_deg"),
                           ("delay_ms", "fusion_delay.csv", "delay_ms")):
        levels = rob["applied_delay_ms"] if sweep == "delay_ms" else rob["levels"][sweep]
        series = {m: overall(rob["methods"][m][sweep]) if m in rob["methods"] else [None] * len(levels)
                  for m in METHODS}
        paths.append(plots.sweep(folder / name, x, list(levels), series))
    bits = sorted({q["bits"] for e in rob["methods"].values() for q in e.get("quantization", [])}, reverse=True)
    series = {}
    for m in METHODS:
        by_bits = {q["bits"]: (q["ap50"]["overall"] or {}).get("value")
                   for q in rob["methods"].get(m, {}).get("quantization", [])}
        series[m] = [by_bits.get(b) for b in bits]
    paths.append(plots.sweep(folder / "fusion_bits.csv", "bits", bits, series))
    return paths
