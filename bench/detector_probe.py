"""Probe the fusion benchmark's detectors (the attempts of reports/fusion_ablation.md) on a workspace after `make run`:
train a network with fusion-block overrides beside the stage's own, score it on real_cav/test,
and compare it with the stage's networks by the paired bootstrap of the evaluate stage.

    python bench/detector_probe.py single NAME='{"steps": 3000}' ...        # the single-agent detector
    python bench/detector_probe.py v2xvit NAME='{"warm_start_steps": 900}' ...  # a warm-started method

``single``: the single-agent detector trained on real_cav/train with each override (one seed,
``fusion.seed``), scored as no fusion and as late fusion (AP@0.5 / 0.7 overall, AP@0.5 50-100 m).
Any other method name: that method warm-started from each seed's saved oracle single-agent network
(``<fusion.out>/models/oracle-late/seed<k>``) with each override, every training seed of the
stage, scored against late fusion on the same networks: the method's AP and its paired
difference to late fusion (frame order and ranked by score) and to no fusion. The trainings run
two at a time on one thread each, as the fusion stage runs them. Networks go to
/tmp/detector_probe/ (their checkpoints resume); the workspace is not touched. The tables of
reports/fusion_ablation.md come from here.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from multiprocessing import get_context
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OUT = Path("/tmp/detector_probe")


def fusion_block(root: Path, changes: dict):
    """The workspace's fusion block with ``changes`` merged in key by key (nested blocks too) and
    checked, as params.yaml overrides are (:func:`typ.config.load_config`)."""
    from typ.config import load_config

    return load_config(root / "params.yaml", overrides={"fusion": changes}).fusion


def _train(job: tuple) -> float:
    """One training in a spawned process on one thread: (root, method, name, overrides, seed)."""
    root, method, name, changes, seed = job
    torch.set_num_threads(1)
    from models.fusion import SINGLE_AGENT
    from tasks.fusion import Roots, model_folder, read_inputs
    from tasks.fusion_train import load, save, train

    cfg = fusion_block(root, changes)
    inputs = read_inputs(cfg, Roots.from_config(cfg, root), "real")
    t0 = time.perf_counter()
    if method == SINGLE_AGENT:
        trained = train(method, cfg, inputs, steps=cfg.steps, out=OUT, name=f"{name}/seed_{seed}", seed=seed)
    else:
        warm = load(model_folder(root / cfg.out, f"oracle-{SINGLE_AGENT}", seed), cfg)
        trained = train(method, cfg, inputs, steps=cfg.warm_start_steps, out=OUT, name=f"{name}/seed_{seed}",
                        seed=seed, warm=warm)
    save(trained, model_folder(OUT, name, seed), cfg)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("method", help="single (the single-agent detector) or a warm-started method: early, attfuse, v2xvit")
    ap.add_argument("variants", nargs="+", help="NAME=JSON overrides of the fusion block")
    ap.add_argument("--root", type=Path, default=Path("."), help="the workspace (after make run)")
    args = ap.parse_args()
    from models.fusion import SINGLE_AGENT
    from tasks.fusion import Roots, dataset_options, model_folder
    from tasks.fusion_data import FusionDataset
    from tasks.fusion_score import Scorer, paired_difference
    from tasks.fusion_train import load

    root = args.root.resolve()
    method = SINGLE_AGENT if args.method == "single" else args.method
    variants = {name: json.loads(text) for name, text in (v.split("=", 1) for v in args.variants)}
    base = fusion_block(root, {})
    seeds = (base.seed,) if method == SINGLE_AGENT else base.training_seeds
    jobs = [(root, method, name, changes, s) for name, changes in variants.items() for s in seeds]
    with get_context("spawn").Pool(2) as pool:
        seconds = pool.map(_train, jobs, chunksize=1)
    print("training seconds:", ", ".join(f"{j[2]}/seed{j[4]} {s:.0f}" for j, s in zip(jobs, seconds)), flush=True)

    networks = {name: [load(model_folder(OUT, name, s), fusion_block(root, changes)) for s in seeds]
                for name, changes in variants.items()}
    if method != SINGLE_AGENT:
        for run in (f"oracle-{SINGLE_AGENT}", f"oracle-{method}"):
            networks[run] = [load(model_folder(root / base.out, run, s), base) for s in seeds]
    roots = Roots.from_config(base, root)
    scorer = Scorer(base, FusionDataset(roots.real_test, **dataset_options(base)), networks)
    fmt = lambda c: f"{c['value']:.3f} [{c['low']:.3f}, {c['high']:.3f}]"  # noqa: E731
    if method == SINGLE_AGENT:
        for name in variants:
            for m in ("none", SINGLE_AGENT):
                c = scorer.cell(name, m)
                print(f"{name} {m}: AP@0.5 {fmt(c['ap50']['overall'])}, AP@0.7 {fmt(c['ap70']['overall'])}, "
                      f"AP@0.5 50-100 m {fmt(c['ap50']['50-100'])}", flush=True)
        return
    kw = {"n_boot": base.bootstrap, "seed": base.seed}
    scenarios = scorer.inputs().scenarios
    late = scorer.matches(f"oracle-{SINGLE_AGENT}", SINGLE_AGENT)
    alone = scorer.matches(f"oracle-{SINGLE_AGENT}", "none")
    for run in [f"oracle-{SINGLE_AGENT}", f"oracle-{method}", *variants]:
        m = SINGLE_AGENT if run == f"oracle-{SINGLE_AGENT}" else method
        c = scorer.cell(run, m, global_sort=True)
        text = (f"{run}: AP@0.5 {fmt(c['ap50']['overall'])}, 50-100 m {fmt(c['ap50']['50-100'])}, "
                f"AP@0.7 {fmt(c['ap70']['overall'])}, ranked by score {fmt(c['ap50_global']['overall'])}")
        if m != SINGLE_AGENT:
            mine = scorer.matches(run, m)
            text += (f"; minus late: {fmt(paired_difference(mine, late, scenarios, **kw))}, ranked by score "
                     f"{fmt(paired_difference(mine, late, scenarios, global_sort=True, **kw))}; minus no fusion: "
                     f"{fmt(paired_difference(mine, alone, scenarios, **kw))}")
        print(text, flush=True)


if __name__ == "__main__":
    main()
