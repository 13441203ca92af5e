"""``reports/summary.md``: what the last pipeline run produced, from the stages' metrics files."""
from __future__ import annotations

import json
from pathlib import Path

from typ.config import Config
from typ.io import write_text


def _rows(metrics: dict, prefix: str = "") -> list[tuple[str, object]]:
    rows = []
    for key, value in metrics.items():
        if isinstance(value, dict):
            rows.extend(_rows(value, f"{prefix}{key}."))
        else:
            rows.append((f"{prefix}{key}", value))
    return rows


def write_summary(root: Path) -> Path:
    lines = ["# typ — pipeline summary", "",
             "Stage metrics from `metrics/*.json` (the same numbers `dvc metrics show` prints). "
             "Runs, params and artifacts: `mlflow ui --backend-store-uri sqlite:///mlruns.db`.", ""]
    for stage in Config.STAGES:
        path = root / "metrics" / f"{stage}.json"
        lines.append(f"## {stage}")
        lines.append("")
        if not path.exists():
            lines += ["not run yet", ""]
            continue
        lines += ["| metric | value |", "|---|---|"]
        lines += [f"| {k} | {v} |" for k, v in _rows(json.loads(path.read_text()))]
        lines.append("")
    tables = sorted(p for p in (root / "reports").glob("*.md")
                    if not p.name.startswith(("bench", "summary")) and p.parent.name == "reports")
    if tables:
        lines += ["## Result tables", ""]
        lines += [f"- [{p.stem}]({p.name})" for p in tables]
        lines.append("")
    benches = sorted((root / "reports").glob("bench_*.md"))
    if benches:
        lines += ["## Benchmarks", ""]
        if (root / "reports" / "bench.md").exists():
            lines.append("- [all benchmarks on one page, with the machine](bench.md) (`make bench`)")
        lines += [f"- [{p.stem}]({p.name})" for p in benches]
        lines.append("")
    out = root / "reports" / "summary.md"
    write_text(out, "\n".join(lines))
    return out
