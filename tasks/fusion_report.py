"""The fusion stage's outputs: ``metrics/fusion.json`` and ``reports/fusion.md`` + plots.

Pure functions of the results dict :func:`tasks.fusion.summarize` builds: the AP tables in the
shape of TYP Tables 1–3 (AP@0.5 / AP@0.7 by range), the PR curves and the robustness curves.
"""
from __future__ import annotations

from pathlib import Path

from tasks.fusion import IOU_THRESHOLDS, METHOD_NAMES, METHODS
from typ.config import FusionConfig
from typ.io import atomic_path, write_text

BANDS = (("0-30", "s"), ("30-50", "m"), ("50-100", "l"), ("overall", "all"))


def _ap_only(cell):
    """A table cell without its PR curve; ``skipped`` cells keep their reason."""
    if cell is None or "skipped" in cell:
        return cell
    return {k: cell[k] for k in IOU_THRESHOLDS}


def metrics_of(results: dict) -> dict:
    """``metrics/fusion.json``: the AP tables, robustness curves at AP@0.5 and bytes per message."""
    rob = results["robustness"]
    curves = {}
    for method, entry in rob["methods"].items():
        c = {sweep: {str(level): {"overall": v["ap50"]["overall"], "50-100": v["ap50"]["50-100"]}
                     for level, v in zip(rob["levels"][sweep], entry[sweep])} for sweep in rob["levels"]}
        c["bytes_per_message"] = round(entry["bytes_per_message"], 1)
        if "quantization" in entry:
            c["quantization"] = {str(q["bits"]): {"overall": q["ap50"]["overall"], "50-100": q["ap50"]["50-100"],
                                                  "bytes_per_message": round(q["bytes_per_message"], 1)}
                                 for q in entry["quantization"]}
        curves[method] = c
    return {"test_frames": results["test_frames"], "test_gt_boxes": results["test_gt_boxes"],
            "train_frames": results["train_frames"], "runs": results["runs"],
            "table2": {m: {k: _ap_only(v) for k, v in row.items()} for m, row in results["table2"].items()},
            "table3": {m: {p: (row if "skipped" in row else {ft: _ap_only(c) for ft, c in row.items()})
                           for p, row in rows.items()} for m, rows in results["table3"].items()},
            "robustness": curves}


def _fmt(v) -> str:
    return "—" if v is None else f"{v:.2f}"


def _cells(cell, key: str) -> list[str]:
    if cell is None:
        return ["—"] * len(BANDS)
    if "skipped" in cell:
        return ["skipped"] + [""] * (len(BANDS) - 1)
    return [_fmt(cell[key][band]) for band, _ in BANDS]


TRAIN_DATA = {"ego": "ego's gt only", "oracle": "gt (oracle)", "generated": "TYP (generated)"}
PRETRAIN = {"scratch": "scratch", "colwaymo": "generated target (ColWaymo)", "source": "source sim (OPV2V)"}


