"""Flow ``stage1``: encode target ego views, train P(x|y), tune post-processing, sample the held-out split."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from prefect import flow

from flows.common import Timer, numeric_leaves, plain_task, write_metrics
from models.postprocess import postprocess
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
    splits = {name: load_views(store, dataset=block.dataset, split=split)
              for name, split in (("train", block.train_split), ("val", block.val_split), ("test", block.eval_split))}
    grid = splits["train"].grid
    metrics: dict = {f"{k}_views": len(v) for k, v in splits.items()}
    with stage_run(STAGE, cfg, root=root_path) as run:
        latents, cond = plain_task(stage.encode_views, "encode")(x_vq, y_vq, splits["train"], mirror=True)
        stage.check_latents(block, latents.shape[-1], cfg.source)
        with Timer() as timer:
            model = plain_task(stage.train, "train")(block, latents, cond, out=out, log_fn=run.metrics)
        metrics["seconds_training"] = round(timer.seconds, 3)
        run.log_model("stage1-ldm", model, {"z_t": model.normalize(latents[:2]),
                                            "t": torch.tensor([0, block.train_timesteps - 1]),
                                            "cond": model.normalize_cond(cond[:2])})

        def generate(views, seed):
            views = views.head(block.eval_views)
            x_true, _ = views.batch(np.arange(len(views)))
            _, y_lat = stage.encode_views(x_vq, y_vq, views)
            logits = stage.sample_logits(model, x_vq, y_lat, cfg=block, generator=torch.Generator().manual_seed(seed))
            return logits, x_true

        val_logits, val_true = plain_task(generate, "sample-val")(splits["val"], block.seed + 1)
        thresholds = stage.tune_thresholds(val_logits, val_true, block, block.seed)
        with Timer() as timer:
            test_logits, test_true = plain_task(generate, "sample-test")(splits["test"], block.seed + 2)
        occupancy = postprocess(test_logits, low=thresholds["low"], high=thresholds["high"],
                                noise_std=thresholds["noise_std"], generator=torch.Generator().manual_seed(block.seed))
        truth = test_true.numpy() > 0.5
        metrics["generated"] = stage.generation_metrics(occupancy.numpy(), truth, grid)
        metrics["generated"]["seconds_per_sample"] = round(timer.seconds / max(len(test_true), 1), 3)
        with torch.no_grad():
            recon = torch.sigmoid(x_vq(test_true).logits) > 0.5
        metrics["vq_reconstruction"] = stage.generation_metrics(recon.numpy(), truth, grid)
        metrics["postprocess"] = thresholds
        stage.save_model(model, block, thresholds, out)
        path = write_metrics(STAGE, metrics, root_path)
        run.metrics(numeric_leaves(metrics))
        run.artifact(path)
        run.artifact(out / "postprocess.json")
    return metrics
