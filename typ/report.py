"""``reports/summary.md``: one page on what the last pipeline run produced, read in two minutes.

Every figure comes from the stages' metrics files (``metrics/<stage>.json``, what ``dvc metrics
show`` prints); the full tables stay in the reports they link to. Sections whose metrics are
missing (a stage not run yet, or skipped) say so in one line.
"""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

from typ.config import FUSION_METHODS, Config
from typ.io import write_text
from typ.registry import METHODS
from typ.metrics.intervals import interval_cell
from typ.reporting import markdown_table
from typ.tracking import stage_seconds

#: ``evaluate``'s generation rows, as the generation report names them
GENERATION_ROWS = {"generated": "what `generate` writes", "cast": "cast view (one scene, the reference LiDAR)",
                   "hybrid": "hybrid (re-simulation + TYP)",
                   "disc_st_dummy": "TYP (stage 1 + 2, self-trained)", "typ_resim": "TYP, re-simulation training",
                   "stage1_only": "stage 1 alone", "resim": "re-simulation", "naive_copy": "copy the ego's view"}
GENERATION_KEYS = (("iou", "IoU"), ("iou_above_ground", "above ground"), ("object_hit_rate", "hit rate"),
                   ("jsd_r2dm", "JSD"))


def fusion_name(method: str) -> str:
    """A fusion method's row: its registry entry's summary name, a name the registry does not hold
    (metrics of an older run) as it is."""
    return METHODS[method].summary_name if method in METHODS else method


def fusion_order(method: str) -> tuple[int, str]:
    """Where a fusion method's row goes: the registry's order (``typ.config.FUSION_METHODS``), a name
    it does not hold (metrics of an older run) after them by name; never an error."""
    return (FUSION_METHODS.index(method), "") if method in FUSION_METHODS else (len(FUSION_METHODS), method)


PRETRAIN_NAMES = {"scratch": "scratch", "colwaymo": "generated target", "source": "source sim"}


def iv(cell: dict | None, digits: int = 3) -> str:
    """``value [low, high]`` of an interval cell of the metrics JSON; — where there is none."""
    return interval_cell(cell if isinstance(cell, dict) else None, digits, missing="—")


def _commit(root: Path) -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                             timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return out.stdout.strip() or "unknown"


def _stages(metrics: dict[str, dict]) -> list[str]:
    rows = []
    for stage in Config.STAGES:
        m = metrics.get(stage)
        seconds = None if m is None else stage_seconds(m)
        rows.append([stage, "not run" if m is None else "—" if seconds is None else f"{seconds:.0f}",
                     f"`metrics/{stage}.json`"])
    return ["## Stages", "", markdown_table(["stage", "seconds of work it reports", "metrics"], rows)]


def _generation(evaluate: dict, reports: Path) -> list[str]:
    gen = evaluate.get("generation")
    if not gen:
        return ["## Generation", "", "No generation scores (the evaluate stage did not score generation)."]
    lines = ["## Generated reference views against the truth", "",
             f"{evaluate.get('pairs', '?')} held-out (ego, reference) pairs of {evaluate.get('scenes', '?')} scenes; "
             "full table by range band: [generation_accuracy.md](generation_accuracy.md).", "",
             markdown_table(["method", *(label for _, label in GENERATION_KEYS)],
                            [[name, *(iv(gen[key].get(k)) for k, _ in GENERATION_KEYS)]
                             for key, name in GENERATION_ROWS.items() if isinstance(gen.get(key), dict)])]
    adapt = evaluate.get("adaptation")
    if adapt and adapt.get("jsd_change") is not None:
        lines += ["", f"Adaptation (TYP Eq. 8–10): JSD of source views through the target decoder "
                  f"{adapt['before']['jsd_r2dm']:.3f} → {adapt['after']['jsd_r2dm']:.3f} "
                  f"({100 * adapt['jsd_change']:+.1f} %)."]
    pictures = sorted((reports / "gallery").glob("*.png"))[:2]
    if pictures:
        lines += ["", " ".join(f"![{p.stem}](gallery/{p.name})" for p in pictures)]
    return lines


