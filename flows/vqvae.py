"""Flow ``vqvae``: train the x and y VQ-VAEs on target ego views, then measure reconstruction."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from prefect import flow

from flows.common import Timer, finish_stage, plain_task, training_task
from models.vqvae import PooledBoxMap
from tasks import vqvae as stage
from tasks.voxel_data import load_views
from typ.config import load_config
from typ.tracking import stage_run

STAGE = "vqvae"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def vqvae_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.vqvae
    store, out = root_path / block.input, root_path / block.out
    train = load_views(store, dataset=block.dataset, split=block.train_split)
    held_out = load_views(store, dataset=block.dataset, split=block.eval_split)
    stage.check_grid(train, block, cfg.source)
    metrics: dict = {"train_views": len(train), "eval_views": len(held_out)}
    with stage_run(STAGE, cfg, root=root_path) as run:
        for kind in stage.KINDS:
            with Timer() as timer:
                model = training_task(f"train-{kind}-seed{block.seed}", lambda: stage.train_one(
                    kind, block, train, out=out, log_fn=run.metrics))
            if isinstance(model, PooledBoxMap):  # nothing learned: y^f is the box map averaged per cell
                metrics[kind] = {"encoding": "pool"}
                continue
            scores = plain_task(stage.evaluate, f"validate-{kind}")(model, kind, held_out, threshold=block.threshold,
                                                                     batch_size=block.batch_size)
            metrics[kind] = {**scores, "seconds_training": round(timer.seconds, 3)}
            x_example, y_example = train.batch(np.arange(min(2, len(train))))
            run.log_model(f"vqvae-{kind}", model, x_example if kind == "x" else y_example, output="logits")
        finish_stage(STAGE, run, metrics, root_path,
                     artifacts=[(out / "x" / "config.json", "x"), (out / "y" / "config.json", "y")])
    return metrics