def report_markdown(results: dict, cfg: FusionConfig) -> str:
    lines = ["# Collaborative detection benchmark (stage `fusion`)", "",
             f"PointPillars ({cfg.detector.voxel_size} m pillars over x {cfg.detector.lidar_range[0]:g}.."
             f"{cfg.detector.lidar_range[3]:g} m, y {cfg.detector.lidar_range[1]:g}..{cfg.detector.lidar_range[4]:g} m) "
             "with each fusion method; AP by range with OpenCOOD's conventions (BEV IoU, frame-order "
             "ranking, VOC all-point AP); s = 0–30 m, m = 30–50 m, l = 50–100 m from the ego. "
             f"Test: real_cav/{cfg.test_split}, {results['test_frames']} frames, {results['test_gt_boxes']} "
             f"vehicles ({', '.join(f'{k} m: {v}' for k, v in results['test_gt_boxes_by_band'].items())}); "
             f"training: real_cav/{cfg.train_split}, {results['train_frames']} frames; {results['runs']} runs, "
             f"{cfg.steps} steps from scratch, {cfg.pretrain_steps} pre-training, {cfg.finetune_steps} fine-tuning; "
             f"stage time {results['seconds_total']:.0f} s, {results['seconds_training']:.0f} s of it training.",
             "", "## Oracle vs generated cooperating views (TYP Tables 1–2)", "",
             "| Method | Train data | " + " | ".join(f"AP@0.{t} {s}" for t in (5, 7) for _, s in BANDS) + " |",
             "|---|---|" + "---|" * (2 * len(BANDS))]
    skipped = []
    for method, row in results["table2"].items():
        for i, (data, cell) in enumerate(row.items()):
            if cell and "skipped" in cell:
                skipped.append(f"{METHOD_NAMES[method]} / {TRAIN_DATA[data]}: {cell['skipped']}")
            lines.append(f"| {METHOD_NAMES[method] if i == 0 else ''} | {TRAIN_DATA[data]} | "
                         + " | ".join(_cells(cell, "ap50") + _cells(cell, "ap70")) + " |")
    sets = results["finetune_sets"]
    for key, title in (("ap50", "AP@0.5"), ("ap70", "AP@0.7")):
        lines += ["", f"## Pre-training and fine-tuning on real_cav (TYP Table 3), {title}", "",
                  "| Method | Pre-train | " + " | ".join(f"FT {n} sc. {s}" for n in sets.values() for _, s in BANDS)
                  + " |", "|---|---|" + "---|" * (len(sets) * len(BANDS))]
        for method, rows in results["table3"].items():
            for i, (source, row) in enumerate(sorted(rows.items(), key=lambda kv: list(PRETRAIN).index(kv[0]))):
                label = "ego's gt only" if method == "none" else PRETRAIN[source]
                cells = _cells(row, key) + [""] * (len(BANDS) * (len(sets) - 1)) if "skipped" in row else \
                    [c for ft in sets for c in _cells(row[ft], key)]
                if "skipped" in row and key == "ap50":
                    skipped.append(f"{METHOD_NAMES[method]} / pre-train {PRETRAIN[source]}: {row['skipped']}")
                lines.append(f"| {METHOD_NAMES[method] if i == 0 else ''} | {label} | " + " | ".join(cells) + " |")
    rob = results["robustness"]
    lines += ["", "## Robustness (V2VSSC §IV), AP@0.5 overall / 50–100 m, oracle models", ""]
    names = {"position_std": "position noise σ (m)", "heading_std_deg": "heading noise σ (°)", "delay_ms": "delay (ms)"}
    for sweep, levels in rob["levels"].items():
        lines += [f"| Method | " + " | ".join(f"{names[sweep].split(' (')[0]} {v:g}" for v in levels) + " |",
                  "|---|" + "---|" * len(levels)]
        for method, entry in rob["methods"].items():
            lines.append(f"| {METHOD_NAMES[method]} | " + " | ".join(
                f"{_fmt(c['ap50']['overall'])} / {_fmt(c['ap50']['50-100'])}" for c in entry[sweep]) + " |")
        lines.append("")
    lines += ["| Method | message | bytes per message | AP@0.5 overall / 50–100 m |", "|---|---|---|---|"]
    for method, entry in rob["methods"].items():
        kinds = {"none": "nothing", "early": "points", "late": "boxes"}
        if method in kinds:
            lines.append(f"| {METHOD_NAMES[method]} | {kinds[method]} | {entry['bytes_per_message']:,.0f} | "
                         f"{_fmt(entry['position_std'][0]['ap50']['overall'])} / "
                         f"{_fmt(entry['position_std'][0]['ap50']['50-100'])} |")
        for q in entry.get("quantization", []):
            lines.append(f"| {METHOD_NAMES[method]} | features, {q['bits']} bit | {q['bytes_per_message']:,.0f} | "
                         f"{_fmt(q['ap50']['overall'])} / {_fmt(q['ap50']['50-100'])} |")
    if skipped:
        lines += ["", "## Skipped", ""] + [f"- {s}" for s in skipped]
    lines += ["", "Plots: [PR curves](fusion_pr.png), [robustness](fusion_robustness.png). "
              "All numbers: `metrics/fusion.json`, `artifacts/fusion/results.json`.", ""]
    return "\n".join(lines)


