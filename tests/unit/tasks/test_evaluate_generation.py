"""Which learned methods the evaluate stage scores: the selftrain variants its params train, by name."""
from __future__ import annotations

from pathlib import Path

import pytest

from tasks import evaluate_generation as gen
from tasks import stage1
from typ.config import config_from_dict
from typ.metrics.intervals import Interval
from typ.projection import RangeLayout


class _Base:
    """Stands in for stage 1's pipeline: an adapter turns it into the adapter's name."""

    def with_adapter(self, adapter):
        return adapter


def _trained(tmp_path: Path, cfg, names) -> None:
    for name in names:
        folder = stage1.replica_dir(tmp_path / cfg.selftrain.out, 0) / name
        folder.mkdir(parents=True)
        (folder / "config.json").write_text("{}")


@pytest.fixture
def no_models(monkeypatch):
    monkeypatch.setattr(gen, "base_pipeline", lambda *a: _Base())
    monkeypatch.setattr(gen.stage2, "load_adapter", lambda folder, stage="stage2": folder.name)


@pytest.mark.parametrize("resim", [False, True])
def test_pipelines_score_every_variant_selftrain_trains_the_switches_own_included(tmp_path, no_models, resim):
    cfg = config_from_dict({"selftrain": {"discriminator": False, "self_training": True, "dummy_ego": True,
                                          "ablation": True}, "stage2": {"resim": resim}})
    _trained(tmp_path, cfg, ["no_adaptation", "disc", "disc_st", "disc_st_dummy", "st_dummy", "typ_resim"])
    out = gen.pipelines(cfg, tmp_path, 0, None, None, None)
    assert list(out) == ["stage1_only", "no_adaptation", "disc", "disc_st", "disc_st_dummy", "st_dummy",
                         *(["typ_resim"] if resim else [])]
    assert all(out[k] == k for k in out if k != "stage1_only")


def test_pipelines_leave_out_variants_the_params_no_longer_train(tmp_path, no_models):
    cfg = config_from_dict({"selftrain": {"ablation": False}})  # the full model only
    _trained(tmp_path, cfg, ["no_adaptation", "disc", "disc_st_dummy"])  # the first two from an older ablation
    assert list(gen.pipelines(cfg, tmp_path, 0, None, None, None)) == ["stage1_only", "disc_st_dummy"]


def test_a_custom_variant_gets_a_row_after_the_known_methods():
    iv = {"iou": Interval(0.5, 0.4, 0.6)}
    rows = gen.report_rows({"table": {"st_dummy": iv, "naive_copy": iv, "disc": iv}})
    assert list(rows) == [gen.METHODS["naive_copy"], gen.METHODS["disc"], "TYP variant st_dummy (selftrain switches)"]


@pytest.mark.parametrize("ablation", [False, True])
def test_the_report_says_which_table_rows_were_not_trained(tmp_path, ablation):
    """tiny trains the switches' model alone: Tables 4 and 5 then say which params add their rows."""
    from tasks.evaluate import ACCURACY_COLUMNS, write_generation_report

    figures = [k for k, _ in ACCURACY_COLUMNS]
    methods = ["naive_copy", "resim", "stage1_only", "disc_st_dummy", "typ_resim"]
    if ablation:
        methods += ["no_adaptation", "disc", "disc_st", "one_stage"]
    table = {m: {f: Interval(0.1 + 0.01 * i, 0.05, 0.2) for f in figures} for i, m in enumerate(methods)}
    result = {"table": table, "typ": "disc_st_dummy", "resim_key": "typ_resim", "pairs": 4, "scenes": 2,
              "seeds": [0], "seconds": {"stage1_only": 0.1}, "spread_iou": 0.3,
              "realism": {m: {"on_beam": Interval(0.9, 0.8, 1.0)} for m in ["truth", *methods]}, "realism_floor": {},
              "realism_missing": "no networks", "layout": RangeLayout((-10.0, 0.0, 2.0), 8, 50.0, 1.0)}
    text = write_generation_report(tmp_path / "r.md", result, extra=[]).read_text()
    table4 = text.split("## TYP Table 4")[1].split("## TYP Table 5")[0]
    table5 = text.split("## TYP Table 5")[1]
    assert ("selftrain.ablation: true" in table4) is not ablation
    assert ("stage2.one_stage: true" in table5) is not ablation
    assert table4.count("\n| ") == (1 + 4 if ablation else 1 + 1)  # header + one row per method
    assert gen.label("one_stage") in table5 if ablation else gen.label("one_stage") not in table5
    realism = text.split("## Scan pattern and realism")[1]
    assert realism.count("\n| ") == 2 + len(methods) and "3 x 8 range image" in realism


def test_the_one_stage_model_samples_as_every_other_row(tmp_path, monkeypatch):
    """Table 5 compares training recipes: the one-stage model gets its own UNet, adapter and
    schedule, and the sampler of the other rows (steps, thresholds, the adapter scale)."""
    from typ import artifacts
    from pipelines.typ.pipeline_typ import TYPPipeline

    base = TYPPipeline("x_vq", "y_enc", "stage1 unet", None, "grid", "linear", 1000, "dpmsolver++", 10,
                       {"threshold": 0.3}, adapter_scale=1.5)
    monkeypatch.setattr(gen, "base_pipeline", lambda *a: base)
    monkeypatch.setattr(gen.stage2, "load_adapter", lambda folder, stage="stage2": f"adapter of {folder.parent.name}")
    monkeypatch.setattr(artifacts, "load_module", lambda folder, build, stage: ("joint unet", {"schedule": "cosine",
                                                                                            "train_timesteps": "500"}))
    cfg = config_from_dict({"stage2": {"one_stage": True}})
    unet = stage1.replica_dir(tmp_path / cfg.stage2.out, 0) / "one_stage" / "unet"
    unet.mkdir(parents=True)
    (unet / "config.json").write_text("{}")
    one = gen.pipelines(cfg, tmp_path, 0, None, None, None)["one_stage"]
    assert (one.unet, one.adapter, one.schedule, one.train_timesteps) == ("joint unet", "adapter of one_stage", "cosine", 500)
    assert (one.adapter_scale, one.thresholds, one.sampler, one.num_inference_steps) == (1.5, {"threshold": 0.3},
                                                                                        "dpmsolver++", 10)
    assert (one.x_vqvae, one.box_encoder, one.grid) == ("x_vq", "y_enc", "grid") and base.unet == "stage1 unet"
