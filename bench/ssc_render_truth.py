"""Render reports/ssc_ground_truth.png: one simulated real_cav ego map (top class per column with the
ego's LiDAR returns, and a side slice through the ego's lane).

    /work/cpu .venv/bin/python bench/ssc_render_truth.py
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # runnable from a checkout

from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402

from typ.reporting import subplots  # noqa: E402
from typ.sim import simulate_scenario  # noqa: E402
from typ.ssc import SSC_CLASSES, scene_occupancy  # noqa: E402


def top_class(labels: np.ndarray, axis: int) -> np.ndarray:
    """The last non-empty class along ``axis`` (the highest voxel for z)."""
    out = np.zeros(np.delete(labels.shape, axis), dtype=int)
    for k in range(labels.shape[axis]):
        layer = np.take(labels, k, axis=axis)
        out = np.where(layer > 0, layer, out)
    return out


def main() -> None:
    labels = scene_occupancy(domain="real_cav", seed=3, n_frames=1, n_agents=2)[0][0]
    points = simulate_scenario(domain="real_cav", seed=3, n_frames=1, n_agents=2, azimuth_step_deg=0.8)[0].ego.points
    cmap = ListedColormap(["white", "dimgray", "blue", "yellowgreen", "orange", "green", "red"])
    fig, ax = subplots(1, 2, figsize=(14, 7))
    ax[0].imshow(top_class(labels, 2).T, origin="lower", cmap=cmap, vmin=0, vmax=6, extent=(-50, 50, -50, 50))
    ax[0].scatter(points[:, 0], points[:, 1], s=0.05, c="k")
    ax[0].set(xlim=(-50, 50), ylim=(-50, 50), title="top class per column + ego LiDAR")
    ax[1].imshow(top_class(labels[:, 60:68], 1).T, origin="lower", cmap=cmap, vmin=0, vmax=6,
                 extent=(-50, 50, -3, 5), aspect=4)
    ax[1].set_title("side view of y in [-3.1, 3.1] m")
    handles = [Rectangle((0, 0), 1, 1, color=cmap(i)) for i in range(1, 7)]
    ax[1].legend(handles, SSC_CLASSES[1:], loc="upper right")
    fig.savefig("reports/ssc_ground_truth.png", dpi=80)
    print(dict(zip(SSC_CLASSES, np.bincount(labels.ravel(), minlength=7).tolist())))


if __name__ == "__main__":
    main()
