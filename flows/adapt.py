"""Flow ``adapt``: adversarial adaptation of the source encoder/decoder to the target latent space."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from prefect import flow

from flows.common import Timer, finish_stage, training_task
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
    tgt_train = load_views(store, dataset=block.target_dataset, split=block.target_split)
    metrics: dict = {"source_views": len(src_train), "target_views": len(tgt_train)}
    with stage_run(STAGE, cfg, root=root_path) as run:
        with Timer() as timer:
            source_vq, disc = training_task(f"train-source_vq-seed{block.seed}", lambda: stage.train(
                block, target_vq, src_train, tgt_train, out=out, log_fn=run.metrics))
        metrics["seconds_training"] = round(timer.seconds, 3)
        # training-side figures on training views (held-out ones are the evaluate stage's):
        # "before" = no adaptation, the target VQ-VAE applied to source views as they are
        for name, encoder in (("before", target_vq), ("after", source_vq)):
            metrics[name] = {**stage.translation_scores(encoder, target_vq, src_train, tgt_train, n=block.eval_views),
                             "disc_accuracy": stage.discriminator_accuracy(disc, encoder, target_vq, src_train, tgt_train,
                                                                           n=block.eval_views)}
        stage.save(source_vq, disc, out)
        run.log_model("adapt-source-vq", source_vq, src_train.batch(np.arange(min(2, len(src_train))))[0],
                      output="logits")
        finish_stage(STAGE, run, metrics, root_path)
    return metrics
