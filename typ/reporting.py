"""Tables and figures of typ's reports, written one way.

- :func:`markdown_table`: a GitHub-flavoured markdown table from a header and rows of cells;
- :func:`figure` / :func:`subplots`: a matplotlib Figure on its own Agg canvas, as pyplot's
  would be but without pyplot's global state or backend switch (nothing to close, safe in
  threads and in a process that has picked another backend).
"""
from __future__ import annotations

from typing import Iterable, Sequence

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

__all__ = ["figure", "markdown_table", "subplots"]


def markdown_table(header: Sequence[str], rows: Iterable[Sequence], *, escape: bool = False) -> str:
    """``| a | b |`` lines: the header, its rule, one line per row (cells through ``str``).
    escape: write a ``|`` inside a cell as ``\\|`` (free text such as run names)."""
    def line(cells) -> str:
        cells = [str(c) for c in cells]
        return "| " + " | ".join(c.replace("|", "\\|") if escape else c for c in cells) + " |"

    return "\n".join([line(header), "|" + "---|" * len(header), *(line(r) for r in rows)])


def figure(**kwargs) -> Figure:
    """A Figure (matplotlib.figure.Figure's keywords: figsize, dpi, layout, ...) on an Agg canvas."""
    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def subplots(nrows: int = 1, ncols: int = 1, *, squeeze: bool = True, sharex=False, sharey=False, **kwargs):
    """``(figure, axes)`` as :func:`matplotlib.pyplot.subplots` gives them, on an Agg canvas."""
    fig = figure(**kwargs)
    return fig, fig.subplots(nrows, ncols, squeeze=squeeze, sharex=sharex, sharey=sharey)
