"""LiDAR DDPM Table II sweep: the ddpm stage with every Table I configuration and 3 seeds.

    python bench/ddpm.py [--out reports] [--root artifacts/bench_ddpm] [--quick]

Run from the repository root after `make run` (the latent route samples artifacts/stage1 with
artifacts/vqvae). The sweep is the ddpm stage itself, run through the CLI in a project of its
own under ``--root`` whose params.yaml is the tiny profile with :data:`SWEEP` over it:

- data: more simulated target-domain scenarios than the tiny pipeline (``simulate`` and
  ``voxelize`` run there first, at the pipeline's azimuth step so TYP's stage 1 sees data like
  its training data);
- ``ddpm``: the range image (the target sensor's 64 beams x 256 azimuth bins) with Table I's
  configurations A, B, C, D, E*, F, G, H, J (I = H and K = J: they differ only in the dataset);
  A, B, F (and so E*) and J over 3 training seeds, the others 1; DDPM-1000 rows (E*: 800), J
  also with DDIM-50 and DPM-Solver++ 20 / 10; TYP's stage 1 beside them. (The BEV image is in
  the stage's tiny run; here it would cost another quarter hour.)
- ``--quick``: 2 configurations x 1 seed at a few steps (checks the wiring in minutes).
- ``--medium``: the issue's targets on the range image at a CPU budget (:data:`MEDIUM`: J and A
  over 3 seeds, B, F and E* over 1, 2000 training steps, 16 samples per set), on the tiny
  pipeline's data (55–61 min on a 2-core Intel Xeon at 2 threads: each model ~5–6 min, each DDPM-1000
  set ~1 min).

Every trained model and generated set is cached under ``--root`` (keys: config, data, code),
so an interrupted sweep resumes where it stopped. Writes <out>/bench_ddpm.md (the stage's
report with this machine's header), bench_ddpm_pareto.png, bench_ddpm_samples.png and
bench_ddpm.json (the stage's metrics).
"""
from __future__ import annotations

import argparse
import copy
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

from typ.io import write_text  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def _config(name: str, schedule: str, embedding: str, seeds=(0, 1, 2), samplers=None, rep="range") -> dict:
    row = {"name": name, "representation": rep, "schedule": schedule, "embedding": embedding, "seeds": list(seeds)}
    if samplers:
        row["samplers"] = samplers
    return row


#: over the tiny profile: the sweep's data and its ddpm block
SWEEP = {
    "profile": "tiny",
    "simulate": {"scenarios": {"target": {"train": 12, "test": 4}}},
    "ddpm": {
        "configs": [
            _config("A", "linear", "sinusoidal"),
            _config("B", "linear", "fourier"),
            _config("C", "hyperbolic", "fourier", seeds=(0,)),
            _config("D", "hyperbolic", "sinusoidal", seeds=(0,)),
            _config("E*", "ramp", "fourier", samplers=[["ddpm", 800]]),
            _config("F", "ramp", "fourier"),
            _config("G", "ramp", "sinusoidal", seeds=(0,)),
            _config("H", "time_dependent", "sinusoidal", seeds=(0,)),
            _config("J", "time_dependent", "fourier",
                    samplers=[["ddpm", 1000], ["ddim", 50], ["dpmsolver++", 20], ["dpmsolver++", 10]]),
        ],
        "samplers": [["ddpm", 1000]],
        "steps": 1500,
        "batch_size": 4,     # the paper's (§IV-2)
        "eval_samples": 12,
        "bootstrap": 1000,
        "features": {"steps": 400},
        "latent": {"samplers": [["ddim", 200], ["dpmsolver++", 20], ["dpmsolver++", 10]], "views": 12},
    },
}
QUICK = {
    "configs": [_config("J", "time_dependent", "fourier", seeds=(0,), samplers=[["ddpm", 1000], ["dpmsolver++", 20]]),
                _config("A", "linear", "sinusoidal", seeds=(0,))],
    "steps": 20, "eval_samples": 3, "bootstrap": 50, "features": {"steps": 10},
    "latent": {"samplers": [["dpmsolver++", 10]], "views": 3},
}
#: The Table II targets at a CPU budget where the range models leave the noise row: J and A over
#: 3 seeds (DDPM-1000 and DPM-Solver++ 20 / 50; J also UniPC 20, DDIM 50 and a respaced DDPM-50),
#: B, and F with E* (DDPM-1000 / DDPM-800 of the same model) over 1, 2000 training steps each, 16
#: samples per set (a set's JSD depends on its size: 4 real scans are no closer to the held-out
#: ones than 4 noise images), on the tiny pipeline's data
MEDIUM = {
    "configs": [_config("J", "time_dependent", "fourier",
                        samplers=[["ddpm", 1000], ["dpmsolver++", 20], ["dpmsolver++", 50], ["unipc", 20], ["ddim", 50],
                                  ["ddpm", 50]]),
                _config("A", "linear", "sinusoidal", samplers=[["ddpm", 1000], ["dpmsolver++", 20], ["dpmsolver++", 50]]),
                _config("B", "linear", "fourier", seeds=(0,)),
                _config("E*", "ramp", "fourier", seeds=(0,), samplers=[["ddpm", 800]]),
                _config("F", "ramp", "fourier", seeds=(0,))],
    "steps": 2000, "batch_size": 8, "eval_samples": 16, "bootstrap": 500, "features": {"steps": 400},
    "latent": {"samplers": [["dpmsolver++", 10]], "views": 16},
}


