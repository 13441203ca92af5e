"""typ.reporting: the one markdown-table writer and the one Agg figure of typ's reports."""
from __future__ import annotations

import subprocess
import sys

from typ.reporting import figure, markdown_table, subplots


def test_a_markdown_table_has_a_header_a_rule_and_one_line_per_row():
    text = markdown_table(["method", "IoU"], [["copy", 0.25], ("cast", "0.54 [0.52, 0.56]")])
    assert text.split("\n") == ["| method | IoU |", "|---|---|", "| copy | 0.25 |", "| cast | 0.54 [0.52, 0.56] |"]
    assert markdown_table(["a"], []) == "| a |\n|---|"


def test_escaping_keeps_a_pipe_inside_its_cell():
    text = markdown_table(["run"], [["a|b"]], escape=True)
    assert text.split("\n")[2] == "| a\\|b |"
    assert markdown_table(["run"], [["a|b"]]).split("\n")[2] == "| a|b |"


def test_figures_draw_on_their_own_agg_canvas_without_pyplot(tmp_path):
    code = ("import sys; from typ.reporting import subplots; fig, axes = subplots(2, 3, figsize=(6, 3)); "
            "axes[1, 2].plot([0, 1], [1, 0]); fig.savefig(sys.argv[1]); "
            "print(axes.shape, type(fig.canvas).__name__, 'matplotlib.pyplot' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "f.png")], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["(2,", "3)", "FigureCanvasAgg", "False"]
    assert (tmp_path / "f.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    fig = figure(figsize=(2, 1), dpi=50)
    assert fig.get_size_inches().tolist() == [2, 1] and fig.dpi == 50
    _, ax = subplots()
    assert ax.get_figure().canvas is not None


def test_one_interval_cell_for_every_report():
    """Every report prints a figure with its interval through interval_cell: the metrics JSON's
    dict, an Interval and a (value, low, high) tuple alike; scaled; None and non-finite named."""
    from typ.metrics.intervals import Interval
    from typ.metrics.intervals import interval_cell

    d = {"value": 0.5361, "low": 0.5149, "high": 0.5572}
    assert interval_cell(d) == interval_cell(Interval(0.5361, 0.5149, 0.5572)) == interval_cell((0.5361, 0.5149, 0.5572)) \
        == "0.536 [0.515, 0.557]" == Interval(0.5361, 0.5149, 0.5572).text()
    assert interval_cell(d, 1, scale=100) == "53.6 [51.5, 55.7]" and interval_cell(d, 2) == "0.54 [0.51, 0.56]"
    assert interval_cell({"value": 0.25, "low": None, "high": None}, 2) == "0.25"          # no interval: the value
    assert interval_cell(Interval(0.25, float("nan"), float("nan"))) == "0.250"
    assert interval_cell(None) == "–" and interval_cell(None, missing="—") == "—" and interval_cell({"value": None}) == "–"
    assert interval_cell(Interval(float("nan"), 0.0, 1.0)) == "–" == interval_cell((float("inf"), 0.0, 1.0))
    assert interval_cell(Interval(0.00412, 0.00301, 0.00518), adaptive=True) == "0.00412 [0.00301, 0.00518]"
    assert interval_cell(Interval(0.0, 0.0, 0.001), adaptive=True) == "0.000 [0.000, 0.001]"   # 0 keeps 3 digits
