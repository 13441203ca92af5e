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
import torch

from models.postprocess import postprocess
from tasks import stage1
from tasks.stage2 import adapter_features
from typ.config import GenerateConfig, Stage1Config, as_dict
from typ.formats.opv2v import list_agents, list_timestamps, read_scene, write_scene
from typ.geometry import invert, pose_to_matrix, transform_boxes
from typ.io import atomic_path, hash_files, hash_obj, read_json_or_none, write_json
from typ.scene import AgentView, Scene
from typ.voxel import Grid, box_map, points_to_reference, voxel_centers, voxelize

MANIFEST = "_typ.json"
#: the ego's own car, which the ego's labels never contain but a reference sees
EGO_CAR_LWH = (4.5, 1.85, 1.5)


@dataclass(frozen=True)
class Models:
    """Everything generation needs, loaded once per stage run."""

    x_vq: object
    y_vq: object
    ldm: object
    adapter: object
    thresholds: dict
    sampling: Stage1Config
    digest: str


@dataclass(frozen=True)
class Reference:
    agent_id: str
    pose: np.ndarray        # (4, 4) float64 sensor-to-world
    boxes: np.ndarray       # (K, 7) in the reference frame
    labels: tuple[str, ...]
    ids: np.ndarray
    x_e: np.ndarray         # (C, H, W) bool, x_e'
    y_r: np.ndarray         # (1, H, W) bool


def candidate_ids(ego: AgentView, cfg: GenerateConfig, skipped: dict[str, int]) -> set[int]:
    """Ids of the ego's labelled vehicles inside the distance band [min_distance, max_distance]."""
    dist = np.hypot(ego.boxes[:, 0], ego.boxes[:, 1])
    near = dist < cfg.min_distance
    far = dist > cfg.max_distance
    skipped["reference_too_close"] += int(near.sum())
    skipped["reference_out_of_range"] += int(far.sum())
    return set(ego.box_ids[~near & ~far].tolist())


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
    box = ego.boxes[index]
    # the reference sensor sits at the ego's mounting height (same sensor), on the vehicle, facing its heading
    in_ego = pose_to_matrix([box[0], box[1], 0.0, 0.0, np.degrees(box[6]), 0.0])
    ref_pose = ego.pose @ in_ego
    keep = np.arange(len(ego.boxes)) != index
    ego_car = np.array([[0.0, 0.0, box[2], *EGO_CAR_LWH, 0.0]])
    boxes = transform_boxes(invert(in_ego), np.concatenate([ego.boxes[keep], ego_car]))
    labels = tuple(np.asarray(ego.box_labels, dtype=object)[keep]) + ("car",)
    ego_numeric = int(ego.agent_id) if ego.agent_id.lstrip("-").isdigit() else -1
    ids = np.concatenate([ego.box_ids[keep], [ego_numeric]])
    moved = points_to_reference(ego.points, ego.pose, ref_pose)
    # OpenCOOD takes the agent folder that sorts first as the ego: prefixing the vehicle id
    # with the ego's id keeps the real ego first and stays unique per vehicle
    return Reference(f"{ego.agent_id}{int(ego.box_ids[index])}", ref_pose, boxes, labels, ids,
                     voxelize(moved, grid).transpose(2, 0, 1), box_map(boxes, grid).transpose(2, 0, 1))


@torch.no_grad()
def generate_points(refs: list[Reference], models: Models, grid: Grid, seed: int) -> list[np.ndarray]:
    """Batched sampling for all references of a scenario: (N, 4) float32 clouds, intensity 0."""
    x_e = torch.from_numpy(np.stack([r.x_e for r in refs]).astype(np.float32))
    y_r = torch.from_numpy(np.stack([r.y_r for r in refs]).astype(np.float32))
    features = adapter_features(models.adapter, models.ldm, models.x_vq.encode_pre_quant(x_e))
    logits = stage1.sample_logits(models.ldm, models.x_vq, models.y_vq.encode_pre_quant(y_r), cfg=models.sampling,
                                  generator=torch.Generator().manual_seed(seed), adapter_features=features)
    t = models.thresholds
    occupancy = postprocess(logits, low=t["low"], high=t["high"], noise_std=t["noise_std"],
                            generator=torch.Generator().manual_seed(seed)).numpy()
    clouds = []
    for occ in occupancy:
        xyz = voxel_centers(occ.transpose(1, 2, 0), grid)
        clouds.append(np.concatenate([xyz, np.zeros((len(xyz), 1))], axis=1).astype(np.float32))
    return clouds


