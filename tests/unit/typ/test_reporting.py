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
