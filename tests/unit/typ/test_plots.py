"""Curves as data: the tables read back exactly, and `dvc plots show` draws the declared plots from
them in a temporary DVC project."""
import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from typ import plots
from typ.errors import TypError

DVC = Path(sys.executable).with_name("dvc")


def test_tables_read_back_with_nan_as_empty_and_the_same_bytes_twice(tmp_path):
    steps = np.arange(4)
    path = plots.loss_curve(tmp_path / "loss.csv", steps, {"train": [1.0, 0.5, 1 / 3, 0.1], "val": [1.2, np.nan, 0.7, 0.4]})
    rows = list(csv.DictReader(path.open()))
    assert rows[2] == {"step": "2", "train": repr(1 / 3), "val": "0.7"} and rows[1]["val"] == ""
    assert float(rows[2]["train"]) == 1 / 3  # shortest repr round-trips
    first = path.read_bytes()
    plots.loss_curve(tmp_path / "loss.csv", steps, {"train": [1.0, 0.5, 1 / 3, 0.1], "val": [1.2, np.nan, 0.7, 0.4]})
    assert path.read_bytes() == first
    path = plots.pr_curve(tmp_path / "pr.json", recall=[0.5, 0.1, 0.9], precision=[0.8, 1.0, 0.4], thresholds=[0.5, 0.9, 0.1])
    assert json.loads(path.read_text()) == [{"recall": 0.1, "precision": 1.0, "threshold": 0.9},
                                            {"recall": 0.5, "precision": 0.8, "threshold": 0.5},
                                            {"recall": 0.9, "precision": 0.4, "threshold": 0.1}]
    path = plots.bands(tmp_path / "bands.tsv", [(0, 20), (20, 40)], {"typ": [0.5, math.inf]})
    assert path.read_text() == "range_m\tband\ttyp\n10.0\t0-20\t0.5\n30.0\t20-40\t\n"
    path = plots.pareto(tmp_path / "pareto.json", [0.1, 0.4], [0.5, 0.3], ["ddim 10", "ddim 50"])
    assert json.loads(path.read_text())[1] == {"seconds": 0.4, "error": 0.3, "setting": "ddim 50"}
    with pytest.raises(TypError, match="equal length"):
        plots.write_table(tmp_path / "x.csv", {"a": [1], "b": [1, 2]})
    with pytest.raises(TypError, match="suffix"):
        plots.write_table(tmp_path / "x.png", {"a": [1]})
    with pytest.raises(TypError, match="swept parameter"):
        plots.declaration("s", "sweep", {"s.csv": "early"})
    with pytest.raises(TypError, match="kind"):
        plots.declaration("s", "histogram", {"s.csv": "early"})


def test_dvc_plots_show_renders_the_declared_curves(tmp_path):
    plots.loss_curve(tmp_path / "plots" / "loss.csv", [0, 10, 20], {"train": [0.9, 0.4, 0.2], "val": [1.0, 0.6, 0.5]})
    plots.sweep(tmp_path / "plots" / "pose_noise.json", "position_std_m", [0.0, 0.2, 0.4],
                {"early": [0.61, 0.52, 0.33], "late": [0.55, 0.51, 0.47]})
    plots.pr_curve(tmp_path / "plots" / "pr_early.csv", [0.2, 0.6], [0.9, 0.7])
    plots.pr_curve(tmp_path / "plots" / "pr_late.csv", [0.3, 0.5], [0.8, 0.75])
    plots.bands(tmp_path / "plots" / "iou_bands.csv", [(0, 20), (20, 40), (40, 80)], {"typ": [0.5, 0.3, 0.1]})
    declared = [plots.declaration("losses", "loss", {"plots/loss.csv": ["train", "val"]}, title="stage-1 losses"),
                plots.declaration("pose_noise", "sweep", {"plots/pose_noise.json": ["early", "late"]},
                                  x="position_std_m"),
                plots.declaration("pr", "pr", {"plots/pr_early.csv": "precision", "plots/pr_late.csv": "precision"}),
                plots.declaration("iou_by_range", "band", {"plots/iou_bands.csv": "typ"})]
    (tmp_path / "dvc.yaml").write_text(yaml.safe_dump({"plots": declared}, sort_keys=False))
    env = {**os.environ, "DVC_NO_ANALYTICS": "1"}
    subprocess.run([str(DVC), "init", "--no-scm", "-q"], cwd=tmp_path, env=env, check=True)
    shown = subprocess.run([str(DVC), "plots", "show", "--json"], cwd=tmp_path, env=env, capture_output=True,
                           text=True, check=True)
    data = json.loads(shown.stdout)["data"]
    assert set(data) == {"losses", "pose_noise", "pr", "iou_by_range"}

    def values(plot_id):
        (plot,) = data[plot_id]
        assert plot["type"] == "vega"
        return plot["content"], plot["content"]["data"]["values"]

    spec, rows = values("losses")
    assert spec["title"]["text"] == "stage-1 losses"
    assert sorted((r["field"], float(r["step"]), float(r["dvc_inferred_y_value"])) for r in rows) == \
        [("train", 0, 0.9), ("train", 10, 0.4), ("train", 20, 0.2), ("val", 0, 1.0), ("val", 10, 0.6), ("val", 20, 0.5)]
    _, rows = values("pose_noise")
    assert {(r["field"], r["position_std_m"], r["dvc_inferred_y_value"]) for r in rows} >= {("early", 0.4, 0.33),
                                                                                            ("late", 0.4, 0.47)}
    _, rows = values("pr")
    assert sorted(float(r["recall"]) for r in rows) == [0.2, 0.3, 0.5, 0.6]
    _, rows = values("iou_by_range")
    assert [(float(r["range_m"]), r["band"]) for r in rows] == [(10.0, "0-20"), (30.0, "20-40"), (60.0, "40-80")]
    html = subprocess.run([str(DVC), "plots", "show", "-o", "rendered"], cwd=tmp_path, env=env, capture_output=True,
                          text=True, check=True)
    page = (tmp_path / "rendered" / "index.html").read_text()
    assert "index.html" in html.stdout and page.count("vegaEmbed") >= 4
