"""bench/two_stage.py's table (the training itself runs in `make bench`)."""
import importlib.util
from pathlib import Path

SPEC = importlib.util.spec_from_file_location("two_stage", Path(__file__).resolve().parents[1] / "bench" / "two_stage.py")
two_stage = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(two_stage)


def test_table_has_one_row_per_training_with_its_scores():
    rows = [{"name": "1-stage", "epochs1": "—", "epochs2": "720 steps", "steps": 720, "train_s": 201.5,
             "jsd_r2dm": 0.51234, "mmd_r2dm": 0.00123, "iou": 0.2},
            {"name": "2-stage", "epochs1": 100, "epochs2": 40, "steps": 720, "train_s": "(pipeline)",
             "jsd_r2dm": 0.41, "mmd_r2dm": 0.0009, "iou": 0.25}]
    text = two_stage.markdown(rows, "note")
    lines = [line for line in text.splitlines() if line.startswith("| ") and "training" not in line]
    assert lines == ["| 1-stage | — | 720 steps | 720 | 201.5 | 0.512 | 1.23e-03 | 0.200 |",
                     "| 2-stage | 100 | 40 | 720 | (pipeline) | 0.410 | 9.00e-04 | 0.250 |"]
    assert "Table 5" in text and "note" in text
