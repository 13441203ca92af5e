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

from typ.config import Config
from typ.errors import TypError
from typ.io import atomic_path, write_text
from typ.reporting import markdown_table

RUN_ID = re.compile(r"^[0-9a-f]{32}$")
BAND = re.compile(r"^\d+(\.\d+)?-\d+(\.\d+)?$")
BAND_NAMES = ("overall", "all")
MAX_PANELS = 24
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


# ---------------------------------------------------------------- metric names


def segments(name: str) -> list[str]:
    """``robustness.position_std.0.2.ap50`` -> ``[robustness, position_std, 0.2, ap50]``."""
    parts = name.split(".")
    out: list[str] = []
    for p in parts:
        if out and p.isdigit() and out[-1].isdigit():
            out[-1] = f"{out[-1]}.{p}"
        else:
            out.append(p)
    return out


def _number(seg: str) -> float | None:
    try:
        value = float(seg)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def _is_band(seg: str) -> bool:
    return bool(BAND.match(seg)) or seg in BAND_NAMES


def _band_key(seg: str) -> tuple[float, float]:
    if seg in BAND_NAMES:
        return (math.inf, 0.0)
    lo, hi = seg.split("-")
    return (float(lo), float(hi))


def _families(names: list[str], test) -> dict[tuple[str, int], dict[str, str]]:
    """Group names that differ in one segment accepted by ``test``: (pattern, position) -> {segment: name}."""
    fams: dict[tuple[str, int], dict[str, str]] = {}
    for name in names:
        segs = segments(name)
        for i, seg in enumerate(segs):
            if test(seg):
                pattern = ".".join(segs[:i] + ["*"] + segs[i + 1:])
                fams.setdefault((pattern, i), {})[seg] = name
    return fams


# ---------------------------------------------------------------- gathering


@dataclass
class StageData:
    finals: list[dict[str, float]]                  # per run set: metric -> final value
    histories: list[dict[str, list[tuple[int, float]]]]  # per run set: metric -> [(step, value)], > 1 step


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


# ---------------------------------------------------------------- plots


def _colors(n: int) -> list:
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return [cmap(i % 10) for i in range(n)]


