"""What a generated reference view is made of: one function per compose mode of
:data:`typ.registry.COMPOSE_MODES`, beside the pipeline that calls them (diffusers keeps a
pipeline's parts in its folder the same way).

:meth:`pipelines.typ.TYPPipeline.generate` samples TYP's occupancy for a batch of references,
turns it into points, and hands the batch to the mode the registry names (``implementation``, a
dotted path), which returns one (N, 4) float32 cloud per reference in its sensor frame:

- ``generated``: TYP's sample alone;
- ``hybrid``: the ego's cloud re-simulated from the reference pose in the BEV cells the ego
  covered, TYP's sample in the others (:func:`typ.resim.hybrid_points`);
- ``cast``: one scene of the ego's surfels where it saw and TYP's cells elsewhere, cast with the
  reference LiDAR (:func:`typ.castview.cast_view`).

A new mode is a function here taking a :class:`Batch` and one registry entry naming it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from pipelines.typ.reference import Reference
from typ.config import CastConfig
from typ.registry import compose_mode, load
from typ.voxel import Grid


@dataclass(frozen=True)
class Batch:
    """A batch of references with TYP's sample for each: ``occupancy`` (N, C, H, W) bool on
    ``grid`` (the reference sensor's grid) and ``clouds`` its points; ``sensor`` the reference
    LiDAR (a SensorSpec; None for modes that do not cast); ``resim_points`` the ego's cloud
    re-simulated from each reference pose, for the modes that re-simulate (else None)."""

    pipe: object            #: the TYPPipeline that sampled it (its point statistics draw intensities)
    refs: Sequence[Reference]
    grid: Grid
    seed: int
    occupancy: np.ndarray
    clouds: list[np.ndarray]
    sensor: object = None
    cast: CastConfig = CastConfig()
    resim_points: list[np.ndarray] | None = None


def generated(batch: Batch) -> list[np.ndarray]:
    return list(batch.clouds)


def hybrid(batch: Batch) -> list[np.ndarray]:
    from typ.resim import coverage_mask, hybrid_points

    return [hybrid_points(batch.pipe.intensities(batch.resim_points[k], batch.grid,
                                                 np.random.default_rng([batch.seed, k, 1])),
                          batch.clouds[k], coverage_mask(r.ego_points, batch.grid), batch.grid)
            for k, r in enumerate(batch.refs)]


def cast(batch: Batch) -> list[np.ndarray]:
    from typ.castview import cast_view
    from typ.distributed import threaded_map
    from typ.resim import EGO_CAR_LWH, own_car_box
    from typ.scene import vehicle_mask

    own = own_car_box(batch.sensor, EGO_CAR_LWH)

    def one(k: int) -> np.ndarray:
        r = batch.refs[k]
        xyz = cast_view(r.ego_points, batch.occupancy[k], batch.grid, batch.sensor,
                        np.random.default_rng([batch.seed, k, 2]), params=batch.cast, ego_origin=r.ego_origin,
                        label_boxes=r.boxes[vehicle_mask(r.labels)], exclude_boxes=own)
        return batch.pipe.intensities(xyz, batch.grid, np.random.default_rng([batch.seed, k, 1]))

    return list(threaded_map(one, range(len(batch.refs))))


def composer(name: str) -> Callable[[Batch], list[np.ndarray]]:
    """The function of compose mode ``name`` (its registry entry's ``implementation``)."""
    return load(compose_mode(name).implementation)
