"""Make the GPU bench's data on the CPU (bench/gpu_bundle.py says what it holds and why).

    python bench/gpu_data.py [--work /tmp/typ-gpu-data] [--out .gpu] [--tiny PROJECT]

Runs the stages that need open3d or the point clouds, at the size bench/gpu.yaml sets, through
their task-level functions in the project folder ``--work`` (created; reused on a second run:
every stage skips what is current): simulate (tiny's scenario seeds, more of them), voxelize on
the GPU grid, stage 2's source tuples with their re-simulated views, self-training's pseudo
references, and the held-out target/test pairs as the evaluate stage builds them. The naive copy
and the re-simulation are scored on the pairs here, as the evaluate stage scores them (they need
the ego's cloud, which does not travel). ``--tiny``: a project whose ``make run`` finished; its
evaluate figures and its x VQ-VAE's reconstruction IoU on the same pairs (at tiny's grid) go into
the bundle, for the table beside the GPU run's, after checking that its test scenarios are
byte-identical to the ones simulated here. Writes the bundle to ``--out`` and prints its size.
"""
from __future__ import annotations

import argparse
import filecmp
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

import gpu_bundle  # noqa: E402
from tasks import evaluate_generation as gen  # noqa: E402
from tasks import genscore, selftrain, simulate, stage2, voxelize  # noqa: E402
from tasks.evaluate import intervals_json  # noqa: E402
from tasks.voxel_data import load_views  # noqa: E402


def run_scene_stage(spec) -> int:
    """A per-scene stage's items without Prefect (:class:`tasks.scene_stage.SceneStage`): how many ran."""
    items, _ = spec.plan()
    ran = 0
    for item in items:
        if spec.unchanged is None or spec.unchanged(item, **spec.work_kwargs) is None:
            spec.work(item, **spec.work_kwargs)
            ran += 1
    return ran


def baselines(pairs: gen.EvalSet, n_boot: int) -> dict:
    """The naive copy's and the re-simulation's scores on ``pairs``, as the evaluate stage gives them."""
    truth_h = [s["histogram"] for s in pairs.truth_stats]
    truth_c = [s["centres"] for s in pairs.truth_stats]
    rows = {"naive_copy": gen.score_method(pairs, pairs.x_e > 0.5, pairs.ego_points),
            "resim": gen.score_method(pairs, pairs.resim > 0.5, pairs.resim_points)}
    return intervals_json({k: genscore.summarize([v], pairs.scenes, truth_h, truth_c, n_boot=n_boot)
                           for k, v in rows.items()})


def same_scenarios(a: Path, b: Path) -> bool:
    """Every file under ``a`` is under ``b`` with the same bytes, and the other way round."""
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    other = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    return bool(files) and files == other and all(filecmp.cmp(a / f, b / f, shallow=False) for f in files)


def tiny_figures(tiny: Path, cfg, work: Path) -> dict:
    """The tiny project's figures on the same pairs: its evaluate metrics and its x VQ-VAE's
    reconstruction IoU (threshold as its vqvae stage), with where they came from."""
    from tasks.pairs import iter_pairs
    from tasks.vqvae import evaluate, load_model
    from typ.config import load_config

    tiny_cfg = load_config(tiny / "params.yaml")
    split = Path(cfg.evaluate.sim) / cfg.evaluate.target_domain / cfg.evaluate.target_split
    out = {"project": str(tiny.resolve()), "same_scenarios": same_scenarios(work / split, tiny / split)}
    metrics = tiny / "metrics" / "evaluate.json"
    if metrics.is_file():
        m = json.loads(metrics.read_text())
        out |= {"evaluate": {k: m[k] for k in ("pairs", "scenes", "seeds", "generation") if k in m},
                "evaluate_mtime": time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(metrics.stat().st_mtime))}
    commit = subprocess.run(["git", "-C", str(tiny), "rev-parse", "HEAD"], capture_output=True, text=True)
    out["commit"] = commit.stdout.strip() or None
    x_dir = tiny / tiny_cfg.vqvae.out / "x"
    if (x_dir / "config.json").is_file():
        grid = tiny_cfg.voxelize.sensor_grid(cfg.evaluate.target_domain)
        pairs = list(iter_pairs(work / split, grid, ego_only=True))   # build_eval_set's pairs, in its order
        views = gpu_bundle.DenseViews(grid, [(p.scenario, p.reference, p.timestamp) for p in pairs], [],
                                      np.stack([p.x_r for p in pairs]), np.stack([p.y_r for p in pairs]))
        out["vqvae_x"] = evaluate(load_model(x_dir), "x", views, threshold=tiny_cfg.vqvae.threshold,
                                  batch_size=tiny_cfg.vqvae.batch_size)
    return out


