"""``typ compare``: two or more runs side by side, from the MLflow store through its client.

A *run set* is what one reference names, as ``{stage: run}``:

- an MLflow run id: a pipeline run brings its nested stage runs (found by their
  ``mlflow.parentRunId`` tag); a stage run stands alone;
- a DVC experiment name (``dvc exp run`` tags every stage run with ``dvc.exp_name``): the
  latest run of each stage carrying it;
- an MLflow experiment name: its latest pipeline run (alone, or with no reference at all
  (the params' experiment): its latest two, so ``typ compare`` compares the last two runs).

The report, ``<out>/<name>.md`` with PNGs beside it, has the params that differ, and per stage
the final metrics side by side and plots chosen from the metric names alone, so a new stage's
metrics show up without changes here. Metric names are dotted paths (``ap50.0-30``,
``robustness.position_std.0.2.ap50``); a path segment is a *band* if it looks like
``30-50`` or is ``overall``, a *number* if it parses as one (``0.2`` spans two segments):

- curves: metrics logged at more than one step (losses first), raw and smoothed, per stage;
- sweeps: metrics that differ only in one numeric segment (>= 3 values) as y against that
  number: robustness curves (AP vs pose noise, delay, bits), fine-tuning budgets, step counts;
- bands: metrics that differ only in a band segment as grouped bars: AP by range;
- Pareto: metrics under variant paths that also have a ``seconds*`` leaf, as quality against
  time with the front drawn: sampler x steps comparisons;
- the other final metrics that differ between the runs, one small panel each (largest
  relative differences first).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from typ.compare_plots import (COMPARE, MAX_PANELS, StageData, _number, pareto_front, plot_bands,  # noqa: F401
                               plot_curves, plot_finals, plot_pareto, plot_sweeps, segments)
from typ.config import Config
from typ.errors import TypError
from typ.io import remove_written, write_text
from typ.reporting import markdown_table


RUN_ID = re.compile(r"^[0-9a-f]{32}$")
STAGE_ORDER = ("pipeline",) + Config.STAGES


@dataclass
class RunSet:
    """What one reference names: its label in tables and legends, and its run per stage."""

    label: str
    runs: dict = field(default_factory=dict)  # stage -> mlflow.entities.Run

    @property
    def first(self):
        return self.runs.get("pipeline") or next(iter(self.runs.values()))


# ---------------------------------------------------------------- resolving references


def _stage(run) -> str:
    return run.data.tags.get("typ.stage") or run.info.run_name or run.info.run_id[:8]


def _children(client, run) -> dict:
    found = client.search_runs([run.info.experiment_id], f"tags.mlflow.parentRunId = '{run.info.run_id}'",
                               order_by=["attributes.start_time DESC"], max_results=1000)
    out = {}
    for child in found:  # newest first: a stage re-run inside one pipeline run keeps the newest
        out.setdefault(_stage(child), child)
    return out


def _stage_key(stage: str) -> tuple[int, str]:
    return (STAGE_ORDER.index(stage) if stage in STAGE_ORDER else len(STAGE_ORDER), stage)


def _from_run(client, run, label: str) -> RunSet:
    runs = {_stage(run): run, **_children(client, run)}
    return RunSet(label, dict(sorted(runs.items(), key=lambda kv: _stage_key(kv[0]))))


def _short_label(run) -> str:
    return run.info.run_id[:7]


def _latest_pipelines(client, experiment, n: int) -> list:
    return client.search_runs([experiment.experiment_id], "tags.`typ.stage` = 'pipeline'",
                              order_by=["attributes.start_time DESC"], max_results=n)


def resolve(client, refs: list[str], *, default_experiment: str | None = None) -> list[RunSet]:
    """Run sets for ``refs`` (see the module docstring); TypError for a name that matches nothing."""
    from mlflow.exceptions import MlflowException

    if not refs:
        if default_experiment is None:
            raise TypError("typ compare", "RUN_OR_EXPERIMENT", "two or more runs or experiment names")
        refs = [default_experiment]
    sets: list[RunSet] = []
    for ref in refs:
        if RUN_ID.match(ref):
            try:
                run = client.get_run(ref)
            except MlflowException:
                raise TypError("typ compare", ref, "a run id in the MLflow store", "no such run") from None
            sets.append(_from_run(client, run, _short_label(run)))
            continue
        experiments = [e.experiment_id for e in client.search_experiments()]
        tagged = client.search_runs(experiments, f"tags.`dvc.exp_name` = '{ref}'",
                                    order_by=["attributes.start_time DESC"], max_results=1000) if experiments else []
        if tagged:
            runs: dict = {}
            for run in tagged:
                runs.setdefault(_stage(run), run)
            sets.append(RunSet(ref, dict(sorted(runs.items(), key=lambda kv: _stage_key(kv[0])))))
            continue
        experiment = client.get_experiment_by_name(ref)
        if experiment is None:
            raise TypError("typ compare", ref, "an MLflow run id, a DVC experiment name or an MLflow experiment name",
                           "none matches")
        latest = _latest_pipelines(client, experiment, 2 if len(refs) == 1 else 1)
        if not latest:
            raise TypError("typ compare", ref, f"an experiment with a pipeline run (typ run all); {ref!r} has none")
        for run in latest:
            sets.append(_from_run(client, run, f"{ref}@{_short_label(run)}" if len(latest) > 1 else ref))
    if len(sets) < 2:
        raise TypError("typ compare", "RUN_OR_EXPERIMENT", "two or more runs to compare", refs)
    seen: dict[str, int] = {}
    for s in sets:  # the same label twice (one experiment named twice) gets a suffix
        seen[s.label] = seen.get(s.label, 0) + 1
        if seen[s.label] > 1:
            s.label += f" #{seen[s.label]}"
    return sets


# ---------------------------------------------------------------- gathering


def gather(client, sets: list[RunSet]) -> dict[str, StageData]:
    stages = sorted({s for rs in sets for s in rs.runs}, key=_stage_key)
    data = {}
    for stage in stages:
        finals, histories = [], []
        for rs in sets:
            run = rs.runs.get(stage)
            finals.append(dict(run.data.metrics) if run else {})
            hist = {}
            for key in (run.data.metrics if run else {}):
                points = client.get_metric_history(run.info.run_id, key)
                if len({p.step for p in points}) > 1:
                    hist[key] = sorted((p.step, p.value) for p in points)
            histories.append(hist)
        data[stage] = StageData(finals, histories)
    return data


def differing_params(sets: list[RunSet]) -> tuple[list[tuple[str, list[str]]], int, int]:
    """Over the params every run set has: (param, value per run set) where they differ, and how
    many are the same; then how many params only some run sets have (their stages ran in those only)."""
    merged = []
    for rs in sets:
        params: dict[str, str] = {}
        for run in rs.runs.values():
            params.update(run.data.params)
        merged.append(params)
    shared = sorted(set.intersection(*(set(m) for m in merged)), key=_natural)
    differ = [(k, [m[k] for m in merged]) for k in shared if len({m[k] for m in merged}) > 1]
    return differ, len(shared) - len(differ), len(set().union(*merged)) - len(shared)


# ---------------------------------------------------------------- report


def _fmt(v) -> str:
    if v is None:
        return "—"
    if isinstance(v, float):
        if not math.isfinite(v):
            return str(v)
        return f"{v:.4g}" if abs(v) >= 1e-3 or v == 0 else f"{v:.3e}"
    text = str(v)
    return text if len(text) <= 60 else text[:57] + "..."


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return markdown_table(header, rows, escape=True).split("\n")


def _natural(name: str) -> list:
    """Sort key with numbers compared as numbers: ``ddim.5`` before ``ddim.10``."""
    return [(0, float(c), "") if _number(c) is not None else (1, 0.0, c) for c in re.split(r"(\d+(?:\.\d+)?)", name) if c]


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip("-")[:80] or "compare"


#: the first line of every report, which tells one typ wrote from a file of the same name
REPORT_TITLE = "# typ compare: "


def earlier_plots(report: Path) -> list[Path]:
    """The plots beside ``report`` that it links, when it is a report ``typ compare`` wrote: what a
    new report of that name replaces. Other files in the folder are not typ's to delete."""
    try:
        text = report.read_text(encoding="utf-8") if report.is_file() else ""
    except (OSError, UnicodeDecodeError):
        return []
    if not text.startswith(REPORT_TITLE):
        return []
    return [report.parent / png for png in re.findall(r"^!\[[^\]]*\]\(([^/()]+\.png)\)$", text, flags=re.M)]


