"""Flow ``stage1``: encode target ego views, train P(x|y) per seed, tune post-processing on val."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from prefect import flow

from flows.common import Timer, finish_stage, plain_task, training_task
from tasks import stage1 as stage
from tasks.voxel_data import load_views
from tasks.vqvae import load_model as load_vqvae
from typ.config import load_config
from typ.tracking import stage_run

STAGE = "stage1"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def stage1_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.stage1
    store, out = root_path / block.input, root_path / block.out
    x_vq, y_vq = (load_vqvae(root_path / block.vqvae / k) for k in ("x", "y"))
    train = stage.train_views(block, root_path)
    val = load_views(store, dataset=block.dataset, split=block.val_split).head(block.eval_views)
    metrics: dict = {"train_views": len(train), "val_views": len(val)}
    with stage_run(STAGE, cfg, root=root_path) as run:
        latents, cond = plain_task(stage.encode_views, "encode")(x_vq, y_vq, train, dihedral=True)
        stage.check_latents(block, latents.shape[-1], cfg.source)
        val_true, _ = val.batch(np.arange(len(val)))
        _, val_cond = stage.encode_views(x_vq, y_vq, val)
        for seed in stage.replica_seeds(block.seed, block.replicas):
            with Timer() as timer:
                model = training_task(f"train-ldm-seed{seed}", lambda: stage.train(
                    block, latents, cond, seed=seed, views=len(train), out=out, log_fn=run.metrics))
            logits = plain_task(stage.sample_logits, "sample-val")(
                model, x_vq, val_cond, cfg=block, generator=torch.Generator().manual_seed(seed + 1))
            thresholds = stage.tune_thresholds(logits, val_true, block, seed)
            stage.save_model(model, block, thresholds, stage.replica_dir(out, seed))
            metrics[f"seed_{seed}"] = {"seconds_training": round(timer.seconds, 3), "val_iou": thresholds["iou"],
                                       "postprocess": thresholds}
            if seed == block.seed:
                run.log_model("stage1-ldm", model, {"z_t": model.normalize(latents[:2]),
                                                    "t": torch.tensor([0, block.train_timesteps - 1]),
                                                    "cond": model.normalize_cond(cond[:2])})
        finish_stage(STAGE, run, metrics, root_path,
                     artifacts=[stage.replica_dir(out, block.seed) / "config.json"])
    return metrics