def scenario_key(folder: Path, cfg: GenerateConfig, models: Models, grid: Grid) -> str:
    files = sorted(p for p in folder.rglob("*") if p.is_file() and not p.name.startswith(("_", ".")))
    return hash_obj({"inputs": hash_files(files), "cfg": as_dict(cfg), "models": models.digest,
                     "grid": grid.to_dict()})


def run_scenario(folder: Path, *, cfg: GenerateConfig, models: Models, grid: Grid, out: Path) -> dict:
    """Generate and write every reference of one scenario; skip it when its key is unchanged."""
    target = out / cfg.dataset / cfg.split / folder.name
    key = scenario_key(folder, cfg, models, grid)
    base = {"scenario": folder.name}
    manifest = read_json_or_none(target / MANIFEST)
    if manifest is not None and manifest.get("key") == key:
        return {**base, "skipped": "unchanged", **manifest["counts"]}
    t0 = time.perf_counter()
    skipped = {"reference_too_close": 0, "reference_out_of_range": 0, "scenario_without_candidate_vehicle": 0,
               "reference_view_empty": 0}
    ego_id = list_agents(folder)[0]
    scenes = [read_scene(folder, ts, agents=[ego_id], dataset=cfg.dataset, split=cfg.split)
              for ts in list_timestamps(folder)]
    rng = np.random.default_rng([cfg.seed, int(hash_obj(folder.name)[:8], 16)])
    chosen = sample_references([s.ego for s in scenes], cfg, rng, skipped)
    frames: list[tuple[Scene, list[Reference]]] = []
    for scene in scenes:
        index = {int(i): n for n, i in enumerate(scene.ego.box_ids)}
        refs = [build_reference(scene.ego, index[vid], grid) for vid in chosen]
        # an empty view is still written (every agent has a view at every timestamp); counted
        skipped["reference_view_empty"] += sum(not r.x_e.any() and not r.y_r.any() for r in refs)
        frames.append((scene, refs))
    all_refs = [r for _, refs in frames for r in refs]
    clouds = iter(generate_points(all_refs, models, grid, cfg.seed) if all_refs else [])
    counts = {"frames": len(frames), "references": len(all_refs), "generated_points": 0, **skipped}
    with atomic_path(target) as tmp:
        tmp.mkdir(parents=True)
        for scene, refs in frames:
            agents = dict(scene.agents)
            for ref in refs:
                points = next(clouds)
                counts["generated_points"] += len(points)
                agents[ref.agent_id] = AgentView(ref.agent_id, points, ref.pose, ref.boxes, ref.labels, ref.ids,
                                                 where=f"generated:{folder.name}/{ref.agent_id}/{scene.timestamp}")
            # write_scene writes into a folder named like the scenario: name it after tmp
            write_scene(dataclasses.replace(scene, scenario=tmp.name, agents=agents), tmp)
        write_json(tmp / MANIFEST, {"key": key, "counts": counts, "generated_agents": sorted(
            {r.agent_id for _, refs in frames for r in refs})})
    return {**base, "skipped": None, "seconds": time.perf_counter() - t0, **counts}


def summarize(results: list[dict]) -> dict:
    done = [r for r in results if r["skipped"] is None]
    metrics = {"scenarios": len(results), "generated": len(done),
               "skipped_unchanged": sum(r["skipped"] == "unchanged" for r in results)}
    for k in ("frames", "references", "generated_points", "reference_too_close", "reference_out_of_range",
              "scenario_without_candidate_vehicle", "reference_view_empty"):
        metrics[k] = sum(r.get(k, 0) for r in results)
    seconds = sum(r.get("seconds", 0.0) for r in done)
    refs_done = sum(r["references"] for r in done)
    metrics["seconds_generating"] = round(seconds, 3)
    if refs_done:
        metrics["seconds_per_reference"] = round(seconds / refs_done, 3)
    if metrics["references"]:
        metrics["points_per_reference"] = round(metrics["generated_points"] / metrics["references"], 1)
    return metrics
