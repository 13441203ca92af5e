"""BEV rasters of clouds and occupancy grids, and error maps of a prediction against the truth: the
arrays the panels of :mod:`typ.viz` draw, with its conventions (the window, the colours)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from typ.errors import TypError
from typ.scene import SEMANTIC_CLASSES
from typ.voxel import Grid


BACKGROUND = (1.0, 1.0, 1.0)
HEIGHT_CMAP = "viridis"
#: RGB per class of :data:`typ.scene.SEMANTIC_CLASSES`
CLASS_COLOURS: dict[str, tuple[float, float, float]] = {
    "ground": (0.62, 0.52, 0.40), "road": (0.45, 0.45, 0.45), "building": (0.30, 0.50, 0.85),
    "vegetation": (0.20, 0.65, 0.25), "pole": (0.85, 0.75, 0.05), "vehicle": (0.95, 0.50, 0.05)}
UNKNOWN_CLASS_COLOUR = (0.70, 0.70, 0.70)
BOX_COLOUR = (0.85, 0.05, 0.15)
AGENT_COLOUR = (0.0, 0.0, 0.0)
TP_COLOUR = (0.15, 0.65, 0.15)
MISS_COLOUR = (0.15, 0.35, 0.95)
FP_COLOUR = (0.98, 0.55, 0.0)
#: the panels of one sample, in order: key -> title
SAMPLE_PANELS: dict[str, str] = {
    "ego": "ego cloud (ego frame)", "x_e": "x_e′: ego cloud in the reference frame", "generated": "generated view",
    "true": "true view", "resim": "re-simulated view", "error": "error: generated vs true"}
#: default BEV window: the paper's ±51.2 m at 0.2 m per pixel
DEFAULT_RANGE = (-51.2, 51.2)
DEFAULT_RESOLUTION = 0.2
#: a panel's axes come out about 540 px wide: a 512-pixel BEV (the default window) is not
#: thinned by nearest-neighbour downsampling
PANEL_INCHES = 4.2
#: metres: the arrow showing another sensor's heading
MARKER_LENGTH = 7.0
DPI = 150
_WHERE = "typ.viz"


@dataclass(frozen=True)
class Window:
    """The BEV rectangle shown, in a sensor frame (metres), and the size of one pixel (metres)."""

    x_range: tuple[float, float] = DEFAULT_RANGE
    y_range: tuple[float, float] = DEFAULT_RANGE
    resolution: float = DEFAULT_RESOLUTION

    def __post_init__(self) -> None:
        for name in ("x_range", "y_range"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise TypError(_WHERE, name, "(min, max) finite metres with min < max", getattr(self, name))
            object.__setattr__(self, name, (float(lo), float(hi)))
        if not (math.isfinite(self.resolution) and self.resolution > 0):
            raise TypError(_WHERE, "resolution", "a positive number of metres per pixel", self.resolution)

    @classmethod
    def of_grid(cls, grid: Grid) -> "Window":
        """The grid's x/y extent at its BEV cell size (square cells: the x size)."""
        sx, sy = grid.voxel_size[:2]
        if abs(sx - sy) > 1e-9 * max(sx, sy):
            raise TypError(_WHERE, "grid", "square BEV cells (equal x and y voxel sizes)", (sx, sy))
        return cls(grid.x_range, grid.y_range, float(sx))

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols): rows along x, cols along y."""
        return (int(math.ceil((self.x_range[1] - self.x_range[0]) / self.resolution - 1e-9)),
                int(math.ceil((self.y_range[1] - self.y_range[0]) / self.resolution - 1e-9)))

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """imshow's (left, right, bottom, top) in (y, x) metres: y_max on the left, x_max on top."""
        rows, cols = self.shape
        return (self.y_range[1], self.y_range[1] - cols * self.resolution,
                self.x_range[1] - rows * self.resolution, self.x_range[1])

    def pixels(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, inside) of (N, >=2) points ``[x, y, ...]``; see the module doc."""
        xy = np.asarray(points, dtype=np.float64)[:, :2]
        row = np.floor((self.x_range[1] - xy[:, 0]) / self.resolution)
        col = np.floor((self.y_range[1] - xy[:, 1]) / self.resolution)
        rows, cols = self.shape
        inside = (row >= 0) & (row < rows) & (col >= 0) & (col < cols) & (xy[:, 0] >= self.x_range[0]) \
            & (xy[:, 1] >= self.y_range[0])
        return row.astype(np.int64), col.astype(np.int64), inside


def _points(points, field: str) -> np.ndarray:
    arr = np.asarray(points)
    if arr.ndim != 2 or arr.shape[1] < 3 or arr.dtype.kind != "f":
        raise TypError(_WHERE, field, "an (N, >=3) float array [x, y, z, ...]", f"{arr.shape} {arr.dtype}")
    if not np.isfinite(arr[:, :3]).all():
        raise TypError(_WHERE, field, "finite x, y, z", f"{int((~np.isfinite(arr[:, :3])).any(axis=1).sum())} bad rows")
    return arr


def _boxes(boxes, field: str = "boxes") -> np.ndarray:
    if boxes is None:
        return np.zeros((0, 7))
    b = np.asarray(boxes, dtype=np.float64)
    if b.size == 0:
        return np.zeros((0, 7))
    if b.ndim != 2 or b.shape[1] != 7 or not np.isfinite(b).all():
        raise TypError(_WHERE, field, "(K, 7) finite boxes [x, y, z, l, w, h, yaw]", b.shape)
    return b


def _occupancy(occupancy, grid: Grid, field: str) -> np.ndarray:
    occ = np.asarray(occupancy)
    if occ.shape != grid.shape or occ.dtype != bool:
        raise TypError(_WHERE, field, f"a {grid.shape} bool occupancy on the grid", f"{occ.shape} {occ.dtype}")
    return occ


def _height_colours(z: np.ndarray, z_range: tuple[float, float]) -> np.ndarray:
    from matplotlib import colormaps

    t = np.clip((np.asarray(z, dtype=np.float64) - z_range[0]) / (z_range[1] - z_range[0]), 0.0, 1.0)
    return colormaps[HEIGHT_CMAP](t)[:, :3]


def class_colours(codes) -> np.ndarray:
    """(N,) uint8 class codes -> (N, 3) RGB (unknown codes grey)."""
    table = np.tile(np.array(UNKNOWN_CLASS_COLOUR), (256, 1))
    for i, name in enumerate(SEMANTIC_CLASSES):
        table[i] = CLASS_COLOURS[name]
    return table[np.asarray(codes, dtype=np.uint8)]


def bev_points_image(points, window: Window = Window(), *, semantics=None,
                     z_range: tuple[float, float] = (-3.0, 1.0)) -> np.ndarray:
    """(rows, cols, 3) float RGB in [0, 1]: a cloud seen from above (module doc's pixel rule).

    points: (N, >=3) float ``[x, y, z, ...]`` in the sensor frame. semantics: (N,) uint8 class
    codes, which colour the points by class; None colours them by height over ``z_range``
    (clipped). Each pixel shows its highest point; empty pixels are :data:`BACKGROUND`.
    """
    pts = _points(points, "points")
    image = np.empty((*window.shape, 3))
    image[:] = BACKGROUND
    row, col, inside = window.pixels(pts)
    z = pts[inside, 2].astype(np.float64)
    if semantics is not None:
        sem = np.asarray(semantics)
        if sem.shape != (len(pts),):
            raise TypError(_WHERE, "semantics", f"({len(pts)},) class codes", sem.shape)
        colours = class_colours(sem[inside])
    else:
        colours = _height_colours(z, z_range)
    order = np.argsort(z, kind="stable")  # the highest point is written last and stays
    image[row[inside][order], col[inside][order]] = colours[order]
    return image


def bev_occupancy_image(occupancy, grid: Grid, *, classes=None) -> np.ndarray:
    """(H, W, 3) float RGB of an (H, W, C) bool grid, heading-up (row 0 = the largest x).

    Each BEV cell takes the colour of its highest occupied voxel: its height (the voxel
    centre's z, on ``viridis`` over the grid's z range) or, with ``classes`` ((H, W, C) uint8
    class codes, :data:`typ.scene.SEMANTIC_UNKNOWN` where empty), its class.
    """
    occ = _occupancy(occupancy, grid, "occupancy")
    H, W, C = grid.shape
    any_ = occ.any(axis=2)
    top = C - 1 - np.argmax(occ[:, :, ::-1], axis=2)
    image = np.empty((H, W, 3))
    image[:] = BACKGROUND
    if classes is not None:
        cls = np.asarray(classes)
        if cls.shape != grid.shape:
            raise TypError(_WHERE, "classes", f"{grid.shape} class codes", cls.shape)
        colours = class_colours(np.take_along_axis(cls, top[:, :, None], axis=2)[:, :, 0][any_])
    else:
        colours = _height_colours(grid.centers(2)[top[any_]], grid.z_range)
    image[any_] = colours
    return image[::-1, ::-1]


def error_counts(pred, true, *, per: str = "cell") -> dict[str, int]:
    """Counts of true positives, misses and false positives of a predicted occupancy.

    pred, true: (H, W, C) bool. ``per="cell"``: BEV cells (a column is occupied when any of its
    voxels is); ``per="voxel"``: voxels.
    """
    p, t = _pair(pred, true, per)
    return {"tp": int((p & t).sum()), "miss": int((t & ~p).sum()), "fp": int((p & ~t).sum())}


def _pair(pred, true, per: str) -> tuple[np.ndarray, np.ndarray]:
    p, t = np.asarray(pred), np.asarray(true)
    if p.dtype != bool or t.dtype != bool or p.shape != t.shape or p.ndim != 3:
        raise TypError(_WHERE, "pred/true", "two (H, W, C) bool grids of one shape",
                       f"{p.shape} {p.dtype} / {t.shape} {t.dtype}")
    if per == "cell":
        return p.any(axis=2), t.any(axis=2)
    if per != "voxel":
        raise TypError(_WHERE, "per", "'cell' or 'voxel'", per)
    return p, t


def error_image(pred, true, *, per: str = "cell") -> np.ndarray:
    """(H, W, 3) float RGB error map of (H, W, C) bool grids, heading-up like :func:`bev_occupancy_image`.

    ``per="cell"``: a BEV cell is a true positive when both columns hold a voxel, a miss when
    only the truth does, a false positive when only the prediction does. ``per="voxel"``: each
    cell takes the category most of its voxels fall in (ties: true positive, then miss, then
    false positive), so a column right in the BEV but wrong in height shows up.
    """
    p, t = _pair(pred, true, per)
    tp, miss, fp = p & t, t & ~p, p & ~t
    if per == "voxel":
        counts = np.stack([tp.sum(axis=2), miss.sum(axis=2), fp.sum(axis=2)])
        best = np.argmax(counts, axis=0)  # first maximum: the tie order of the docstring
        some = counts.sum(axis=0) > 0
        tp, miss, fp = some & (best == 0), some & (best == 1), some & (best == 2)
    image = np.empty((*p.shape[:2], 3))
    image[:] = BACKGROUND
    image[tp], image[miss], image[fp] = TP_COLOUR, MISS_COLOUR, FP_COLOUR
    return image[::-1, ::-1]
