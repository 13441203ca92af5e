"""``typ show``: PNGs of any OPV2V-layout scenario, simulated, generated or real.

For one timestamp of a scenario folder (``scenario/agent/timestamp.pcd|.yaml``) it writes

- ``<scenario>_<timestamp>_<agent>.png``: that agent's cloud from above, its labelled boxes,
  the other agents' sensors as arrows (:func:`typ.viz.bev_figure`);
- ``<scenario>_<timestamp>_agents.png``: every agent side by side;
- ``<scenario>_<timestamp>_<agent>_range.png``: its range image, when the sensor is known
  (``--sensor``, the simulated scenario's domain, or a generated set named after a domain);
- for a generated scenario (``generate``'s ``_typ.json`` lists its ``generated_agents``),
  ``<scenario>_<timestamp>_<agent>_sample.png`` per generated agent: the ego's cloud, x_e′,
  the generated view, the true view, the re-simulated view and the error map, with scores.

The true view of a generated agent comes from the simulated scenario of the same name
(``<sim>/<dataset>/<split>/<scenario>``; ``<sim>`` defaults to the ``sim`` folder beside the
generated root, as ``data/generated`` and ``data/sim``): the simulated agent's own file when
it stands where the generated one does — a ``cavs`` set keeps the CAV ids; a ``vehicles`` set
names an agent ``<ego id><vehicle id>`` (:func:`tasks.generate.build_reference`) — otherwise
the simulator's world cast again from the generated pose (:mod:`tasks.sim_truth`).
A folder of scenarios (a generated or simulated split) shows each of them.
"""
from __future__ import annotations

import logging
import math
import typing
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tasks.generate import MANIFEST as GENERATED_MANIFEST
from tasks.sim_truth import job_sensor, scenario_job, true_view
from typ import viz
from typ.config import GenerateSet
from typ.errors import TypError
from typ.formats.opv2v import list_agents, list_timestamps, read_scene
from typ.geometry import invert
from typ.io import fit_name, read_json_or_none
from typ.metrics.truth import chamfer_distance, occupancy_iou
from typ.resim import EGO_CAR_LWH, resimulate
from typ.scene import AgentView, Scene
from typ.sim.sensor import DOMAINS, SensorSpec, domain_spec
from typ.voxel import Grid, points_to_reference, voxel_centers, voxelize

#: what typ's records name as the writer of a ``typ show`` picture (:func:`typ.io.written_by`)
SHOW = "show"

log = logging.getLogger("typ.show")
#: what a generated set's references are (GenerateSet.references)
REFERENCE_KINDS = typing.get_args(typing.get_type_hints(GenerateSet)["references"])
COLOR_MODES = ("height", "class")
#: a file truth counts as standing where the generated agent does within these
SAME_POSE_M, SAME_POSE_DEG = 0.05, 0.5


@dataclass(frozen=True)
class ShowOptions:
    """grid: voxelizes views for the error map and scores (the models' grid); window: the BEV
    shown; color: ``height`` or ``class`` (where the cloud has point classes); sensor: a domain
    name for range images and re-simulation (None: from the data); sim_root: the simulated
    scenarios' root (None: the ``sim`` folder beside the generated root); resim: draw the
    re-simulated view."""

    grid: Grid
    window: viz.Window
    color: str = "height"
    sensor: str | None = None
    sim_root: Path | None = None
    resim: bool = True

    def __post_init__(self) -> None:
        if self.color not in COLOR_MODES:
            raise TypError("typ show", "--color", f"one of {COLOR_MODES}", self.color)
        if self.sensor is not None and self.sensor not in DOMAINS:
            raise TypError("typ show", "--sensor", f"one of {sorted(DOMAINS)}", self.sensor)


def is_scenario(folder: Path) -> bool:
    """A scenario folder: its sub-folders (agents) hold ``.yaml`` files."""
    return folder.is_dir() and any(a.is_dir() and any(a.glob("*.yaml")) for a in folder.iterdir()
                                   if not a.name.startswith("."))


def scenario_folders(path: Path) -> list[Path]:
    """``path`` itself when it is a scenario, else the scenarios directly under it."""
    path = Path(path)
    if not path.is_dir():
        raise TypError(path, "PATH", "an OPV2V-layout scenario folder or a folder of them", "not a folder")
    if is_scenario(path):
        return [path]
    found = [p for p in sorted(path.iterdir()) if not p.name.startswith(".") and is_scenario(p)]
    if not found:
        raise TypError(path, "PATH", "an OPV2V-layout scenario folder (agent/timestamp.yaml) or a folder of them",
                       "no agent folders with .yaml files")
    return found


