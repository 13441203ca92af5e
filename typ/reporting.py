"""Tables and figures of typ's reports, written one way.

- :func:`markdown_table`: a GitHub-flavoured markdown table from a header and rows of cells;
- :func:`interval_cell`: a figure with its interval as every report prints it, ``value [low, high]``;
- :func:`figure` / :func:`subplots`: a matplotlib Figure on its own Agg canvas, as pyplot's
  would be but without pyplot's global state or backend switch (nothing to close, safe in
  threads and in a process that has picked another backend).
"""
from __future__ import annotations

import math
from typing import Iterable, Sequence

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

__all__ = ["figure", "interval_cell", "markdown_table", "subplots"]


def markdown_table(header: Sequence[str], rows: Iterable[Sequence], *, escape: bool = False) -> str:
    """``| a | b |`` lines: the header, its rule, one line per row (cells through ``str``).
    escape: write a ``|`` inside a cell as ``\\|`` (free text such as run names)."""
    def line(cells) -> str:
        cells = [str(c) for c in cells]
        return "| " + " | ".join(c.replace("|", "\\|") if escape else c for c in cells) + " |"

    return "\n".join([line(header), "|" + "---|" * len(header), *(line(r) for r in rows)])


#: a figure that does not exist (not finite)
NOT_A_NUMBER = "–"


def interval_cell(cell, digits: int = 3, *, scale: float = 1.0, missing: str = "–", adaptive: bool = False) -> str:
    """A figure with its bootstrap interval as a report cell: ``value [low, high]`` to ``digits``.

    cell: a :class:`typ.metrics.intervals.Interval`, its dict (``{"value", "low", "high"}``, as the
    metrics JSON holds it) or a ``(value, low, high)`` tuple, each multiplied by ``scale``; None
    (the figure does not apply) gives ``missing``, a value that is not finite ``–``, bounds that are
    absent or not finite the value alone. adaptive: 5 digits for a value under 0.01 (but not 0), so
    that small figures keep their digits.
    """
    if cell is None:
        return missing
    if isinstance(cell, dict):
        value, low, high = cell.get("value"), cell.get("low"), cell.get("high")
    elif isinstance(cell, tuple):
        value, low, high = cell
    else:
        value, low, high = cell.value, cell.low, cell.high
    if value is None:
        return missing
    value = value * scale
    if not math.isfinite(value):
        return NOT_A_NUMBER
    if adaptive and value != 0 and abs(value) < 0.01:
        digits = 5
    if low is None or high is None or not (math.isfinite(low * scale) and math.isfinite(high * scale)):
        return f"{value:.{digits}f}"
    return f"{value:.{digits}f} [{low * scale:.{digits}f}, {high * scale:.{digits}f}]"


def figure(**kwargs) -> Figure:
    """A Figure (matplotlib.figure.Figure's keywords: figsize, dpi, layout, ...) on an Agg canvas."""
    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def subplots(nrows: int = 1, ncols: int = 1, *, squeeze: bool = True, sharex=False, sharey=False, **kwargs):
    """``(figure, axes)`` as :func:`matplotlib.pyplot.subplots` gives them, on an Agg canvas."""
    fig = figure(**kwargs)
    return fig, fig.subplots(nrows, ncols, squeeze=squeeze, sharex=sharex, sharey=sharey)
