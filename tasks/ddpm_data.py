"""The data of stage ``ddpm`` (module :mod:`tasks.ddpm`): the scans it learns from and their two
representations as images in [-1, 1], range images (R2DM, LiDARGen) and BEV occupancy
(:class:`Representation`: pixels from points and back, the references samples are scored against)."""
from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from typ.config import DdpmConfig
from typ.errors import TypError
from typ.formats.opv2v import list_agents, list_scenarios, list_timestamps, read_scene
from typ.projection import (RangeLayout, bev_image, bev_to_points, from_unit, range_image, range_pixels,
                            range_to_points, to_unit)
from typ.sim import domain_spec
from typ.voxel import Grid


# ---------------------------------------------------------------- scans


@dataclass
class Scan:
    """One view: ``key = (scenario, agent, timestamp)``, (N, 4) float32 points in its sensor
    frame, (N,) uint8 semantic codes (None for data without point labels)."""

    key: tuple[str, str, str]
    points: np.ndarray
    semantics: np.ndarray | None


def unlabelled(scans: list[Scan], where: str) -> str | None:
    """Why the stage cannot run on ``scans``, or None: its feature networks (FRID / FPVD) learn the
    points' classes, which a real dataset's scans (KITTI, nuScenes, Waymo) do not carry."""
    if any(s.semantics is None for s in scans):
        return (f"the scans of {where} carry no per-point classes (a real dataset's), which the FRID / FPVD "
                "feature networks learn; ddpm.domain can name a simulated domain")
    return None


def load_scans(sim_root: Path, *, domain: str, split: str, ego_only: bool) -> list[Scan]:
    """Every (scenario, agent, timestamp) view of ``sim_root/domain/split``, sorted."""
    folder = sim_root / domain / split
    if not folder.is_dir():
        raise TypError(folder, f"{domain}/{split}", "simulated scenarios of that domain and split "
                       "(simulate.scenarios; run: dvc repro simulate)", "no such folder")
    scans = []
    for scenario in list_scenarios(folder):
        agents = list_agents(scenario)
        for ts in list_timestamps(scenario):
            scene = read_scene(scenario, ts, agents=agents[:1] if ego_only else agents)
            for agent_id, view in scene.agents.items():
                scans.append(Scan((scenario.name, agent_id, ts), view.points, view.semantics))
    if not scans:
        raise TypError(folder, f"{domain}/{split}", "at least one scan", "none")
    return scans


# ---------------------------------------------------------------- representations


