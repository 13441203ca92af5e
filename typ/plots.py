"""Curves as data for ``dvc plots``: small CSV / JSON tables and the ``plots:`` entries declaring them.

DVC renders a plot from a table file (CSV/TSV with a header row, or JSON: a list of
``{column: value}`` records) and an entry in ``dvc.yaml``'s top-level ``plots:`` naming the
x column, the y column(s) per file and a Vega-Lite template; ``dvc plots show`` draws the
workspace's, ``dvc plots diff <rev or exp>`` overlays revisions and experiments. So each curve
is written once, here, in one layout per kind (:data:`KINDS`), and :func:`declaration` makes
its ``plots:`` entry from the same kind, so the x column and template cannot drift apart:

========  =====================  ======================  ==========================================
kind      x column               template                one row per
========  =====================  ======================  ==========================================
loss      ``step``               smooth                  logged step; one column per loss
pr        ``recall``             simple                  threshold; ``precision``, ``threshold``
sweep     the swept parameter    linear                  value of pose noise / delay / bits; one
                                                         column per method (AP)
band      ``range_m``            linear                  range band: its centre (m) and its label
                                                         ``band`` (``20-40``); one column per method
pareto    ``seconds``            scatter                 sampler setting; ``error`` and its label
========  =====================  ======================  ==========================================

Files are written atomically; floats as the shortest repr that round-trips (so the same
numbers give the same bytes) and NaN and inf as an empty CSV cell / JSON null, which Vega skips.
"""
from __future__ import annotations

import csv
import io
import json
import math
import numbers
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from typ.errors import TypError
from typ.io import write_text

_WHERE = "typ.plots"


@dataclass(frozen=True)
class Kind:
    """How one kind of curve is laid out and drawn."""

    x: str | None          #: the x column; None: the writer names it (a sweep's parameter)
    template: str          #: DVC's Vega-Lite template
    x_label: str
    y_label: str


KINDS: dict[str, Kind] = {
    "loss": Kind("step", "smooth", "step", "loss"),
    "pr": Kind("recall", "simple", "recall", "precision"),
    "sweep": Kind(None, "linear", "", "AP"),
    "band": Kind("range_m", "linear", "range band centre (m from the sensor)", ""),
    "pareto": Kind("seconds", "scatter", "seconds per sample", "error"),
}


def _cell(value):
    """A JSON/CSV scalar: ints and floats as Python numbers (NaN/inf: None), text as str."""
    if value is None or isinstance(value, (bool, np.bool_)):
        return None if value is None else bool(value)
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        v = float(value)
        return v if math.isfinite(v) else None
    return str(value)


def write_table(path: str | Path, columns: Mapping[str, Sequence]) -> Path:
    """Write ``{column: values}`` (equal lengths) as ``path``'s format: ``.csv``, ``.tsv`` or ``.json``."""
    path = Path(path)
    names = list(columns)
    if not names:
        raise TypError(path, "columns", "at least one column", 0)
    lengths = {k: len(v) for k, v in columns.items()}
    if len(set(lengths.values())) != 1:
        raise TypError(path, "columns", "columns of equal length", lengths)
    rows = [{k: _cell(columns[k][i]) for k in names} for i in range(lengths[names[0]])]
    return write_records(path, rows, columns=names)


def write_records(path: str | Path, rows: Sequence[Mapping], *, columns: Sequence[str] | None = None) -> Path:
    """Write ``rows`` ({column: value}) as ``path``'s format; columns in order of first appearance."""
    path = Path(path)
    names = list(columns or [])
    for row in rows:
        names += [k for k in row if k not in names]
    clean = [{k: _cell(row.get(k)) for k in names} for row in rows]
    suffix = path.suffix.lower()
    if suffix == ".json":
        text = json.dumps(clean, indent=1, allow_nan=False) + "\n"
    elif suffix in (".csv", ".tsv"):
        buf = io.StringIO()
        writer = csv.writer(buf, delimiter="," if suffix == ".csv" else "\t", lineterminator="\n")
        writer.writerow(names)
        for row in clean:
            writer.writerow(["" if row[k] is None else (repr(row[k]) if isinstance(row[k], float) else row[k])
                             for k in names])
        text = buf.getvalue()
    else:
        raise TypError(path, "suffix", "one of .csv, .tsv, .json", path.suffix)
    write_text(path, text)
    return path


