"""Top-down pictures of generated scenarios, in the style of the paper's Figs. 5 and 7.

Map: drivable area in light grey, lane centrelines in grey, crosswalks hatched. Agents: the initial
state as a dot, the goal as a star, and a line pairing them (Fig. 5) or, when trajectories are
given, the infilled trajectory (Fig. 7); one colour per agent type.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from tdiff_jax import types  # noqa: E402

TYPE_COLOURS = {"vehicle": "tab:blue", "bus": "tab:purple", "pedestrian": "tab:green", "cyclist": "tab:orange",
                "motorcyclist": "tab:red"}


def draw_hl_scenario(ax, scene: types.Scene, state: np.ndarray, valid: np.ndarray, agent_type: np.ndarray,
                     title: str = "", trajectories: np.ndarray | None = None, legend: bool = True) -> None:
  """Draws one scene (unbatched numpy `Scene`) with states `[A, 2, >=2]` (metres) and optional
  trajectories `[A, H, 2]` (metres) on a matplotlib axis."""
  for ring, ok in zip(scene.da_xy, scene.da_valid):
    if ok.any():
      ax.fill(ring[ok, 0], ring[ok, 1], color="0.92", zorder=0)
  k3 = scene.num_points // 3
  crosswalk = types.POLYGON_TYPES.index("PEDESTRIAN")
  for p in np.flatnonzero(scene.pl_valid):
    centre = scene.pt_xy[p, 2 * k3:]
    if scene.pl_type[p] == crosswalk:
      left, right = scene.pt_xy[p, :k3], scene.pt_xy[p, k3:2 * k3]
      ax.fill(np.r_[left[:, 0], right[::-1, 0]], np.r_[left[:, 1], right[::-1, 1]], facecolor="none",
              edgecolor="0.55", hatch="///", lw=0.3, zorder=1)
    else:
      ax.plot(centre[:, 0], centre[:, 1], color="0.6", lw=0.6, zorder=1)
  for a in np.flatnonzero(valid):
    colour = TYPE_COLOURS[types.AGENT_TYPES[int(agent_type[a])]]
    (x0, y0), (x1, y1) = state[a, 0, :2], state[a, 1, :2]
    if trajectories is None:
      ax.plot([x0, x1], [y0, y1], color=colour, lw=0.8, alpha=0.7, zorder=2)
    else:
      ax.plot(trajectories[a, :, 0], trajectories[a, :, 1], color=colour, lw=1.2, alpha=0.85, zorder=2)
    ax.scatter([x0], [y0], color=colour, s=18, zorder=3)
    ax.scatter([x1], [y1], color=colour, marker="*", s=70, zorder=3)
  if legend:
    handles = [plt.Line2D([], [], color=c, marker="o", ls="", label=t) for t, c in TYPE_COLOURS.items()
               if (agent_type[valid] == types.AGENT_TYPES.index(t)).any()]
    handles += [plt.Line2D([], [], color="k", marker="o", ls="", label="initial"),
                plt.Line2D([], [], color="k", marker="*", ls="", markersize=10, label="goal")]
    ax.legend(handles=handles, loc="upper right", fontsize=7)
  ax.set_aspect("equal")
  ax.set_title(title, fontsize=9)


def plot_hl_scenario(scene: types.Scene, state: np.ndarray, valid: np.ndarray, agent_type: np.ndarray,
                     path: Path | str, title: str = "", trajectories: np.ndarray | None = None) -> None:
  """One scene (see `draw_hl_scenario`) to a PNG."""
  fig, ax = plt.subplots(figsize=(7, 7))
  draw_hl_scenario(ax, scene, state, valid, agent_type, title, trajectories)
  ax.set_xlabel("x (m, scene frame)")
  ax.set_ylabel("y (m)")
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def plot_comparison_grid(rows: list[tuple[types.Scene, np.ndarray, str]], path: Path | str,
                         columns: tuple[str, ...] = ("ground truth", "generated")) -> None:
  """A grid with one row per map and one column per state set: `rows` holds (unbatched numpy scene,
  states `[C, A, 2, >=2]` in `columns` order, row title). Agents and types are the scene's."""
  n, c = len(rows), len(columns)
  fig, axes = plt.subplots(n, c, figsize=(3.6 * c, 3.6 * n), squeeze=False)
  for r, (scene, states, name) in enumerate(rows):
    for j, label in enumerate(columns):
      draw_hl_scenario(axes[r, j], scene, states[j], scene.agent_valid, scene.agent_type,
                       f"{name}: {label}", legend=False)
      axes[r, j].tick_params(labelsize=6)
  fig.tight_layout()
  fig.savefig(path, dpi=90)
  plt.close(fig)
