"""Flow ``generate``: the collaborative dataset, one Prefect task per single-agent scenario."""
from __future__ import annotations

import dataclasses
from pathlib import Path

from prefect import flow

from flows.common import per_scene_stage
from pipelines.typ.pipeline_typ import TYPPipeline
from tasks import generate as stage
from tasks.ingest import READERS, read_frames, write_single_agent
from tasks.scene_stage import SceneStage
from typ.config import GenerateSet, load_config
from typ.errors import TypError
from typ.io import hash_files, output_lock
from typ.sensors import resolve

STAGE = "generate"


def load_generator(root: Path, cfg) -> stage.Generator:
    """The generator ``selftrain`` wrote for replica ``stage1.seed`` (the first), with the
    sampler ``generate`` asks for and every dataset's sensor height."""
    from pipelines.typ.pipeline_typ import generator_dir

    folder = generator_dir(root / cfg.generate.generator, cfg.stage1.seed)
    pipe = TYPPipeline.from_pretrained(folder)
    pipe = dataclasses.replace(pipe, sampler=cfg.generate.sampler, num_inference_steps=cfg.generate.sample_steps)
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    return stage.Generator(pipe, dict(cfg.voxelize.mount_height), hash_files(files)[:16], cfg.simulate.azimuth_step_deg)


@flow(name=STAGE, log_prints=False, validate_parameters=False)
def generate_flow(params: str = "params.yaml", root: str = ".") -> dict:
    root_path = Path(root)
    cfg = load_config(root_path / params)
    block = cfg.generate
    out = root_path / block.out
    generator = load_generator(root_path, cfg)

    return per_scene_stage(STAGE, cfg, root_path, SceneStage(
        out=out, plan=lambda: stage.plan(block, root_path / block.input, out),
        work=stage.run_scenario,
        work_kwargs={"cfg": block, "generator": generator, "out": out},
        label=lambda item: f"{item[0].dataset}/{item[0].split}/{item[1].name}", summarize=stage.summarize,
        unchanged=stage.unchanged))


def generate_external(fmt: str, input_path: Path, out: Path, *, root: Path, params: str,
                      references_per_frame: int | None = None, roadside_units: int | None = None,
                      compose: str | None = None, sensor: str | None = None) -> dict:
    """``typ generate``: KITTI / nuScenes / Waymo frames -> collaborative OPV2V scenarios under ``out``.

    The frames are first written as single-agent OPV2V scenarios under
    ``<out>/single_agent/<fmt>/``, then generated like the simulator's target split into
    ``<out>/<fmt>/frames/<scenario>/`` (real ego + generated references), skipping scenarios
    whose inputs, params and models are unchanged (``sensor``: the frames' LiDAR preset, ``--sensor``;
    unset, the format's own or the one a drive's scans show). It holds the generate stage's lock on ``out``
    (:func:`typ.io.output_lock`) while it writes.
    """
    cfg = load_config(root / params)
    block = cfg.generate
    overrides = {k: v for k, v in (("references_per_frame", references_per_frame),
                                    ("roadside_units", roadside_units), ("compose", compose)) if v is not None}
    if compose is not None and compose not in stage.COMPOSE:
        raise TypError("typ generate", "--compose", f"one of {list(stage.COMPOSE)}", compose)
    if overrides:
        block = dataclasses.replace(block, **overrides)
        block.check("typ generate", "--references/--rsu")
    # generate.compose applies as in the stage: hybrid and cast views cast the dataset's LiDAR
    # preset (typ.sensors), which the single-agent yaml names
    generator = load_generator(root, cfg)
    # the written yamls name their LiDAR; a yaml without one is the format's (or --sensor's) preset
    lidar = resolve(sensor or READERS[fmt].preset, where="typ generate", field="--sensor")
    generator = dataclasses.replace(generator, mount_height={**generator.mount_height, fmt: lidar.mount_height})
    gset = GenerateSet(dataset=fmt, split="frames", references="vehicles")
    with output_lock(STAGE, out):
        folders = write_single_agent(read_frames(fmt, input_path, sensor=sensor), out / "single_agent" / fmt,
                                     inside=out)
        results = [stage.run_scenario((gset, f), cfg=block, generator=generator, out=out) for f in folders]
    return stage.summarize(results)
