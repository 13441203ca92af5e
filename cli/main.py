"""``typ`` command line: run stages, check params, write the report.

Exit codes: 0 done, 2 bad input (params, files, arguments: the message names which),
1 anything else.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from flows.run import run_command, setup_env, with_server
from typ.config import COMPOSE, SINGLE_AGENT_FORMATS, Config
from typ.errors import TypError
from typ.io import check_folder

STAGES = Config.STAGES


def _cmd_run(args) -> int:
    return run_command(args.stage, params=args.params, root=Path(args.root), runner=args.runner, address=args.address)


def _cmd_with_server(args) -> int:
    return with_server(args.cmd, root=Path(args.root))


def _cmd_serve(args) -> int:
    from typ.config import load_config

    root = Path(args.root).resolve()
    load_config(root / args.params)  # fail on bad params before a server starts
    setup_env(root)
    from flows.server import prefect_api, terminate_raises

    # SIGTERM at any moment, also while the server starts, stops the server started here
    with terminate_raises(), prefect_api(Path(os.environ["PREFECT_HOME"]), host=args.host, port=args.port,
                                         ui=True) as (url, server):
        if server is not None:
            print(f"Prefect server {server.ui_url} (state in {os.environ['PREFECT_HOME']}, log {server.log}; "
                  f"the UI and the prefect CLI ask for the secret in {server.auth_file})", flush=True)
        else:
            print(f"Prefect API {url}", flush=True)
        from flows.deploy import serve

        serve(root, args.params, only=args.only, poll_seconds=args.poll_seconds)
    return 0


def _cmd_compare(args) -> int:
    from typ.compare import compare

    root = Path(args.root)
    out = compare(args.runs, out=root / args.out, name=args.name, tracking_uri=args.tracking_uri, root=root,
                  params=root / args.params)
    print(f"wrote {out}")
    return 0


def _cmd_check(args) -> int:
    from typ.config import as_dict, load_config

    import yaml

    cfg = load_config(Path(args.root) / args.params)
    print(yaml.safe_dump({"profile": cfg.profile, **{s: as_dict(cfg.block(s)) for s in cfg.STAGES}},
                         sort_keys=False), end="")
    return 0


def _cmd_dvc_yaml(args) -> int:
    import difflib

    from flows import dvcyaml

    root = Path(args.root)
    text, path = dvcyaml.render(root), root / "dvc.yaml"
    if not args.check:
        dvcyaml.write(root)
        print(f"wrote {path}")
        return 0
    old = path.read_text() if path.is_file() else ""
    if old == text:
        print(f"{path} is what the stage declarations give")
        return 0
    sys.stdout.writelines(difflib.unified_diff(old.splitlines(True), text.splitlines(True), str(path), "typ dvc-yaml"))
    print(f"{path} differs from what the stage declarations give: run `typ dvc-yaml`", file=sys.stderr)
    return 1


def _cmd_schema(args) -> int:
    from typ.config_schema import config_schema
    from typ.io import write_json

    path = Path(args.root) / args.out
    write_json(path, config_schema())
    print(f"wrote {path}")
    return 0


def _cmd_report(args) -> int:
    from typ.report import write_summary

    path = write_summary(Path(args.root))
    print(f"wrote {path}")
    return 0


def _cmd_generate(args) -> int:
    from tasks.ingest import FORMATS

    if args.format not in FORMATS:
        raise TypError("typ generate", "--format", f"one of {list(FORMATS)}", args.format)
    if args.compose is not None and args.compose not in COMPOSE:   # before seconds of imports
        raise TypError("typ generate", "--compose", f"one of {list(COMPOSE)}", args.compose)
    root = Path(args.root)
    check_folder(args.out, where="typ generate", field="--out")
    setup_env(root)
    from flows.generate import generate_external

    metrics = generate_external(args.format, Path(args.input), Path(args.out), root=root, params=args.params,
                                references_per_frame=args.references, roadside_units=args.rsu, compose=args.compose,
                                sensor=args.sensor)
    print(f"generated {metrics['references']} reference views for {metrics['frames']} frames "
          f"({metrics['skipped_unchanged']} scenarios unchanged) under {args.out}")
    return 0


def _cmd_novel_view(args) -> int:
    if args.max_pairs < 0:
        raise TypError("typ novel-view", "--max-pairs", "a count >= 0 (0: every pair)", args.max_pairs)
    frames = None
    if args.frames is not None:
        first, _, stop = args.frames.partition(":")
        if not (first.isdigit() and stop.isdigit() and int(first) < int(stop)):
            raise TypError("typ novel-view", "--frames", "FIRST:STOP, scan numbers with FIRST < STOP", args.frames)
        frames = (int(first), int(stop))
    check_folder(args.out, where="typ novel-view", field="--out")
    root = Path(args.root)
    setup_env(root)
    from flows.novel_view import run_novel_view

    methods = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else None
    result = run_novel_view(args.format, Path(args.input), Path(args.out), root=root, params=args.params,
                            sequence=args.sequence, sensor=args.sensor, methods=methods, max_pairs=args.max_pairs,
                            frames=frames, pictures=not args.no_pictures)
    print(f"scored {len(result.pairs)} pairs of {result.drive.root.name}/{result.drive.name} "
          f"({', '.join(result.methods)}) under {args.out}")
    return 0


def _cmd_show(args) -> int:
    from tasks.show import ShowOptions, show
    from typ import viz

    check_folder(args.out, where="typ show", field="--out")
    root = Path(args.root)
    params = root / args.params
    if params.is_file():
        from tasks.voxelize import to_grid
        from typ.config import load_config

        grid = to_grid(load_config(params).voxelize.grid)
    else:
        from typ.voxel import TINY_GRID as grid

        print(f"no {params}: scoring on the tiny profile's grid", file=sys.stderr)
    half = args.range
    window = viz.Window((-half, half), (-half, half), args.resolution) if half else \
        viz.Window(grid.x_range, grid.y_range, args.resolution)
    opts = ShowOptions(grid=grid, window=window, color=args.color, sensor=args.sensor,
                       sim_root=Path(args.sim) if args.sim else None, resim=not args.no_resim)
    written = show(Path(args.path), Path(args.out), opts, args.timestamp)
    for path in written:
        print(f"wrote {path}")
    return 0


def _numbers(text: str, flag: str, counts: tuple[int, ...]) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) not in counts:
        raise TypError("typ edit", flag, f"{' or '.join(str(c) for c in counts)} comma-separated numbers", text)
    return values


def _cmd_edit(args) -> int:
    import numpy as np

    from tasks.edit import BoxEdit

    move = {}
    for spec in args.move:
        vid, _, delta = spec.partition(":")
        if not vid.lstrip("-").isdigit():
            raise TypError("typ edit", "--move", "ID:dx,dy[,dyaw_deg]", spec)
        dx, dy, *dyaw = _numbers(delta, "--move", (2, 3))
        move[int(vid)] = (dx, dy, float(np.radians(dyaw[0])) if dyaw else 0.0)
    add = []
    for spec in args.add:
        x, y, yaw, *lwh = _numbers(spec, "--add", (3, 6))
        add.append((x, y, float(np.radians(yaw)), *lwh))
    edit = BoxEdit(remove=tuple(args.remove), move=move, add=tuple(add))
    check_folder(args.out, where="typ edit", field="--out")
    root = Path(args.root)
    setup_env(root)
    from flows.edit import edit_scenario

    path, render = edit_scenario(Path(args.scenario), args.timestamp, edit, Path(args.out), root=root,
                                 params=args.params, agent=args.agent, seed=args.seed, compose=args.compose)
    print(f"wrote {path}")
    print(f"wrote {render}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="typ", description="typ: turn single-agent LiDAR datasets into collaborative ones (Transfer Your Perspective).")
    parser.add_argument("--root", default=".", help="project root holding params.yaml (default: .)")
    parser.add_argument("--params", default="params.yaml", help="params file relative to the root")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p = sub.add_parser("run", help="run one stage's Prefect flow, or `all` for the whole pipeline")
    p.add_argument("stage", help=f"one of: all, {', '.join(STAGES)}")
    p.add_argument("--runner", choices=("thread", "dask"), default="thread",
                   help="task runner of the per-scene stages (simulate, voxelize, generate): threads here, "
                        "or Dask (a LocalCluster of <workers> processes, or --address)")
    p.add_argument("--address", help="an existing Dask scheduler, e.g. tcp://10.0.0.5:8786 (with --runner dask)")
    p.set_defaults(fn=_cmd_run)
    p = sub.add_parser("with-server", help="run COMMAND (e.g. dvc repro, dvc exp run) with one Prefect API for every "
                                           "stage it starts: a local server, stopped when COMMAND ends, unless "
                                           "PREFECT_API_URL names one")
    p.add_argument("cmd", nargs=argparse.REMAINDER, metavar="COMMAND ...")
    p.set_defaults(fn=_cmd_with_server)
    p = sub.add_parser("serve", help="serve the Prefect deployments (scheduled pipeline, watched-folder generate); "
                                     "starts a local Prefect server unless PREFECT_API_URL is set")
    p.add_argument("--only", nargs="+", metavar="NAME", help="serve only these: pipeline, watch-generate, typ-stage")
    p.add_argument("--host", default="127.0.0.1", help="local server address (default: loopback)")
    p.add_argument("--port", type=int, default=4200, help="local server port (default: 4200)")
    p.add_argument("--poll-seconds", type=float, help="how often to ask the server for due runs (Prefect's default: 10)")
    p.set_defaults(fn=_cmd_serve)
    p = sub.add_parser("compare", help="compare two or more MLflow runs: reports/compare/<name>.md + plots")
    p.add_argument("runs", nargs="+", metavar="RUN_OR_EXPERIMENT",
                   help="run id (a pipeline run brings its stage runs), DVC experiment name, or MLflow experiment "
                        "name (its latest pipeline run)")
    p.add_argument("--name", help="report name (default: from the runs)")
    p.add_argument("--out", default="reports/compare", help="folder for the report (default: reports/compare)")
    p.add_argument("--tracking-uri", help="MLflow store (default: MLFLOW_TRACKING_URI, else params' tracking.uri)")
    p.set_defaults(fn=_cmd_compare)
    p = sub.add_parser("check", help="load and validate params.yaml; print the values in effect")
    p.set_defaults(fn=_cmd_check)
    p = sub.add_parser("schema", help="write the JSON Schema of params.yaml (for editors; params.yaml's first line "
                                      "points a YAML language server at it)")
    p.add_argument("--out", default="params.schema.json", help="path relative to the root (default: params.schema.json)")
    p.set_defaults(fn=_cmd_schema)
    p = sub.add_parser("dvc-yaml", help="write dvc.yaml from the stage declarations (tasks/<stage>.py), code deps from "
                                        "each flow's imports")
    p.add_argument("--check", action="store_true", help="write nothing; exit 1 with a diff when dvc.yaml differs")
    p.set_defaults(fn=_cmd_dvc_yaml)
    p = sub.add_parser("report", help="write reports/summary.md from the stage metrics and benches")
    p.set_defaults(fn=_cmd_report)
    p = sub.add_parser("generate", help="turn KITTI / nuScenes / Waymo frames or drives in the KITTI odometry layout "
                                        "into collaborative OPV2V scenarios with the trained models")
    p.add_argument("--format", required=True, help=" | ".join(SINGLE_AGENT_FORMATS))
    p.add_argument("--input", required=True, help="KITTI object root, nuScenes folder (bins + info json), "
                                                  "Waymo .tfrecord file / folder, or a KITTI odometry root "
                                                  "(sequences/<seq>/velodyne, calib.txt, poses.txt)")
    p.add_argument("--sensor", default=None, help="the LiDAR preset of the frames (default: the format's; "
                                                  "kitti-odometry: estimated from each drive's first scan)")
    p.add_argument("--out", default="data/generated_external", help="output root (default: data/generated_external)")
    p.add_argument("--references", type=int, default=None, help="reference views per frame (default: params)")
    p.add_argument("--rsu", type=int, default=None, help="roadside units per scenario (default: params)")
    p.add_argument("--compose", default=None, help="generated | hybrid | cast: what a reference view is made of "
                                                   "(default: params' generate.compose)")
    p.set_defaults(fn=_cmd_generate)
    p = sub.add_parser("novel-view", help="score the views generated from each scan of a real drive for the poses of "
                                          "its other scans against the real scans there (LiDAR4D's metrics): "
                                          "OUT/novel_view.json, OUT/novel_view.md and pictures")
    p.add_argument("--format", required=True, help="kitti-odometry (a drive with a pose per scan)")
    p.add_argument("--input", required=True, help="a dataset root in the KITTI odometry layout: sequences/<seq>/ with "
                                                  "velodyne/*.bin, calib.txt (Tr) and poses.txt")
    p.add_argument("--sequence", default=None, help="the drive, e.g. 00 (default: the only one under sequences/)")
    p.add_argument("--sensor", default=None, help="the drive's LiDAR preset, e.g. kitti or nuscenes (default: "
                                                  "estimated from its first scan)")
    p.add_argument("--out", required=True, help="folder the report, its JSON and the pictures are written to")
    p.add_argument("--methods", default=None, help="comma-separated subset of copy, resim, hybrid, cast, typ, "
                                                   "cast_no_typ, map_oracle (default: all)")
    p.add_argument("--max-pairs", type=int, default=0, help="score only the first N pairs of the pair rule (default 0: "
                                                            "every pair)")
    p.add_argument("--frames", default=None, metavar="FIRST:STOP", help="score only pairs of scans FIRST .. STOP-1 "
                                                                        "(a range the generator did not train on)")
    p.add_argument("--no-pictures", action="store_true", help="write the JSON and the report only")
    p.set_defaults(fn=_cmd_novel_view)
    p = sub.add_parser("show", help="PNGs of an OPV2V-layout scenario (simulated, generated or real) or a folder of "
                                    "them: each agent from above, all agents side by side, range images, and for "
                                    "generated agents the ego / x_e' / generated / true / re-simulated / error panels")
    p.add_argument("path", help="a scenario folder (agent/timestamp.pcd|.yaml) or a folder of scenarios")
    p.add_argument("--timestamp", default=None, help="the frame, e.g. 000000 (default: each scenario's first)")
    p.add_argument("--out", required=True, help="folder the PNGs are written to")
    p.add_argument("--color", choices=("height", "class"), default="height",
                   help="colour points by height (default) or by their simulated class where known")
    p.add_argument("--sensor", default=None, help="LiDAR preset for range images and re-simulation: source, target "
                                                  "or real_cav (default: from the simulated scenario or set name)")
    p.add_argument("--sim", default=None, help="root of the simulated scenarios holding true views (default: the "
                                               "'sim' folder beside the generated root, e.g. data/sim)")
    p.add_argument("--range", type=float, default=None, metavar="M",
                   help="show [-M, M] metres around the sensor (default: the voxel grid's extent)")
    p.add_argument("--resolution", type=float, default=0.2, metavar="M", help="metres per pixel (default 0.2)")
    p.add_argument("--no-resim", action="store_true", help="skip the re-simulated view (0.5 s per generated agent)")
    p.set_defaults(fn=_cmd_show)
    p = sub.add_parser("edit", help="regenerate one view with boxes added, removed or moved (TYP Fig. 5)")
    p.add_argument("scenario", help="an OPV2V-layout scenario folder")
    p.add_argument("--timestamp", required=True, help="the frame to edit, e.g. 000000")
    p.add_argument("--agent", default=None, help="the agent whose view is edited (default: the ego)")
    p.add_argument("--remove", type=int, action="append", default=[], metavar="ID", help="remove box ID")
    p.add_argument("--move", action="append", default=[], metavar="ID:dx,dy[,dyaw]",
                   help="move box ID by dx, dy metres (and dyaw degrees) in the sensor frame")
    p.add_argument("--add", action="append", default=[], metavar="x,y,yaw[,l,w,h]",
                   help="add a car at x, y (m) with heading yaw (degrees), default size 4.5x1.85x1.5 m")
    p.add_argument("--out", required=True, help="folder the edited copy of the scenario is written to, as "
                                                "OUT/<scenario>: not the folder holding the scenario (the copy "
                                                "would replace it); an earlier edit's copy there is replaced")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--compose", choices=("generated", "cast"), default=None,
                   help="what the edited footprint is made of: points in the generated voxels, or a scan of "
                        "the view's own LiDAR cast through the edited scene, which also hides the real points "
                        "behind an added or moved vehicle (default: cast when params' generate.compose is cast)")
    p.set_defaults(fn=_cmd_edit)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.fn(args)
    except TypError as exc:
        print(f"typ: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
