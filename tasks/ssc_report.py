"""The ssc stage's report: V2VSSC Table I analogue (perfect and noisy), the robustness curves
(Figs. 4–5) and a render of predicted against true semantic maps."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from models.ssc import SSC_PILLAR
from tasks.ssc_data import DISPLAY, FOOTPRINT_CELLS, N_CLASSES, NETWORK
from typ.config import SscConfig
from typ.io import atomic_path, write_text
from typ.metrics.ssc import FIGURES as SSC_FIGURES, SSC_CLASSES
from typ.metrics.intervals import interval_cell
from typ.reporting import markdown_table

#: Table I's columns: (figure, header), the figures typ.metrics.ssc declares with a header
COLUMNS = tuple((figure, header) for figure, header in SSC_FIGURES.items() if header)
#: V2VSSC Table I's columns, in its order
PAPER_COLUMNS = ("iou", "miou", "ciou", *(f"iou_{c}" for c in SSC_CLASSES[1:]))
#: V2VSSC Table I (OPV2V-based V2VSSC test set, VoxelNet), in %
PAPER = {"none": (53.2, 42.2, 60.0, 65.6, 54.4, 48.3, 31.8, 41.2, 12.0),
         "early": (56.1, 45.7, 66.8, 68.8, 64.8, 48.1, 33.1, 42.9, 16.4),
         "attfuse": (55.6, 45.1, 64.6, 66.8, 62.4, 48.3, 33.1, 43.3, 16.7),
         "late": (61.5, 48.2, 63.6, 71.4, 55.8, 55.6, 40.5, 49.0, 16.9)}
#: the class colours of the renders (empty white)
COLORS = ("white", "dimgray", "blue", "yellowgreen", "orange", "green", "red")
#: what the generated arm's single-agent network learns from, by ``ssc.generated_views``
GENERATED_VIEWS = {"all": "every agent's view, the generated ones scored on their whole map",
                   "footprint": "every agent's view, the generated ones scored only on the map columns within "
                                f"{FOOTPRINT_CELLS} columns ({FOOTPRINT_CELLS * SSC_PILLAR:.1f} m) of one of their "
                                "points",
                   "ego": "the egos' true views only (the cooperators' generated clouds reach only the fused "
                          "networks)"}
SWEEPS = {"position_std": "position noise σ (m)", "heading_std_deg": "heading noise σ (°)",
          "delay_ms": "time delay applied (ms)"}


def _joined(names: list[str]) -> str:
    """"a", "a and b", "a, b and c"."""
    if len(names) < 2:
        return "".join(names) or "nothing"
    return ", ".join(names[:-1]) + " and " + names[-1]


def _pct(cell: dict) -> str:
    return interval_cell(cell, 1, scale=100)


def _table(rows: dict) -> list[str]:
    return markdown_table(["method", *(h for _, h in COLUMNS)],
                          ([DISPLAY[m], *(_pct(row["figures"][f]) for f, _ in COLUMNS)] for m, row in rows.items())
                          ).split("\n")


def _beats(rows: dict) -> list[str]:
    if "none" not in rows:
        return []
    none = rows["none"]["figures"]
    lines = []
    for method, row in rows.items():
        if method == "none":
            continue
        for f, h in (("iou", "IoU"), ("miou", "mIoU")):
            a, b = row["figures"][f], none[f]
            verb = "**beats**" if a["low"] > b["high"] else ("is **below**" if a["high"] < b["low"] else "does not separate from")
            lines.append(f"- {DISPLAY[method]} {verb} No Fusion on {h}: {_pct(a)} vs {_pct(b)}")
    return lines


def _generated(results: dict, block: SscConfig) -> list[str]:
    """TYP Table 1 for SSC: networks trained with generated cooperating clouds, on true test clouds."""
    if "generated" not in block.data:
        return []
    head = ["## Trained on TYP-generated cooperators (TYP Table 1 for SSC), perfect setting", ""]
    if "generated" not in results["tables"]:
        return head + [f"Not run: {results['skipped'].get('generated', 'no generated data')}.", ""]
    oracle = results["tables"]["perfect"]
    lines = head + [
        f"The same training frames and maps, with the cooperating agents' clouds those `{block.generated}/"
        f"{block.domain}/{block.train_split}` holds (what the generate stage wrote for them; the ego's cloud is "
        "true, so no fusion has no generated row); scored on the true test clouds. The single-agent network (no "
        f"and late fusion) learns from {GENERATED_VIEWS[block.generated_views]}. Ratio: generated over oracle, "
        "its interval from the same scenario resamples on both sides (the bar: ≥ 0.85).", ""]
    rows = []
    for method, row in results["tables"]["generated"].items():
        f, o = row["figures"], oracle[method]["figures"]
        r, q = row["ratio_miou"], row["ratio_iou"]
        rows.append([DISPLAY[method], _pct(o["miou"]), _pct(f["miou"]),
                     interval_cell(r), _pct(o["iou"]), _pct(f["iou"]), interval_cell(q)])
    return lines + [markdown_table(["method", "mIoU oracle", "mIoU generated", "generated / oracle mIoU", "IoU oracle",
                                    "IoU generated", "generated / oracle IoU"], rows), ""]


def report_markdown(results: dict, block: SscConfig) -> str:
    t, tr = results["test"], results["train"]
    seeds = results["seeds"]
    noisy = block.noisy
    lines = [
        "# Collaborative semantic scene completion (V2VSSC) on simulated real_cav",
        "",
        f"Written by the `ssc` stage (profile's `ssc` block). Test: {t['samples']} ego frames from "
        f"{t['scenarios']} held-out `{block.domain}/{block.test_split}` scenarios; training: {tr['views']} agent "
        f"views ({tr['samples']} samples) from {tr['scenarios']} `{block.train_split}` scenarios. "
        f"{len(seeds)} training seed(s) {seeds}; the single-agent network trains {block.steps} steps, "
        f"{_joined([DISPLAY[m] for m in block.methods if NETWORK[m] == m])} {block.warm_start_steps} more from "
        "it. Each cell is the figure (%) with counts "
        f"pooled over the frames (SemanticKITTI), mean over seeds, and its 95 % bootstrap interval over "
        f"scenarios and seeds ({block.bootstrap} replicates). Grid: V2VSSC's 128 × 128 × 20 voxels over "
        f"x, y ∈ [−50, 50) m, z ∈ [−3, 5) m in the ego's frame; classes as V2VSSC (empty, road, car, terrain, "
        "building, vegetation, pole); cIoU is the mean of road and car. How the ground truth, the metric and "
        "the late-fusion merge are built: [ssc_notes.md](ssc_notes.md).",
        "",
        "## Table I analogue: perfect setting",
        "",
        *_table(results["tables"]["perfect"]),
        "",
        *_beats(results["tables"]["perfect"]),
        "",
        f"## Noisy setting: position σ {noisy.position_std:g} m, heading σ {noisy.heading_std_deg:g}°, "
        f"{noisy.delay_ms} ms delay",
        "",
        "The same networks (trained in the perfect setting; V2VSSC fine-tunes for this setting), scored on the "
        f"frames t ≥ {noisy.delay_ms // 100} of each test sequence.",
        "",
        *_table(results["tables"]["noisy"]),
        "",
        *_beats(results["tables"]["noisy"]),
        "",
        *_generated(results, block),
        "## V2VSSC Table I (OPV2V-based V2VSSC test set, VoxelNet), for reference",
        "",
        *markdown_table(["method", *(SSC_FIGURES[f] for f in PAPER_COLUMNS)],
                        ([DISPLAY[m], *(f"{v:.1f}" for v in PAPER[m])] for m in DISPLAY if m in PAPER)).split("\n"),
        "",
        "## Robustness (Figs. 4–5), first seed",
        "",
        f"Every sweep is scored on the test frames t ≥ {max(block.robustness.delay_ms, default=0) // 100} "
        "(the frames the longest delay can use), one level of one perturbation at a time.",
        "",
        "![robustness](ssc_robustness.png)",
        "",
    ]
    rob = results["robustness"]
    for sweep, label in SWEEPS.items():
        levels = rob["levels"][sweep]
        xs = rob["applied_delay_ms"] if sweep == "delay_ms" else levels
        lines += [f"mIoU (%) against {label}" + (" (every message exactly this old)" if sweep == "delay_ms"
                                                 else "") + ":", "",
                  markdown_table(["method", *(f"{x:g}" for x in xs)],
                                 ([DISPLAY[m], *(_pct(c["miou"]) for c in entry[sweep])]
                                  for m, entry in rob["methods"].items())), ""]
    for method, per in rob["quantization"].items():
        lines += [f"{DISPLAY[method]} with its messages quantised (per-channel min-max, V2VSSC Fig. 5's "
                  "compression), mIoU (%): " + ", ".join(f"{b} bit {_pct(v['miou'])}" for b, v in per.items()) + ".",
                  ""]
    lines += ["## Predicted against true maps (first test frame, first seed)", "",
              "![ssc gallery](ssc_gallery.png)", "",
              "Top class of each voxel column (the highest non-empty voxel), the ego at the centre.", "",
              "Class weights of the cross-entropy (mean 1): "
              + ", ".join(f"{c} {w:g}" for c, w in results["class_weights"].items()) + ".", ""]
    return "\n".join(lines)


def top_class(labels: np.ndarray) -> np.ndarray:
    """(X, Y) the class of the highest non-empty voxel of each column of an (X, Y, Z) map (0: none)."""
    labels = np.asarray(labels)
    occupied = labels > 0
    top = labels.shape[2] - 1 - np.argmax(occupied[:, :, ::-1], axis=2)
    out = np.take_along_axis(labels, top[:, :, None], axis=2)[:, :, 0]
    return np.where(occupied.any(axis=2), out, 0)


def _savefig(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90, bbox_inches="tight")


def render_maps(truth: np.ndarray, predictions: dict[str, np.ndarray], path: Path, title: str) -> Path:
    """Top-class images of the true map and each method's prediction side by side."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Rectangle

    from typ.reporting import subplots

    cmap = ListedColormap(COLORS[:N_CLASSES])
    panels = [("truth", truth), *((DISPLAY[m], p) for m, p in predictions.items())]
    fig, axes = subplots(1, len(panels), figsize=(3.6 * len(panels), 3.9))
    for ax, (name, labels) in zip(np.atleast_1d(axes), panels):
        ax.imshow(top_class(labels).T, origin="lower", cmap=cmap, vmin=0, vmax=N_CLASSES - 1,
                  extent=(-50, 50, -50, 50), interpolation="nearest")
        ax.set(title=name, xticks=[-50, 0, 50], yticks=[-50, 0, 50])
    handles = [Rectangle((0, 0), 1, 1, color=COLORS[i]) for i in range(1, N_CLASSES)]
    fig.legend(handles, SSC_CLASSES[1:], loc="lower center", ncol=N_CLASSES - 1, fontsize=8)
    fig.suptitle(title, fontsize=9)
    _savefig(fig, path)
    return path


