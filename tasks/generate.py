"""Stage ``generate`` (TYP §4.1, §4.5): turn single-agent frames into collaborative ones.

For each frame of a single-agent scenario (only the ego's view is read), reference poses
are sampled from the labelled vehicles — one set per scenario, kept for the whole sequence
(a sensor on the vehicle's roof at the ego's
mounting height, facing the vehicle's heading). For each reference: y_r = the boxes in the
reference frame (the ego car added, the reference vehicle itself removed), x_e' = the ego
cloud moved there; x^f_e' = E_tgt(x_e') drives the adapter, P(x_r | x_e', y_r) is sampled,
post-processed with the stage-1 thresholds and turned back into points (occupied voxel
centres). The reference is written as another agent (id: the ego's id followed by the
vehicle's id, so the real ego still sorts first) of an OPV2V-layout scenario
(``<out>/<dataset>/<split>/<scenario>/<agent>/<timestamp>.pcd|.yaml``) so existing CAV
loaders read it. Skipped references and frames are counted with their reason.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipelines.typ import Reference, TYPPipeline, reference_at
from typ.config import GenerateConfig, GenerateSet, as_dict
from typ.errors import TypError
from typ.formats.opv2v import list_agents, list_scenarios, list_timestamps, read_scene, scenario_sensor, write_scene
from typ.geometry import points_in_boxes, pose_to_matrix
from typ.io import SCENARIO_MANIFEST, atomic_path, hash_files, hash_obj, read_json_or_none, write_manifest
from typ.scene import AgentView, Scene, vehicle_mask
from typ.voxel import Grid
from typ.registry import declare

STAGE = "generate"
#: what the stage reads and writes (dvc.yaml is generated from it; kind and torch: typ.registry.STAGES)
DECLARATION = declare("generate", data=("data/sim/target/pretrain", "data/sim/real_cav/train",
                                        "artifacts/selftrain/generator"),
                      params=("stage1", "voxelize"), outs=("data/generated",))
MANIFEST = SCENARIO_MANIFEST
#: why a reference view or a scenario was not generated, counted per stage run
SKIP_REASONS = ("reference_too_close", "reference_out_of_range", "scenario_without_candidate_vehicle",
                "roadside_unit_without_ground", "reference_view_empty")


def candidate_ids(ego: AgentView, cfg, skipped: dict[str, int]) -> set[int]:
    """Ids of the ego's labelled vehicles inside the distance band [cfg.min_distance, cfg.max_distance]
    (``cfg``: the generate or selftrain block).

    Only vehicles carry a reference sensor: pedestrians, cyclists and signs (KITTI, Waymo,
    nuScenes labels) are never candidates and are not counted as skipped.
    """
    vehicle = vehicle_mask(ego.box_labels)  # only vehicles carry a reference sensor
    dist = np.hypot(ego.boxes[:, 0], ego.boxes[:, 1])
    near = vehicle & (dist < cfg.min_distance)
    far = vehicle & (dist > cfg.max_distance)
    skipped["reference_too_close"] += int(near.sum())
    skipped["reference_out_of_range"] += int(far.sum())
    return set(ego.box_ids[vehicle & ~near & ~far].tolist())


def sample_references(egos: list[AgentView], cfg: GenerateConfig, rng: np.random.Generator,
                      skipped: dict[str, int]) -> list[int]:
    """Vehicle ids that become reference agents of a scenario (TYP §4.5).

    A reference agent is one vehicle for the whole sequence, as a CAV is in OPV2V (every
    agent has a view at every timestamp), so only vehicles inside the band in every frame
    qualify; ``references_per_frame`` of them are drawn with ``rng``.
    """
    per_frame = [candidate_ids(ego, cfg, skipped) for ego in egos]
    common = sorted(set.intersection(*per_frame)) if per_frame else []
    if not common:
        skipped["scenario_without_candidate_vehicle"] += 1
        return []
    k = min(cfg.references_per_frame, len(common))
    return sorted(int(i) for i in rng.choice(common, size=k, replace=False))


def build_reference(ego: AgentView, index: int, grid: Grid) -> Reference:
    """The reference on labelled vehicle ``ego.boxes[index]``: a sensor on its roof at the ego's
    mounting height, facing its heading; its id is the ego's id followed by the vehicle's."""
    box = ego.boxes[index]
    in_ego = pose_to_matrix([box[0], box[1], 0.0, 0.0, np.degrees(box[6]), 0.0])
    # OpenCOOD takes the agent folder that sorts first as the ego: prefixing the vehicle id
    # with the ego's id keeps the real ego first and stays unique per vehicle
    return reference_at(ego, ego.pose @ in_ego, f"{ego.agent_id}{int(ego.box_ids[index])}",
                        int(ego.box_ids[index]), grid)


def roadside_poses(ego: AgentView, cfg: GenerateConfig, rng: np.random.Generator,
                   skipped: dict[str, int]) -> list[np.ndarray]:
    """``cfg.roadside_units`` sensor poses (4x4 float64, world) fixed for the whole sequence.

    Each stands on ground the ego observed in its first frame — a point within 0.3 m of the
    ground level (the 5th height percentile of the ego's cloud), inside the distance band and
    outside every labelled box — at the ego's mounting height, facing the ego. A roadside
    unit needs no labelled vehicle, so frames without one still get a reference view.
    """
    xyz = ego.points[:, :3].astype(np.float64)
    if len(xyz) == 0:
        skipped["roadside_unit_without_ground"] += cfg.roadside_units
        return []
    ground = np.percentile(xyz[:, 2], 5)
    dist = np.hypot(xyz[:, 0], xyz[:, 1])
    ok = (np.abs(xyz[:, 2] - ground) < 0.3) & (dist >= cfg.min_distance) & (dist <= cfg.max_distance)
    if len(ego.boxes):
        ok &= ~points_in_boxes(xyz, ego.boxes).any(axis=1)
    spots = xyz[ok]
    if len(spots) == 0:
        skipped["roadside_unit_without_ground"] += cfg.roadside_units
        return []
    picks = spots[rng.choice(len(spots), size=min(cfg.roadside_units, len(spots)), replace=False)]
    return [ego.pose @ pose_to_matrix([x, y, 0.0, 0.0, np.degrees(np.arctan2(-y, -x)), 0.0]) for x, y, _ in picks]


def cav_references(scene: Scene, grid: Grid) -> list[Reference]:
    """References at the scenario's own cooperating agents' true poses (their clouds unused).

    Every CAV gets one, however far (within communication range, as the dataset has it): the
    result must be a drop-in for the real split, with the same agents, for the fusion
    benchmark's generated-vs-oracle comparison; the distance band applies to sampled poses only.
    """
    ego = scene.ego
    refs = []
    for agent_id, view in scene.agents.items():
        if agent_id != ego.agent_id:
            exclude = int(agent_id) if agent_id.lstrip("-").isdigit() else None
            refs.append(reference_at(ego, view.pose, agent_id, exclude, grid))
    return refs


def scenario_key(folder: Path, gset: GenerateSet, cfg: GenerateConfig, digest: str, grid: Grid) -> str:
    files = sorted(p for p in folder.rglob("*") if p.is_file() and not p.name.startswith(("_", ".")))
    if gset.references == "vehicles":
        # only the ego's files are read; a change to another agent's must not regenerate
        ego = list_agents(folder)[0]
        files = [p for p in files if p.parent.name == ego]
    return hash_obj({"inputs": hash_files(files), "set": as_dict(gset),
                     "cfg": {k: v for k, v in as_dict(cfg).items() if k not in ("sets", "workers")},
                     "models": digest, "grid": grid.to_dict()})


def plan(cfg: GenerateConfig, source: Path, out: Path) -> tuple[list[tuple[GenerateSet, Path]], list[Path]]:
    """The scenarios to generate, ``(set, folder)`` for each scenario under ``source/<dataset>/<split>``
    of ``cfg.sets``, and the stale outputs: what lies where generated scenarios go that the plan
    does not make (its input is gone, its set was dropped from ``cfg.sets``, someone else's)."""
    items, stale = [], []
    for gset in cfg.sets:
        folders = list_scenarios(source / gset.dataset / gset.split)
        items += [(gset, f) for f in folders]
        wanted = {f.name for f in folders}
        stale += [p for p in _visible(out / gset.dataset / gset.split) if p.name not in wanted]
    sets = {(g.dataset, g.split) for g in cfg.sets}
    for dropped in (p for p in out.glob("*/*") if p.is_dir() and (p.parent.name, p.name) not in sets
                    and not p.name.startswith(".") and not p.parent.name.startswith(".")):
        stale += _visible(dropped)
    return items, stale


def _visible(folder: Path) -> list[Path]:
    """What ``folder`` holds, sorted, without hidden names (temporaries, the watched run's params)."""
    return sorted(p for p in folder.glob("*") if not p.name.startswith("."))


def new_skip_counts() -> dict[str, int]:
    return {k: 0 for k in SKIP_REASONS}


def _scenario_state(item: tuple[GenerateSet, Path], cfg: GenerateConfig, generator: "Generator", out: Path):
    """(output folder, grid, key, result fields, the skipped result when the stored output has the key)."""
    gset, folder = item
    target = out / gset.dataset / gset.split / folder.name
    grid = generator.grid(_sensor_name(folder, gset))
    key = scenario_key(folder, gset, cfg, generator.digest, grid)
    base = {"scenario": f"{gset.dataset}/{gset.split}/{folder.name}", "set": f"{gset.dataset}/{gset.split}"}
    manifest = read_json_or_none(target / MANIFEST)
    done = {**base, "skipped": "unchanged", **manifest["counts"]} if manifest and manifest.get("key") == key else None
    return target, grid, key, base, done


def _sensor_name(folder: Path, gset: GenerateSet) -> str:
    """The LiDAR of a scenario's ego: the one its yaml names (a real dataset typ read), else its dataset's."""
    return scenario_sensor(folder) or gset.dataset


def unchanged(item: tuple[GenerateSet, Path], *, cfg: GenerateConfig, generator: "Generator", out: Path) -> dict | None:
    """The skipped result of a scenario whose generated output has its key, else None (without
    computing the key, which hashes the scenario's inputs, when nothing was generated for it)."""
    gset, folder = item
    if not (out / gset.dataset / gset.split / folder.name / MANIFEST).is_file():
        return None
    return _scenario_state(item, cfg, generator, out)[4]


def run_scenario(item: tuple[GenerateSet, Path], *, cfg: GenerateConfig, generator: "Generator",
                 out: Path) -> dict:
    """Generate and write every reference of one scenario; skip it when its key is unchanged."""
    gset, folder = item
    target, grid, key, base, done = _scenario_state(item, cfg, generator, out)
    if done is not None:
        return done
    t0 = time.perf_counter()
    skipped = new_skip_counts()
    agents = list_agents(folder)
    # vehicles: the ego's cloud and labels only; cavs: the cooperating agents' poses too
    read_agents = agents[:1] if gset.references == "vehicles" else agents
    scenes = [read_scene(folder, ts, agents=read_agents, dataset=gset.dataset, split=gset.split)
              for ts in list_timestamps(folder)]
    frames: list[tuple[Scene, list[Reference]]] = []
    if gset.references == "vehicles":
        rng = np.random.default_rng([cfg.seed, int(hash_obj(folder.name)[:8], 16)])
        chosen = sample_references([s.ego for s in scenes], cfg, rng, skipped)
        rsu_poses = roadside_poses(scenes[0].ego, cfg, rng, skipped) if cfg.roadside_units else []
        for scene in scenes:
            index = {int(i): n for n, i in enumerate(scene.ego.box_ids)}
            refs = [build_reference(scene.ego, index[vid], grid) for vid in chosen]
            # OpenCOOD's convention: roadside units have negative ids and sort after the vehicles
            refs += [reference_at(scene.ego, pose, f"-{k + 1}", None, grid) for k, pose in enumerate(rsu_poses)]
            frames.append((scene, refs))
    else:
        frames = [(scene, cav_references(scene, grid)) for scene in scenes]
    for _, refs in frames:
        # an empty view is still written (every agent has a view at every timestamp); counted
        skipped["reference_view_empty"] += sum(not r.x_e.any() and not r.y_r.any() for r in refs)
    all_refs = [r for _, refs in frames for r in refs]
    sensor = generator.sensor(_sensor_name(folder, gset)) if all_refs and generator.pipe.needs_sensor(cfg.compose) \
        else None
    clouds = iter(generator.pipe.generate(all_refs, grid, cfg.seed, sensor=sensor, compose=cfg.compose, cast=cfg.cast)
                  if all_refs else [])
    counts = {"frames": len(frames), "references": len(all_refs), "generated_points": 0, **skipped}
    with atomic_path(target, stage=STAGE, inside=out) as tmp:
        tmp.mkdir(parents=True)
        for scene, refs in frames:
            views = {scene.ego.agent_id: scene.ego}  # the real ego; cavs: the real CAVs are replaced
            for ref in refs:
                points = next(clouds)
                counts["generated_points"] += len(points)
                views[ref.agent_id] = AgentView(ref.agent_id, points, ref.pose, ref.boxes, ref.labels, ref.ids,
                                                where=f"generated:{folder.name}/{ref.agent_id}/{scene.timestamp}")
            # write_scene writes into a folder named like the scenario: name it after tmp
            write_scene(dataclasses.replace(scene, scenario=tmp.name, agents=views), tmp)
        write_manifest(tmp, STAGE, {"key": key, "counts": counts, "references": gset.references, "compose": cfg.compose,
                                    "generated_agents": sorted({r.agent_id for _, refs in frames for r in refs})})
    return {**base, "skipped": None, "seconds": time.perf_counter() - t0, **counts}


def summarize(results: list[dict]) -> dict:
    done = [r for r in results if r["skipped"] is None]
    metrics = {"scenarios": len(results), "generated": len(done),
               "skipped_unchanged": sum(r["skipped"] == "unchanged" for r in results)}
    for k in ("frames", "references", "generated_points", *SKIP_REASONS):
        metrics[k] = sum(r.get(k, 0) for r in results)
    for name in sorted({r["set"] for r in results}):
        mine = [r for r in results if r["set"] == name]
        metrics[name.replace("/", "_")] = {"scenarios": len(mine), "references": sum(r.get("references", 0) for r in mine)}
    seconds = sum(r.get("seconds", 0.0) for r in done)
    refs_done = sum(r["references"] for r in done)
    metrics["seconds_generating"] = round(seconds, 3)
    if refs_done:
        metrics["seconds_per_reference"] = round(seconds / refs_done, 3)
    if metrics["references"]:
        metrics["points_per_reference"] = round(metrics["generated_points"] / metrics["references"], 1)
    return metrics


@dataclass(frozen=True)
class Generator:
    """The trained generator with what a stage run needs around it: its sensor grids per dataset
    (``mount_height``: each dataset's LiDAR height) and a digest of its files for the skip keys."""

    pipe: TYPPipeline
    mount_height: dict
    digest: str
    azimuth_step_deg: float = 0.4   #: the simulated sensors' azimuth step (re-simulation casts with it)

    def grid(self, dataset: str) -> Grid:
        """The generator's grid in the frame of ``dataset``'s LiDAR (a domain or a sensor name)."""
        from typ.sensors import mount_height

        return self.pipe.grid.for_sensor(mount_height(dataset, self.mount_height))

    def sensor(self, dataset: str):
        """The LiDAR re-simulation and cast views cast with in ``dataset``'s reference views (a
        re-simulation-conditioned generator, ``generate.compose: hybrid`` or ``cast``): a simulated
        domain's (at the simulator's azimuth step) or a real dataset's preset (:mod:`typ.sensors`)."""
        from typ.sensors import SENSORS
        from typ.sim.sensor import DOMAINS, domain_spec

        if dataset in DOMAINS:
            return domain_spec(dataset, azimuth_step_deg=self.azimuth_step_deg).sensor
        if dataset not in SENSORS:
            raise TypError("params.yaml", "selftrain.generator / generate.compose",
                           f"a known LiDAR for dataset {dataset!r}: re-simulation and cast views cast with it "
                           f"(one of {sorted(SENSORS)})", dataset)
        return SENSORS[dataset]
