"""``reports/bench_novel_view.md``: seconds per scored pair of the real-scan benchmark.

    python bench/novel_view.py [--out reports] [--root .] [--max-pairs 6]

On each drive of shared/data in the KITTI odometry layout (KITTI seq 00: 124 k points a scan,
HDL-64E; a nuScenes scene: 35 k, HDL-32E), the first ``--max-pairs`` pairs of the pair rule are
made and scored by every method (:func:`tasks.novel_view.run_benchmark`, the generator of
``make run`` when it exists under ``--root``), two ways on the machine's 2 cores: one pair at a
time with 2 torch threads (per method: seconds making the view and scoring it, per pair), and
two pairs at a time with 1 torch thread each (wall seconds per pair, every method). Open3D's
ray casts and the KD-tree queries use every core either way. The map oracle's view depends on
the reference frame alone: it is cast once per frame (its seconds are spread over the pairs),
from surfels built once per scan of the drive (counted here). Goal: cast, scoring
included, at most 2 s a pair on 2 cores.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
DRIVES = ("kitti_odometry_00", "nuscenes_scene_seq")
GOAL_SECONDS = 2.0


def measure(root: Path, drive: Path, max_pairs: int, *, workers: int = 1, methods: list[str] | None = None) -> dict:
    """One drive's timings: {method: {view, scoring, total}}, pairs, wall seconds, surfel builds."""
    from tasks import novel_view as nvt
    from tasks.novel_view_report import seconds
    from tasks.voxelize import to_grid
    from typ.config import load_config

    cfg = load_config(root / "params.yaml")
    generator, model = nvt.trained_generator(root, cfg)
    builds = []
    original = nvt.build_surface

    def counted(points, **kw):
        builds.append(len(points))
        return original(points, **kw)

    nvt.build_surface = counted          # the oracle's per-scan surfels (resim and cast build their own)
    try:
        t0 = time.perf_counter()
        result = nvt.run_benchmark(drive, "00", sensor=None, grid=to_grid(cfg.voxelize.grid), generator=generator,
                                   model=model, cast=cfg.generate.cast, max_pairs=max_pairs, n_boot=50,
                                   workers=workers, methods=methods)
        wall = time.perf_counter() - t0
    finally:
        nvt.build_surface = original
    return {"seconds": seconds(result), "pairs": len(result.pairs), "wall": wall, "surfel_builds": len(builds),
            "scans": len(result.drive), "points": int(sum(builds) / max(len(builds), 1)), "model": model,
            "skipped": result.skipped, "methods": result.methods}


def page(rows: dict[str, dict], paired: dict[str, dict], cast_paired: dict[str, dict], info: dict) -> str:
    from bench.report import machine_line
    from typ.reporting import markdown_table

    lines = ["# bench: seconds per scored pair of the real-scan benchmark (typ novel-view)", "",
             f"Machine: {machine_line(info)}; the machine idle otherwise. Each drive's first pairs of the "
             "pair rule (every ordered pair of scans 2-40 m apart), every method, scoring included (LiDAR4D's "
             "figures, the range image, the beams, the seen / unseen split). Generator: "
             + "; ".join(f"{d}: {r['model']}" for d, r in rows.items()) + ".", ""]
    for drive, r in rows.items():
        lines += [f"## {drive}: {r['pairs']} pairs, one at a time (2 torch threads), {r['wall']:.0f} s in all", "",
                  markdown_table(["method", "view (s / pair)", "scoring (s / pair)", "total (s / pair)"],
                                 ([m, *(f"{r['seconds'][m][k]:.2f}" for k in ("view", "scoring", "total"))]
                                  for m in r["methods"])), "",
                  f"Two pairs at a time (1 torch thread each): {paired[drive]['wall']:.0f} s for the "
                  f"{paired[drive]['pairs']} pairs, {paired[drive]['wall'] / paired[drive]['pairs']:.2f} s a pair "
                  f"with every method, against {r['wall'] / r['pairs']:.2f} s one at a time; cast alone, two "
                  f"pairs at a time: {cast_paired[drive]['wall'] / cast_paired[drive]['pairs']:.2f} s a pair.", "",
                  f"Map oracle: surfels built {r['surfel_builds']} times for the drive's {r['scans']} scans "
                  f"({r['points']} points each on average): once per scan.", ""]
        if r["skipped"]:
            lines += ["Not run: " + "; ".join(f"{m}: {why}" for m, why in r["skipped"].items()) + ".", ""]
    verdicts = []
    for drive, r in rows.items():
        if "cast" not in r["seconds"]:
            continue
        alone, two = r["seconds"]["cast"]["total"], cast_paired[drive]["wall"] / cast_paired[drive]["pairs"]
        verdicts.append(f"- **cast on {drive}: {alone:.2f} s a pair one at a time, {two:.2f} s two at a time "
                        f"({'within' if min(alone, two) <= GOAL_SECONDS else 'over'} the {GOAL_SECONDS:g} s goal)**")
    if verdicts:
        lines += ["## Verdict", "", *verdicts, ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--out", default="reports")
    parser.add_argument("--root", default=".", help="project root with params.yaml and make run's artifacts")
    parser.add_argument("--max-pairs", type=int, default=6)
    parser.add_argument("--drives", nargs="+", default=list(DRIVES))
    args = parser.parse_args(argv)
    import torch

    from bench.report import machine
    from typ.io import write_text

    drives = [d for d in args.drives if (DATA / d).is_dir()]
    if not drives:
        print(f"no drive of {list(args.drives)} under {DATA}", file=sys.stderr)
        return 1
    torch.set_num_threads(2)
    info = machine()
    rows = {d: measure(Path(args.root), DATA / d, args.max_pairs) for d in drives}
    torch.set_num_threads(1)
    paired = {d: measure(Path(args.root), DATA / d, args.max_pairs, workers=2) for d in drives}
    cast_paired = {d: measure(Path(args.root), DATA / d, args.max_pairs, workers=2, methods=["cast"])
                   for d in drives if "cast" in rows[d]["methods"]}
    text = page(rows, paired, cast_paired, info)
    write_text(Path(args.out) / "bench_novel_view.md", text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
