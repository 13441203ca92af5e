"""Bad-input cases: the voxel grid and voxelize (registered with :func:`bad_inputs.make_corpus.case`)."""
from __future__ import annotations

import numpy as np

from typ.voxel import Grid, box_map, voxelize

from bad_inputs.make_corpus import GRID, Probe, case, cloud


@case("voxel", "nan_and_inf_points", "nan/inf")
def _(d):
    pts = cloud()
    pts[1, 0], pts[2, 2] = np.nan, -np.inf
    return Probe(says=("points", "finite x, y, z", "2 rows with NaN/Inf"), call=lambda: voxelize(pts, GRID))


@case("voxel", "integer_points", "wrong dtype")
def _(d):
    pts = (cloud() * 100).astype(np.int32)
    return Probe(says=("points", "dtype float32 or float64", "int32"), call=lambda: voxelize(pts, GRID))


@case("voxel", "points_with_2_columns", "misaligned")
def _(d):
    pts = cloud()[:, :2]
    return Probe(says=("points", "(N, >=3)", "(64, 2)"), call=lambda: voxelize(pts, GRID))


@case("voxel", "grid_range_reversed", "wrong units")
def _(d):
    return Probe(says=("x_range", "min < max"), call=lambda: Grid((51.2, -51.2), (-51.2, 51.2), (-3.0, 1.0), (8, 8, 2)))


@case("voxel", "box_with_nan_yaw", "nan/inf")
def _(d):
    return Probe(says=("boxes", "finite box parameters"), call=lambda: box_map([[0, 0, 0, 4, 2, 1.5, np.nan]], GRID))
