"""Scene editing (TYP Fig. 5): regenerate one view with boxes added, removed or moved.

The edited box map y' conditions stage 1; the view's own cloud, with the points inside the
boxes that were removed or moved taken out, conditions the adapter (x_e' = the edited view
itself). Only the BEV cells under an edited box — its old and its new footprint, with a
margin — take the generated occupancy; everywhere else the real points are kept as they
are, so an edit changes what it names and nothing else.

What the footprint cells get (``compose``, as ``generate.compose``):

- ``generated``: points drawn in the generated voxels (:func:`pipelines.typ.pipeline_typ.occupancy_to_points`);
- ``cast``: a scan of the view's own LiDAR (:mod:`typ.castview`): one scene of the view's
  surfels, the generated cells of the footprints standing on the road, and the added or moved
  vehicles as boxes, cast once from the view's sensor; the returns in the footprint cells are
  kept, on the sensor's beams. Real points behind an added or moved vehicle are dropped: the
  sensor cannot see through it. (The area a removed vehicle shadowed beyond its footprint stays
  as the sensor saw it, empty.) Carving is off: an edit puts vehicles where the view saw free road.
"""
from __future__ import annotations

import dataclasses
import os
import shutil
import stat
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from tasks.generate import Generator
from typ.config import CastConfig
from typ.errors import TypError
from typ.geometry import points_in_boxes
from typ.registry import COMPOSE_MODES
from typ.resim import EGO_CAR_LWH, in_mask
from typ.scene import AgentView
from typ.voxel import Grid, box_map, voxelize

#: metres around an edited box whose cells are regenerated too (shadows and box slack)
FOOTPRINT_MARGIN = 1.0
#: what the manifest of an edited copy names as its writer (typ.io.write_manifest)
STAGE = "edit"
#: what an edited footprint is made of (module doc): the compose modes that can remake one
COMPOSE = tuple(name for name, mode in COMPOSE_MODES.items() if mode.editable)
#: a real point counts as hidden behind an edited vehicle when its ray meets the box this far before it
OCCLUSION_SLACK_M = 0.1


@dataclass(frozen=True)
class BoxEdit:
    """Edits of one view's labelled boxes, in its sensor frame (metres, radians)."""

    remove: tuple[int, ...] = ()
    #: box id -> (dx, dy, dyaw)
    move: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    #: (x, y, yaw) or (x, y, yaw, l, w, h): a new car standing on the road
    add: tuple[tuple[float, ...], ...] = ()

    def is_empty(self) -> bool:
        return not (self.remove or self.move or self.add)


@dataclass(frozen=True)
class EditedView:
    view: AgentView           # boxes edited, points: real outside the footprints, generated inside
    footprint: np.ndarray     # (H, W) bool, the regenerated cells
    x_e: np.ndarray           # (C, H, W) bool conditioning cloud (edited boxes' points removed)
    y_r: np.ndarray           # (1, H, W) bool edited box map


def edit_boxes(view: AgentView, edit: BoxEdit, where: str = "typ edit") -> tuple[AgentView, np.ndarray, np.ndarray]:
    """The view with its boxes edited, and the (K_old, 7) old and (K_new, 7) new footprints touched."""
    ids = [int(i) for i in view.box_ids]
    for vid in (*edit.remove, *edit.move):
        if vid not in ids:
            raise TypError(where, "box id", f"one of the view's box ids {ids}", vid)
    boxes = view.boxes.copy()
    old, new = [], []
    for vid, (dx, dy, dyaw) in edit.move.items():
        k = ids.index(vid)
        old.append(boxes[k].copy())
        boxes[k, 0] += dx
        boxes[k, 1] += dy
        boxes[k, 6] = (boxes[k, 6] + dyaw + np.pi) % (2 * np.pi) - np.pi
        new.append(boxes[k].copy())
    keep = np.array([i not in edit.remove for i in ids], dtype=bool)
    old += [b for b, k in zip(view.boxes, keep) if not k]
    car_z = float(np.median(view.boxes[:, 2])) if len(view.boxes) else -1.0
    added, next_id = [], max(ids, default=0) + 1
    for k, spec in enumerate(edit.add):
        if len(spec) not in (3, 6) or not np.all(np.isfinite(spec)):
            raise TypError(where, f"--add[{k}]", "x,y,yaw or x,y,yaw,l,w,h (finite numbers)", spec)
        x, y, yaw, *lwh = spec
        added.append([x, y, car_z, *(lwh or EGO_CAR_LWH), yaw])
    added = np.array(added, dtype=np.float64).reshape(-1, 7)
    new += list(added)
    edited = dataclasses.replace(
        view, boxes=np.concatenate([boxes[keep], added]),
        box_labels=tuple(np.asarray(view.box_labels, dtype=object)[keep]) + ("car",) * len(added),
        box_ids=np.concatenate([view.box_ids[keep], np.arange(next_id, next_id + len(added))]))
    return edited, np.array(old, dtype=np.float64).reshape(-1, 7), np.array(new, dtype=np.float64).reshape(-1, 7)