def loss_curve(path: str | Path, steps: Sequence[int], losses: Mapping[str, Sequence[float]]) -> Path:
    """Losses against optimizer step: columns ``step`` and one per loss (``train``, ``val``, ...)."""
    return write_table(path, {"step": list(steps), **{k: list(v) for k, v in losses.items()}})


def pr_curve(path: str | Path, recall: Sequence[float], precision: Sequence[float],
             thresholds: Sequence[float] | None = None) -> Path:
    """One precision-recall curve, rows in order of increasing recall; columns ``recall``,
    ``precision`` and ``threshold`` when given. Several methods: one file each, overlaid by
    naming them all in one :func:`declaration`."""
    order = sorted(range(len(recall)), key=lambda i: (recall[i], -precision[i]))
    columns = {"recall": [recall[i] for i in order], "precision": [precision[i] for i in order]}
    if thresholds is not None:
        columns["threshold"] = [thresholds[i] for i in order]
    return write_table(path, columns)


def sweep(path: str | Path, parameter: str, values: Sequence[float], series: Mapping[str, Sequence[float]]) -> Path:
    """A metric against a swept parameter (``position_std_m``, ``delay_s``, ``bits``): columns
    ``parameter`` and one per method."""
    return write_table(path, {parameter: list(values), **{k: list(v) for k, v in series.items()}})


def bands(path: str | Path, edges: Sequence[tuple[float, float]], series: Mapping[str, Sequence[float]]) -> Path:
    """A metric per range band ``[lo, hi)`` metres: columns ``range_m`` (the band's centre, the
    x DVC draws against: its line templates need a number), ``band`` (``lo-hi``) and one per method."""
    return write_table(path, {"range_m": [(lo + hi) / 2 for lo, hi in edges],
                              "band": [f"{lo:g}-{hi:g}" for lo, hi in edges], **{k: list(v) for k, v in series.items()}})


def pareto(path: str | Path, seconds: Sequence[float], error: Sequence[float], labels: Sequence[str]) -> Path:
    """Run time against error, one row per setting: columns ``seconds``, ``error``, ``setting``."""
    return write_table(path, {"seconds": list(seconds), "error": list(error), "setting": [str(s) for s in labels]})


def declaration(plot_id: str, kind: str, files: Mapping[str, str | Sequence[str]], *, title: str = "",
                x: str | None = None, x_label: str | None = None, y_label: str | None = None) -> dict:
    """One item of ``dvc.yaml``'s top-level ``plots:`` list for ``files`` ({path: y column(s)}).

    ``x`` is the kind's x column (a sweep's parameter must be given). Paths are relative to
    ``dvc.yaml``. E.g. ``declaration("fusion_pose_noise", "sweep", {"plots/fusion/pose_noise.csv":
    ["early", "late"]}, x="position_std_m")``.
    """
    if kind not in KINDS:
        raise TypError(_WHERE, "kind", f"one of {list(KINDS)}", kind)
    spec = KINDS[kind]
    x = x or spec.x
    if x is None:
        raise TypError(_WHERE, "x", f"the swept parameter's column for a {kind} plot", None)
    if not files:
        raise TypError(_WHERE, "files", "at least one {path: y column}", files)
    y = {str(p): (cols if isinstance(cols, str) else list(cols)) for p, cols in files.items()}
    entry = {"x": x, "y": y, "template": spec.template, "x_label": x_label or spec.x_label or x,
             "y_label": y_label or spec.y_label or ", ".join(sorted({c for v in y.values()
                                                                      for c in ([v] if isinstance(v, str) else v)}))}
    if title:
        entry["title"] = title
    return {plot_id: entry}
