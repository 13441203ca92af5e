"""A small measured run of the SSC pieces (not the stage): simulate real_cav scenarios with their maps,
train the single-agent SSC network, score no fusion and late fusion on held-out scenarios.

    /work/cpu .venv/bin/python bench/ssc_small.py --out /tmp/ssc_small [--train 4 --test 2 --frames 3 --steps 150]

Writes <out>/results.json. Seeds: scenario seeds 1000+i (train) and 2000+i (test), model seeds given.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

from tasks.simulate import ScenarioJob  # noqa: E402
from tasks.ssc import evaluate, ssc_dataset, train  # noqa: E402


def simulate(root: Path, split: str, n: int, frames: int, agents: int, base: int) -> None:
    for i in range(n):
        job = ScenarioJob(domain="real_cav", split=split, index=i, seed=base + i, n_agents=agents, n_frames=frames,
                          azimuth_step_deg=0.4, comm_range=70.0, dt=0.1)
        folder = job.folder(root)
        if not folder.exists():
            folder.mkdir(parents=True)
            job.write(folder)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--train", type=int, default=4)
    ap.add_argument("--test", type=int, default=2)
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--agents", type=int, default=3)
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    a = ap.parse_args()
    t0 = time.time()
    simulate(a.out, "train", a.train, a.frames, a.agents, 1000)
    simulate(a.out, "test", a.test, a.frames, a.agents, 2000)
    t_sim = time.time() - t0
    tr, te = ssc_dataset(a.out / "real_cav" / "train"), ssc_dataset(a.out / "real_cav" / "test")
    model_kw = dict(layer_nums=(1, 2, 2), num_filters=(32, 64, 64), num_upsample_filters=(32, 32, 32),
                    pillar_channels=32, head_hidden=32)
    runs = []
    for seed in a.seeds:
        t1 = time.time()
        trained = train(tr, steps=a.steps, seed=seed, lr=2e-3, model_kw=model_kw)
        t_train = time.time() - t1
        scores = {m: evaluate(trained, te, m) for m in ("no_fusion", "late_fusion")}
        runs.append({"seed": seed, "seconds_train": round(t_train, 1), "loss_first10": sum(trained.losses[:10]) / 10,
                     "loss_last10": sum(trained.losses[-10:]) / 10, "scores": scores})
        print(json.dumps(runs[-1], indent=1), flush=True)
    res = {"args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(a).items()},
           "train_samples": len(tr), "test_samples": len(te), "seconds_simulate": round(t_sim, 1), "runs": runs}
    (a.out / "results.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