def build(work: Path, out: Path, tiny: Path | None, overrides: dict) -> Path:
    from typ.sim.sensor import domain_spec

    cfg = gpu_bundle.config(overrides)
    t0 = time.perf_counter()
    simulated = run_scene_stage(simulate.scene_stage(cfg, work))
    voxelized = run_scene_stage(voxelize.scene_stage(cfg, work))
    print(f"simulated {simulated}, voxelized {voxelized} scenarios ({time.perf_counter() - t0:.0f} s)", flush=True)
    tuples = stage2.source_tuples(cfg, work, resim=cfg.stage2.resim)
    stage2.save_tuples(tuples, work / cfg.stage2.out)
    inputs = selftrain.gather(cfg, work)
    print(f"{len(tuples)} source tuples, {len(inputs.references.x_e)} pseudo references "
          f"({time.perf_counter() - t0:.0f} s)", flush=True)
    block, store = cfg.evaluate, work / cfg.vqvae.input
    grid = cfg.voxelize.sensor_grid(block.target_domain)
    spec = domain_spec(block.target_domain, azimuth_step_deg=cfg.simulate.azimuth_step_deg).sensor
    pairs = gen.build_eval_set(work / block.sim / block.target_domain / block.target_split, grid, spec)
    meta = {"overrides": overrides, "data": gpu_bundle.data_fields(cfg), "stats": inputs.stats.to_dict(),
            "pairs": len(pairs), "scenes": len(set(pairs.scenes)), "baselines": baselines(pairs, block.n_boot),
            "tiny": tiny_figures(tiny, cfg, work) if tiny is not None else None}
    print(f"{len(pairs)} pairs scored ({time.perf_counter() - t0:.0f} s)", flush=True)
    return gpu_bundle.write(
        out, meta=meta,
        train=load_views(store, dataset=block.target_domain, split=cfg.vqvae.train_split),
        val=load_views(store, dataset=block.target_domain, split=cfg.vqvae.eval_split),
        source=load_views(store, dataset=cfg.adapt.source_dataset, split=cfg.adapt.source_split, ego_only=False),
        tuples=tuples, references=inputs.references, pairs=pairs)


def add_tiny(work: Path, out: Path, tiny: Path) -> Path:
    """The tiny project's figures into an existing bundle's meta.json (the grids stay as they are)."""
    from typ.io import write_json

    meta = json.loads((out / gpu_bundle.META).read_text())
    meta["tiny"] = tiny_figures(tiny, gpu_bundle.config(meta.get("overrides")), work)
    write_json(out / gpu_bundle.META, meta)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", default="/tmp/typ-gpu-data", help="project folder the stages write to (reused)")
    ap.add_argument("--out", default=".gpu", help="the bundle's folder (carry it to the GPU machine)")
    ap.add_argument("--tiny", default=None, help="a project whose `make run` finished: its figures on the same pairs")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override bench/gpu.yaml (dotted key, YAML value; e.g. simulate.scenarios.target.train=8)")
    ap.add_argument("--tiny-only", action="store_true",
                    help="only (re)place the tiny project's figures in the bundle at --out (made earlier from --work)")
    args = ap.parse_args(argv)
    if args.tiny_only:
        if not args.tiny:
            ap.error("--tiny-only needs --tiny PROJECT")
        folder = add_tiny(Path(args.work), Path(args.out), Path(args.tiny))
    else:
        folder = build(Path(args.work), Path(args.out), Path(args.tiny) if args.tiny else None,
                       gpu_bundle.overrides_of(args.set))
    sizes = {p.name: p.stat().st_size for p in sorted(folder.iterdir()) if p.is_file()}
    print(f"{folder}: " + ", ".join(f"{k} {v / 2**20:.1f} MiB" for k, v in sizes.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
