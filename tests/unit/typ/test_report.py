"""reports/summary.md: one page, every figure from metrics/*.json, missing stages said so."""
from __future__ import annotations

import json

from typ.report import iv, write_summary
from typ.tracking import stage_seconds


def _cell(value: float, low: float, high: float) -> dict:
    return {"value": value, "low": low, "high": high}


def _ap(value: float) -> dict:
    return {"ap50": {"overall": _cell(value, value - 0.05, value + 0.05)}}


def test_summary_is_one_page_of_the_metrics(tmp_path):
    metrics, reports = tmp_path / "metrics", tmp_path / "reports"
    metrics.mkdir()
    (reports / "gallery").mkdir(parents=True)
    for name in ("b.png", "a.png", "c.png"):
        (reports / "gallery" / name).write_bytes(b"png")
    (reports / "fusion.md").write_text("# fusion\n")
    (metrics / "simulate.json").write_text(json.dumps({"seconds_total": 44.4}))
    (metrics / "stage1.json").write_text(json.dumps({"seed_0": {"seconds_training": 200.0},
                                                     "seed_1": {"seconds_training": 70.6}}))
    table3 = {m: {"scratch": {"1": _ap(0.11), "all": _ap(0.50), "5": _ap(0.30)},
                  "colwaymo": {"0": _ap(0.02), "1": _ap(0.25), "5": _ap(0.41), "all": _ap(0.49)}}
              for m in ("late", "none")}
    evaluate = {"pairs": 64, "scenes": 16,
                "generation": {"resim": {"iou": _cell(0.461, 0.427, 0.492)},
                               "hybrid": {"iou": _cell(0.493, 0.469, 0.515), "jsd_r2dm": _cell(0.114, 0.1, 0.134)}},
                "adaptation": {"before": {"jsd_r2dm": 0.4}, "after": {"jsd_r2dm": 0.3}, "jsd_change": -0.25},
                "fusion": {"test_frames": 40, "test_scenarios": 10, "seeds": 1,
                           "table1": {"late": {"oracle": _ap(0.54), "generated": _ap(0.44)}, "none": {"ego": _ap(0.5)}},
                           "table3": table3}}
    (metrics / "evaluate.json").write_text(json.dumps(evaluate))

    text = write_summary(tmp_path).read_text()
    lines = text.splitlines()
    assert len(lines) <= 150
    assert "| simulate | 44 | " in text and "| stage1 | 271 | " in text and "| vqvae | not run | " in text
    assert "| hybrid (re-simulation + TYP) | 0.493 [0.469, 0.515] | — | — | 0.114 [0.100, 0.134] |" in lines
    assert "| re-simulation | 0.461 [0.427, 0.492] | — | — | — |" in lines
    assert "64 held-out (ego, reference) pairs of 16 scenes" in text
    assert "0.400 → 0.300 (-25.0 %)" in text
    assert "![a](gallery/a.png) ![b](gallery/b.png)" in lines          # the first two pictures, sorted
    # Table 1 in the paper's method order; Table 3's columns 0, 1, 5, all
    assert lines.index("| No fusion | 0.50 [0.45, 0.55] | — |") < lines.index("| Late | 0.54 [0.49, 0.59] | 0.44 [0.39, 0.49] |")
    assert "| method | pre-training | 0 sc. | 1 sc. | 5 sc. | all sc. |" in lines
    assert "|  | generated target | 0.02 [-0.03, 0.07] | 0.25 [0.20, 0.30] | 0.41 [0.36, 0.46] | 0.49 [0.44, 0.54] |" in lines
    assert "Not run." in text and "[fusion](fusion.md)" in text


def test_interval_and_seconds_helpers():
    assert iv(None) == "—" and iv({"value": None}) == "—"
    assert iv({"value": 0.5, "low": None, "high": None}) == "0.500"
    assert iv(_cell(0.1234, 0.1, 0.15), 2) == "0.12 [0.10, 0.15]"
    assert stage_seconds({"seconds_total": 3, "seconds_training": 9}) == 3.0
    assert stage_seconds({"x": {"seconds_training": 2.5}, "y": {"z": {"seconds_training": 1.5}}}) == 4.0
    assert stage_seconds({"count": 3}) is None


def test_a_fusion_method_the_registry_gains_gets_its_row(monkeypatch):
    """Rows follow the fusion registry's order; a method added there (or one only an older run's
    metrics name) gets a row of its own instead of an error."""
    from typ import report

    monkeypatch.setattr(report, "FUSION_METHODS", (*report.FUSION_METHODS[:2], "newfuse", *report.FUSION_METHODS[2:]))
    cell = lambda v: {"ap50": {"overall": {"value": v, "low": v - 0.1, "high": v + 0.1}}}  # noqa: E731
    table1 = {m: {"oracle": cell(0.5), "generated": cell(0.4)} for m in ("late", "oldfuse", "newfuse", "none")}
    lines = report._fusion({"fusion": {"table1": table1, "table3": {"newfuse": {"scratch": {"1": cell(0.3)}}}}})
    rows = [line.split("|")[1].strip() for line in "\n".join(lines).splitlines() if line.startswith("| ") and "[" in line]
    assert rows == ["No fusion", "newfuse", "Late", "oldfuse", "newfuse"]
    ssc = report._ssc({"tables": {"perfect": {m: {"iou": cell(0.2)["ap50"]["overall"]} for m in ("attfuse", "newfuse")}}})
    assert [line.split("|")[1].strip() for line in "\n".join(ssc).splitlines()
            if line.startswith("| ") and "[" in line] == ["newfuse", "AttFuse"]
