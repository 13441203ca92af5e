"""tasks/ssc.py on a small simulated scenario: maps written beside the clouds, training, no/late fusion."""
from __future__ import annotations

import numpy as np
import pytest

from tasks.simulate import ScenarioJob
from tasks.ssc import evaluate, predict, sample_maps, ssc_dataset, train

SMALL = dict(layer_nums=(1, 1, 1), num_filters=(8, 8, 8), num_upsample_filters=(8, 8, 8), pillar_channels=8,
             head_hidden=8)


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    root = tmp_path_factory.mktemp("ssc") / "real_cav" / "train"
    job = ScenarioJob(domain="real_cav", split="train", index=0, seed=11, n_agents=2, n_frames=2,
                      azimuth_step_deg=1.0, comm_range=70.0, dt=0.1)
    (root / job.name).mkdir(parents=True)
    job.write(root / job.name)
    return root, job


def test_train_then_no_and_late_fusion(split):
    root, _ = split
    ds = ssc_dataset(root)
    assert len(ds) == 2 and len(ds[0].agent_ids) == 2
    assert len(sample_maps(ds, 0)) == 2
    trained = train(ds, steps=20, seed=0, lr=5e-3, model_kw=SMALL)
    assert np.isfinite(trained.losses).all() and np.mean(trained.losses[-4:]) < np.mean(trained.losses[:4])
    for method in ("no_fusion", "late_fusion"):
        r = evaluate(trained, ds, method)
        assert r["frames"] == 2 and 0.0 <= r["miou"] <= 1.0 and np.isfinite(r["iou"])
    # late fusion of the ego alone is no fusion
    solo = ssc_dataset(root, max_agents=1)
    assert np.array_equal(predict(trained, solo[0], "late_fusion"), predict(trained, solo[0], "no_fusion"))
    late = predict(trained, ds[0], "late_fusion")
    assert late.shape == (128, 128, 20) and late.dtype == np.uint8 and late.max() < 7
