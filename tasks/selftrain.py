"""Stage ``selftrain`` (TYP §3.4): enhance the stage-2 adapter in the target domain.

The target domain is single-agent: no reference agent's cloud exists there. Two ways to
still fine-tune the adapter F_AD on it, jointly with the source (simulated CAV) tuples:

- **dummy ego** — for the target's own views, (x_r, y_r) = (the ego's view, its box map)
  with an empty ego, x_e = 0^{H×W×C}: the output side sees real target clouds;
- **self-training** — sample a reference pose on a labelled vehicle of a target scene,
  generate x̂_r with the current model from (x_e', y_r), and train on (x̂_r, x_e', y_r): the
  input side sees real target ego clouds.

Each can be switched off, as can the adversarial adaptation of the source encoder (then the
source tuples are encoded by E_tgt and the adapter is trained anew: "no adaptation"), so
TYP Table 4's ablation is one params change. The UNet stays frozen throughout.
"""
from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from tasks import generate
from tasks.stage2 import build_adapter, encode, fit_adapter
from tasks.training import seed_everything
from tasks.voxel_data import ViewSet
from typ.config import GenerateConfig, SelftrainConfig, Stage2Config, as_dict
from typ.errors import TypError
from typ.formats.opv2v import list_agents, list_scenarios, list_timestamps, read_scene
from typ.voxel import Grid


@dataclass(frozen=True)
class Variant:
    """One row of TYP Table 4."""

    name: str
    discriminator: bool
    self_training: bool
    dummy_ego: bool


#: TYP Table 4's rows, in its order
TABLE4 = (Variant("no_adaptation", False, False, False), Variant("disc", True, False, False),
          Variant("disc_st", True, True, False), Variant("disc_st_dummy", True, True, True))


def variant_of(cfg: SelftrainConfig) -> Variant:
    """The variant the switches in params ask for (named like its Table 4 row when it is one)."""
    for v in TABLE4:
        if (v.discriminator, v.self_training, v.dummy_ego) == (cfg.discriminator, cfg.self_training, cfg.dummy_ego):
            return v
    name = "_".join(n for n, on in (("disc", cfg.discriminator), ("st", cfg.self_training),
                                    ("dummy", cfg.dummy_ego)) if on) or "no_adaptation"
    return Variant(name, cfg.discriminator, cfg.self_training, cfg.dummy_ego)


def variants_to_run(cfg: SelftrainConfig) -> list[Variant]:
    chosen = variant_of(cfg)
    if not cfg.ablation:
        return [chosen]
    return list(TABLE4) + ([chosen] if chosen not in TABLE4 else [])


Latents = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


def dummy_ego_tuples(x_vq, y_vq, views: ViewSet, batch_size: int = 8) -> Latents:
    """(x_r^f, y_r^f, x_e^f) for target ego views with x_e = 0 (TYP §3.4, first solution)."""
    index = np.arange(len(views))
    x, y = views.occupancy(index), views.box_maps(index)
    return encode(x_vq, y_vq, x, y, np.zeros_like(x), batch_size)


def pseudo_references(split_root: Path, cfg: SelftrainConfig, generate_cfg: GenerateConfig, grid: Grid,
                      rng: np.random.Generator) -> list[generate.Reference]:
    """Up to ``cfg.pseudo_references`` reference poses, one per target frame in turn, each on a
    labelled vehicle inside [min_distance, max_distance] drawn with ``rng`` (only egos are read)."""
    band = dataclasses.replace(generate_cfg, min_distance=cfg.min_distance, max_distance=cfg.max_distance)
    skipped = generate.new_skip_counts()
    frames = []
    for folder in list_scenarios(split_root):
        ego_id = list_agents(folder)[0]
        frames += [read_scene(folder, ts, agents=[ego_id]).ego for ts in list_timestamps(folder)]
    refs: list[generate.Reference] = []
    for ego in frames:
        if len(refs) == cfg.pseudo_references:
            break
        ids = sorted(generate.candidate_ids(ego, band, skipped))
        if ids:
            vid = int(rng.choice(ids))
            refs.append(generate.build_reference(ego, int(np.flatnonzero(ego.box_ids == vid)[0]), grid))
    if not refs:
        raise TypError(split_root, "selftrain.min_distance/max_distance",
                       "target scenes with labelled vehicles inside the distance band (for pseudo references)",
                       f"none in {len(frames)} frames")
    return refs


def pseudo_tuples(refs: list[generate.Reference], models: generate.Models, seed: int,
                  batch_size: int = 8) -> tuple[Latents, np.ndarray]:
    """Generate x̂_r for each reference with ``models`` and encode (x̂_r, y_r, x_e') with E_tgt."""
    x_e = np.stack([r.x_e for r in refs]).astype(np.float32)
    y_r = np.stack([r.y_r for r in refs]).astype(np.float32)
    occupancy = sample_batched(x_e, y_r, models, seed, batch_size)
    return encode(models.x_vq, models.y_vq, occupancy.astype(np.float32), y_r, x_e, batch_size), occupancy


def sample_batched(x_e: np.ndarray, y_r: np.ndarray, models: generate.Models, seed: int,
                   batch_size: int = 8) -> np.ndarray:
    """:func:`tasks.generate.generate_occupancy` in batches (batch i seeded ``seed + i``)."""
    return np.concatenate([generate.generate_occupancy(x_e[i:i + batch_size], y_r[i:i + batch_size], models, seed + i)
                           for i in range(0, len(x_e), batch_size)])


def concat(*parts: Latents) -> Latents:
    return tuple(torch.cat([p[k] for p in parts]) for k in range(3))


def no_adaptation(stage2_cfg: Stage2Config, ldm, schedule: str, train_timesteps: int, source_tgt: Latents, *,
                  out: Path, log_fn: Callable[[dict, int], None]):
    """Stage 2 without adaptation: a fresh adapter on source tuples encoded by E_tgt, stage 2's recipe."""
    seed_everything(stage2_cfg.seed)  # before the adapter's initial weights are drawn
    return fit_adapter(build_adapter(stage2_cfg, ldm), ldm, schedule, train_timesteps, *source_tgt,
                       name="selftrain.no_adaptation", seed=stage2_cfg.seed, lr=stage2_cfg.lr,
                       epochs=stage2_cfg.epochs, batch_size=stage2_cfg.batch_size,
                       checkpoint_every=stage2_cfg.checkpoint_every, key_extra=as_dict(stage2_cfg), out=out,
                       log_fn=log_fn)


def finetune(cfg: SelftrainConfig, variant: Variant, base, ldm, schedule: str, train_timesteps: int,
             pool: Latents, *, out: Path, log_fn: Callable[[dict, int], None]):
    """Joint fine-tuning of a copy of ``base`` on the pooled source and target tuples."""
    return fit_adapter(copy.deepcopy(base), ldm, schedule, train_timesteps, *pool, name=f"selftrain.{variant.name}",
                       seed=cfg.seed, lr=cfg.lr, epochs=cfg.epochs, batch_size=cfg.batch_size,
                       checkpoint_every=cfg.checkpoint_every, key_extra={**as_dict(cfg), "variant": variant.name},
                       out=out, log_fn=log_fn)
