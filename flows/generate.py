"""Flow ``generate``: the collaborative dataset, one Prefect task per single-agent scenario."""
from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

from prefect import flow

from flows.common import per_scene_stage
from tasks import generate as stage
from tasks import stage1
from tasks.edit import edit_figure, edit_view
from tasks.ingest import read_frames, write_single_agent
from tasks.stage2 import load_adapter
from tasks.voxelize import to_grid
from tasks.vqvae import load_model as load_vqvae
from typ.config import GenerateSet, load_config
from typ.errors import TypError
from typ.formats.opv2v import list_agents, list_scenarios, read_scene, write_scene
from typ.io import atomic_path, hash_files
from typ.store import list_scenes, store_grid, stored_grid
from typ.viz import save_png
from typ.voxel import Grid

STAGE = "generate"


def load_models(root: Path, cfg) -> stage.Models:
    block = cfg.generate
    paths = [root / block.vqvae / "x" / "model.pt", root / block.vqvae / "y" / "model.pt",
             root / block.stage1 / "model.pt", root / block.adapter / "adapter.pt"]
    for p in paths:
        if not p.exists():
            raise TypError(p, "file", "a trained model (run the earlier stages first: dvc repro)", "missing")
    ldm, saved = stage1.load_model(root / block.stage1)
    adapter = load_adapter(paths[3], ldm)
    sampling = stage1.sampling_config(cfg.stage1, saved, block.sampler, block.sample_steps)
    return stage.Models(load_vqvae(root / block.vqvae / "x"), load_vqvae(root / block.vqvae / "y"), ldm,
                        adapter, saved["postprocess"], sampling, hash_files(paths)[:16])


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def generate_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.generate
    out = root_path / block.out
    grid = store_grid(root_path / cfg.stage1.input, "stage1.input")
    models = load_models(root_path, cfg)

    def plan():
        items, stale = [], []
        for gset in block.sets:
            folders = list_scenarios(root_path / block.input / gset.dataset / gset.split)
            items += [(gset, f) for f in folders]
            wanted = {f.name for f in folders}
            stale += [p for p in (out / gset.dataset / gset.split).glob("*")
                      if p.is_dir() and not p.name.startswith(".") and p.name not in wanted]
        # a (dataset, split) dropped from generate.sets: its generated scenarios go too
        kept = {(g.dataset, g.split) for g in block.sets}
        stale += [p for p in out.glob("*/*") if p.is_dir() and not p.name.startswith(".")
                  and (p.parent.name, p.name) not in kept]
        return items, stale

    return per_scene_stage(STAGE, cfg, root_path, out=out, plan=plan, work=stage.run_scenario,
                           work_kwargs={"cfg": block, "models": models, "grid": grid, "out": out},
                           label=lambda item: f"{item[0].dataset}/{item[0].split}/{item[1].name}", summarize=stage.summarize)


def model_grid(root: Path, cfg) -> Grid:
    """The grid the models were trained on: the voxel store's, else the params' (same by construction)."""
    stored = list_scenes(root / cfg.stage1.input)
    return stored_grid(stored[0].path) if stored else to_grid(cfg.voxelize.grid)


def generate_external(fmt: str, input_path: Path, out: Path, *, root: Path, params: str,
                      references_per_frame: int | None = None, roadside_units: int | None = None) -> dict:
    """``typ generate``: KITTI / nuScenes / Waymo frames -> collaborative OPV2V scenarios under ``out``.

    The frames are first written as single-agent OPV2V scenarios under
    ``<out>/single_agent/<fmt>/``, then generated like the simulator's target split into
    ``<out>/<fmt>/frames/<scenario>/`` (real ego + generated references), skipping scenarios
    whose inputs, params and models are unchanged.
    """
    cfg = load_config(root / params)
    block = cfg.generate
    overrides = {k: v for k, v in (("references_per_frame", references_per_frame),
                                    ("roadside_units", roadside_units)) if v is not None}
    if overrides:
        block = dataclasses.replace(block, **overrides)
        block.check("typ generate", "--references/--rsu")
    models, grid = load_models(root, cfg), model_grid(root, cfg)
    folders = write_single_agent(read_frames(fmt, input_path), out / "single_agent" / fmt)
    gset = GenerateSet(dataset=fmt, split="frames", references="vehicles")
    results = [stage.run_scenario((gset, f), cfg=block, models=models, grid=grid, out=out) for f in folders]
    return stage.summarize(results)


def edit_scenario(scenario: Path, timestamp: str, edit, out: Path, *, root: Path, params: str,
                  agent: str | None = None, seed: int = 0) -> tuple[Path, Path]:
    """``typ edit``: a copy of ``scenario`` under ``out`` with one view regenerated after ``edit``,
    and beside it ``<scenario>_<timestamp>_<agent>_edit.png``, the view before and after.
    Returns (the copy, the PNG)."""
    cfg = load_config(root / params)
    models, grid = load_models(root, cfg), model_grid(root, cfg)
    agents = list_agents(scenario)
    agent = agent or agents[0]
    if agent not in agents:
        raise TypError(scenario, "--agent", f"one of {agents}", agent)
    scene = read_scene(scenario, timestamp, agents=[agent])
    result = edit_view(scene.agents[agent], edit, models, grid, seed)
    target = out / scenario.name
    with atomic_path(target) as tmp:
        shutil.copytree(scenario, tmp, ignore=shutil.ignore_patterns("_*", ".*"))
        write_scene(dataclasses.replace(scene, scenario=tmp.name, agents={agent: result.view}), tmp)
    render = save_png(edit_figure(scene.agents[agent], result, grid,
                                  title=f"typ edit: {scenario.name} {timestamp} agent {agent}"),
                      out / f"{scenario.name}_{timestamp}_{agent}_edit.png")
    return target, render
