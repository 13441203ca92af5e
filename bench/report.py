"""``reports/bench.md``: every ``reports/bench_*.md`` (and ``reports/*/bench_*.md``) on one page,
under a header naming the machine.

    python bench/report.py [--out reports]

Each bench writes its own page (method, notes, tables, plot). This page keeps, per bench in
file-name order, its title (linked to the page, and its plot when there is one), its tables
with the heading just above each, and its one-line verdicts (``- **...``); the method and
notes stay on the bench's own page. The header names the machine this script runs on:
``make bench`` runs it right after the benches, in the same environment. The pages, plots
and raw JSON then go to MLflow as the artifacts of one run named ``bench`` (``--no-mlflow``: not).
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

from typ.io import write_text  # noqa: E402


def cpu_model() -> str:
    """The CPU's marketing name from /proc/cpuinfo (Linux), else what platform knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine() -> dict:
    """Cores, CPU model, torch and its intra-op threads: what every bench's numbers depend on."""
    import torch

    return {"cores": os.cpu_count(), "cpu": cpu_model(), "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(), "python": platform.python_version()}


def machine_line(info: dict) -> str:
    return (f"{info['cores']} cores ({info['cpu']}), Python {info['python']}, torch {info['torch']} with "
            f"{info['torch_threads']} intra-op thread(s)")


def digest(markdown: str) -> str:
    """A bench page's tables, each under the last heading before it, and its ``- **`` verdict lines.

    Headings move one level down (the page's title becomes the aggregate's section); headings
    with nothing kept under them are dropped.
    """
    out: list[str] = []
    heading, last = None, None          # last: the kind of the previous line, "table" / "bullet" / None
    for line in markdown.splitlines():
        if line.startswith("#"):
            level = len(line) - len(line.lstrip("#"))
            if level > 1 and line[level:level + 1] == " ":  # the page title (level 1) is the caller's
                heading, last = "#" + line, None
            continue
        kind = "table" if line.startswith("|") else "bullet" if line.startswith("- **") else None
        if kind is not None:
            if heading is not None:
                out += ["", heading, ""] if out else [heading, ""]
                heading = None
            elif kind != last and out:
                out.append("")
            out.append(line)
        last = kind
    return "\n".join(out)


def aggregate(folder: Path, info: dict) -> str:
    """The text of ``<folder>/bench.md`` from the bench pages found in ``folder``, then those of its
    sub-folders (benches run on another machine, e.g. ``gpu/`` from bench/gpu.py: their page names
    the machine and their folder's README how the run was made; ``make bench`` does not rerun them)."""
    lines = ["# typ benchmarks", "",
             f"Machine: {machine_line(info)}. Every figure below is a ratio or a curve measured side by side "
             "in one run of its bench; absolute times are this machine's, except on the pages of a sub-folder, "
             "measured on the machine that page names. `make bench` regenerates this page.", ""]
    pages = sorted(folder.glob("bench_*.md")) + sorted(folder.glob("*/bench_*.md"))
    if not pages:
        lines.append("No bench pages yet: run `make bench`.")
    for page in pages:
        text = page.read_text(encoding="utf-8")
        title = next((ln[2:].strip() for ln in text.splitlines() if ln.startswith("# ")), page.stem)
        plot = page.with_suffix(".png")
        links = f"[page]({page.relative_to(folder).as_posix()})"
        if plot.exists():
            links += f", [plot]({plot.relative_to(folder).as_posix()})"
        if page.parent != folder and (page.parent / "README.md").is_file():
            links += f", [how it was made]({page.parent.relative_to(folder).as_posix()}/README.md)"
        lines += [f"## {title}", "", f"{page.stem} — {links}", ""]
        body = digest(text)
        lines += [body, ""] if body else ["(no tables)", ""]
    return "\n".join(lines)


def log_to_mlflow(folder: Path, *, root: Path = Path("."), params: str = "params.yaml") -> str:
    """One MLflow run ``bench`` (the project's experiment and store, git commit tagged) holding
    ``bench.md`` and every bench page, plot and raw JSON of ``folder`` as artifacts; its run id."""
    from typ.config import load_config
    from typ.tracking import stage_run

    cfg = load_config(root / params)
    files = sorted(p for p in folder.glob("bench*") if p.suffix in (".md", ".png", ".json"))
    with stage_run("bench", cfg, root=root) as run:
        for path in files:
            run.artifact(path, "bench")
        run.metrics({"bench_pages": len([p for p in files if p.name.startswith("bench_") and p.suffix == ".md"])})
    return run.run_id


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="reports", help="folder holding the bench_*.md pages; bench.md goes there")
    ap.add_argument("--no-mlflow", action="store_true", help="do not log the pages as an MLflow run")
    args = ap.parse_args(argv)
    out = Path(args.out)
    write_text(out / "bench.md", aggregate(out, machine()))
    print(out / "bench.md")
    if not args.no_mlflow:
        print(f"MLflow run {log_to_mlflow(out)}: bench pages as artifacts")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
