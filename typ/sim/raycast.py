"""typ's one ray caster: the simulator's eyes and ground truth, re-simulation, cast views and edits.

:class:`RayScene` is the only place typ builds an open3d ``RaycastingScene`` and casts rays;
:func:`sensor_rays` makes a sensor's rays. :func:`cast` scans the town at one frame from any pose
with its materials (semantics, reflectivity, intensity); :func:`cast_mesh` scans a bare surface
given in the sensor frame (the re-simulated, cast and edited views).

In the town, one scene holds the static town (geometry 0) and the frame's vehicles
(geometry 1, 24 triangles each); a hit's geometry and primitive ids give its semantic class
and reflectivity. A vehicle can be left out of the scene so that a sensor on its roof does
not see it (the CARLA LiDAR ignores its parent actor the same way); scenes are cached per
excluded vehicle on the :class:`TownFrame`. All rays of one sensor go in one ``cast_rays`` call.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from typ.errors import TypError
from typ.scene import SEMANTIC_CODE
from typ.sim.sensor import SensorSpec
from typ.sim.town import Town
from typ.sim.traffic import Traffic
from typ.sim.vehicles import TRIS_PER_VEHICLE, vehicle_mesh

_VEHICLE = SEMANTIC_CODE["vehicle"]
_REFERENCE_RANGE = 20.0  # range (m) at which echo strength is not reduced by distance


@dataclass
class TownFrame:
    """The world at one frame: the static town plus every vehicle, boxes in world coordinates.

    vehicle_ids (M,) int64; vehicle_labels M class names; vehicle_boxes (M, 7) float64
    ``[x, y, z, l, w, h, yaw]``; vehicle_paint (M,) float32 reflectivity.
    """

    town: Town
    vehicle_ids: np.ndarray
    vehicle_labels: tuple[str, ...]
    vehicle_boxes: np.ndarray
    vehicle_paint: np.ndarray
    _scenes: dict = field(default_factory=dict, repr=False, compare=False)


class RayScene:
    """Triangle meshes in one open3d ``RaycastingScene``: every ray typ casts goes through :meth:`trace`.

    meshes: ``(vertices (V, 3), triangles (T, 3))`` pairs, stored as float32 / uint32; ``ids`` are
    their geometry ids, in order. Triangles are hit from either side.
    """

    def __init__(self, *meshes):
        import open3d as o3d  # here, not at import: a scenario with nothing to do skips its second of loading

        self._scene = o3d.t.geometry.RaycastingScene()
        self.ids = tuple(self._scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(v, dtype=np.float32)),
                                                   o3d.core.Tensor(np.ascontiguousarray(t, dtype=np.uint32)))
                         for v, t in meshes)

    def trace(self, rays: np.ndarray, *fields: str):
        """Cast (N, 6) float32 rays ``[origin, unit direction]`` in one call: the (N,) ``t_hit``
        (inf where a ray meets nothing), or a tuple of the open3d result ``fields`` named."""
        import open3d as o3d

        hit = self._scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32)))
        return tuple(hit[f].numpy() for f in fields) if fields else hit["t_hit"].numpy()

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(N,) float32 metres from each of (N, 3) ``points`` to the nearest triangle."""
        import open3d as o3d

        return self._scene.compute_distance(o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))).numpy()


def sensor_rays(directions: np.ndarray, origins: np.ndarray | None, pose: np.ndarray | None = None,
                start: float = 0.0) -> np.ndarray:
    """(N, 6) float32 rays ``[origin, direction]`` of a sensor's beams, in its ray order.

    directions, origins: ``SensorSpec.ray_directions()`` and ``ray_origins()`` (the caller keeps them
    to place the returns); pose: (4, 4) float64 sensor-to-world, or None for the sensor frame; start
    (sensor frame only): each ray begins this far along its direction from its origin.
    """
    rays = np.zeros((len(directions), 6), dtype=np.float32)
    if pose is not None:
        rays[:, :3] = pose[:3, 3] if origins is None else pose[:3, 3] + origins @ pose[:3, :3].T
        rays[:, 3:] = directions @ pose[:3, :3].T
        return rays
    rays[:, 3:] = directions
    if start:
        rays[:, :3] = directions * start + (0.0 if origins is None else origins)
    elif origins is not None:
        rays[:, :3] = origins
    return rays


def cast_mesh(vertices, triangles, spec: SensorSpec, rng: np.random.Generator | None = None, *,
              start: float = 0.0) -> np.ndarray:
    """Every ray of ``spec`` from its origin into a bare surface: (M, 3) float32 returns, sensor frame.

    vertices (V, 3) and triangles (T, 3) in the sensor frame. A return lies in
    ``[min_range, max_range]`` along its ray; rays begin ``start`` out (a surface nearer is not
    seen and does not blind the ray). With ``rng`` it is lost with probability ``spec.dropout`` and
    its range gets Gaussian noise of ``spec.range_noise_std`` clipped at 3 std (drawn in that
    order); without, the scan is ideal. Beam-major in ``spec``'s ray order. As :func:`cast`
    without a material.
    """
    if len(triangles) == 0:
        return np.zeros((0, 3), dtype=np.float32)
    directions, origins = spec.ray_directions(), spec.ray_origins()
    t = RayScene((vertices, triangles)).trace(sensor_rays(directions, origins, start=start))
    if start:
        t = t.astype(np.float64) + start
    hit = np.flatnonzero(np.isfinite(t) & (t <= spec.max_range) & (t >= spec.min_range))
    if rng is not None and spec.dropout > 0:
        hit = hit[rng.random(len(hit)) >= spec.dropout]
    r = t[hit].astype(np.float64)
    if rng is not None and spec.range_noise_std > 0:
        r = r + np.clip(rng.standard_normal(len(r)), -3.0, 3.0) * spec.range_noise_std
    points = directions[hit] * r[:, None]
    return (points if origins is None else origins[hit] + points).astype(np.float32)