def footprint_mask(boxes: np.ndarray, grid: Grid, margin: float = FOOTPRINT_MARGIN) -> np.ndarray:
    """(H, W) bool: the BEV cells under ``boxes`` grown by ``margin`` on every side."""
    grown = boxes.copy()
    grown[:, 3:5] += 2 * margin
    return box_map(grown, grid)[:, :, 0]


def edit_view(view: AgentView, edit: BoxEdit, generator: Generator, grid: Grid, seed: int, *,
              compose: str = "generated", sensor=None, cast: CastConfig = CastConfig()) -> EditedView:
    """Regenerate ``view`` with ``edit`` applied (see the module docstring). ``sensor``: the
    view's LiDAR (a SensorSpec, :meth:`tasks.generate.Generator.sensor`), which ``compose: cast``
    casts; ``cast``: the cast view's scene (:class:`typ.config.CastConfig`)."""
    if edit.is_empty():
        raise TypError("typ edit", "edits", "at least one of --remove, --move, --add", "none")
    if compose not in COMPOSE:
        raise TypError("typ edit", "--compose", f"one of {COMPOSE}", compose)
    if COMPOSE_MODES[compose].casts and sensor is None:
        raise TypError("typ edit", "sensor", "the view's LiDAR (a SensorSpec), which a cast edit casts with", None)
    edited, old, new = edit_boxes(view, edit)
    touched = np.concatenate([old, new])
    footprint = footprint_mask(touched, grid)
    # the edited objects' own points go from the conditioning cloud: the ego "sees" the edit
    grown_old = old.copy()
    grown_old[:, 3:6] += 0.4
    inside_old = points_in_boxes(view.points, grown_old).any(axis=1) if len(old) else np.zeros(len(view.points), bool)
    x_e = voxelize(view.points[~inside_old], grid).transpose(2, 0, 1)
    y_r = box_map(edited.boxes, grid).transpose(2, 0, 1)
    # a re-simulation-conditioned generator: the view re-simulated from its own pose is the view
    resim = x_e[None].astype(np.float32) if generator.pipe.conditions == 2 else None
    occupancy = generator.pipe.occupancy(x_e[None], y_r[None], seed=seed, resim=resim)[0]
    kept = view.points[~in_mask(view.points, footprint, grid)]
    if compose == "cast":
        generated = cast_footprint(view.points[~inside_old], occupancy, footprint, new, grid, sensor, seed,
                                   generator.pipe.point_stats, cast)
        kept = kept[~behind_boxes(kept, new * np.r_[1, 1, 1, [cast.label_boxes] * 3, 1])]
    else:
        generated = generator.pipe.points(occupancy & footprint[None], grid, seed)
    points = np.concatenate([kept[:, :4].astype(np.float32), generated]).astype(np.float32)
    out = dataclasses.replace(edited, points=points, semantics=None)
    return EditedView(out, footprint, x_e, y_r)


def cast_footprint(points: np.ndarray, occupancy: np.ndarray, footprint: np.ndarray, boxes: np.ndarray, grid: Grid,
                   sensor, seed: int, stats, cast: CastConfig) -> np.ndarray:
    """(M, 4) float32: the sensor's returns in the ``footprint`` cells of one scene made of the
    view's ``points`` as surfels, the generated ``occupancy`` of the footprint, and ``boxes``
    (the added and moved vehicles), with intensities drawn as the generated points'."""
    from pipelines.typ.pipeline_typ import draw_intensities
    from typ.resim import own_car_box
    from typ.castview import cast as cast_rays, scene_model

    params = dataclasses.replace(cast, carve=False)
    verts, tris = scene_model(points, occupancy & footprint[None], grid, sensor, params=params, label_boxes=boxes,
                              exclude_boxes=own_car_box(sensor, EGO_CAR_LWH), mask=~footprint)
    xyz = cast_rays(verts, tris, sensor, np.random.default_rng([seed, 2]))
    xyz = xyz[in_mask(xyz, footprint, grid)]
    return draw_intensities(xyz, grid, stats, np.random.default_rng([seed, 1]))