@dataclass(frozen=True)
class Representation(ABC):
    """One LiDAR image of the paper: points <-> the [-1, 1] pixels the model sees.

    Subclasses say how a cloud becomes an image and back (:mod:`typ.projection`), how the image
    mirrors across the x axis, and how well the round trip keeps real scans.
    """

    name: str
    layout: RangeLayout | Grid
    patch: tuple[int, int]
    depth: str = "linear"  #: a range image's depth encoding (typ.projection.to_unit); BEV: linear

    @property
    @abstractmethod
    def shape(self) -> tuple[int, int, int]:
        """(C, H, W) of the model's pixels."""

    @abstractmethod
    def image(self, points: np.ndarray) -> np.ndarray:
        """The physical image of a non-empty cloud."""

    @abstractmethod
    def empty_image(self) -> np.ndarray:
        """The physical image of a cloud with no point (what :meth:`pixels` gives for one)."""

    @abstractmethod
    def image_points(self, image: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`image` for a canonical image."""

    @abstractmethod
    def mirror_index(self, width: int) -> np.ndarray:
        """Column order of the image of the cloud mirrored across the x axis (y -> -y)."""

    @abstractmethod
    def round_trip(self, scans: list["Scan"]) -> dict:
        """How much of real ``scans`` survives points -> image -> points (figures for the report)."""

    def pixels(self, points: np.ndarray) -> np.ndarray:
        """(N, >=3) points -> (C, H, W) float32 pixels in [-1, 1]; an empty cloud gives an empty image."""
        return to_unit(self.image(points) if len(points) else self.empty_image(), self.layout, depth=self.depth)

    def points(self, pixels: np.ndarray) -> np.ndarray:
        """(C, H, W) model pixels -> (M, 3) float32 points (canonicalised first, see from_unit)."""
        return self.image_points(from_unit(pixels, self.layout, depth=self.depth))

    def mirror(self, pixels: np.ndarray) -> np.ndarray:
        """Pixels of the scan mirrored across the x axis (y -> -y)."""
        return pixels[..., self.mirror_index(pixels.shape[-1])]

    def describe(self) -> dict:
        return {"name": self.name, "layout": self.layout.to_dict(), "patch": list(self.patch),
                "depth": self.depth, "shape": list(self.shape)}


class RangeRepresentation(Representation):
    """The equirectangular range image (1 channel: depth)."""

    @property
    def shape(self) -> tuple[int, int, int]:
        return (1, *self.layout.shape)

    def image(self, points: np.ndarray) -> np.ndarray:
        return range_image(points, self.layout)

    def empty_image(self) -> np.ndarray:
        return np.zeros(self.layout.shape, np.float32)

    def image_points(self, image: np.ndarray) -> np.ndarray:
        return range_to_points(image, self.layout)

    def mirror_index(self, width: int) -> np.ndarray:
        return (width - np.arange(width)) % width  # azimuth φ_c -> -φ_c

    def round_trip(self, scans: list["Scan"]) -> dict:
        """Share of points with a pixel of their own (the rest shared one with a nearer point) and
        each kept point's reconstruction error, also against the guaranteed bound
        (:meth:`typ.projection.RangeLayout.error_bound`; 1 = at the bound)."""
        layout, kept, inside, worst, errors = self.layout, 0, 0, 0.0, []
        for s in scans:
            px = range_pixels(s.points, layout)
            # range_to_points returns pixels in row-major order: sort the kept points the same way
            order = np.flatnonzero(px.winner)
            order = order[np.argsort(px.row[order] * layout.width + px.col[order])]
            back = range_to_points(range_image(s.points, layout), layout)
            err = np.linalg.norm(back.astype(np.float64) - s.points[order, :3].astype(np.float64), axis=1)
            worst = max(worst, float((err / layout.error_bound(px.depth[order], px.row[order])).max()))
            errors.append(err)
            kept, inside = kept + px.kept, inside + px.inside
        err = np.concatenate(errors)
        return {"points_kept": round(kept / max(inside, 1), 4), "median_error_m": float(np.median(err)),
                "max_error_m": float(err.max()), "max_error_over_bound": worst}


class BevRepresentation(Representation):
    """The BEV image (2 channels: occupancy, height of the highest point)."""

    @property
    def shape(self) -> tuple[int, int, int]:
        return (2, self.layout.shape[0], self.layout.shape[1])

    def image(self, points: np.ndarray) -> np.ndarray:
        return bev_image(points, self.layout)

    def empty_image(self) -> np.ndarray:
        img = np.zeros(self.shape, np.float32)
        img[1] = self.layout.z_range[0]
        return img

    def image_points(self, image: np.ndarray) -> np.ndarray:
        return bev_to_points(image, self.layout)

    def mirror_index(self, width: int) -> np.ndarray:
        return np.arange(width)[::-1]  # y_j -> -y_j on a grid symmetric in y

    def round_trip(self, scans: list["Scan"]) -> dict:
        """Share of points that are the highest of their cell (the rest lie below it); the kept
        ones come back within half a cell in x and y, exactly in z."""
        kept = sum(int(bev_image(s.points, self.layout)[0].sum()) for s in scans)
        return {"points_kept": round(kept / max(sum(len(s.points) for s in scans), 1), 4)}


def representations(cfg: DdpmConfig, where: str = "params.yaml") -> dict[str, Representation]:
    """``range``: the domain sensor's beams x ``range_image.azimuth_bins``; ``bev``: ``bev.grid``."""
    layout = RangeLayout.from_sensor(domain_spec(cfg.domain).sensor, cfg.range_image.azimuth_bins)
    factor = 2 ** (len(cfg.unet.block_out_channels) - 1)
    ph, pw = cfg.range_image.patch
    if layout.height % ph or (layout.height // ph) % factor:
        raise TypError(where, "ddpm.range_image.patch", f"a block whose height divides the {layout.height} beams "
                       f"into a multiple of 2^(levels-1) = {factor}", [ph, pw])
    g = cfg.bev.grid
    if g.y_range[0] != -g.y_range[1]:
        raise TypError(where, "ddpm.bev.grid.y_range", "a range symmetric about 0 (training mirrors y -> -y)",
                       list(g.y_range))
    grid = Grid(g.x_range, g.y_range, g.z_range, g.shape)
    return {"range": RangeRepresentation("range", layout, tuple(cfg.range_image.patch), cfg.range_image.depth),
            "bev": BevRepresentation("bev", grid, tuple(cfg.bev.patch))}


def pixel_set(rep: Representation, scans: list[Scan], *, mirror: bool = False) -> torch.Tensor:
    """(N, C, H, W) float32 pixels of every scan (then every mirrored scan when ``mirror``)."""
    x = np.stack([rep.pixels(s.points) for s in scans])
    if mirror:
        x = np.concatenate([x, rep.mirror(x)])
    return torch.from_numpy(np.ascontiguousarray(x))


def data_key(scans: list[Scan]) -> list:
    """What identifies a training set in run keys: its view keys and point counts."""
    return [[*s.key, int(len(s.points))] for s in scans]
