"""Render reports/ssc_ground_truth.png: one simulated ego map (top class per column, a side slice) with the ego LiDAR.

    /work/cpu .venv/bin/python bench/ssc_render_truth.py
"""
import numpy as np, matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.colors import ListedColormap
from typ.ssc import scene_occupancy
from typ.sim import simulate_scenario
m = scene_occupancy(domain="real_cav", seed=3, n_frames=1, n_agents=2)[0][0]
sc = simulate_scenario(domain="real_cav", seed=3, n_frames=1, n_agents=2, azimuth_step_deg=0.8)[0]
pts = sc.ego.points
top = np.zeros(m.shape[:2], int)
for z in range(m.shape[2]):
    top = np.where(m[:, :, z] > 0, m[:, :, z], top)
cmap = ListedColormap(["white", "dimgray", "blue", "yellowgreen", "orange", "green", "red"])
fig, ax = plt.subplots(1, 2, figsize=(14, 7))
ax[0].imshow(top.T, origin="lower", cmap=cmap, vmin=0, vmax=6, extent=(-50, 50, -50, 50))
ax[0].scatter(pts[:, 0], pts[:, 1], s=0.05, c="k")
ax[0].set_xlim(-50, 50); ax[0].set_ylim(-50, 50); ax[0].set_title("top class per column + ego LiDAR")
side = np.zeros((m.shape[0], m.shape[2]), int)
for y in range(60, 68):
    side = np.where(m[:, y, :] > 0, m[:, y, :], side)
ax[1].imshow(side.T, origin="lower", cmap=cmap, vmin=0, vmax=6, extent=(-50, 50, -3, 5), aspect=4)
ax[1].set_title("side slice y in [-3.1, 3.1] m")
fig.savefig("reports/ssc_ground_truth.png", dpi=80)
print(np.bincount(m.ravel(), minlength=7))
