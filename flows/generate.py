"""Flow ``generate``: the collaborative dataset, one Prefect task per single-agent scenario."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from diffusers import T2IAdapter
from prefect import flow

from flows.common import per_scene_stage
from tasks import generate as stage
from tasks import stage1
from tasks.training import load_torch
from tasks.vqvae import load_model as load_vqvae
from typ.config import load_config
from typ.errors import TypError
from typ.formats.opv2v import list_scenarios
from typ.io import hash_files
from typ.store import list_scenes, stored_grid

STAGE = "generate"


def load_models(root: Path, cfg) -> stage.Models:
    block = cfg.generate
    paths = [root / block.vqvae / "x" / "model.pt", root / block.vqvae / "y" / "model.pt",
             root / block.stage1 / "model.pt", root / block.stage2 / "adapter.pt"]
    for p in paths:
        if not p.exists():
            raise TypError(p, "file", "a trained model (run the earlier stages first: dvc repro)", "missing")
    ldm, saved = stage1.load_model(root / block.stage1)
    adapter_saved = load_torch(paths[3], "stage-2 adapter (run the stage2 stage")
    adapter = T2IAdapter(in_channels=ldm.config["latent_channels"], channels=list(ldm.config["block_out_channels"]),
                         num_res_blocks=adapter_saved["config"]["adapter_res_blocks"], downscale_factor=1,
                         adapter_type="full_adapter")
    adapter.load_state_dict(adapter_saved["state_dict"])
    sampling = dataclasses.replace(cfg.stage1, sampler=block.sampler, sample_steps=block.sample_steps,
                                   schedule=saved["schedule"], train_timesteps=saved["train_timesteps"], eta=0.0)
    return stage.Models(load_vqvae(root / block.vqvae / "x"), load_vqvae(root / block.vqvae / "y"), ldm,
                        adapter.eval(), saved["postprocess"], sampling, hash_files(paths)[:16])


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def generate_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.generate
    source = root_path / block.input / block.dataset / block.split
    out = root_path / block.out
    stored = list_scenes(root_path / cfg.stage1.input)
    if not stored:
        raise TypError(root_path / cfg.stage1.input, "voxel store", "voxelized scenes (run voxelize first)", "none")
    grid = stored_grid(stored[0].path)
    models = load_models(root_path, cfg)

    def plan():
        folders = list_scenarios(source)
        wanted = {f.name for f in folders}
        stale = [p for p in (out / block.dataset / block.split).glob("*")
                 if p.is_dir() and not p.name.startswith(".") and p.name not in wanted]
        return folders, stale

    return per_scene_stage(STAGE, cfg, root_path, out=out, plan=plan, work=stage.run_scenario,
                           work_kwargs={"cfg": block, "models": models, "grid": grid, "out": out},
                           label=lambda folder: folder.name, summarize=stage.summarize)
