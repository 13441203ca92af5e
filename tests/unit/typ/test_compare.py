"""`typ compare` on a sqlite MLflow store holding two realistic pipeline runs and two DVC experiments."""
import math

import matplotlib.image as mpimg
import numpy as np
import pytest

from cli.main import main
from typ.compare import compare, pareto_front, segments
from typ.config import config_from_dict
from typ.io import record_path
from typ.tracking import PARENT_ENV, stage_run


def _pipeline(tmp_path, monkeypatch, *, lr: float, noise: float, seed: int) -> str:
    """One pipeline run with vqvae, stage1 and fusion nested under it, logged through typ.tracking."""
    cfg = config_from_dict({"profile": "tiny", "stage1": {"lr": lr}})
    rng = np.random.default_rng(seed)
    with stage_run("pipeline", cfg, root=tmp_path) as parent:
        monkeypatch.setenv(PARENT_ENV, parent.run_id)
        with stage_run("vqvae", cfg, root=tmp_path) as run:
            for step in range(60):
                loss = 0.8 * math.exp(-step / 20) + 0.05 + noise * rng.random()
                run.metrics({"x.loss": loss, "x.rec": 0.9 * loss, "x.grad_norm": 2 + rng.random()}, step=step)
            run.metrics({"x.iou": 0.61 + noise, "x.codes_used": 0.4, "train_views": 16})
        with stage_run("stage1", cfg, root=tmp_path) as run:
            for step in range(40):
                run.metrics({"stage1.loss": 1 / (1 + step * lr * 100) + noise * rng.random()}, step=step)
            for sampler, base in (("ddim", 0.2), ("dpmsolver++", 0.15)):
                for steps in (5, 10, 20, 50):
                    run.metrics({f"sampling.{sampler}.{steps}.seconds_per_sample": 0.016 * steps,
                                 f"sampling.{sampler}.{steps}.chamfer_m": base + 1 / steps + noise})
            run.metrics({"generated.iou": 0.3 + noise, "generated.jsd_r2dm": 0.12 - noise / 2})
        with stage_run("fusion", cfg, root=tmp_path) as run:
            for method, ap in (("early", 0.62), ("late", 0.55)):
                for band, drop in (("overall", 0.0), ("0-30", -0.1), ("30-50", 0.05), ("50-100", 0.2)):
                    run.metrics({f"{method}.ap50.{band}": ap - drop + noise})
                for std in (0.0, 0.2, 0.4, 0.6):
                    run.metrics({f"robustness.position_std.{std}.{method}.ap50": ap - std * 0.5 + noise})
        monkeypatch.delenv(PARENT_ENV)
    return parent.run_id


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp_path = tmp_path_factory.mktemp("store")
    uri = f"sqlite:///{tmp_path / 'mlruns.db'}"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", uri)
        a = _pipeline(tmp_path, mp, lr=0.0005, noise=0.0, seed=0)
        b = _pipeline(tmp_path, mp, lr=0.001, noise=0.03, seed=1)
    return tmp_path, uri, a, b


def _nontrivial_png(path):
    assert path.stat().st_size > 10_000, path
    img = mpimg.imread(path)
    assert img.shape[0] > 200 and img.shape[1] > 200
    assert img[..., :3].std() > 0.05, f"{path} is nearly blank"


def test_compare_two_pipeline_runs_writes_report_and_plots(store):
    tmp_path, uri, a, b = store
    out = tmp_path / "reports" / "lr"
    report = compare([a, b], out=out, name="lr", tracking_uri=uri)
    text = report.read_text()
    # the one param that differs, with both values; params equal in both runs are only counted
    assert "| `stage1.lr` | 0.0005 | 0.001 |" in text
    assert "`vqvae.lr`" not in text
    for stage in ("## vqvae", "## stage1", "## fusion"):
        assert stage in text
    assert "| `x.iou` | 0.61 | 0.64 | 0.03 |" in text
    assert "## pipeline" not in text  # no metrics of its own
    pngs = {p.name for p in out.glob("*.png")}
    assert {"lr_vqvae_curves.png", "lr_stage1_curves.png", "lr_stage1_pareto.png", "lr_fusion_bands.png",
            "lr_fusion_sweeps.png", "lr_vqvae_finals.png"} <= pngs
    for name in pngs:
        assert f"]({name})" in text
        _nontrivial_png(out / name)


def test_a_new_report_replaces_only_the_plots_of_the_earlier_one(store):
    """The plots an earlier report of the name linked go; a user's file that only looks
    like one (the same name prefix) stays."""
    tmp_path, uri, a, b = store
    out = tmp_path / "reports" / "again"
    compare([a, b], out=out, name="again", tracking_uri=uri)
    # a stage no longer compared: as if an earlier report had drawn it (its record moves with it)
    (out / "again_vqvae_curves.png").rename(out / "again_gone_curves.png")
    record_path(out / "again_vqvae_curves.png").rename(record_path(out / "again_gone_curves.png"))
    report = out / "again.md"
    report.write_text(report.read_text().replace("(again_vqvae_curves.png)", "(again_gone_curves.png)"))
    (out / "again_my_sketch.png").write_bytes(b"a user's picture")
    compare([a, b], out=out, name="again", tracking_uri=uri)
    assert (out / "again_my_sketch.png").read_bytes() == b"a user's picture"
    assert not (out / "again_gone_curves.png").exists() and (out / "again_vqvae_curves.png").exists()


def test_compare_cli_resolves_experiment_and_dvc_experiments(store, monkeypatch, capsys):
    tmp_path, uri, a, b = store
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    # an experiment name alone: its latest two pipeline runs
    assert main(["--root", str(tmp_path), "compare", "typ", "--tracking-uri", uri, "--name", "latest"]) == 0
    text = (tmp_path / "reports" / "compare" / "latest.md").read_text()
    assert a in text and b in text
    # dvc exp run sets DVC_EXP_NAME for each stage command; typ tags the stage runs with it
    cfg = config_from_dict({"profile": "tiny"})
    for exp, epochs in (("brisk-bass", 50), ("tidy-tuna", 100)):
        monkeypatch.setenv("DVC_EXP_NAME", exp)
        cfg = config_from_dict({"profile": "tiny", "stage1": {"epochs": epochs}})
        with stage_run("stage1", cfg, root=tmp_path) as run:
            for step in range(epochs // 10):
                run.metrics({"stage1.loss": 1 / (step + 1)}, step=step)
    monkeypatch.delenv("DVC_EXP_NAME")
    report = compare(["brisk-bass", "tidy-tuna"], out=tmp_path / "out", tracking_uri=uri)
    assert report.name == "brisk-bass-vs-tidy-tuna.md"
    assert "| `stage1.epochs` | 50 | 100 |" in report.read_text()
    assert main(["--root", str(tmp_path), "compare", "no-such-thing", a, "--tracking-uri", uri]) == 2
    assert "no-such-thing" in capsys.readouterr().err


def test_metric_name_segments_and_pareto_front():
    assert segments("robustness.position_std.0.2.ap50") == ["robustness", "position_std", "0.2", "ap50"]
    assert segments("early.ap50.0-30") == ["early", "ap50", "0-30"]
    # (seconds, error): lower error is better; (3, 0.5) is beaten by (2, 0.4)
    assert pareto_front([(1, 0.9), (2, 0.4), (3, 0.5), (4, 0.1)], higher_is_better=False) == [0, 1, 3]