def _fusion(evaluate: dict) -> list[str]:
    f = evaluate.get("fusion")
    if not f or "table1" not in f:
        return ["## Collaborative detection", "", "No detection scores (the fusion stage did not run)."]
    lines = ["## Collaborative detection, AP@0.5 overall (TYP Tables 1 and 3)", "",
             f"real_cav/test, {f.get('test_frames', '?')} frames of {f.get('test_scenarios', '?')} scenarios, "
             f"{f.get('seeds', '?')} seed(s); full tables, ranges and robustness: [fusion.md](fusion.md).", ""]
    rows = []
    for method, row in sorted(f["table1"].items(), key=lambda kv: fusion_order(kv[0])):
        ap = {data: (cell or {}).get("ap50", {}).get("overall") for data, cell in row.items()}
        rows.append([fusion_name(method), iv(ap.get("oracle") or ap.get("ego"), 2),
                     iv(ap.get("generated"), 2)])
    lines.append(markdown_table(["method", "true cooperating views", "generated ones"], rows))
    t3 = f.get("table3", {})
    columns = sorted({c for rows in t3.values() for cols in rows.values() for c in cols},
                     key=lambda c: (c == "all", int(c) if c.isdigit() else 0))
    if t3:
        table = []
        for method, rows in sorted(t3.items(), key=lambda kv: fusion_order(kv[0])):
            for i, source in enumerate(s for s in PRETRAIN_NAMES if s in rows):
                table.append([fusion_name(method) if i == 0 else "", PRETRAIN_NAMES[source],
                              *(iv((rows[source].get(c) or {}).get("ap50", {}).get("overall"), 2) for c in columns)])
        lines += ["", "Pre-trained, then fine-tuned on n real scenes with scratch's steps on the same scenes:", "",
                  markdown_table(["method", "pre-training", *(f"{c} sc." for c in columns)], table)]
    return lines


def _ssc(ssc: dict | None) -> list[str]:
    if not ssc or not ssc.get("tables"):
        return ["## Collaborative semantic scene completion", "", "Not run."]
    tables = ssc["tables"]
    data = [d for d in ("perfect", "generated", "noisy") if d in tables]
    lines = ["## Collaborative semantic scene completion (V2VSSC Table I), IoU / mIoU", "",
             "Full table, classes and robustness: [ssc.md](ssc.md).", ""]
    rows = [[fusion_name(method),
             *(f"{iv(tables[d][method].get('iou'), 2)} / {iv(tables[d][method].get('miou'), 2)}"
               if method in tables[d] else "—" for d in data)]
            for method in sorted({m for d in data for m in tables[d]}, key=fusion_order)]
    lines.append(markdown_table(["method", *data], rows))
    return lines


def _ddpm(ddpm: dict | None, reports: Path) -> list[str]:
    if not ddpm or not ddpm.get("rows"):
        return ["## LiDAR DDPM", "", "Not run."]
    lines = ["## Unconditional LiDAR generation (LiDAR-DDPM Table II), lower is better", "",
             "Every configuration and sampler: [ddpm.md](ddpm.md).", "",
             markdown_table(["representation", "model", "sampler", "FRID", "FPVD", "JSD", "s / sample"],
                            [[row.get("representation"), row.get("config"), row.get("sampler") or "(reference)",
                              iv(row.get("frid")), iv(row.get("fpvd")), iv(row.get("jsd")),
                              f"{row.get('seconds_per_sample') or 0.0:.3f}"] for row in ddpm["rows"].values()])]
    if (reports / "ddpm_pareto.png").is_file():
        lines += ["", "![samplers: quality against time](ddpm_pareto.png)"]
    return lines


def write_summary(root: Path) -> Path:
    """Write ``reports/summary.md`` under ``root`` (module doc); its path."""
    metrics = {}
    for stage in Config.STAGES:
        path = root / "metrics" / f"{stage}.json"
        if path.is_file():
            metrics[stage] = json.loads(path.read_text())
    reports = root / "reports"
    evaluate = metrics.get("evaluate", {})
    lines = ["# typ — what the last pipeline run produced", "",
             f"Commit `{_commit(root)}`. Every figure is in `metrics/*.json` (`dvc metrics show`); runs, params and "
             "artifacts in MLflow (`mlflow ui --backend-store-uri sqlite:///mlruns.db`). Cells: value "
             "[95 % bootstrap interval over test scenarios and seeds]; \"A beats B\" only where they do not overlap.",
             "", *_stages(metrics), "", *_generation(evaluate, reports), "", *_fusion(evaluate), "",
             *_ssc(metrics.get("ssc")), "", *_ddpm(metrics.get("ddpm"), reports), ""]
    pages = sorted(p.name for p in reports.glob("*.md") if p.name not in ("summary.md", "bench.md")
                   and not p.name.startswith("bench_"))
    lines += ["## All reports", "", ", ".join(f"[{Path(p).stem}]({p})" for p in pages)
              + (" · benchmarks: [bench.md](bench.md) (`make bench`)" if (reports / "bench.md").is_file() else ""),
              ""]
    out = reports / "summary.md"
    write_text(out, "\n".join(lines))
    return out
