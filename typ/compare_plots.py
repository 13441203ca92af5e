"""The figures of ``typ compare`` (module :mod:`typ.compare`): metric names read as families
(sweeps, distance bands), and one PNG per stage for loss curves, sweeps, bands, Pareto fronts and
the final metrics that differ between the compared runs."""
from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

from typ.io import atomic_path

#: what typ's records name as the writer of a ``typ compare`` plot (:func:`typ.io.written_by`)
COMPARE = "compare"


BAND = re.compile(r"^\d+(\.\d+)?-\d+(\.\d+)?$")
BAND_NAMES = ("overall", "all")
MAX_PANELS = 24


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


@dataclass
class StageData:
    finals: list[dict[str, float]]                  # per run set: metric -> final value
    histories: list[dict[str, list[tuple[int, float]]]]  # per run set: metric -> [(step, value)], > 1 step


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
    with atomic_path(path, stage=COMPARE) as tmp:  # recorded: a later report of the name replaces it
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