def _savefig(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")


def write_report(results: dict, cfg: FusionConfig, folder: Path) -> list[Path]:
    """``fusion.md``, ``fusion_pr.png`` and ``fusion_robustness.png`` under ``folder``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    md, pr_png, rob_png = folder / "fusion.md", folder / "fusion_pr.png", folder / "fusion_robustness.png"
    write_text(md, report_markdown(results, cfg))
    colors = {m: f"C{i}" for i, m in enumerate(METHODS)}

    fig, ax = plt.subplots(figsize=(6, 4.5))
    for method, row in results["table2"].items():
        for data, cell in row.items():
            if cell and "pr" in cell:
                ax.plot(cell["pr"]["recall"], cell["pr"]["precision"], color=colors[method],
                        linestyle="--" if data == "generated" else "-",
                        label=f"{METHOD_NAMES[method]}, {TRAIN_DATA[data]} (AP {_fmt(cell['ap50']['overall'])})")
    ax.set(xlabel="recall", ylabel="precision (interpolated)", xlim=(0, 1), ylim=(0, 1.02),
           title="PR curves on real_cav/test, AP@0.5, all ranges")
    ax.legend(fontsize=7, loc="upper right")
    _savefig(fig, pr_png)
    plt.close(fig)

    rob = results["robustness"]
    fig, axes = plt.subplots(1, 4, figsize=(17, 4))
    labels = {"position_std": "position noise σ (m)", "heading_std_deg": "heading noise σ (°)",
              "delay_ms": "time delay (ms)"}
    for ax, (sweep, levels) in zip(axes, rob["levels"].items()):
        for method, entry in rob["methods"].items():
            ax.plot(levels, [c["ap50"]["overall"] or 0.0 for c in entry[sweep]], "o-", color=colors[method],
                    label=f"{METHOD_NAMES[method]} all")
            ax.plot(levels, [c["ap50"]["50-100"] or 0.0 for c in entry[sweep]], "x:", color=colors[method],
                    label=f"{METHOD_NAMES[method]} 50–100 m")
        ax.set(xlabel=labels[sweep], ylabel="AP@0.5", title=f"AP vs {labels[sweep].split(' (')[0]}")
    ax = axes[3]
    for method, entry in rob["methods"].items():
        if "quantization" in entry:
            q = entry["quantization"]
            ax.plot([c["bytes_per_message"] for c in q], [c["ap50"]["overall"] or 0.0 for c in q], "o-",
                    color=colors[method], label=f"{METHOD_NAMES[method]} ({'/'.join(str(c['bits']) for c in q)} bit)")
        elif method != "none":
            ax.plot([entry["bytes_per_message"]], [entry["position_std"][0]["ap50"]["overall"] or 0.0], "s",
                    color=colors[method], label=METHOD_NAMES[method])
    if "none" in rob["methods"]:
        ax.axhline(rob["methods"]["none"]["position_std"][0]["ap50"]["overall"] or 0.0, color=colors["none"],
                   linestyle="--", label="No Fusion")
    ax.set(xscale="log", xlabel="bytes per message (cooperating agent, frame)", ylabel="AP@0.5",
           title="AP vs message size (compression)")
    axes[0].legend(fontsize=6, ncol=2)
    ax.legend(fontsize=7)
    fig.tight_layout()
    _savefig(fig, rob_png)
    plt.close(fig)
    return [md, pr_png, rob_png]
