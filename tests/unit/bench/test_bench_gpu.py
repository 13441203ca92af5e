"""bench/gpu.py's parts that run without a GPU: the bundle's round trip, its views against the
store's, the device voxelizer against typ's, the config checks, the pages from partial results,
and the GPU machine's constraint: none of it imports Prefect, MLflow, DVC or open3d."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from bench_modules import ROOT, load_bench
from tasks.evaluate_generation import EvalSet
from tasks.selftrain import References
from tasks.stage2 import Tuples
from tasks.voxel_data import ViewSet
from typ.errors import TypError
from typ.voxel import Grid, voxelize

bundle = load_bench("gpu_bundle")
GRID = Grid((-8.0, 8.0), (-8.0, 8.0), (-1.0, 1.0), (16, 16, 4))


def _views(seed: int, n: int, grid: Grid = GRID) -> ViewSet:
    rng = np.random.default_rng(seed)
    records = [(np.argwhere(rng.random(grid.shape) < 0.1), np.argwhere(rng.random(grid.shape[:2]) < 0.2))
               for _ in range(n)]
    return ViewSet(grid, [(f"s{i // 2}", str(i % 2), "000000") for i in range(n)], records)


def _bool(rng, *shape):
    return rng.random(shape) < 0.1


def test_dense_views_batch_as_the_store_views_do():
    views = _views(0, 6)
    dense = bundle.dense(views)
    rng = np.random.default_rng(1)
    for _ in range(4):
        index, dihedral, flips = rng.integers(0, 6, 5), rng.integers(0, 8, 5), rng.random(5) < 0.5
        for kw in ({}, {"dihedral": dihedral}, {"flips": flips}):
            for a, b in zip(views.batch(index, **kw), dense.batch(index, **kw)):
                assert torch.equal(a, b), kw
    assert np.array_equal(dense.head(2).occupancy([1]), views.occupancy([1]))


def test_the_bundle_round_trips(tmp_path):
    rng = np.random.default_rng(2)
    C, H, W = 4, 16, 16
    tuples = Tuples(_bool(rng, 3, C, H, W), _bool(rng, 3, 1, H, W), _bool(rng, 3, C, H, W), _bool(rng, 3, C, H, W))
    refs = References(_bool(rng, 2, C, H, W), _bool(rng, 2, 1, H, W), _bool(rng, 2, C, H, W))
    boxes = [np.array([[1.0, 2.0, 0.0, 4.0, 2.0, 1.5, 0.3]]), np.zeros((0, 7)), rng.random((2, 7))]
    pairs = EvalSet(GRID, ["a", "a", "b"], _bool(rng, 3, C, H, W), _bool(rng, 3, 1, H, W), _bool(rng, 3, C, H, W),
                    _bool(rng, 3, C, H, W), _bool(rng, 3, H, W), boxes, [], [])
    source_grid = GRID.for_sensor(0.5)
    train, val, source = _views(3, 4), _views(4, 2), _views(5, 3, source_grid)
    bundle.write(tmp_path, meta={"stats": {"x": 1}}, train=train, val=val, source=source, tuples=tuples,
                 references=refs, pairs=pairs)
    got = bundle.read(tmp_path)
    assert got.meta["stats"] == {"x": 1} and got.train.grid == GRID and got.source.grid == source_grid
    for mine, theirs in ((got.train, train), (got.val, val), (got.source, source)):
        assert mine.keys == theirs.keys
        assert np.array_equal(mine.x, theirs.occupancy(range(len(theirs))) > 0.5)
        assert np.array_equal(mine.y, theirs.box_maps(range(len(theirs))) > 0.5)
    for k in ("x_r", "y_r", "x_e", "resim"):
        assert np.array_equal(getattr(got.tuples, k), getattr(tuples, k)) and getattr(got.tuples, k).dtype == bool
    assert all(np.array_equal(getattr(got.references, k), getattr(refs, k)) for k in ("x_e", "y_r", "resim"))
    for k in ("x_r", "y_r", "x_e", "resim", "seen"):
        assert np.array_equal(getattr(got.pairs, k), getattr(pairs, k))
    assert got.pairs.scenes == ["a", "a", "b"] and [b.shape for b in got.pairs.boxes] == [(1, 7), (0, 7), (2, 7)]
    assert np.array_equal(got.pairs.boxes[2], boxes[2]) and len(got.pairs.truth_stats) == 3


def test_a_missing_bundle_names_the_script_that_makes_it(tmp_path):
    with pytest.raises(TypError, match=r"grids.npz: file: expected the GPU bench's data \(make it with: python "
                                       r"bench/gpu_data.py\)"):
        bundle.read(tmp_path)


def test_overrides_and_a_stale_bundle():
    assert bundle.overrides_of(["a.b=1", "a.c=[1, 2]", "d=x"]) == {"a": {"b": 1, "c": [1, 2]}, "d": "x"}
    with pytest.raises(TypError, match="KEY=VALUE"):
        bundle.overrides_of(["novalue"])
    cfg = bundle.config({"simulate": {"scenarios": {"target": {"train": 4}}}})
    assert cfg.voxelize.grid.shape == (256, 256, 20) and cfg.simulate.scenarios["target"]["train"] == 4
    made = bundle.Bundle({"overrides": {"simulate": {"scenarios": {"target": {"train": 4}}}},
                          "data": json.loads(json.dumps(bundle.data_fields(cfg)))}, *([None] * 6))
    assert bundle.config_for(made, {"stage1": {"batch_size": 2}}).stage1.batch_size == 2   # training keys: free
    with pytest.raises(TypError, match="remake it: python bench/gpu_data.py"):
        bundle.config_for(made, {"voxelize": {"grid": {"shape": [128, 128, 20]}}})


def test_the_device_voxelizer_bins_as_typ_does():
    gpu = load_bench("gpu")
    grid = Grid((-51.2, 51.2), (-51.2, 51.2), (-0.9, 3.1), (256, 256, 20))
    rng = np.random.default_rng(3)
    points = rng.uniform([-60, -60, -2, 0], [60, 60, 4, 1], (20000, 4)).astype(np.float32)
    # points on every x edge and just below the upper bound: the bins' edge cases
    edges = np.stack([grid.edges(0), np.full(257, 0.1), np.full(257, 0.5), np.zeros(257)], axis=1)
    cloud = np.concatenate([points, edges.astype(np.float32), [[51.2, 0.0, 0.0, 0.0]]])
    assert np.array_equal(gpu.device_voxelize(cloud, grid, "cpu").numpy(), voxelize(cloud, grid))


def _results(**phases) -> dict:
    run = {"command": "python3 bench/gpu.py --out x", "commit": "abc", "dirty": False, "device": "NVIDIA H200",
           "device_type": "cuda", "cores": 16, "torch": "2.11", "cuda": "13.0", "python": "3.12", "numpy": "2.5",
           "started": "today", "minutes": 7.5, "wall_s": 12.0}
    return {"run": run, "phases": phases}


def _interval(v: float, low: float | None = None, high: float | None = None) -> dict:
    return {"value": v, "low": v - 0.01 if low is None else low, "high": v + 0.01 if high is None else high}


def test_pages_from_partial_results_and_the_targets(tmp_path):
    pages = load_bench("gpu_pages")
    timings = {"networks": {"stage-1 UNet": {"batch": 8, "fp32": {"samples_per_s": 20.0},
                                             "bf16": {"samples_per_s": 40.0}},
                            "AttFuse": {"batch": 1, "fp32": {"error": "boom"}}}}
    cpu = {"run": {"device": "CPU: test", "cores": 2},
           "phases": {"timings": {"networks": {"stage-1 UNet": {"batch": 2, "fp32": {"samples_per_s": 0.5},
                                                                "bf16": {"samples_per_s": 0.25}}}}}}
    figures = {"iou": _interval(0.5), "iou_above_ground": _interval(0.3), "object_hit_rate": _interval(0.9),
               "jsd_r2dm": _interval(0.2)}
    train = {"final": {"vqvae_x": {"iou": 0.82}, "typ": figures}, "config": {"voxelize": {"grid": {"shape": [256, 256, 20]}}},
             "baselines": {"naive_copy": {**figures, "iou_above_ground": _interval(0.2)}}, "data": {"pairs": 64},
             "networks": {"vqvae": {"epochs": 3, "steps_planned": 48, "steps_run": 48, "status": "done"},
                          "stage1": {"epochs": 2, "steps_planned": 16, "steps_run": 5, "status": "cut at the deadline"}},
             "cut": "the deadline stopped training at stage1",
             "curve": [{"network": "vqvae", "step": 10, "train_s": 5.0, "recon_iou": 0.5},
                       {"network": "stage1", "step": 4, "train_s": 9.0, "iou": 0.2, "jsd_r2dm": 0.3}]}
    results = _results(tests={"status": "running"}, timings=timings, train=train)
    pages.write(tmp_path, results, cpu)
    page = (tmp_path / "bench_gpu.md").read_text()
    assert "| stage-1 UNet | 8 | 2 | 20.00 | 40.00 | 0.5000 | 0.2500 | 40.0× | 160.0× | 80.0× |" in page
    assert "| AttFuse | 1 | – | – | – | – | – | – | – | – |" in page
    assert "- **x VQ-VAE reconstruction IoU 0.820: target ≥ 0.80 met**" in page
    assert "- **TYP above-ground IoU 0.300 [0.290, 0.310] against the naive copy's 0.200 [0.190, 0.210]: " \
           "above (intervals apart)**" in page
    assert "- **TYP object hit rate 0.900: target ≥ 0.85 met**" in page
    readme = (tmp_path / "README.md").read_text()
    assert "- timing of AttFuse in fp32: boom" in readme and "- training of stage1: cut at the deadline" in readme
    assert "`python3 bench/gpu.py --out x`" in readme and (tmp_path / "bench_gpu.png").stat().st_size > 1000
    # the bench page joins reports/bench.md with its plot and the folder's README
    report = load_bench("report")
    (tmp_path / "gpu").mkdir()
    for name in ("bench_gpu.md", "bench_gpu.png", "README.md"):
        (tmp_path / "gpu" / name).write_bytes((tmp_path / name).read_bytes())
    text = report.aggregate(tmp_path, {"cores": 2, "cpu": "Test", "torch": "2.13", "torch_threads": 1,
                                       "python": "3.11"})
    assert "[page](gpu/bench_gpu.md), [plot](gpu/bench_gpu.png), [how it was made](gpu/README.md)" in text
    assert "- **TYP object hit rate 0.900: target ≥ 0.85 met**" in text


BLOCKER = '''
import sys
BLOCKED = {"prefect", "mlflow", "dvc", "open3d", "pydantic"}
class Blocked:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{name} is not on the GPU machine")
sys.meta_path.insert(0, Blocked())
'''


def test_the_gpu_bench_imports_nothing_the_gpu_machine_lacks(tmp_path):
    """The GPU machine has no Prefect, MLflow, DVC, open3d or pydantic: every module bench/gpu.py and
    tests/e2e/test_cuda.py reach imports without them (an import hook makes any of them fail)."""
    (tmp_path / "sitecustomize.py").write_text(BLOCKER)
    code = ("import sys; sys.path[:0] = ['bench', 'tests/e2e', 'tests/helpers']; import gpu, gpu_train, gpu_pages, gpu_bundle, test_cuda; "
            "from tasks import adapt, ddpm, fusion_train, selftrain, ssc, stage1, stage2, vqvae, evaluate_generation; "
            "import prefect")
    env = {"PYTHONPATH": f"{tmp_path}:{ROOT}", "PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1 and proc.stderr.strip().endswith("ImportError: prefect is not on the GPU machine"), \
        proc.stderr[-2000:]
