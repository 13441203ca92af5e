"""Pictures of point clouds and occupancy grids: BEV images, per-sample panels, range images.

Everything is a pure function of arrays that returns a :class:`matplotlib.figure.Figure`
(Agg canvas, no pyplot state, nothing shown), plus :func:`save_png` (atomic) and
:func:`gallery` (PNGs + a markdown index) for reports.

BEV convention (every panel): the sensor frame seen from above, x forward pointing *up* the
page and y left pointing *left*, so the picture is what a driver sees on a map turned
heading-up. A :class:`Window` is the rectangle shown and its pixel size; pixel ``(row, col)``
covers ``x in (x_max - (row + 1) * res, x_max - row * res]`` and ``y in (y_max - (col + 1) * res,
y_max - col * res]``, so a point at ``(x, y)`` lands on ``row = floor((x_max - x) / res)``,
``col = floor((y_max - y) / res)``. The axes are in metres: horizontal = y (decreasing to the
right), vertical = x. Where several points share a pixel the highest one is shown (the view
from above). Occupancy grids (:class:`typ.voxel.Grid`, (H, W, C) bool, H along x, W along y)
are drawn one pixel per BEV cell, coloured by their highest occupied channel.

Colours: height on ``viridis`` over a fixed z range (the grid's, so every panel of a sample
shares one scale), or the simulator's point classes (:data:`typ.scene.SEMANTIC_CLASSES`,
:data:`CLASS_COLOURS`); boxes ((K, 7) ``[x, y, z, l, w, h, yaw]``) in :data:`BOX_COLOUR`.
Error maps compare a prediction with the truth per BEV cell or per voxel: true positives
:data:`TP_COLOUR`, misses (true, not predicted) :data:`MISS_COLOUR`, false positives
:data:`FP_COLOUR`.

The rasters (BEV images, error maps) and these constants live in :mod:`typ.viz_images`; this module
draws them into figures and is the one callers import.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from typ.errors import TypError
from typ.io import atomic_path, write_text
from typ.reporting import markdown_table, subplots
from typ.scene import SEMANTIC_CLASSES
from typ.sim.sensor import SensorSpec
from typ.viz_images import (AGENT_COLOUR, BACKGROUND, BOX_COLOUR, CLASS_COLOURS, DEFAULT_RANGE,  # noqa: F401
                            DEFAULT_RESOLUTION, DPI, FP_COLOUR, HEIGHT_CMAP, MARKER_LENGTH, MISS_COLOUR, PANEL_INCHES,
                            SAMPLE_PANELS, TP_COLOUR, UNKNOWN_CLASS_COLOUR, Window, _WHERE, _boxes, _height_colours,
                            _occupancy, _pair, _points, bev_occupancy_image, bev_points_image, class_colours,
                            error_counts, error_image)
from typ.voxel import Grid, voxelize


# ---------------------------------------------------------------- panels and figures


@dataclass
class Panel:
    """One BEV picture: an RGB image over ``window`` with boxes, agent markers and a title.

    markers: (M, 3) ``[x, y, yaw]`` of other sensors in this frame (drawn as arrows).
    legend: (label, RGB) pairs shown under the panel.
    """

    title: str
    image: np.ndarray
    window: Window
    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    markers: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    legend: tuple[tuple[str, tuple[float, float, float]], ...] = ()
    note: str = ""


def cloud_panel(title: str, cloud, *, grid: Grid | None = None, window: Window | None = None, boxes=None,
                semantics=None, markers=None, z_range: tuple[float, float] | None = None, note: str = "") -> Panel:
    """A :class:`Panel` of a point cloud ((N, >=3) float) or, with ``grid``, of an (H, W, C) bool grid."""
    arr = np.asarray(cloud)
    if arr.dtype == bool:
        if grid is None:
            raise TypError(_WHERE, title, "a grid to draw an occupancy with", "none")
        image, win = bev_occupancy_image(arr, grid), Window.of_grid(grid)
        count = f"{int(arr.any(axis=2).sum())} cells"
    else:
        win = window or (Window.of_grid(grid) if grid is not None else Window())
        zr = z_range or (grid.z_range if grid is not None else (-3.0, 1.0))
        image = bev_points_image(arr, win, semantics=semantics, z_range=zr)
        count = f"{len(arr)} points"
    legend = tuple((name, CLASS_COLOURS[name]) for name in SEMANTIC_CLASSES) if semantics is not None else ()
    return Panel(title, image, win, _boxes(boxes), _markers(markers), legend, note or count)


def _markers(markers) -> np.ndarray:
    if markers is None:
        return np.zeros((0, 3))
    m = np.asarray(markers, dtype=np.float64).reshape(-1, 3)
    return m


def error_panel(pred, true, grid: Grid, *, per: str = "cell", boxes=None, title: str = SAMPLE_PANELS["error"],
                labels: tuple[str, str, str] = ("true positive", "miss", "false positive")) -> Panel:
    """The error map of :func:`error_image` as a :class:`Panel`: the three counts in its legend
    (named ``labels``, e.g. ``("unchanged", "removed", "added")`` for before/after), IoU in its note."""
    counts = error_counts(pred, true, per=per)
    union = counts["tp"] + counts["miss"] + counts["fp"]
    iou = counts["tp"] / union if union else float("nan")
    legend = tuple((f"{label} {counts[k]}", colour) for label, k, colour in
                   zip(labels, ("tp", "miss", "fp"), (TP_COLOUR, MISS_COLOUR, FP_COLOUR)))
    return Panel(title, error_image(pred, true, per=per), Window.of_grid(grid), _boxes(boxes), np.zeros((0, 3)),
                 legend, f"IoU per {per} {iou:.3f}")


def _box_outlines(boxes: np.ndarray) -> np.ndarray:
    """(K, 5, 2) closed BEV outlines in (y, x) plot coordinates."""
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    hl, hw = boxes[:, 3] / 2, boxes[:, 4] / 2
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1], [1, 1]], dtype=np.float64)
    lx, ly = local[None, :, 0] * hl[:, None], local[None, :, 1] * hw[:, None]
    x = boxes[:, None, 0] + lx * c[:, None] - ly * s[:, None]
    y = boxes[:, None, 1] + lx * s[:, None] + ly * c[:, None]
    return np.stack([y, x], axis=2)


def draw_panel(ax, panel: Panel) -> None:
    """Draw ``panel`` on a matplotlib Axes (data coordinates: horizontal y, vertical x, metres)."""
    from matplotlib.collections import LineCollection

    win = panel.window
    ax.imshow(panel.image, extent=win.extent, interpolation="nearest", origin="upper", aspect="equal",
              resample=False)
    if len(panel.boxes):
        outlines = _box_outlines(panel.boxes)
        ax.add_collection(LineCollection(list(outlines), colors=[BOX_COLOUR], linewidths=1.2))
        # heading: a tick from the centre to the front edge
        front = np.stack([panel.boxes[:, [1, 0]], (outlines[:, 0] + outlines[:, 1]) / 2], axis=1)
        ax.add_collection(LineCollection(list(front), colors=[BOX_COLOUR], linewidths=1.0))
    for x, y, yaw in panel.markers:
        ax.annotate("", xy=(y + MARKER_LENGTH * math.sin(yaw), x + MARKER_LENGTH * math.cos(yaw)), xytext=(y, x),
                    arrowprops={"arrowstyle": "-|>", "color": AGENT_COLOUR, "lw": 1.5})
        ax.plot([y], [x], marker="o", ms=4, color=AGENT_COLOUR)
    ax.set_xlim(win.extent[0], win.extent[1])
    ax.set_ylim(win.extent[2], win.extent[3])
    ax.set_title(panel.title, fontsize=9)
    ax.set_xlabel("y (m, left +)", fontsize=7)
    ax.set_ylabel("x (m, forward +)", fontsize=7)
    ax.tick_params(labelsize=6)
    if panel.note:
        ax.text(0.01, 0.01, panel.note, transform=ax.transAxes, fontsize=6.5, va="bottom", ha="left",
                bbox={"facecolor": "white", "alpha": 0.75, "lw": 0, "pad": 1.5})
    if panel.legend:
        from matplotlib.patches import Patch

        ax.legend(handles=[Patch(color=c, label=name) for name, c in panel.legend], fontsize=6, loc="upper right",
                  framealpha=0.8, handlelength=1.0, borderpad=0.3, labelspacing=0.2)


def panels_figure(panels: Sequence[Panel], *, title: str = "", ncols: int | None = None,
                  colorbar_z: tuple[float, float] | None = None) -> Figure:
    """Panels side by side (``ncols`` per row, default: all in one row up to 4, then wrapping).

    colorbar_z: the z range of the height colours, drawn as one colour bar for the figure.
    """
    if not panels:
        raise TypError(_WHERE, "panels", "at least one panel", 0)
    n = len(panels)
    ncols = ncols or (n if n <= 4 else min(n, 3 if n in (5, 6, 9) else 4))
    nrows = math.ceil(n / ncols)
    fig, axes = subplots(nrows, ncols, squeeze=False, dpi=DPI, layout="constrained",
                         figsize=(PANEL_INCHES * ncols + (0.6 if colorbar_z else 0), PANEL_INCHES * nrows + (0.4 if title else 0)))
    for ax, panel in zip(axes.flat, panels):
        draw_panel(ax, panel)
    for ax in list(axes.flat)[n:]:
        ax.set_visible(False)
    if colorbar_z:
        from matplotlib import colormaps
        from matplotlib.cm import ScalarMappable
        from matplotlib.colors import Normalize

        mappable = ScalarMappable(Normalize(*colorbar_z), colormaps[HEIGHT_CMAP])
        bar = fig.colorbar(mappable, ax=axes.ravel().tolist(), shrink=0.6, pad=0.01)
        bar.set_label("z (m, sensor frame)", fontsize=7)
        bar.ax.tick_params(labelsize=6)
    if title:
        fig.suptitle(title, fontsize=10)
    return _fixed_layout(fig)


def _fixed_layout(fig: Figure) -> Figure:
    """Solve the constrained layout once, then keep it: it moves by a pixel or so on every draw
    otherwise, and the saved PNG would not be the canvas that was looked at or tested."""
    fig.canvas.draw()
    fig.set_layout_engine("none")
    return fig


def bev_figure(cloud, *, title: str = "", grid: Grid | None = None, window: Window | None = None, boxes=None,
               semantics=None, markers=None, z_range: tuple[float, float] | None = None) -> Figure:
    """One BEV image of a cloud ((N, >=3) float) or an occupancy ((H, W, C) bool, needs ``grid``)."""
    panel = cloud_panel(title, cloud, grid=grid, window=window, boxes=boxes, semantics=semantics, markers=markers,
                        z_range=z_range)
    zr = None if semantics is not None else (z_range or (grid.z_range if grid is not None else (-3.0, 1.0)))
    return panels_figure([panel], colorbar_z=zr)


def format_scores(scores: Mapping[str, object]) -> str:
    """``iou 0.412 · chamfer_m 0.53`` (numbers rounded to 3 significant digits, others as text)."""
    parts = []
    for k, v in scores.items():
        if isinstance(v, (float, np.floating)):
            parts.append(f"{k} {v:.3g}")
        else:
            parts.append(f"{k} {v}")
    return " · ".join(parts)


def sample_figure(sample: Mapping[str, object], grid: Grid, *, window: Window | None = None,
                  per: str = "cell", cells: bool = True) -> Figure:
    """The panels of one (ego, reference) sample side by side (:data:`SAMPLE_PANELS` order).

    sample keys, each optional except that at least one view must be present:

    - ``ego``: the ego's cloud, (N, >=3) float, ego sensor frame; ``ego_boxes`` (K, 7) there;
      ``ego_semantics`` (N,) class codes colour it by class;
    - ``x_e``, ``generated``, ``true``, ``resim``: reference-frame views, each a cloud
      ((N, >=3) float) or an occupancy ((H, W, C) bool on ``grid``); ``boxes`` (K, 7) in the
      reference frame (y_r's boxes) are drawn on each;
    - ``reference_in_ego``: ``[x, y, yaw]`` of the reference sensor in the ego frame (an arrow
      on the ego panel);
    - ``name``, ``scores`` ({name: value}): the figure's title; ``titles``: {panel key: title}
      replacing :data:`SAMPLE_PANELS`' (e.g. where the true view came from).

    cells: draw the reference-frame views on ``grid``'s BEV cells (clouds voxelized), the
    resolution they are generated and scored at; False draws clouds as points. The error map
    (generated against true, :func:`error_image` ``per`` cell or voxel) is added when both
    are present.
    """
    titles = {**SAMPLE_PANELS, **(sample.get("titles") or {})}
    panels = []
    boxes = sample.get("boxes")
    if sample.get("ego") is not None:
        marker = sample.get("reference_in_ego")
        panels.append(cloud_panel(titles["ego"], sample["ego"], grid=grid, window=window,
                                  boxes=sample.get("ego_boxes"), semantics=sample.get("ego_semantics"),
                                  markers=None if marker is None else [marker]))
    for key in ("x_e", "generated", "true", "resim"):
        if sample.get(key) is not None:
            view = as_occupancy(sample[key], grid) if cells else sample[key]
            panels.append(cloud_panel(titles[key], view, grid=grid, window=window, boxes=boxes))
    if sample.get("generated") is not None and sample.get("true") is not None:
        panels.append(error_panel(as_occupancy(sample["generated"], grid), as_occupancy(sample["true"], grid), grid,
                                  per=per, boxes=boxes, title=titles["error"]))
    if not panels:
        raise TypError(_WHERE, "sample", f"at least one of {list(SAMPLE_PANELS)[:-1]}", sorted(sample))
    title = str(sample.get("name", ""))
    if sample.get("scores"):
        title = f"{title}  —  {format_scores(sample['scores'])}" if title else format_scores(sample["scores"])
    return panels_figure(panels, title=title, ncols=min(len(panels), 3), colorbar_z=grid.z_range)


def as_occupancy(view, grid: Grid) -> np.ndarray:
    """A cloud voxelized on ``grid``, or an (H, W, C) bool occupancy checked against it."""
    arr = np.asarray(view)
    if arr.dtype == bool:
        return _occupancy(arr, grid, "occupancy")
    return voxelize(_points(arr, "points"), grid)


# ---------------------------------------------------------------- range image


def range_image(points, spec: SensorSpec) -> np.ndarray:
    """(n_beams, n_azimuths) float32 ranges (m) of a cloud in ``spec``'s frame; NaN where no return.

    Row 0 is the *highest* beam (the picture's top), column ``a`` the azimuth bin centred on
    ``-180 + a * step`` deg (the order of :meth:`SensorSpec.ray_directions`). A point goes to
    the beam of nearest elevation and is dropped when it is further than half the gap to the
    next beam outside the outermost beams; several points in one cell keep the nearest (the
    return a LiDAR reports).
    """
    pts = _points(points, "points")[:, :3].astype(np.float64)
    elev = np.asarray(spec.elevations_deg, dtype=np.float64)
    n_az = spec.n_azimuths
    rng = np.linalg.norm(pts, axis=1)
    ok = rng > 1e-9
    pts, rng = pts[ok], rng[ok]
    e = np.degrees(np.arcsin(np.clip(pts[:, 2] / rng, -1.0, 1.0)))
    a = np.degrees(np.arctan2(pts[:, 1], pts[:, 0]))
    mids = (elev[1:] + elev[:-1]) / 2
    beam = np.searchsorted(mids, e)
    lo_gap = (elev[1] - elev[0]) / 2 if len(elev) > 1 else 0.5
    hi_gap = (elev[-1] - elev[-2]) / 2 if len(elev) > 1 else 0.5
    keep = (e >= elev[0] - lo_gap) & (e <= elev[-1] + hi_gap)
    col = np.rint((a + 180.0) / spec.azimuth_step_deg).astype(np.int64) % n_az
    out = np.full((len(elev), n_az), np.inf)
    row = len(elev) - 1 - beam[keep]
    np.minimum.at(out, (row, col[keep]), rng[keep])
    out[np.isinf(out)] = np.nan
    return out.astype(np.float32)


def range_figure(points, spec: SensorSpec, *, title: str = "") -> Figure:
    """The range image of :func:`range_image`: azimuth across (-180..180 deg, 0 = forward), beams down."""
    from matplotlib import colormaps

    image = range_image(points, spec)
    cmap = colormaps["turbo_r"].with_extremes(bad=BACKGROUND)
    n_beams, n_az = image.shape
    fig, ax = subplots(figsize=(12, max(1.6, 0.03 * n_beams + 1.0)), dpi=DPI, layout="constrained")
    shown = ax.imshow(np.ma.masked_invalid(image), aspect="auto", cmap=cmap, vmin=0.0, vmax=spec.max_range,
                      interpolation="nearest", extent=(-180.0 - spec.azimuth_step_deg / 2,
                                                        180.0 - spec.azimuth_step_deg / 2, n_beams - 0.5, -0.5))
    ax.set_xlabel("azimuth (deg, 0 = forward, + = left)", fontsize=7)
    ax.set_ylabel("beam (0 = highest)", fontsize=7)
    ax.tick_params(labelsize=6)
    filled = np.isfinite(image).mean()
    ax.set_title(f"{title}  ({spec.name}: {n_beams} beams × {n_az} azimuths, {filled:.0%} of cells hit)".strip(),
                 fontsize=9)
    bar = fig.colorbar(shown, ax=ax, pad=0.01)
    bar.set_label("range (m)", fontsize=7)
    bar.ax.tick_params(labelsize=6)
    return _fixed_layout(fig)


# ---------------------------------------------------------------- output


def figure_array(fig: Figure) -> np.ndarray:
    """(H, W, 4) uint8 RGBA of the drawn figure, exactly what :func:`save_png` writes."""
    canvas = fig.canvas if isinstance(fig.canvas, FigureCanvasAgg) else FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba()).copy()


def save_png(fig: Figure, path: str | Path, *, stage: str | None = None) -> Path:
    """Write ``fig`` as a PNG at its own size and dpi (no cropping, so pixels match
    :func:`figure_array`), atomically; the same figure gives the same bytes. With ``stage`` (a
    command writing into a folder of the user's), it replaces only a PNG that command wrote
    (:func:`typ.io.atomic_path`)."""
    path = Path(path)
    with atomic_path(path, stage=stage) as tmp:
        with open(tmp, "wb") as fh:
            fig.savefig(fh, format="png", dpi=fig.dpi, metadata={"Software": None})
    return path


_SAFE_NAME = re.compile(r"[^A-Za-z0-9._-]+")


def safe_name(name: str) -> str:
    """A file name from a sample name: runs of other characters become ``_``."""
    cleaned = _SAFE_NAME.sub("_", str(name)).strip("._")
    return cleaned or "sample"


def gallery(samples: Sequence[Mapping[str, object]], out_dir: str | Path, grid: Grid, *, link_prefix: str = "",
            title: str = "Gallery", window: Window | None = None, per: str = "cell", cells: bool = True) -> str:
    """One PNG per sample (:func:`sample_figure`) under ``out_dir`` and a markdown index.

    samples: dicts as :func:`sample_figure` takes, each with a unique ``name`` and its
    ``scores``. Writes ``out_dir/<name>.png`` and ``out_dir/index.md`` (links relative to
    ``out_dir``) and returns the markdown snippet with links prefixed by ``link_prefix``
    (e.g. ``"gallery/"`` for a page beside the folder): a table of every sample's scores,
    then the images.
    """
    out = Path(out_dir)
    names = [safe_name(s.get("name", f"sample_{i:03d}")) for i, s in enumerate(samples)]
    if len(set(names)) != len(names):
        raise TypError(_WHERE, "samples.name", "unique names (after making them file names)", names)
    for name, sample in zip(names, samples):
        save_png(sample_figure(sample, grid, window=window, per=per, cells=cells), out / f"{name}.png")
    write_text(out / "index.md", f"# {title}\n\n" + _gallery_markdown(samples, names, "") + "\n")
    return _gallery_markdown(samples, names, link_prefix)


def _gallery_markdown(samples, names, prefix: str) -> str:
    keys: list[str] = []
    for s in samples:
        keys += [k for k in (s.get("scores") or {}) if k not in keys]
    def cells(name: str, scores: dict) -> list[str]:
        return [f"[{name}]({prefix}{name}.png)", *((f"{scores[k]:.3g}" if isinstance(scores[k], (float, np.floating))
                                                   else str(scores[k])) if k in scores else "–" for k in keys)]

    lines = markdown_table(["sample", *keys], (cells(n, s.get("scores") or {}) for n, s in zip(names, samples))).split("\n")
    lines.append("")
    for name in names:
        lines.append(f"![{name}]({prefix}{name}.png)")
    return "\n".join(lines)
