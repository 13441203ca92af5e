"""Probe the adapt stage (TYP Eq. 8-10): retrain it with other settings beside `make run`'s, and
score each the way the evaluate stage does (the adaptation figure of reports/generation_accuracy.md).

    python bench/adapt_probe.py '{"epochs": 8}' '{"adv_weight": 4}' ...

Each argument is a JSON object of adapt-block overrides, checked as params.yaml's are
(:func:`typ.config.load_config`); ``adv_weight`` (not a config field) scales Eq. 9's adversarial
term L_src, which the stage weighs 1 as the paper does. ``{}`` retrains the stage as configured.

It prints one line per model, beside two references:
- before: source test views through the target VQ-VAE (E_tgt, G_tgt): no adaptation;
- floor: target test views through the target VQ-VAE: the JSD left by the VQ-VAE alone, which
  no encoder feeding G_tgt can go below in expectation;
- each model: source test views through its E_src and G_tgt (:func:`tasks.adapt.translation_scores`),
  its JSD change against before, and the share of the gap before → floor that it closes.
Models train in /tmp/adapt_probe/ (their checkpoints resume); artifacts/ is not touched. The
numbers in reports/generation_ablation.md's adaptation section come from here.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Callable

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from models.losses import hinge_g_loss  # noqa: E402
from tasks import adapt  # noqa: E402
from tasks.voxel_data import load_views  # noqa: E402
from tasks.vqvae import load_model as load_vqvae  # noqa: E402
from typ.config import AdaptConfig, load_config  # noqa: E402

OUT = Path("/tmp/adapt_probe")


def variant(root: Path, text: str) -> tuple[AdaptConfig, float]:
    """The adapt block with ``text``'s overrides (checked by the config) and the adversarial weight."""
    changes = json.loads(text)
    weight = float(changes.pop("adv_weight", 1.0))
    if weight <= 0:
        raise ValueError(f"adv_weight: expected a positive number, got {weight}")
    return load_config(root / "params.yaml", overrides={"adapt": changes}).adapt, weight


def weighted_g_loss(weight: float) -> Callable[[torch.Tensor], torch.Tensor]:
    """Eq. 10's L_src times ``weight``."""
    return lambda logits: weight * hinge_g_loss(logits)


def gap_closed(before: float, after: float, floor: float) -> float:
    """Share of the JSD gap between no adaptation and the VQ-VAE's own floor that ``after`` closes."""
    return (before - after) / (before - floor) if before != floor else float("nan")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("variants", nargs="+", help="JSON overrides of the adapt block (and adv_weight)")
    args = ap.parse_args()
    torch.set_num_threads(2)
    root = Path(".")
    cfg = load_config(root / "params.yaml")
    variants = [(text, *variant(root, text)) for text in args.variants]   # every bad one before any training
    block, ev = cfg.adapt, cfg.evaluate
    x_vq = load_vqvae(root / block.vqvae / "x")
    src_train = load_views(root / block.input, dataset=block.source_dataset, split=block.source_split, ego_only=False)
    tgt_train = load_views(root / block.input, dataset=block.target_dataset, split=block.target_split)
    src = load_views(root / ev.voxels, dataset=ev.source_domain, split=ev.source_split, ego_only=False)
    tgt = load_views(root / ev.voxels, dataset=ev.target_domain, split=ev.target_split)
    before = adapt.translation_scores(x_vq, x_vq, src, tgt)["jsd_r2dm"]
    floor = adapt.translation_scores(x_vq, x_vq, tgt, tgt)["jsd_r2dm"]
    print(f"{len(src)} source / {len(tgt)} target test views: JSD before {before:.3f}, floor {floor:.3f}", flush=True)
    original = adapt.hinge_g_loss
    try:
        for text, changed, weight in variants:
            adapt.hinge_g_loss = weighted_g_loss(weight)
            t0 = time.perf_counter()
            source_vq, _ = adapt.train(changed, x_vq, src_train, tgt_train, out=OUT / text.replace(" ", ""),
                                       log_fn=lambda values, step: None)
            seconds = time.perf_counter() - t0
            after = adapt.translation_scores(source_vq, x_vq, src, tgt)
            print(f"{text} ({seconds:.0f} s): JSD {after['jsd_r2dm']:.3f} "
                  f"({100 * (after['jsd_r2dm'] - before) / before:+.1f} %, "
                  f"{100 * gap_closed(before, after['jsd_r2dm'], floor):.0f} % of the gap to the floor), "
                  f"source reconstruction IoU {after['rec_iou_source']:.3f}", flush=True)
    finally:
        adapt.hinge_g_loss = original


if __name__ == "__main__":
    main()
