"""``typ edit``: one view of a scenario regenerated after box edits (TYP Fig. 5), written as a copy.

Not a pipeline stage: a user's command, run on any OPV2V-layout scenario with the generator the
``selftrain`` stage trained (the one ``generate`` uses, :func:`flows.generate.load_generator`).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from flows import generate as generate_flow
from tasks.edit import STAGE as EDIT, copy_scenario, edit_figure, edit_target, edit_view
from typ.config import load_config
from typ.errors import TypError
from typ.formats.opv2v import list_agents, read_scene, scenario_sensor, write_scene
from typ.io import atomic_path, fit_name, write_manifest
from typ.registry import COMPOSE_MODES
from typ.viz import save_png


def edit_scenario(scenario: Path, timestamp: str, edit, out: Path, *, root: Path, params: str,
                  agent: str | None = None, seed: int = 0, dataset: str | None = None,
                  compose: str | None = None) -> tuple[Path, Path]:
    """``typ edit``: a copy of ``scenario`` under ``out`` with one view regenerated after ``edit``,
    and beside it ``<scenario>_<timestamp>_<agent>_edit.png``, the view before and after.
    Returns (the copy, the PNG).

    dataset: whose LiDAR took the scenario (its ``voxelize.mount_height``); by default the name
    of the folder two levels up (``<dataset>/<split>/<scenario>``), else the target domain.
    compose: what the edited footprint is made of (:data:`tasks.edit.COMPOSE`); by default
    ``cast`` when the params' ``generate.compose`` is, else ``generated``. A cast edit casts the
    LiDAR the scenario's yaml names (a real dataset typ read), else ``dataset``'s.

    The copy replaces only an earlier ``typ edit`` copy (typ's record of it matches it); an ``out`` where
    the copy would be, hold or lie inside ``scenario`` is refused (:func:`tasks.edit.edit_target`)."""
    scenario = scenario.resolve()
    target = edit_target(scenario, out)
    cfg = load_config(root / params)
    if dataset is None:
        guess = scenario.parent.parent.name
        dataset = guess if guess in cfg.voxelize.mount_height else cfg.stage1.dataset
    generator = generate_flow.load_generator(root, cfg)
    grid = generator.grid(dataset)
    agents = list_agents(scenario)
    agent = agent or agents[0]
    if agent not in agents:
        raise TypError(scenario, "--agent", f"one of {agents}", agent)
    scene = read_scene(scenario, timestamp, agents=[agent])
    # the stage's compose where typ edit can remake a footprint with it, else TYP's sample alone
    compose = compose or (cfg.generate.compose if COMPOSE_MODES[cfg.generate.compose].editable else "generated")
    sensor = generator.sensor(scenario_sensor(scenario) or dataset) if COMPOSE_MODES[compose].casts else None
    result = edit_view(scene.agents[agent], edit, generator, grid, seed, compose=compose, sensor=sensor,
                       cast=cfg.generate.cast)
    with atomic_path(target, stage=EDIT) as tmp:
        copy_scenario(scenario, tmp)
        write_scene(dataclasses.replace(scene, scenario=tmp.name, agents={agent: result.view}), tmp)
        write_manifest(tmp, EDIT, {"source": str(scenario), "timestamp": timestamp, "agent": agent, "seed": seed,
                                   "compose": compose, "edit": dataclasses.asdict(edit)})
    render = save_png(edit_figure(scene.agents[agent], result, grid,
                                  title=f"typ edit: {scenario.name} {timestamp} agent {agent}"),
                      target.parent / fit_name(f"{scenario.name}_{timestamp}_{agent}_edit.png"), stage=EDIT)
    return target, render