def sweep_params(repo: Path, *, quick: bool = False, medium: bool = False, depth: str | None = None,
                 prediction: str | None = None) -> dict:
    """The bench project's params.yaml: :data:`SWEEP` (or its quick / medium version), with the
    latent route pointed at this checkout's trained stage-1 and VQ-VAE models, ``depth`` (if
    given) as the range image's depth encoding and ``prediction`` (if given) as what the U-Net
    outputs."""
    params = copy.deepcopy(SWEEP)
    if depth is not None:
        params["ddpm"]["range_image"] = {"depth": depth}
    if prediction is not None:
        params["ddpm"]["prediction"] = prediction
    if quick:
        params["simulate"]["scenarios"] = {"target": {"train": 2, "test": 1}}
        params["ddpm"].update(copy.deepcopy(QUICK))
    elif medium:
        del params["simulate"]  # the tiny pipeline's data
        params["ddpm"].update(copy.deepcopy(MEDIUM))
    params["ddpm"]["latent"].update({"stage1": str((repo / "artifacts" / "stage1").resolve()),
                                     "vqvae": str((repo / "artifacts" / "vqvae").resolve())})
    return params


def bench_stem(depth: str | None, prediction: str | None) -> str:
    """The report's file stem: ``bench_ddpm`` for the profile's settings, each override appended
    (``bench_ddpm_linear_epsilon``: linear depth, ε-prediction)."""
    return "_".join(["bench_ddpm", *([depth] if depth else []),
                     *([{"epsilon": "epsilon", "v_prediction": "v"}[prediction]] if prediction else [])])


def run_stages(root: Path, env: dict) -> dict[str, float]:
    """simulate, voxelize and ddpm in the bench project through the CLI; wall seconds per stage."""
    seconds = {}
    for stage in ("simulate", "voxelize", "ddpm"):
        t0 = time.perf_counter()
        subprocess.run([str(Path(sys.executable).parent / "typ"), "--root", str(root), "run", stage], env=env,
                       check=True)
        seconds[stage] = round(time.perf_counter() - t0, 1)
    return seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="reports", help="folder for bench_ddpm.md and its plots")
    parser.add_argument("--root", default="artifacts/bench_ddpm", help="the bench project (cache, data, models)")
    parser.add_argument("--quick", action="store_true", help="2 configurations, 1 seed, a few steps")
    parser.add_argument("--medium", action="store_true",
                        help="the targets on the range image: J, A x3 seeds, B, E*/F, 2000 steps (about an hour)")
    parser.add_argument("--depth", choices=["linear", "log"],
                        help="the range image's depth encoding (default: the profile's); one given writes "
                             "bench_ddpm_<depth>.* beside the default's bench_ddpm.*")
    parser.add_argument("--prediction", choices=["epsilon", "v_prediction"],
                        help="what the U-Net outputs (default: the profile's); one given adds _epsilon or _v "
                             "to the file names")
    args = parser.parse_args(argv)
    from bench.report import machine, machine_line

    from typ.artifacts import WEIGHTS
    from tasks.stage1 import replica_dir
    from typ.config import config_from_dict

    root, out = Path(args.root).resolve(), Path(args.out)
    params = sweep_params(REPO, quick=args.quick, medium=args.medium, depth=args.depth, prediction=args.prediction)
    stem = bench_stem(args.depth, args.prediction)
    cfg = config_from_dict(params)
    latent = cfg.ddpm.latent  # the weights the latent route will load
    needed = [replica_dir(Path(latent.stage1), cfg.stage1.seed) / WEIGHTS,
              *(Path(latent.vqvae) / k / WEIGHTS for k in ("x", "y"))]
    missing = [str(p) for p in needed if not p.exists()]
    if missing:
        print(f"bench/ddpm.py: {', '.join(missing)} missing: run `make run` (or dvc repro stage1) first")
        return 2
    root.mkdir(parents=True, exist_ok=True)
    write_text(root / "params.yaml", yaml.safe_dump(params, sort_keys=False))
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{root / 'mlruns.db'}", "PYTHONPATH": str(REPO)}
    seconds = run_stages(root, env)
    info = machine()
    md = (root / "reports" / "ddpm.md").read_text()
    md = md.replace("(ddpm_pareto.png)", f"({stem}_pareto.png)").replace("(ddpm_samples.png)",
                                                                         f"({stem}_samples.png)")
    title, _, body = md.partition("\n")
    header = (f"{title.replace('# ', '# bench: ', 1)}\n\nMachine: {machine_line(info)}; `OMP_NUM_THREADS="
              f"{os.environ.get('OMP_NUM_THREADS', 'unset')}`. Wall time per stage of the bench project "
              f"({'--quick' if args.quick else '--medium' if args.medium else 'full sweep'}): "
              + ", ".join(f"{k} {v:.0f} s" for k, v in seconds.items())
              + ". Params: `bench/ddpm.py` SWEEP over the tiny profile (written to "
              f"`{args.root}/params.yaml`); range-image depth encoding: "
              f"`{cfg.ddpm.range_image.depth}`; the U-Net predicts `{cfg.ddpm.prediction}`.\n")
    out.mkdir(parents=True, exist_ok=True)
    write_text(out / f"{stem}.md", header + body)
    for name in ("pareto.png", "samples.png"):
        shutil.copyfile(root / "reports" / f"ddpm_{name}", out / f"{stem}_{name}")
    shutil.copyfile(root / "metrics" / "ddpm.json", out / f"{stem}.json")
    print(f"wrote {out / f'{stem}.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