def behind_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N,) bool: the ray from the sensor origin to the point meets one of ``boxes`` (K, 7) more
    than :data:`OCCLUSION_SLACK_M` before it."""
    if len(boxes) == 0 or len(points) == 0:
        return np.zeros(len(points), dtype=bool)
    from typ.castview import oriented_boxes_mesh
    from typ.sim.raycast import RayScene

    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    dist = np.linalg.norm(xyz, axis=1)
    rays = np.zeros((len(xyz), 6), dtype=np.float32)
    rays[:, 3:] = xyz / np.maximum(dist, 1e-9)[:, None]
    hit = RayScene(oriented_boxes_mesh(boxes)).trace(rays)
    return np.isfinite(hit) & (hit < dist - OCCLUSION_SLACK_M)


def edit_figure(before: AgentView, result: EditedView, grid: Grid, *, title: str = ""):
    """Before / after BEV renders of an edited view and the cells the edit changed.

    Panels: the view as it was with its boxes, as edited with the edited boxes (the
    regenerated footprint outlined by its cells in the change map), and the change of the
    occupancy on ``grid`` per voxel (each BEV cell shows what most of its voxels did): unchanged,
    removed (only before), added (only after).
    """
    from typ import viz

    old_occ, new_occ = voxelize(before.points, grid), voxelize(result.view.points, grid)
    # per voxel: a removed car leaves the ground under it, so its column is still occupied
    change = viz.error_panel(new_occ, old_occ, grid, per="voxel", boxes=result.view.boxes,
                             title="change (after vs before, per voxel)", labels=("unchanged", "removed", "added"))
    panels = [viz.cloud_panel("before", before.points, grid=grid, boxes=before.boxes),
              viz.cloud_panel("after", result.view.points, grid=grid, boxes=result.view.boxes,
                              note=f"{len(result.view.points)} points, {int(result.footprint.sum())} cells regenerated"),
              change]
    return viz.panels_figure(panels, title=title, colorbar_z=grid.z_range)


def edit_target(scenario: Path, out: Path) -> Path:
    """``out/<scenario's name>``, the edited copy of ``scenario`` (both resolved: ``typ edit .`` is
    the folder's own name). TypError when the copy would be the input, hold it or lie inside it:
    writing it would replace or grow what it copies."""
    scenario, out = Path(scenario).resolve(), Path(out).resolve()
    target = out / scenario.name
    if target == scenario or scenario in target.parents or target in scenario.parents:
        raise TypError("typ edit", "--out", f"a folder that is not the scenario {scenario}, nor inside it, nor the "
                       f"folder holding it (the copy {target} would replace or grow its input)", str(out))
    return target


#: the most entries and folder levels a scenario copy takes: a link to ``/`` or a deep tree must end in an error
MAX_COPY_ENTRIES = 200_000
MAX_COPY_DEPTH = 32


def copy_scenario(source: Path, dest: Path) -> None:
    """Copy the scenario folder ``source`` to ``dest`` as real files, leaving out typ's own files
    (``_*``) and hidden ones. A link is followed and what it names is copied, so the copy never
    writes through to a dataset a scenario was assembled from by links; a link back to a folder
    being copied (a loop) is copied no further, a dangling link and other special files are
    skipped. More than :data:`MAX_COPY_ENTRIES` entries or :data:`MAX_COPY_DEPTH` levels raise
    TypError naming ``source``."""
    count = 0

    def copy_folder(src: Path, dst: Path, ancestors: frozenset, depth: int) -> None:
        nonlocal count
        if depth > MAX_COPY_DEPTH:
            raise TypError(source, "scenario", f"a scenario folder at most {MAX_COPY_DEPTH} levels deep", str(src))
        dst.mkdir()
        with os.scandir(src) as entries:
            names = sorted(e.name for e in entries if not e.name.startswith(("_", ".")))
        for name in names:
            count += 1
            if count > MAX_COPY_ENTRIES:
                raise TypError(source, "scenario", f"a scenario of at most {MAX_COPY_ENTRIES} files and folders "
                               "(its links included)", f"more, at {src / name}")
            try:
                info = os.stat(src / name)  # through a link: what it names
            except OSError:
                continue
            if stat.S_ISDIR(info.st_mode) and (info.st_dev, info.st_ino) not in ancestors:
                copy_folder(src / name, dst / name, ancestors | {(info.st_dev, info.st_ino)}, depth + 1)
            elif stat.S_ISREG(info.st_mode):
                shutil.copy2(src / name, dst / name)

    top = os.stat(source)
    copy_folder(Path(source), Path(dest), frozenset({(top.st_dev, top.st_ino)}), 0)