def show(path: Path, out: Path, opts: ShowOptions, timestamp: str | None = None) -> list[Path]:
    """Every PNG of the module doc for each scenario under ``path``; returns the files written."""
    written = []
    for folder in scenario_folders(path):
        stamps = list_timestamps(folder)
        ts = stamps[0] if timestamp is None else str(timestamp)
        if ts not in stamps:
            raise TypError(folder, "--timestamp", f"one of {stamps[:8]}{' ...' if len(stamps) > 8 else ''}", ts)
        written += show_scenario(folder, ts, out, opts)
    return written


def show_scenario(folder: Path, timestamp: str, out: Path, opts: ShowOptions) -> list[Path]:
    scene = read_scene(folder, timestamp)
    generated, references = generated_agents(folder)  # a bad manifest stops the scenario before any PNG

    def png(what: str) -> Path:  # a long scenario name is shortened to fit NAME_MAX, not refused
        return out / fit_name(f"{folder.name}_{timestamp}_{what}.png")

    def save(fig, path: Path) -> Path:  # --out is the user's folder: replace only what `typ show` wrote
        return viz.save_png(fig, path, stage=SHOW)

    sim_folder = simulated_counterpart(folder, opts)
    job = scenario_job(sim_folder) if sim_folder is not None else None
    spec = sensor_of(folder, opts, job)
    written = []
    panels = []
    for agent_id, view in scene.agents.items():
        panel = agent_panel(scene, agent_id, opts)
        panels.append(panel)
        written.append(save(viz.panels_figure([panel], colorbar_z=_colorbar(view, opts)),
                                    png(agent_id)))
        if spec is not None:
            written.append(save(viz.range_figure(view.points, spec, title=f"{folder.name} {timestamp} "
                                                         f"agent {agent_id}"), png(f"{agent_id}_range")))
    title = f"{folder.name}  {timestamp}  ({len(scene.agents)} agents, first = ego)"
    colorbar = None if opts.color == "class" and all(v.semantics is not None for v in scene.agents.values()) \
        else opts.grid.z_range
    written.append(save(viz.panels_figure(panels, title=title, colorbar_z=colorbar),
                                png("agents")))
    for agent_id in generated:
        if agent_id not in scene.agents:
            continue
        sample = generated_sample(scene, agent_id, references=references,
                                  sim_folder=sim_folder, job=job, spec=spec, opts=opts)
        written.append(save(viz.sample_figure(sample, opts.grid, window=opts.window),
                                    png(f"{agent_id}_sample")))
    return written


def generated_agents(folder: Path) -> tuple[list[str], str]:
    """(the agents ``generate`` wrote into a scenario, its reference kind) from its ``_typ.json``;
    ``([], "vehicles")`` for a scenario that is not generated. A manifest that says it is generated
    but whose list is not agent names, or whose kind is unknown, raises TypError naming it."""
    path = folder / GENERATED_MANIFEST
    manifest = read_json_or_none(path)
    if not isinstance(manifest, dict) or "generated_agents" not in manifest:
        return [], "vehicles"
    agents, references = manifest["generated_agents"], manifest.get("references", "vehicles")
    if not isinstance(agents, list) or not all(isinstance(a, str) for a in agents):
        raise TypError(path, "generated_agents", "a list of agent folder names", agents)
    if references not in REFERENCE_KINDS:
        raise TypError(path, "references", f"one of {list(REFERENCE_KINDS)}", references)
    return agents, references


def _colorbar(view: AgentView, opts: ShowOptions):
    return None if (opts.color == "class" and view.semantics is not None) else opts.grid.z_range


def agent_panel(scene: Scene, agent_id: str, opts: ShowOptions) -> viz.Panel:
    view = scene.agents[agent_id]
    others = [a for a in scene.agents if a != agent_id]
    markers = [_planar(invert(view.pose) @ scene.agents[a].pose) for a in others]
    role = "ego" if agent_id == scene.ego_id else "agent"
    semantics = view.semantics if opts.color == "class" else None
    return viz.cloud_panel(f"{role} {agent_id}", view.points, grid=opts.grid, window=opts.window, boxes=view.boxes,
                           semantics=semantics, markers=markers,
                           note=f"{len(view.points)} points, {len(view.boxes)} boxes")


def _planar(transform: np.ndarray) -> np.ndarray:
    """[x, y, yaw] of a (4, 4) transform's origin and heading in the xy-plane."""
    return np.array([transform[0, 3], transform[1, 3], math.atan2(transform[1, 0], transform[0, 0])])