def write_report(client, sets: list[RunSet], out: Path, name: str) -> Path:
    labels = [s.label for s in sets]
    data = gather(client, sets)
    for old in earlier_plots(out / f"{_slug(name)}.md"):
        remove_written(old, COMPARE)
    lines = [f"{REPORT_TITLE}{name}", "",
             "Written by `typ compare` from the MLflow store; plots are beside this file.", ""]
    rows = []
    for rs in sets:
        run = rs.first
        tags = run.data.tags
        rows.append([rs.label, f"`{run.info.run_id}`", ", ".join(rs.runs),
                     datetime.fromtimestamp(run.info.start_time / 1000, tz=timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                     tags.get("mlflow.source.git.commit", "—")[:12], tags.get("dvc.exp_name", "—"),
                     tags.get("typ.profile", "—"), run.info.status])
    lines += _table(["run", "id", "stages", "started", "git", "dvc exp", "profile", "status"], rows) + [""]
    lines += ["Stage runs: " + "; ".join(f"{rs.label}: " + ", ".join(f"{s} `{r.info.run_id[:7]}`" for s, r in rs.runs.items())
                                       for rs in sets), ""]
    differ, same, partial = differing_params(sets)
    lines += ["## Params that differ", ""]
    if differ:
        lines += _table(["param", *labels], [[f"`{k}`", *[_fmt(v) for v in vals]] for k, vals in differ])
    else:
        lines.append("None.")
    lines += ["", f"{same} other params are the same in every run"
              + (f"; {partial} belong to stages that ran in only some of them." if partial else "."), ""]
    for stage, sd in data.items():
        keys = sorted(set().union(*sd.finals), key=_natural)
        if not keys:
            continue
        present = [lab for lab, rs in zip(labels, sets) if stage in rs.runs]
        lines += [f"## {stage}", ""]
        if len(present) < 2:
            lines += [f"Only in {present[0]}: nothing to compare (e.g. DVC skipped the unchanged stage).", ""]
            continue
        if len(present) < len(sets):
            lines += [f"Only in: {', '.join(present)}.", ""]
        stem = out / f"{_slug(name)}_{_slug(stage)}"
        pictures = [plot_curves(stage, sd, labels, Path(f"{stem}_curves.png"))]
        sweep, used_sweep = plot_sweeps(stage, sd.finals, labels, Path(f"{stem}_sweeps.png"))
        bands, used_bands = plot_bands(stage, sd.finals, labels, Path(f"{stem}_bands.png"))
        pareto, used_pareto = plot_pareto(stage, sd.finals, labels, Path(f"{stem}_pareto.png"))
        finals, n_differ = plot_finals(stage, sd.finals, labels, used_sweep | used_bands | used_pareto | set().union(
            *sd.histories), Path(f"{stem}_finals.png"))
        pictures += [sweep, bands, pareto, finals]
        lines += [f"![{p.stem}]({p.name})" for p in pictures if p is not None]
        if finals is not None and n_differ > MAX_PANELS:
            lines.append(f"({n_differ - MAX_PANELS} more differing metrics in the table below.)")
        header = ["metric", *labels] + ([f"Δ ({labels[1]} − {labels[0]})"] if len(sets) == 2 else [])
        body = []
        for k in keys:
            vals = [f.get(k) for f in sd.finals]
            row = [f"`{k}`", *[_fmt(v) for v in vals]]
            if len(sets) == 2:
                row.append(_fmt(vals[1] - vals[0]) if None not in vals else "—")
            body.append(row)
        lines += ["", "Final values (the last logged step):", ""] + _table(header, body) + [""]
    path = out / f"{_slug(name)}.md"
    write_text(path, "\n".join(lines) + "\n")
    return path


def compare(refs: list[str], *, out: Path, name: str | None = None, tracking_uri: str | None = None,
            root: Path = Path("."), params: Path | None = None) -> Path:
    """Resolve ``refs`` in the MLflow store and write ``<out>/<name>.md`` and its PNGs."""
    from mlflow.tracking import MlflowClient

    default_experiment = None
    if tracking_uri is None or not refs:
        from typ.config import load_config
        from typ.tracking import tracking_uri as configured_uri

        cfg = load_config(params or Path(root) / "params.yaml")
        tracking_uri = tracking_uri or configured_uri(cfg, Path(root))
        default_experiment = cfg.tracking.experiment
    client = MlflowClient(tracking_uri=tracking_uri)
    sets = resolve(client, refs, default_experiment=default_experiment)
    name = name or "-vs-".join(_slug(s.label) for s in sets)
    return write_report(client, sets, Path(out), name)