def town_frame(town: Town, traffic: Traffic, frame: int) -> TownFrame:
    """The :class:`TownFrame` of ``traffic`` at frame index ``frame``."""
    return TownFrame(town, traffic.ids, traffic.labels, traffic.boxes(frame), traffic.paint)


def _scene(world: TownFrame, exclude_vehicle_id: int | None):
    """(RaycastingScene, static geometry id, vehicle geometry id, (K,) kept vehicle indices), cached."""
    key = None if exclude_vehicle_id is None else int(exclude_vehicle_id)
    if key in world._scenes:
        return world._scenes[key]
    keep = np.arange(len(world.vehicle_ids))
    if key is not None:
        if key not in set(world.vehicle_ids.tolist()):
            raise TypError("typ.sim.cast", "exclude_vehicle_id", "the id of a vehicle in this frame or None", key)
        keep = keep[world.vehicle_ids != key]
    meshes = [(world.town.vertices, world.town.triangles)]
    if len(keep):
        meshes.append(vehicle_mesh(world.vehicle_boxes[keep], tuple(world.vehicle_labels[i] for i in keep)))
    scene = RayScene(*meshes)
    world._scenes[key] = (scene, scene.ids[0], scene.ids[1] if len(keep) else -1, keep)
    return world._scenes[key]


def cast(town_at_frame: TownFrame, pose: np.ndarray, spec: SensorSpec, rng: np.random.Generator,
         exclude_vehicle_id: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What ``spec`` mounted at ``pose`` sees in ``town_at_frame``.

    pose: (4, 4) float64 sensor-to-world. exclude_vehicle_id: a vehicle left out of the scene
    (the one carrying the sensor). ``rng`` draws dropout and noise only.
    Returns points (N, 4) float32 ``[x, y, z, intensity]`` in the SENSOR frame (x forward,
    y left, z up), intensity in [0, 1], and semantics (N,) uint8 codes of
    :data:`typ.scene.SEMANTIC_CLASSES` (sidewalks and kerbs are ground).
    """
    if not isinstance(spec, SensorSpec):
        raise TypError("typ.sim.cast", "spec", "a SensorSpec (e.g. domain_spec(name).sensor)", type(spec).__name__)
    if not isinstance(rng, np.random.Generator):
        raise TypError("typ.sim.cast", "rng", "a numpy.random.Generator", type(rng).__name__)
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4) or not np.isfinite(pose).all():
        raise TypError("typ.sim.cast", "pose", "a finite (4, 4) sensor-to-world matrix", pose.shape)
    scene, static_id, vehicle_id, keep = _scene(town_at_frame, exclude_vehicle_id)
    d_sensor = spec.ray_directions()
    o_sensor = spec.ray_origins()
    rays = sensor_rays(d_sensor, o_sensor, pose)
    t, geom, prim, normal = scene.trace(rays, "t_hit", "geometry_ids", "primitive_ids", "primitive_normals")
    idx = np.flatnonzero(np.isfinite(t) & (t <= spec.max_range) & (t >= spec.min_range))
    t = t[idx].astype(np.float64)
    geom = geom[idx]
    prim = prim[idx].astype(np.int64)
    normal = normal[idx].astype(np.float64)

    on_vehicle = geom == vehicle_id
    static_prim = np.where(on_vehicle, 0, prim)
    semantics = np.where(on_vehicle, _VEHICLE, town_at_frame.town.tri_class[static_prim]).astype(np.uint8)
    reflectivity = town_at_frame.town.tri_reflectivity[static_prim].astype(np.float64)
    if on_vehicle.any():
        owner = keep[prim[on_vehicle] // TRIS_PER_VEHICLE]
        reflectivity[on_vehicle] = town_at_frame.vehicle_paint[owner]
    cos = np.abs(np.einsum("ij,ij->i", rays[idx, 3:].astype(np.float64), normal))
    cos /= np.maximum(np.linalg.norm(normal, axis=1), 1e-12)

    # Missing returns: random dropout, plus weak echoes (dark, grazing or far) fading out.
    p_keep = np.full(len(t), 1.0 - spec.dropout)
    if spec.detection_energy > 0:
        energy = reflectivity * cos * (_REFERENCE_RANGE / np.maximum(t, 1.0)) ** 2
        p_keep *= 1.0 - np.exp(-energy / spec.detection_energy)
    if spec.dropout > 0 or spec.detection_energy > 0:
        kept = rng.random(len(t)) < p_keep
        idx, t, semantics, reflectivity, cos = idx[kept], t[kept], semantics[kept], reflectivity[kept], cos[kept]

    if spec.range_noise_std > 0:
        # Clipped at 3 std so no point lies further than max_range + 3 std.
        t = t + np.clip(rng.standard_normal(len(t)), -3.0, 3.0) * spec.range_noise_std
    if spec.intensity_model == "attenuation":
        intensity = np.exp(-spec.attenuation_rate * t)
    else:
        intensity = reflectivity * (1.0 - spec.incidence_weight + spec.incidence_weight * cos)
    if spec.intensity_noise > 0:
        intensity = intensity + rng.normal(0.0, spec.intensity_noise, len(t))
    points = np.empty((len(t), 4), dtype=np.float32)
    points[:, :3] = d_sensor[idx] * t[:, None] if o_sensor is None else o_sensor[idx] + d_sensor[idx] * t[:, None]
    points[:, 3] = np.clip(intensity, 0.0, 1.0)
    return points, semantics