def simulated_counterpart(folder: Path, opts: ShowOptions) -> Path | None:
    """The simulated scenario ``<sim>/<dataset>/<split>/<name>`` of a scenario folder, if it exists;
    a simulated scenario is its own counterpart."""
    folder = folder.resolve()
    if scenario_job(folder) is not None:
        return folder
    if len(folder.parents) < 4:
        return None
    root = opts.sim_root or folder.parents[2].parent / "sim"
    candidate = Path(root) / folder.parent.parent.name / folder.parent.name / folder.name
    return candidate if candidate.is_dir() else None


def sensor_of(folder: Path, opts: ShowOptions, job) -> SensorSpec | None:
    """The LiDAR of a scenario's views: ``--sensor``, the simulated job's, or a set named after a domain."""
    if opts.sensor is not None:
        return domain_spec(opts.sensor).sensor
    if job is not None:
        return job_sensor(job)
    dataset = folder.resolve().parent.parent.name
    return domain_spec(dataset).sensor if dataset in DOMAINS else None


def own_car_box(spec: SensorSpec) -> np.ndarray:
    """(1, 7) the reference vehicle's own body around its sensor, enlarged by 0.4 m a side: the ego
    saw it, the reference's LiDAR does not (so re-simulation must drop those points)."""
    return np.array([[0.0, 0.0, 0.75 - spec.mount_height, EGO_CAR_LWH[0] + 0.8, EGO_CAR_LWH[1] + 0.8, 2.0, 0.0]])


def reference_vehicle(agent_id: str, ego: AgentView, references: str) -> int | None:
    """The vehicle carrying a generated agent's sensor: ``<ego id><vehicle id>`` in a ``vehicles``
    set, the agent's own id in a ``cavs`` set, None for a roadside unit (negative id)."""
    if agent_id.startswith("-"):
        return None
    if references == "cavs":
        return int(agent_id) if agent_id.isdigit() else None
    rest = agent_id[len(ego.agent_id):] if agent_id.startswith(ego.agent_id) else ""
    return int(rest) if rest.isdigit() and int(rest) in set(ego.box_ids.tolist()) else None


def generated_sample(scene: Scene, agent_id: str, *, references: str, sim_folder: Path | None, job,
                     spec: SensorSpec | None, opts: ShowOptions) -> dict:
    """The :func:`typ.viz.sample_figure` dict of one generated agent, with its scores."""
    ego, ref = scene.ego, scene.agents[agent_id]
    x_e = points_to_reference(ego.points, ego.pose, ref.pose)
    sample: dict = {"name": f"{scene.scenario} {scene.timestamp} {agent_id}", "ego": ego.points,
                    "ego_boxes": ego.boxes, "reference_in_ego": _planar(invert(ego.pose) @ ref.pose),
                    "x_e": x_e, "generated": ref.points, "boxes": ref.boxes}
    vehicle = reference_vehicle(agent_id, ego, references)
    truth, how = find_truth(scene.timestamp, ref.pose, vehicle, sim_folder, job)
    if truth is not None:
        sample["true"] = truth
        sample["titles"] = {"true": f"true view ({how})"}
    if opts.resim and spec is not None:
        sample["resim"] = resimulate(x_e[:, :3], spec, exclude_boxes=own_car_box(spec))
    scores: dict = {}
    if truth is not None:
        gen_occ, true_occ = voxelize(ref.points, opts.grid), voxelize(truth, opts.grid)
        scores.update(occupancy_iou(gen_occ, true_occ))
        a, b = voxel_centers(gen_occ, opts.grid), voxel_centers(true_occ, opts.grid)
        scores["chamfer_m"] = chamfer_distance(a, b) if len(a) and len(b) else float("nan")
        if "resim" in sample:
            scores["resim_iou"] = occupancy_iou(voxelize(sample["resim"], opts.grid), true_occ)["iou"]
    sample["scores"] = scores
    return sample


def find_truth(timestamp: str, pose: np.ndarray, vehicle: int | None, sim_folder: Path | None,
               job) -> tuple[np.ndarray | None, str]:
    """(points, how) of the true view at ``pose``: ``"simulated file"``, ``"re-cast"`` or (None, ``"none"``)."""
    if sim_folder is None:
        return None, "none"
    if vehicle is not None and (sim_folder / str(vehicle) / f"{timestamp}.yaml").is_file():
        view = read_scene(sim_folder, timestamp, agents=[str(vehicle)]).ego
        rel = invert(view.pose) @ pose
        if np.hypot(*rel[:2, 3]) < SAME_POSE_M and abs(math.degrees(math.atan2(rel[1, 0], rel[0, 0]))) < SAME_POSE_DEG:
            return view.points, "simulated file"
    if job is None:
        log.info("no re-cast truth in %s: its simulator key does not match this code", sim_folder)
        return None, "none"
    points, _ = true_view(job, timestamp, pose, vehicle_id=vehicle, where=str(sim_folder))
    return points, "re-cast"
