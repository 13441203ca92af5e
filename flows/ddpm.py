"""Flow ``ddpm``: LiDAR DDPM on the target domain — feature nets, Table II rows, TYP side by side, report."""
from __future__ import annotations

import logging
from pathlib import Path

import torch
from prefect import flow

from flows.common import PrefectTrainings, Timer, numeric_leaves, plain_task, write_metrics
from tasks import ddpm as stage
from tasks import ddpm_report
from tasks.lidar_features import train_feature_nets
from typ import distributed
from typ.config import load_config
from typ.tracking import stage_run

STAGE = "ddpm"
LOG = logging.getLogger(__name__)


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def ddpm_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.ddpm
    out = root_path / block.out
    reps = stage.representations(block, cfg.source)
    train, test = (plain_task(stage.load_scans, f"scans-{split}")(root_path / block.input, domain=block.domain,
                                                                   split=split, ego_only=block.ego_only)
                   for split in (block.train_split, block.test_split))
    reason = stage.unlabelled([*train, *test], f"{block.domain}/{block.train_split} and {block.test_split}")
    if reason is not None:
        return skipped(cfg, root_path, reason, {"train_scans": len(train), "test_scans": len(test)})
    with stage_run(STAGE, cfg, root=root_path) as run:
        with Timer() as timer:
            nets, feature_scores = plain_task(train_feature_nets, "feature-nets")(
                block.features, block.seed, reps["range"].layout, train, test, out=out, log_fn=run.metrics)
            run.log_model("ddpm-frid-net", nets.range_net, torch.zeros(1, 1, *reps["range"].layout.shape))
            run.log_model("ddpm-fpvd-net", nets.voxel_net, torch.zeros(1, nets.grid.shape[2], *nets.grid.shape[:2]))
            with PrefectTrainings() as trainings:
                rows, trained, examples = stage.table(block, reps, train, test, nets, out=out, log_fn=run.metrics,
                                                      trainings=trainings)
            for tm in trained.values():
                c = tm.model.config
                run.log_model(f"ddpm-{tm.name}", tm.model, {"x_t": torch.zeros(1, c["channels"], c["height"], c["width"]),
                                                            "t": torch.tensor([0])})
            if block.latent.samplers:
                rows += plain_task(stage.latent_route, "latent-route")(cfg, root_path, nets)
            round_trips = stage.round_trips(reps, test)
            paths = ddpm_report.write_all(root_path / block.reports, rows, examples, round_trips=round_trips,
                                          feature_scores=feature_scores, context=stage.context(block, train, test)) \
                if distributed.is_main() else []
        metrics = ddpm_report.metrics_of(rows, round_trips, feature_scores, stage.model_summary(trained),
                                         {"train_scans": len(train), "test_scans": len(test),
                                          "seconds_total": round(timer.seconds, 3)})
        path = write_metrics(STAGE, metrics, root_path)
        run.metrics(numeric_leaves(metrics))
        for p in (path, *paths):
            run.artifact(p)
    return metrics


def skipped(cfg, root: Path, reason: str, counts: dict) -> dict:
    """The stage's run, metrics and report files when it cannot train on its data: each says why."""
    LOG.warning("ddpm: not run: %s", reason)
    with stage_run(STAGE, cfg, root=root) as run:
        (root / cfg.ddpm.out).mkdir(parents=True, exist_ok=True)
        paths = ddpm_report.write_skipped(root / cfg.ddpm.reports, reason)
        metrics = {"skipped": reason, **counts}
        path = write_metrics(STAGE, metrics, root)
        run.metrics(numeric_leaves(metrics))
        for p in (path, *paths):
            run.artifact(p)
    return metrics