def _grid(n: int, width: float = 4.6, height: float = 3.2):
    from typ.reporting import subplots

    cols = min(3, n)
    rows = math.ceil(n / cols)
    fig, axes = subplots(rows, cols, figsize=(max(width * cols, 8.0), height * rows + 0.7), squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, list(axes.flat[:n])


def _save(fig, path: Path, title: str) -> Path:
    fig.suptitle(title, fontsize=12, fontweight="bold")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    return path


def _smooth(values: list[float], window: int) -> list[float]:
    """Centred moving mean over ``window`` steps (shorter at the ends): no lag, unlike an EMA."""
    import numpy as np

    v = np.asarray(values, dtype=float)
    kernel = np.ones(window)
    return (np.convolve(v, kernel, "same") / np.convolve(np.ones_like(v), kernel, "same")).tolist()


def _maybe_log(ax, values) -> None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    if finite and min(finite) > 0 and max(finite) / min(finite) > 100:
        ax.set_yscale("log")


def plot_curves(stage: str, data: StageData, labels: list[str], path: Path) -> Path | None:
    keys = sorted(set().union(*data.histories), key=lambda k: ("loss" not in k.split(".")[-1], k))
    if not keys:
        return None
    keys = keys[:MAX_PANELS]
    colors = _colors(len(labels))
    fig, axes = _grid(len(keys))
    for ax, key in zip(axes, keys):
        seen = []
        for label, color, hist in zip(labels, colors, data.histories):
            if key not in hist:
                continue
            steps, values = zip(*hist[key])
            seen += values
            if len(values) > 20:
                ax.plot(steps, values, color=color, alpha=0.25, linewidth=0.8)
                ax.plot(steps, _smooth(list(values), max(3, len(values) // 10)), color=color, linewidth=1.8,
                        label=label)
            else:
                ax.plot(steps, values, color=color, marker="o", markersize=3, linewidth=1.5, label=label)
        _maybe_log(ax, seen)
        ax.set_title(key, fontsize=10)
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    return _save(fig, path, f"{stage}: training curves (faint: per step, bold: smoothed)")


def _family_panels(finals: list[dict[str, float]], test, at_least: int):
    """Metric families (see :func:`_families`) with at least ``at_least`` members: the first
    MAX_PANELS as sorted ``((pattern, position), family)`` items, and every metric they hold."""
    fams = {k: v for k, v in _families(sorted(set().union(*finals)), test).items() if len(v) >= at_least}
    return sorted(fams.items())[:MAX_PANELS], {n for fam in fams.values() for n in fam.values()}


def plot_sweeps(stage: str, finals: list[dict[str, float]], labels: list[str], path: Path) -> tuple[Path | None, set]:
    items, used = _family_panels(finals, lambda s: _number(s) is not None, 3)
    if not items:
        return None, used
    colors = _colors(len(labels))
    fig, axes = _grid(len(items))
    for ax, ((pattern, pos), fam) in zip(axes, items):
        xs = sorted(fam, key=float)
        for label, color, values in zip(labels, colors, finals):
            pts = [(float(x), values[fam[x]]) for x in xs if fam[x] in values]
            if pts:
                ax.plot(*zip(*pts), color=color, marker="o", markersize=4, linewidth=1.6, label=label)
        segs = pattern.split(".")
        ax.set_xlabel(segs[pos - 1] if pos > 0 else "value")
        ax.set_title(pattern, fontsize=10)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    return _save(fig, path, f"{stage}: sweeps (metric against the number in its name)"), used


def plot_bands(stage: str, finals: list[dict[str, float]], labels: list[str], path: Path) -> tuple[Path | None, set]:
    items, used = _family_panels(finals, _is_band, 2)
    if not items:
        return None, used
    colors = _colors(len(labels))
    fig, axes = _grid(len(items))
    width = 0.8 / len(labels)
    for ax, ((pattern, _), fam) in zip(axes, items):
        bands = sorted(fam, key=_band_key)
        for j, (label, color, values) in enumerate(zip(labels, colors, finals)):
            ys = [values.get(fam[b], math.nan) for b in bands]
            bars = ax.bar([i + (j - (len(labels) - 1) / 2) * width for i in range(len(bands))], ys, width,
                          color=color, label=label)
            ax.bar_label(bars, fmt="%.3g", fontsize=7)
        ax.set_xticks(range(len(bands)), [f"{b} m" if BAND.match(b) else b for b in bands])
        ax.set_title(pattern, fontsize=10)
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=8)
    return _save(fig, path, f"{stage}: by range band"), used


def pareto_front(points: list[tuple[float, float]], higher_is_better: bool) -> list[int]:
    """Indices of the points no other point beats on both time (lower) and quality."""
    sign = 1 if higher_is_better else -1
    front = []
    for i, (t, q) in enumerate(points):
        if not any((t2 <= t and sign * q2 >= sign * q) and (t2 < t or sign * q2 > sign * q)
                   for j, (t2, q2) in enumerate(points) if j != i):
            front.append(i)
    return sorted(front, key=lambda i: points[i][0])


HIGHER_IS_BETTER = re.compile(r"(^|_)(iou|ap\d*|precision|recall|accuracy|codes_used|map|miou)($|_)")


def plot_pareto(stage: str, finals: list[dict[str, float]], labels: list[str], path: Path) -> tuple[Path | None, set]:
    names = sorted(set().union(*finals))
    by_variant: dict[str, dict[str, str]] = {}
    for name in names:
        segs = segments(name)
        if len(segs) >= 2:
            by_variant.setdefault(".".join(segs[:-1]), {})[segs[-1]] = name
    timed = {v: leaves for v, leaves in by_variant.items() if any(k.startswith("seconds") for k in leaves)}
    if len(timed) < 3:  # fewer variants make a table, not a front
        return None, set()
    qualities = sorted({k for leaves in timed.values() for k in leaves if not k.startswith("seconds")})
    panels = [q for q in qualities if sum(q in leaves for leaves in timed.values()) >= 2][:MAX_PANELS]
    if not panels:
        return None, set()
    used = {leaves[k] for leaves in timed.values() for k in leaves if k in panels or k.startswith("seconds")}
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    prefix = _common_prefix(list(timed))
    kinds = sorted({(v[len(prefix):] or v).split(".")[0] for v in timed})  # e.g. the sampler
    markers = dict(zip(kinds, "osD^vPX*<>" * 4))
    colors = _colors(len(labels))
    fig, axes = _grid(len(panels), width=5.2, height=3.8)
    for ax, quality in zip(axes, panels):
        higher = bool(HIGHER_IS_BETTER.search(quality))
        named: set[str] = set()
        for label, color, values in zip(labels, colors, finals):
            pts, names_ = [], []
            for variant, leaves in sorted(timed.items()):
                cost = next((leaves[k] for k in sorted(leaves) if k.startswith("seconds")), None)
                if quality in leaves and cost in values and leaves[quality] in values:
                    pts.append((values[cost], values[leaves[quality]]))
                    names_.append(variant[len(prefix):] or variant)
            if not pts:
                continue
            for kind in kinds:
                mine = [pt for pt, n in zip(pts, names_) if n.split(".")[0] == kind]
                if mine:
                    ax.scatter(*zip(*mine), color=color, marker=markers[kind], s=26, alpha=0.85)
            front = pareto_front(pts, higher)
            ax.plot([pts[i][0] for i in front], [pts[i][1] for i in front], color=color, linewidth=1.2)
            for i in front:
                if names_[i] not in named:
                    named.add(names_[i])
                    ax.annotate(names_[i], pts[i], fontsize=7, xytext=(4, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel(f"{prefix}*.seconds (log)" if prefix else "seconds (log)")
        ax.set_title(f"{quality} ({'higher' if higher else 'lower'} is better)", fontsize=10)
        ax.grid(alpha=0.3)
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=c, linewidth=1.5, label=lab) for lab, c in zip(labels, colors)]
    if len(kinds) > 1:
        handles += [Line2D([], [], color="0.4", marker=markers[k], linestyle="", label=k) for k in kinds]
    axes[0].legend(handles=handles, fontsize=8)
    return _save(fig, path, f"{stage}: quality against time, Pareto front per run"), used


def _common_prefix(names: list[str]) -> str:
    """The dotted segments every name starts with, with the trailing dot (``sampling.``)."""
    split = [n.split(".") for n in names]
    common = []
    for parts in zip(*split):
        if len(set(parts)) > 1:
            break
        common.append(parts[0])
    common = common[:min(len(s) for s in split) - 1]
    return ".".join(common) + "." if common else ""


def _relative_spread(values: list[float]) -> float:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    if len(finite) < 2:
        return 0.0
    scale = max(abs(v) for v in finite) or 1.0
    return (max(finite) - min(finite)) / scale


def plot_finals(stage: str, finals: list[dict[str, float]], labels: list[str], skip: set, path: Path
                ) -> tuple[Path | None, int]:
    names = sorted(set().union(*finals) - skip)
    spread = {n: _relative_spread([f.get(n) for f in finals]) for n in names}
    differing = sorted((n for n in names if spread[n] > 1e-9), key=lambda n: -spread[n])
    if not differing:
        return None, 0
    shown = differing[:MAX_PANELS]
    colors = _colors(len(labels))
    fig, axes = _grid(len(shown), width=3.6, height=2.4)
    for ax, name in zip(axes, shown):
        ys = [f.get(name, math.nan) for f in finals]
        bars = ax.barh(range(len(labels)), ys, color=colors)
        ax.bar_label(bars, fmt="%.4g", fontsize=7, padding=2)
        ax.margins(x=0.18)
        ax.set_yticks(range(len(labels)), labels, fontsize=8)
        ax.invert_yaxis()
        change = ""
        if len(ys) == 2 and ys[0] and math.isfinite(ys[0]) and math.isfinite(ys[1]):
            change = f" ({(ys[1] - ys[0]) / abs(ys[0]):+.1%})"
        ax.set_title(name + change, fontsize=9)
        ax.grid(alpha=0.3, axis="x")
    return _save(fig, path, f"{stage}: final metrics that differ (largest relative difference first)"), len(differing)


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
        old.unlink(missing_ok=True)
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
