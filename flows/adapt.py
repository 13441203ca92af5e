"""Flow ``adapt``: adversarial adaptation of the source encoder/decoder to the target latent space."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.common import Timer, numeric_leaves, write_metrics
from tasks import adapt as stage
from tasks.voxel_data import load_views
from tasks.vqvae import load_model as load_vqvae
from typ.config import load_config
from typ.tracking import stage_run

STAGE = "adapt"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def adapt_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.adapt
    store, out = root_path / block.input, root_path / block.out
    target_vq = load_vqvae(root_path / block.vqvae / "x")
    # source scenarios are multi-agent: every agent's view is a training sample
    src_train = load_views(store, dataset=block.source_dataset, split=block.source_split, ego_only=False)
    src_eval = load_views(store, dataset=block.source_dataset, split=block.source_eval_split, ego_only=False)
    tgt_train = load_views(store, dataset=block.target_dataset, split=block.target_split)
    tgt_eval = load_views(store, dataset=block.target_dataset, split=block.target_eval_split)
    metrics: dict = {"source_views": len(src_train), "target_views": len(tgt_train)}
    with stage_run(STAGE, cfg, root=root_path) as run:
        with Timer() as timer:
            source_vq, disc = task(stage.train, name="train", cache_policy=NO_CACHE)(
                block, target_vq, src_train, tgt_train, out=out, log_fn=run.metrics)
        metrics["seconds_training"] = round(timer.seconds, 3)
        evaluate = task(stage.evaluate, name="evaluate", cache_policy=NO_CACHE)
        # "before" = no adaptation: the target VQ-VAE applied to source views as they are
        metrics["before"] = evaluate(target_vq, target_vq, src_eval, tgt_eval, disc, n=block.eval_views)
        metrics["after"] = evaluate(source_vq, target_vq, src_eval, tgt_eval, disc, n=block.eval_views)
        stage.save(source_vq, disc, out)
        run.log_model("adapt-source-vq", source_vq, src_train.batch(np.arange(min(2, len(src_train))))[0],
                      output="logits")
        path = write_metrics(STAGE, metrics, root_path)
        run.metrics(numeric_leaves(metrics))
        run.artifact(path)
    return metrics
