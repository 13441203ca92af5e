"""Flow ``stage2``: train the adapter on source tuples; score reference views of held-out target scenes."""
from __future__ import annotations

from pathlib import Path

import torch
from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.common import Timer, numeric_leaves, write_metrics
from models.postprocess import postprocess
from tasks import stage1, stage2 as stage
from tasks.pairs import iter_pairs, stack
from tasks.vqvae import load_model as load_vqvae
from typ.config import load_config
from typ.store import store_grid
from typ.tracking import stage_run

STAGE = "stage2"


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def stage2_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.stage2
    out, sim = root_path / block.out, root_path / block.sim
    grid = store_grid(root_path / block.voxels, "stage2.voxels")
    target_x, y_vq = load_vqvae(root_path / block.vqvae / "x"), load_vqvae(root_path / block.vqvae / "y")
    source_x = load_vqvae(root_path / block.adapt / "source_vq")
    ldm, saved = stage1.load_model(root_path / block.stage1)
    thresholds = saved["postprocess"]
    metrics: dict = {}
    with stage_run(STAGE, cfg, root=root_path) as run:
        train_pairs = stack(list(iter_pairs(sim / block.source_domain / block.source_split, grid)))
        x_r, y_r, x_e = stage.encode(source_x, y_vq, *train_pairs)
        metrics["train_pairs"] = len(x_r)
        with Timer() as timer:
            adapter = task(stage.train, name="train", cache_policy=NO_CACHE)(
                block, ldm, saved["schedule"], saved["train_timesteps"], x_r, y_r, x_e, out=out, log_fn=run.metrics)
        metrics["seconds_training"] = round(timer.seconds, 3)

        # held-out target scenes: the ego's real cloud, the reference view as hidden truth
        pairs = list(iter_pairs(sim / block.target_domain / block.target_eval_split, grid, ego_only=True))
        pairs = pairs[:block.eval_pairs]
        xt_r, yt_r, xt_e = stack(pairs)
        _, yf, xef = stage.encode(target_x, y_vq, xt_r, yt_r, xt_e)
        truth = xt_r > 0.5
        metrics["eval_pairs"] = len(pairs)

        def sample(features, seed):
            logits = stage1.sample_logits(ldm, target_x, yf, cfg=cfg.stage1,
                                          generator=torch.Generator().manual_seed(seed), adapter_features=features)
            occ = postprocess(logits, low=thresholds["low"], high=thresholds["high"],
                              noise_std=thresholds["noise_std"], generator=torch.Generator().manual_seed(seed))
            return occ.numpy()

        score = task(stage1.generation_metrics, name="score", cache_policy=NO_CACHE)
        metrics["naive_copy"] = score(xt_e > 0.5, truth, grid)
        metrics["stage1_only"] = score(sample(None, block.seed), truth, grid)
        with Timer() as timer:
            generated = sample(stage.adapter_features(adapter, ldm, xef), block.seed)
        metrics["typ"] = score(generated, truth, grid)
        metrics["typ"]["seconds_per_sample"] = round(timer.seconds / max(len(pairs), 1), 3)
        stage.save(adapter, block, out)
        run.log_model("stage2-adapter", adapter, ldm.normalize(x_e[:2]))  # F_AD(x^f_e') -> one map per UNet level
        path = write_metrics(STAGE, metrics, root_path)
        run.metrics(numeric_leaves(metrics))
        run.artifact(path)
    return metrics