def render_curves(results: dict, path: Path) -> Path:
    """mIoU with its interval against each robustness sweep, and the feature-sending methods' against
    message bits."""
    from typ.reporting import subplots

    rob = results["robustness"]
    fig, axes = subplots(1, 4, figsize=(17, 4))
    colors = {m: f"C{i}" for i, m in enumerate(DISPLAY)}
    for ax, (sweep, label) in zip(axes, SWEEPS.items()):
        xs = rob["applied_delay_ms"] if sweep == "delay_ms" else rob["levels"][sweep]
        for method, entry in rob["methods"].items():
            cells = entry[sweep]
            y = [100 * c["miou"]["value"] for c in cells]
            ax.plot(xs, y, "o-", color=colors[method], label=DISPLAY[method])
            ax.fill_between(xs, [100 * c["miou"]["low"] for c in cells], [100 * c["miou"]["high"] for c in cells],
                            color=colors[method], alpha=0.12)
        ax.set(xlabel=label, ylabel="mIoU (%)", title=f"mIoU vs {label.split(' (')[0]}")
    ax = axes[3]
    for method, per in rob["quantization"].items():
        ax.plot([int(b) for b in per], [100 * v["miou"]["value"] for v in per.values()], "o-",
                color=colors[method], label=DISPLAY[method])
    if any(rob["quantization"].values()):
        if "none" in rob["methods"]:
            ax.axhline(100 * rob["methods"]["none"]["position_std"][0]["miou"]["value"], color=colors["none"],
                       linestyle="--", label="No Fusion")
        ax.set(xscale="log", xlabel="bits per feature (message)", ylabel="mIoU (%)", title="mIoU vs compression")
        ax.legend(fontsize=7)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    _savefig(fig, path)
    return path


def write_report(results: dict, block: SscConfig, folder: Path, gallery: tuple[np.ndarray, dict, str] | None) -> list[Path]:
    """``ssc.md``, ``ssc_robustness.png`` and ``ssc_gallery.png`` under ``folder``."""
    md = folder / "ssc.md"
    write_text(md, report_markdown(results, block))
    paths = [md, render_curves(results, folder / "ssc_robustness.png")]
    if gallery is not None:
        truth, preds, title = gallery
        paths.append(render_maps(truth, preds, folder / "ssc_gallery.png", title))
    return paths
