"""Cast reference views against the hybrid on held-out simulated pairs (typ.castview).

    python bench/cast_probe.py [--split test] [--max-pairs 64]

Needs ``make run``'s artifacts. Samples the generator ``generate`` uses once (seed
stage1.seed) on every (ego, reference) pair of the split and scores, against the hidden true
view: TYP's sample, the voxel hybrid (what ``generate.compose: hybrid`` writes) and cast
views with the variants below; prints one line per method (IoU, above-ground IoU, hit rate,
JSD, pooled over pairs) and the fraction of points on the reference sensor's beams.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipelines.typ.pipeline_typ import TYPPipeline  # noqa: E402
from tasks import evaluate_generation as gen, genscore  # noqa: E402
from pipelines.typ.pipeline_typ import generator_dir  # noqa: E402
from typ import castview  # noqa: E402
from typ.config import COMPOSE, CastConfig, as_dict, load_config  # noqa: E402
from typ.resim import EGO_CAR_LWH, hybrid, hybrid_points, own_car_box  # noqa: E402
from typ.sensors import on_beam_fractions  # noqa: E402
from typ.sim.sensor import domain_spec  # noqa: E402
from typ.reporting import markdown_table  # noqa: E402
from typ.voxel import Grid, voxelize  # noqa: E402

KEYS = ("iou", "iou_above_ground", "iou_seen", "iou_unseen", *(f"iou_{genscore.band_label(*b)}" for b in genscore.BANDS),
        "object_hit_rate", "jsd_r2dm")


def line(name: str, data, occ: np.ndarray, points: list[np.ndarray], spec, seconds: float) -> str:
    s = genscore.summarize([gen.score_method(data, occ, points)], data.scenes,
                           [t["histogram"] for t in data.truth_stats], [t["centres"] for t in data.truth_stats],
                           n_boot=200)
    beams = np.mean([on_beam_fractions(p, spec, (0.05,), min_range=1.0)[0.05] for p in points if len(p)])
    cells = " | ".join(f"{s[k].value:.3f} [{s[k].low:.3f}, {s[k].high:.3f}]" for k in KEYS)
    return f"| {name} | {cells} | {beams:.3f} | {seconds:.2f} |"


def main() -> None:
    global PARAMS, COMPOSES
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--split", default="test")
    ap.add_argument("--max-pairs", type=int, default=64)
    ap.add_argument("--real", action="store_true", help="also typ generate on the real frames of shared/data")
    ap.add_argument("--no-sim", action="store_true", help="skip the simulated pairs")
    ap.add_argument("--params", default="params.yaml", help="params file typ generate reads on the real frames")
    ap.add_argument("--composes", default="generated,hybrid,cast", help="what the real frames' views are made of")
    args = ap.parse_args()
    PARAMS, COMPOSES = args.params, tuple(args.composes.split(","))   # noqa: F841 (read by real_frames)
    cfg, root = load_config("params.yaml"), Path(".")
    if args.no_sim:
        return real_frames(root)
    grid = cfg.voxelize.sensor_grid("target")
    spec = domain_spec("target", azimuth_step_deg=cfg.simulate.azimuth_step_deg).sensor
    pipe = TYPPipeline.from_pretrained(generator_dir(root / cfg.selftrain.out, cfg.stage1.seed))
    data = gen.build_eval_set(root / cfg.simulate.out / "target" / args.split, grid, spec, max_pairs=args.max_pairs)
    seed = cfg.stage1.seed
    occ, points, sec = gen.sample_method(pipe, data, seed)
    print(f"{len(data)} pairs, {len(set(data.scenes))} scenes")
    print(markdown_table(["method", *KEYS, "on beam ±0.05°", "s/view"], []))
    print(line("TYP", data, occ, points, spec, sec))
    print(line("re-simulation", data, data.resim > 0.5, data.resim_points, spec, data.resim_seconds))
    hyb = hybrid(data.resim > 0.5, occ, data.seen)
    hyb_points = [hybrid_points(data.resim_points[i][:, :3], points[i][:, :3], data.seen[i], grid) for i in range(len(data))]
    print(line("hybrid", data, hyb, hyb_points, spec, 0.0), flush=True)
    own = own_car_box(spec, EGO_CAR_LWH)
    chosen = cfg.generate.cast
    above_road = np.arange(grid.shape[2])[:, None, None] > castview.ground_layer(grid, -spec.mount_height)
    variants = {
        "cast: ego surfels + generated cells": (CastConfig(label_boxes=0.0, road="generated", carve=False), occ, spec),
        "+ label boxes": (CastConfig(label_boxes=1.0, road="generated", carve=False), occ, spec),
        "+ label boxes x0.9": (CastConfig(label_boxes=0.9, road="generated", carve=False), occ, spec),
        "+ road in every unseen cell": (CastConfig(label_boxes=0.9, road="unseen", carve=False), occ, spec),
        "+ road everywhere": (CastConfig(label_boxes=0.9, road="everywhere", carve=False), occ, spec),
        "+ free space carved": (CastConfig(label_boxes=0.9, road="everywhere", carve=True), occ, spec),
        f"params' generate.cast {as_dict(chosen)}": (chosen, occ, spec),
        "params', ideal sensor (no drop, no noise)": (chosen, occ, dataclasses.replace(spec, dropout=0.0,
                                                                                      range_noise_std=0.0)),
        "params', no generated cells above the road": (chosen, occ & ~above_road, spec),
    }
    for name, (params, occupancy, sensor) in variants.items():
        t0 = time.perf_counter()
        cast = [castview.cast_view(data.ego_points[i], occupancy[i], grid, sensor, np.random.default_rng([seed, i]),
                                   params=params, ego_origin=data.ego_origins[i], label_boxes=data.boxes[i],
                                   exclude_boxes=own, mask=data.seen[i]) for i in range(len(data))]
        sec = (time.perf_counter() - t0) / len(data)
        cast_occ = np.stack([voxelize(p, grid).transpose(2, 0, 1) for p in cast])
        print(line(name, data, cast_occ, cast, spec, sec), flush=True)
    if args.real:
        real_frames(root)


#: the real frames of shared/data, as ``typ generate`` reads them
REAL = {"kitti": "kitti_object_vis", "nuscenes": "nuscenes_mmdet3d_demo", "waymo": "waymo_mmdet3d_testdata/val.tfrecord"}
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
ROADSIDE_UNITS = 2
NEAR_M = 0.5
PARAMS = "params.yaml"   #: the params file typ generate reads (--params)
COMPOSES = COMPOSE   #: every compose mode of the registry (typ.registry.COMPOSE_MODES)


def real_frames(root: Path) -> None:
    """``typ generate`` on each real frame of shared/data with each compose: of every generated
    reference view, the fraction of points on the dataset LiDAR's beams (±0.05°) and, in the BEV
    cells the ego's cloud covers, the fraction within 0.5 m of an ego return; the L1 distance of its
    range-image row-occupancy profile from the real scan's own (:mod:`tasks.realism`)."""
    import tempfile

    from scipy.spatial import cKDTree

    from flows.generate import generate_external
    from tasks.realism import layout_of, view_pattern
    from typ.formats.opv2v import list_agents, list_scenarios, list_timestamps, read_scene
    from typ.resim import coverage_mask, in_mask
    from typ.sensors import SENSORS
    from typ.voxel import points_to_reference

    cfg = load_config(root / "params.yaml")
    print("\n" + markdown_table(["frame set", "compose", "views", "points per view", "on beam ±0.05°",
                                 f"within {NEAR_M} m of the ego's surface (seen cells)", "... of an ego return",
                                 "row profile L1 to the real scan's"], []))
    for fmt, rel in REAL.items():
        if not (DATA / rel).exists():
            print(f"| {fmt} | (not in shared/data) | | | | |")
            continue
        for compose in COMPOSES:
            with tempfile.TemporaryDirectory() as tmp:
                # two roadside units a frame: a frame without a vehicle in the band still gets views
                generate_external(fmt, DATA / rel, Path(tmp), root=root, params=PARAMS, compose=compose,
                                  roadside_units=ROADSIDE_UNITS)
                beams, near, near_points, sizes, rows = [], [], [], [], []
                layout = layout_of(SENSORS[fmt])
                g = Grid(*(getattr(cfg.voxelize.grid, k) for k in ("x_range", "y_range", "z_range", "shape"))
                         ).for_sensor(SENSORS[fmt].mount_height)
                for folder in list_scenarios(Path(tmp) / fmt / "frames"):
                    agents = list_agents(folder)
                    for ts in list_timestamps(folder):
                        scene = read_scene(folder, ts, agents=agents)
                        ego = scene.agents[agents[0]]
                        real_rows = view_pattern(ego.points, SENSORS[fmt], layout).rows / layout.width
                        for a in agents[1:]:
                            ref = scene.agents[a]
                            moved = points_to_reference(ego.points, ego.pose, ref.pose)
                            seen = coverage_mask(moved, g)
                            pts = ref.points[:, :3]
                            inside = in_mask(pts, seen, g)
                            sizes.append(len(pts))
                            beams.append(on_beam_fractions(pts, SENSORS[fmt], (0.05,), min_range=1.0)[0.05])
                            rows.append(np.abs(view_pattern(pts, SENSORS[fmt], layout).rows / layout.width - real_rows).mean())
                            if inside.any():
                                d, _ = cKDTree(moved[:, :3]).query(pts[inside], k=1)
                                near_points.append(float(np.mean(d <= NEAR_M)))
                                near.append(float(np.mean(surface_distance(moved, pts[inside]) <= NEAR_M)))
                print(f"| {fmt} | {compose} | {len(sizes)} | {np.mean(sizes):.0f} | {np.mean(beams):.3f} | "
                      f"{np.mean(near):.3f} | {np.mean(near_points):.3f} | {np.mean(rows):.3f} |", flush=True)


def surface_distance(ego_points: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(M,) metres from each of ``points`` to the surface the ego saw: the surfels its returns
    describe (:func:`typ.resim.build_surface`, as re-simulation and cast views build it)."""
    from typ.resim import build_surface
    from typ.sim.raycast import RayScene

    return RayScene(build_surface(np.asarray(ego_points, dtype=np.float64)[:, :3])).distance(points[:, :3])


if __name__ == "__main__":
    main()
