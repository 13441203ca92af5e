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

from typ.errors import TypError

from typ.config import Config

STAGES = Config.STAGES


def _setup_env(root: Path) -> None:
    # Prefect keeps its state inside the project and runs without a server by default.
    os.environ.setdefault("PREFECT_HOME", str((root / ".prefect").resolve()))
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    os.environ.setdefault("DO_NOT_TRACK", "1")
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    os.environ.setdefault("DVC_NO_ANALYTICS", "1")


def _cmd_run(args) -> int:
    root = Path(args.root)
    if args.stage != "all" and args.stage not in STAGES:
        raise TypError("typ run", "stage", f"one of {['all', *STAGES]}", args.stage)
    from typ.config import load_config

    load_config(root / args.params)  # fail on bad params before Prefect starts
    _setup_env(root)
    from flows.pipeline import pipeline_flow, run_stage

    if args.stage == "all":
        pipeline_flow(params=args.params, root=str(root))
    else:
        run_stage(args.stage, params=args.params, root=str(root))
    return 0


def _cmd_check(args) -> int:
    from typ.config import as_dict, load_config

    import yaml

    cfg = load_config(Path(args.root) / args.params)
    print(yaml.safe_dump({"profile": cfg.profile, **{s: as_dict(cfg.block(s)) for s in cfg.STAGES}},
                         sort_keys=False), end="")
    return 0


def _cmd_report(args) -> int:
    from typ.report import write_summary

    path = write_summary(Path(args.root))
    print(f"wrote {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="typ", description="typ: turn single-agent LiDAR datasets into collaborative ones (Transfer Your Perspective).")
    parser.add_argument("--root", default=".", help="project root holding params.yaml (default: .)")
    parser.add_argument("--params", default="params.yaml", help="params file relative to the root")
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p = sub.add_parser("run", help="run one stage's Prefect flow, or `all` for the whole pipeline")
    p.add_argument("stage", help=f"one of: all, {', '.join(STAGES)}")
    p.set_defaults(fn=_cmd_run)
    p = sub.add_parser("check", help="load and validate params.yaml; print the values in effect")
    p.set_defaults(fn=_cmd_check)
    p = sub.add_parser("report", help="write reports/summary.md from the stage metrics and benches")
    p.set_defaults(fn=_cmd_report)
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
