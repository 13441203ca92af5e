"""typ.tracking's media helpers on a sqlite store: figures and images as PNG artifacts, score tables
the MLflow UI can sort, dataset inputs, system metrics on training stages only; NullRun in step."""
import inspect
import json

import matplotlib.image as mpimg
import numpy as np
import pytest
from mlflow.tracking import MlflowClient

from typ import viz
from typ.config import config_from_dict
from typ.errors import TypError
from typ.tracking import NullRun, StageRun, listing_digest, stage_run, table_frame

CFG = config_from_dict({"profile": "tiny"})


@pytest.fixture
def store(tmp_path, monkeypatch):
    uri = f"sqlite:///{tmp_path / 'mlruns.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    return tmp_path, MlflowClient(uri)


def test_figures_images_tables_and_inputs_land_in_the_stage_run(store):
    tmp_path, client = store
    data = tmp_path / "data" / "sim" / "target" / "test"
    (data / "s0" / "1").mkdir(parents=True)
    (data / "s0" / "1" / "000000.pcd").write_bytes(b"x" * 100)
    (data / "s0" / "1" / "000000.yaml").write_text("lidar_pose: []\n")
    (data / "s0" / ".tmp-half").write_text("ignored")
    fig = viz.bev_figure(np.array([[5.0, 5.0, -1.0, 0.0]], np.float32), title="one point")
    rows = [{"sample": "a", "iou": 0.5}, {"sample": "b", "iou": float("nan"), "chamfer_m": 1.25}]
    with stage_run("simulate", CFG, root=tmp_path) as run:
        run.log_figure(fig, "renders/figure.png")
        run.log_image(viz.figure_array(fig), "renders/image.png")
        run.log_image(np.full((4, 5, 3), 2.0), "renders/clipped.png")  # floats are clipped to [0, 1]
        run.log_table(rows, "scores.json")
        run.log_input(data, context="eval", root=tmp_path)
        run.log_input(data / "s0" / "1" / "000000.pcd", context="eval", root=tmp_path, name="one scan", digest="abc")
    got = client.get_run(run.run_id)
    names = {a.path for a in client.list_artifacts(run.run_id, "renders")}
    assert names == {"renders/figure.png", "renders/image.png", "renders/clipped.png"}
    local = client.download_artifacts(run.run_id, "renders", str(tmp_path / "dl"))
    assert np.array_equal((mpimg.imread(f"{local}/image.png") * 255).round().astype(np.uint8), viz.figure_array(fig))
    assert mpimg.imread(f"{local}/figure.png").shape[:2] == viz.figure_array(fig).shape[:2]
    assert np.all(mpimg.imread(f"{local}/clipped.png")[..., :3] == 1.0)
    table = json.loads(open(client.download_artifacts(run.run_id, "scores.json", str(tmp_path / "dl2"))).read())
    assert table == {"columns": ["sample", "iou", "chamfer_m"], "data": [["a", 0.5, None], ["b", None, 1.25]]}
    assert json.loads(got.data.tags["mlflow.loggedArtifacts"]) == [{"path": "scores.json", "type": "table"}]
    inputs = {d.dataset.name: d for d in got.inputs.dataset_inputs}
    assert set(inputs) == {"data/sim/target/test", "one scan"}
    sim = inputs["data/sim/target/test"]
    assert json.loads(sim.dataset.profile) == {"files": 2, "bytes": 100 + len("lidar_pose: []\n")}
    assert sim.dataset.digest == listing_digest(data)[0] and sim.dataset.source_type == "local"
    assert json.loads(sim.dataset.source)["uri"] == data.resolve().as_uri()
    assert [(t.key, t.value) for t in sim.tags] == [("mlflow.data.context", "eval")]
    assert inputs["one scan"].dataset.digest == "abc"
    # a simulate run logs no system metrics
    assert not [k for k in got.data.metrics if k.startswith("system/")]


def test_listing_digest_follows_names_and_sizes_only(tmp_path):
    (tmp_path / "a").write_bytes(b"12")
    first = listing_digest(tmp_path)
    (tmp_path / "a").write_bytes(b"34")
    assert listing_digest(tmp_path) == first  # same name, same size: by design not a content hash
    (tmp_path / "a").write_bytes(b"345")
    assert listing_digest(tmp_path)[0] != first[0]
    with pytest.raises(TypError, match="dataset"):
        from typ.tracking import dataset_entity

        dataset_entity(tmp_path / "missing")


def test_training_stages_log_system_metrics_offline(store, monkeypatch):
    import os
    import time

    pytest.importorskip("psutil")
    tmp_path, client = store
    from flows.pipeline import SYSTEM_METRICS_ENV, registry, scoped_environ

    monkeypatch.setenv("MLFLOW_SYSTEM_METRICS_SAMPLING_INTERVAL", "0.5")
    monkeypatch.delenv(SYSTEM_METRICS_ENV, raising=False)
    assert registry.STAGES["vqvae"].kind == "training" != registry.STAGES["simulate"].kind
    with scoped_environ({SYSTEM_METRICS_ENV: "true"}, keep_set=True):   # what run_stage sets for training
        with stage_run("vqvae", CFG, root=tmp_path) as run:
            time.sleep(1.6)
    assert SYSTEM_METRICS_ENV not in os.environ
    metrics = client.get_run(run.run_id).data.metrics
    assert {"system/cpu_utilization_percentage", "system/system_memory_usage_megabytes"} <= set(metrics)
    assert 0.0 <= metrics["system/cpu_utilization_percentage"] <= 100.0 * 64


def test_table_frame_keeps_column_order_and_null_run_has_every_method():
    frame = table_frame([{"b": 1}, {"a": 2, "b": 3}])
    assert list(frame.columns) == ["b", "a"] and frame["a"].isna().tolist() == [True, False]
    assert list(table_frame({"x": [1, 2]}).columns) == ["x"]
    public = {n for n, _ in inspect.getmembers(StageRun, inspect.isfunction) if not n.startswith("_")}
    assert public <= {n for n, _ in inspect.getmembers(NullRun, inspect.isfunction)}
    null = NullRun()
    null.log_table([{"a": 1}], "t.json")
    null.log_input("nowhere", context="train")
