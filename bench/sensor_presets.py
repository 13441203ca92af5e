"""``reports/sensor_presets.md``: every LiDAR preset recovered from typ's own scans and checked
against the real frames in shared/data.

    python bench/sensor_presets.py [--out reports]

1. Each sensor of ``typ.sensors.SENSORS`` casts one sweep in a simulated town (the target
   domain's town, seed 7, the first agent's car); ``fit_sensor`` recovers its beams, beam
   origins, azimuth step and mount height from it.
2. Each real frame: the fraction of its returns (3 m or more from the sensor, horizontally)
   within 0.05 / 0.1 / 0.2 deg of its preset's beams, and what ``fit_sensor`` makes of it.
3. KITTI: the preset's table measured again from the frames' scan order (each ring a line
   z = h + d tan e), against the datasheet's nominal two-block layout.
4. nuScenes: each ring's elevations (the file's ring column) against the HDL-32E's.
5. Waymo: the preset against the tfrecord's TOP calibration, and what its 800-point clouds hold.
Writes ``<out>/sensor_presets.md`` atomically and prints it.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

from tasks.evaluate import table  # noqa: E402
from typ.errors import TypError  # noqa: E402
from typ.formats.binfile import read_bin  # noqa: E402
from typ.sensors import SENSORS, fit_sensor, on_beam_fractions  # noqa: E402
from typ.sim import build_town, cast, domain_spec, sensor_pose, simulate_traffic, town_frame  # noqa: E402
from typ.io import write_text  # noqa: E402

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
NEAR = 3.0   #: returns nearer than this (m, horizontally) are left out: the car's body, no-return placeholders
KITTI = {"KITTI training 000000": ("kitti_object_vis/training/velodyne/000000.bin", 4),
         "KITTI training 000001": ("kitti_object_vis/training/velodyne/000001.bin", 4),
         "KITTI testing 000002 (camera view)": ("pointpillars_kitti_demo/testing/velodyne_reduced/000002.bin", 4)}
NUSCENES = ("nuscenes_mmdet3d_demo/n015-2018-07-24-11-22-45+0800__LIDAR_TOP__1532402927647951.pcd.bin", 5)
WAYMO_BINS = {f"Waymo {n} (800 points)": f"waymo_mmdet3d_testdata/kitti_format/velodyne/{n}.bin"
              for n in ("0000000", "1000000")}
WAYMO_RECORD = "waymo_mmdet3d_testdata/val.tfrecord"
#: the HDL-64E S2 datasheet's nominal layout: upper block +2 .. -8.33 deg at 1/3 deg, lower -8.83 .. -24.33 at 1/2
NOMINAL_HDL64 = tuple(float(v) for v in np.r_[np.linspace(-24.33, -8.83, 32), np.linspace(-8.33, 2.0, 32)])


def f(v, digits: int = 3) -> str:
    return "–" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{digits}f}"


# ---------------------------------------------------------------- 1. the presets, and typ's own scans


def presets_table() -> str:
    rows = {}
    for name, s in SENSORS.items():
        gaps = np.diff(s.elevations_deg)
        rows[name] = {"beams": str(s.n_beams), "elev": f"{s.elevations_deg[0]:+.2f} .. {s.elevations_deg[-1]:+.2f}",
                      "gap": f"{gaps.min():.3f} .. {gaps.max():.3f}", "az": f(s.azimuth_step_deg, 4),
                      "range": f"{s.min_range:g} .. {s.max_range:g}", "mount": f(s.mount_height),
                      "origins": "per beam" if s.beam_heights_m else "shared"}
    return table(rows, [("beams", "beams"), ("elev", "elevations (deg)"), ("gap", "spacing (deg)"),
                        ("az", "azimuth step (deg)"), ("range", "range (m)"), ("mount", "mount height (m)"),
                        ("origins", "beam origins")], first="sensor")


def own_scans_table() -> str:
    spec = domain_spec("target")
    town_seed, traffic_seed, _ = np.random.SeedSequence(7).spawn(3)
    town = build_town(spec.town, np.random.default_rng(town_seed))
    traffic = simulate_traffic(town, np.random.default_rng(traffic_seed), n_frames=1, dt=0.1, n_agents=1,
                               comm_range=70.0, moving_vehicles=spec.moving_vehicles,
                               class_probs=spec.moving_class_probs)
    world, car = town_frame(town, traffic, 0), traffic.agents[0]
    rows = {}
    for name, s in SENSORS.items():
        pose = sensor_pose(traffic.xy[0, car], traffic.yaw[0, car], s.mount_height)
        points, _ = cast(world, pose, s, np.random.default_rng(0), exclude_vehicle_id=int(traffic.ids[car]))
        fit = fit_sensor(points)
        same = fit.n_beams == s.n_beams
        rows[name] = {
            "points": str(len(points)), "beams": f"{fit.n_beams} / {s.n_beams}",
            "de": f(np.abs(np.subtract(fit.elevations_deg, s.elevations_deg)).max(), 4) if same else "–",
            "dh": (f(np.abs(np.subtract(fit.beam_heights_m, s.beam_heights_m)).max(), 4)
                   if same and s.beam_heights_m and fit.beam_heights_m else "shared" if not fit.beam_heights_m else "–"),
            "mount": f"{fit.mount_height:.3f} / {s.mount_height:.3f}",
            "az": f"{fit.azimuth_step_deg:.4f} / {s.azimuth_step_deg:.4f}", "q": f(fit.quality, 4)}
    return table(rows, [("points", "returns"), ("beams", "beams found / true"), ("de", "max abs Δ elevation (deg)"),
                        ("dh", "max abs Δ beam origin (m)"), ("mount", "mount height found / true (m)"),
                        ("az", "azimuth step found / true (deg)"), ("q", "on a fitted beam ±0.05°")],
                 first="sensor")


# ---------------------------------------------------------------- 2. the real frames


def real_frames() -> list[tuple[str, str, np.ndarray]]:
    """(label, preset name, (N, 3) float64 points in the preset's frame) of each real frame present."""
    frames = []
    for label, (path, columns) in KITTI.items():
        if (DATA / path).is_file():
            frames.append((label, "kitti", read_bin(DATA / path, columns)[:, :3].astype(np.float64)))
    if (DATA / NUSCENES[0]).is_file():
        frames.append(("nuScenes LIDAR_TOP keyframe", "nuscenes", read_bin(DATA / NUSCENES[0], 5)[:, :3].astype(np.float64)))
    top = waymo_top()
    for label, path in WAYMO_BINS.items():
        if (DATA / path).is_file() and top is not None:
            vehicle = read_bin(DATA / path, 6)[:, :3].astype(np.float64)
            # vehicle frame -> TOP LiDAR frame, through the only extrinsic at hand (another car's)
            frames.append((label, "waymo", (vehicle - top["extrinsic"][:3, 3]) @ top["extrinsic"][:3, :3]))
    return frames


def real_table(frames) -> str:
    rows = {}
    for label, name, xyz in frames:
        spec = SENSORS[name]
        on = on_beam_fractions(xyz, spec, min_range=NEAR)
        try:
            fit = fit_sensor(xyz, min_range=NEAR)
        except TypError:
            fit = None
        rows[label] = {
            "preset": name, "points": str(int((np.hypot(xyz[:, 0], xyz[:, 1]) >= NEAR).sum())),
            "p05": f(on[0.05]), "p10": f(on[0.1]), "p20": f(on[0.2]),
            "beams": f"{fit.n_beams} ({'own origins' if fit.beam_heights_m else 'shared origin'})" if fit else "–",
            "q": f(fit.quality) if fit else "–",
            "mount": f"{fit.mount_height:.3f} / {spec.mount_height:.3f}" if fit else f"– / {spec.mount_height:.3f}",
            "az": f"{fit.azimuth_step_deg:.4f} / {spec.azimuth_step_deg:.4f}" if fit else "–"}
    return table(rows, [("preset", "preset"), ("points", "returns ≥ 3 m"), ("p05", "on preset ±0.05°"),
                        ("p10", "±0.1°"), ("p20", "±0.2°"), ("beams", "fit_sensor: beams"), ("q", "fit: on its beams ±0.05°"),
                        ("mount", "mount height fit / preset (m)"), ("az", "azimuth step fit / preset (deg)")],
                 first="frame")


# ---------------------------------------------------------------- 3. KITTI


def scan_order_rings(xyz: np.ndarray) -> np.ndarray:
    """(N,) ring of each point of a full KITTI sweep, whose points come laser by laser, each ring
    one turn from azimuth 0: a ring ends where the unwrapped azimuth completes a turn."""
    turn = np.degrees(np.unwrap(np.arctan2(xyz[:, 1], xyz[:, 0])))
    return np.floor((turn - turn[0] + 1.0) / 360.0).astype(np.int64)


def ring_cones(sweeps: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, float]:
    """(elevations, origin heights, largest robust residual in m) of a line z = h + d tan e fitted
    to each ring of all sweeps together (returns 3 m or more away), ascending."""
    per_ring: dict[int, list[np.ndarray]] = {}
    for xyz in sweeps:
        rings = scan_order_rings(xyz)
        far = np.hypot(xyz[:, 0], xyz[:, 1]) >= NEAR
        for r in np.unique(rings):
            per_ring.setdefault(int(r), []).append(xyz[far & (rings == r)])
    cones, worst = [], 0.0
    for pts in per_ring.values():
        pts = np.concatenate(pts)
        d, z = np.hypot(pts[:, 0], pts[:, 1]), pts[:, 2]
        keep = np.ones(len(d), dtype=bool)
        for _ in range(4):   # refit on the points within 3 robust sigmas (a few stray returns)
            slope, height = np.polyfit(d[keep], z[keep], 1)
            residual = np.abs(z - slope * d - height)
            keep = residual <= max(3 * 1.4826 * np.median(residual[keep]), 1e-3)
        worst = max(worst, float(np.median(residual[keep])))
        cones.append((np.degrees(np.arctan(slope)), height))
    cones.sort()
    return np.array([c[0] for c in cones]), np.array([c[1] for c in cones]), worst


def kitti_section(frames) -> list[str]:
    sweeps = {label: xyz for label, name, xyz in frames if name == "kitti" and "training" in label}
    if not sweeps:
        return ["_KITTI frames not available._"]
    kitti = SENSORS["kitti"]
    elevations, heights, worst = ring_cones(list(sweeps.values()))
    measured = np.asarray(kitti.elevations_deg)
    lines = [f"The preset's table, measured again from the scan order of {len(sweeps)} training frames: "
             f"{len(elevations)} rings, largest median residual {worst * 1000:.2f} mm; largest difference from "
             f"the preset {np.abs(elevations - measured).max():.4f} deg and "
             f"{np.abs(heights - np.asarray(kitti.beam_heights_m)).max() * 1000:.1f} mm.", ""]
    rows = {}
    for block, idx, nominal in (("upper (32)", slice(32, 64), np.linspace(-8.33, 2.0, 32)),
                                ("lower (32)", slice(0, 32), np.linspace(-24.33, -8.83, 32))):
        e, h = measured[idx], np.asarray(kitti.beam_heights_m)[idx]
        gaps = np.diff(e)
        rows[block] = {"span": f"{e[-1]:+.3f} .. {e[0]:+.3f}", "nominal": f"{nominal[-1]:+.2f} .. {nominal[0]:+.2f}",
                       "gap": f"{gaps.min():.3f} / {gaps.mean():.3f} / {gaps.max():.3f}",
                       "ngap": f"{np.diff(nominal).mean():.3f}",
                       "off": f"{np.abs(e - nominal).max():.3f}", "h": f"{h.min():.3f} .. {h.max():.3f}"}
    lines.append(table(rows, [("span", "measured (deg, top .. bottom)"), ("nominal", "datasheet (deg)"),
                              ("gap", "spacing min / mean / max (deg)"), ("ngap", "datasheet spacing"),
                              ("off", "max abs measured − datasheet (deg)"), ("h", "beam origin above the frame (m)")],
                       first="block"))
    lines += ["", "Returns (≥ 3 m) within ±0.05° of a beam, by beam model:", ""]
    variants = {"datasheet layout, from the origin": dataclasses.replace(kitti, elevations_deg=NOMINAL_HDL64, beam_heights_m=()),
                "measured elevations, from the origin": dataclasses.replace(kitti, beam_heights_m=()),
                "measured elevations from each beam's origin (the preset)": kitti}
    on = {v: {label: on_beam_fractions(xyz, spec, min_range=NEAR)[0.05] for label, name, xyz in frames if name == "kitti"}
          for v, spec in variants.items()}
    labels = [label for label, name, _ in frames if name == "kitti"]
    lines.append(table({v: {k: f(x) for k, x in row.items()} for v, row in on.items()},
                       [(label, label) for label in labels], first="beam model"))
    upper_h = np.mean(kitti.beam_heights_m[32:])
    fractions = [x for row in list(on.values())[:2] for x in row.values()]
    lines += ["", f"The two blocks lie where the datasheet puts them, but not at its even spacings, and each "
              f"block's lasers sit above the origin of the frame KITTI gives its points in ({upper_h:.2f} m for the "
              f"upper block). Seen from that origin a ring's elevation changes with distance (by h/d: "
              f"{np.degrees(upper_h / 20):.2f}° at 20 m for the upper block), so no elevation table alone puts "
              f"KITTI's returns on its beams ({min(fractions):.2f} .. {max(fractions):.2f} within ±0.05°). "
              f"The preset keeps each beam's origin height; typ casts from there, and every return of the three "
              f"frames, the testing frame the table was not measured on too, lies within 0.05° of a beam."]
    lines += ["", "`fit_sensor` on each frame alone (no scan order), against the preset:", ""]
    rows = {}
    for label, xyz in sweeps.items():
        fit = fit_sensor(xyz, min_range=NEAR)
        same = fit.n_beams == kitti.n_beams
        rows[label] = {"beams": str(fit.n_beams),
                       "de": f(np.abs(np.subtract(fit.elevations_deg, kitti.elevations_deg)).max(), 4) if same else "–",
                       "dh": f(np.abs(np.subtract(fit.beam_heights_m, kitti.beam_heights_m)).max() * 1000, 1)
                       if same and fit.beam_heights_m else "–"}
    lines.append(table(rows, [("beams", "beams"), ("de", "max abs Δ elevation (deg)"), ("dh", "max abs Δ origin (mm)")],
                       first="frame"))
    return lines


# ---------------------------------------------------------------- 4. nuScenes


def nuscenes_section() -> list[str]:
    if not (DATA / NUSCENES[0]).is_file():
        return ["_nuScenes keyframe not available._"]
    raw = read_bin(DATA / NUSCENES[0], 5).astype(np.float64)
    spec = SENSORS["nuscenes"]
    d = np.hypot(raw[:, 0], raw[:, 1])
    far = d >= NEAR
    seen = np.degrees(np.arctan2(raw[far, 2], d[far]))
    ring = raw[far, 4].astype(int)
    azimuth = np.degrees(np.arctan2(raw[far, 1], raw[far, 0]))
    rows = {}
    for r in range(32):
        e = seen[ring == r] - spec.elevations_deg[r]
        if len(e) < 20:
            continue
        sector = ((azimuth[ring == r] + 180.0) // 45).astype(int)
        by_sector = [np.median(e[sector == s]) for s in range(8) if (sector == s).sum() >= 5]
        rows[str(r)] = {"nominal": f"{spec.elevations_deg[r]:+.3f}", "n": str(len(e)), "median": f"{np.median(e):+.3f}",
                        "spread": f"{np.percentile(e, 5):+.3f} .. {np.percentile(e, 95):+.3f}",
                        "sectors": f"{min(by_sector):+.3f} .. {max(by_sector):+.3f}"}
    fit = fit_sensor(raw, min_range=NEAR)
    found = sum(np.min(np.abs(np.subtract(fit.elevations_deg, e))) <= 0.05 for e in spec.elevations_deg)
    on = on_beam_fractions(raw, spec, min_range=NEAR)
    upper = [r for r in range(32) if spec.elevations_deg[r] > -9.5]
    worst = max(abs(np.median(seen[ring == r]) - spec.elevations_deg[r]) for r in upper)
    return [table(rows, [("nominal", "HDL-32E (deg)"), ("n", "returns ≥ 3 m"), ("median", "median − nominal"),
                         ("spread", "5 .. 95 % − nominal"), ("sectors", "45° sector medians − nominal")], first="ring"),
            "", f"The rings sit at the HDL-32E's nominal elevations: the median of each ring above -9.5° is within "
                f"{worst:.3f}° of it. But a ring's returns do not lie on one cone from the sensor origin: their "
                f"offset changes with azimuth (the sector medians) and grows as the returns get nearer (the low "
                f"rings, which meet the road 3 .. 10 m away, spread over up to 2°), as a shift of the sweep's origin "
                f"by a few decimetres would make: the car moves during the 50 ms turn. So {on[0.05]:.3f} of the "
                f"keyframe's returns lie within ±0.05° of the preset's beams ({on[0.2]:.3f} within ±0.2°), and "
                f"`fit_sensor`, which takes one origin per beam, finds the upper rings but splits or misses the lower "
                f"ones: {fit.n_beams} beams, {found} of the preset's 32 within 0.05° of one, {fit.quality:.3f} of the "
                f"returns within 0.05° of its beams. The mount height agrees (table above)."]


# ---------------------------------------------------------------- 5. Waymo


def waymo_top() -> dict | None:
    """The TOP LiDAR's beam inclinations (deg) and extrinsic of the tfrecord's frame, or None."""
    if not (DATA / WAYMO_RECORD).is_file():
        return None
    try:
        from waymo_open_dataset import dataset_pb2, label_pb2
    except ImportError:
        return None
    from typ.formats.waymo import iter_tfrecord

    frame = dataset_pb2.Frame.FromString(next(iter_tfrecord(DATA / WAYMO_RECORD)))
    (top,) = [c for c in frame.context.laser_calibrations if dataset_pb2.LaserName.Name.Name(c.name) == "TOP"]
    cars = [lb.box for lb in frame.laser_labels if lb.type == label_pb2.Label.Type.Value("TYPE_VEHICLE")]
    return {"inclinations": np.degrees(np.asarray(top.beam_inclinations)),
            "extrinsic": np.asarray(top.extrinsic.transform, dtype=np.float64).reshape(4, 4),
            "context": frame.context.name,
            # (distance, box bottom z) of its labelled vehicles: where the vehicle frame's z = 0 is
            "car_bottoms": [(float(np.hypot(b.center_x, b.center_y)), b.center_z - b.height / 2) for b in cars]}


def waymo_section(frames) -> list[str]:
    top = waymo_top()
    if top is None:
        return ["_The Waymo tfrecord (or waymo_open_dataset) is not available._"]
    spec = SENSORS["waymo"]
    lines = [f"Preset against frame {top['context']}'s TOP calibration: {len(top['inclinations'])} inclinations, "
             f"largest difference {np.abs(top['inclinations'] - spec.elevations_deg).max():.4f} deg; "
             f"extrinsic z {top['extrinsic'][2, 3]:.3f} m (preset {spec.mount_height:.3f}).", ""]
    for label, name, xyz in frames:
        if name != "waymo":
            continue
        seen = np.degrees(np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1])))
        top3 = ", ".join(f"{e:+.3f}" for e in spec.elevations_deg[-3:])
        lines.append(f"- {label}: elevations {seen.min():+.3f} .. {seen.max():+.3f} deg, ranges "
                     f"{np.linalg.norm(xyz, axis=1).min():.1f} .. {np.linalg.norm(xyz, axis=1).max():.1f} m: the first "
                     f"rows of the range image only (the preset's top three beams: {top3}).")
    cars = "; ".join(f"{z:+.2f} m, {dist:.0f} m away" for dist, z in top["car_bottoms"])
    lines += ["", "What can be checked: the preset is this frame's TOP calibration, and its extrinsic gives the mount "
              f"height (the vehicle frame's origin is on the road: the box bottoms of its labelled vehicles: {cars}). "
              "What cannot: the 800-point clouds are the first 800 points of two other "
              "frames' range images, the top rows only, all above the horizon (no road: `fit_sensor` finds no ground "
              "below the sensor and gives up), in the vehicle frames of other cars whose extrinsics are not given; "
              "their fractions above, taken through this frame's extrinsic, only say that they lie near the top two "
              "or three beams. No full Waymo frame is here: the other 61 beams, the azimuth step and the mount height "
              "cannot be checked against Waymo returns, and other cars' calibrations differ from this one by a few "
              "hundredths of a degree."]
    return lines


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="reports")
    args = parser.parse_args(argv)
    frames = real_frames()
    page = [
        "# LiDAR presets: recovered from typ's scans, checked against real frames",
        "",
        "`python bench/sensor_presets.py` writes this page. Each preset's values and their sources are in "
        "`typ/sensors/presets.py`; `typ.sensors.fit_sensor` is the estimator. Fractions count the returns 3 m or "
        "more from the sensor (horizontally), their elevation seen from each beam's own origin.",
        "",
        "## The sensors", "", presets_table(), "",
        "## Recovered from one sweep typ casts with each", "",
        "A town of the simulated target domain (seed 7), the first agent's car, each sensor at its own azimuth "
        "step, range noise and dropout.", "", own_scans_table(), "",
        "## Against the real frames in shared/data", "", real_table(frames) if frames else "_No real frames available._", "",
        "## KITTI: the HDL-64E's beams", "", *kitti_section(frames), "",
        "## nuScenes: the HDL-32E's rings", "", *nuscenes_section(), "",
        "## Waymo: the TOP LiDAR", "", *waymo_section(frames), "",
    ]
    text = "\n".join(page)
    write_text(Path(args.out) / "sensor_presets.md", text)
    print(text)
    return text


if __name__ == "__main__":
    main()
