"""Top-down pictures of generated scenarios, in the style of the paper's Figs. 5 and 7, and animations.

Map: drivable area in light grey, lane centrelines in grey, crosswalks hatched. Agents: the initial
state as a dot, the goal as a star, and a line pairing them (Fig. 5) or, when trajectories are
given, the infilled trajectory (Fig. 7); one colour per agent type. `animate_scenario` moves each
agent as an oriented box of its type's size along its trajectory over the 6 s (an animated GIF
written by matplotlib's animation module with Pillow; no ffmpeg needed).
"""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from tdiff_jax import files, datatypes  # noqa: E402

TYPE_COLOURS = {"vehicle": "tab:blue", "bus": "tab:purple", "pedestrian": "tab:green", "cyclist": "tab:orange",
                "motorcyclist": "tab:red"}


def draw_map(ax, scene: datatypes.Scene) -> None:
  """The drivable areas, lane centrelines and crosswalks of one unbatched numpy scene."""
  for ring, ok in zip(scene.da_xy, scene.da_valid):
    if ok.any():
      ax.fill(ring[ok, 0], ring[ok, 1], color="0.92", zorder=0)
  k3 = scene.num_points // 3
  crosswalk = datatypes.POLYGON_TYPES.index("PEDESTRIAN")
  for p in np.flatnonzero(scene.pl_valid):
    centre = scene.pt_xy[p, 2 * k3:]
    if scene.pl_type[p] == crosswalk:
      left, right = scene.pt_xy[p, :k3], scene.pt_xy[p, k3:2 * k3]
      ax.fill(np.r_[left[:, 0], right[::-1, 0]], np.r_[left[:, 1], right[::-1, 1]], facecolor="none",
              edgecolor="0.55", hatch="///", lw=0.3, zorder=1)
    else:
      ax.plot(centre[:, 0], centre[:, 1], color="0.6", lw=0.6, zorder=1)


def draw_hl_scenario(ax, scene: datatypes.Scene, state: np.ndarray, valid: np.ndarray, agent_type: np.ndarray,
                     title: str = "", trajectories: np.ndarray | None = None, legend: bool = True) -> None:
  """Draws one scene (unbatched numpy `Scene`) with states `[A, 2, >=2]` (metres) and optional
  trajectories `[A, H, 2]` (metres) on a matplotlib axis."""
  draw_map(ax, scene)
  for a in np.flatnonzero(valid):
    colour = TYPE_COLOURS[datatypes.AGENT_TYPES[int(agent_type[a])]]
    (x0, y0), (x1, y1) = state[a, 0, :2], state[a, 1, :2]
    if trajectories is None:
      ax.plot([x0, x1], [y0, y1], color=colour, lw=0.8, alpha=0.7, zorder=2)
    else:
      ax.plot(trajectories[a, :, 0], trajectories[a, :, 1], color=colour, lw=1.2, alpha=0.85, zorder=2)
    ax.scatter([x0], [y0], color=colour, s=18, zorder=3)
    ax.scatter([x1], [y1], color=colour, marker="*", s=70, zorder=3)
  if legend:
    _legend(ax, valid, agent_type)
  ax.set_aspect("equal")
  ax.set_title(title, fontsize=9)


def _legend(ax, valid: np.ndarray, agent_type: np.ndarray) -> None:
  handles = [plt.Line2D([], [], color=c, marker="o", ls="", label=t) for t, c in TYPE_COLOURS.items()
             if (agent_type[valid] == datatypes.AGENT_TYPES.index(t)).any()]
  handles += [plt.Line2D([], [], color="k", marker="o", ls="", label="initial"),
              plt.Line2D([], [], color="k", marker="*", ls="", markersize=10, label="goal")]
  ax.legend(handles=handles, loc="upper right", fontsize=7)


def plot_hl_scenario(scene: datatypes.Scene, state: np.ndarray, valid: np.ndarray, agent_type: np.ndarray,
                     path: Path | str, title: str = "", trajectories: np.ndarray | None = None) -> None:
  """One scene (see `draw_hl_scenario`) to a PNG."""
  fig, ax = plt.subplots(figsize=(7, 7))
  draw_hl_scenario(ax, scene, state, valid, agent_type, title, trajectories)
  ax.set_xlabel("x (m, scene frame)")
  ax.set_ylabel("y (m)")
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def plot_comparison_grid(rows: list[tuple[datatypes.Scene, np.ndarray, str]], path: Path | str,
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


def trajectory_headings(trajectories: np.ndarray, observed: np.ndarray, initial_heading: np.ndarray,
                        min_step_m: float = 0.05) -> np.ndarray:
  """`[A, T]` heading (rad) of each agent along its trajectory `[A, T, 2]`: the direction of motion
  between observed steps, kept while the agent moves less than `min_step_m` a step (standing still),
  starting from `initial_heading` `[A]`."""
  num_agents, steps = trajectories.shape[:2]
  out = np.zeros((num_agents, steps))
  for a in range(num_agents):
    h = float(initial_heading[a])
    for t in range(steps):
      nxt = t + 1 if t + 1 < steps else t
      prev = t if t + 1 < steps else t - 1
      if prev >= 0 and observed[a, prev] and observed[a, nxt]:
        d = trajectories[a, nxt] - trajectories[a, prev]
        if np.hypot(*d) >= min_step_m:
          h = float(np.arctan2(d[1], d[0]))
      out[a, t] = h
  return out


def box_outline(centre: np.ndarray, heading: float, size: tuple[float, float]) -> np.ndarray:
  """`[4, 2]` corners of a box of (length, width) metres at `centre`, turned by `heading`."""
  length, width = size
  local = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]]) * [length, width]
  c, s_ = np.cos(heading), np.sin(heading)
  return local @ np.array([[c, s_], [-s_, c]]) + centre


def animate_scenario(scene: datatypes.Scene, trajectories: np.ndarray, observed: np.ndarray, valid: np.ndarray,
                     agent_type: np.ndarray, initial_heading: np.ndarray, path: Path | str, title: str = "",
                     frame_stride: int = 2, step_s: float = 0.1) -> int:
  """Writes an animated GIF of agents moving along their trajectories; returns the frame count.

  Args:
    scene: one unbatched numpy scene (its map is drawn underneath).
    trajectories: `[A, T, 2]` positions (m, scene frame), T steps of `step_s` seconds (AV2: 60 x 0.1 s).
    observed: `[A, T]` which steps exist (ground truth has gaps; generated trajectories do not).
    valid, agent_type: `[A]`. initial_heading: `[A]` rad, the heading before the first move.
    frame_stride: draw every n-th step; the GIF plays in real time.
  Each agent is a box of its type's size (`datatypes.AGENT_BOX_SIZE_M`) turned along its motion, with its
  trail so far; its first and last observed positions are marked (dot, star) as in the still pictures.
  """
  from matplotlib import animation
  from matplotlib.patches import Polygon

  agents = [a for a in np.flatnonzero(valid) if observed[a].any()]
  headings = trajectory_headings(trajectories, observed, initial_heading)
  fig, ax = plt.subplots(figsize=(6, 6))
  draw_map(ax, scene)
  boxes, trails = {}, {}
  for a in agents:
    colour = TYPE_COLOURS[datatypes.AGENT_TYPES[int(agent_type[a])]]
    seen = np.flatnonzero(observed[a])
    first, last = trajectories[a, seen[0]], trajectories[a, seen[-1]]
    ax.scatter([first[0]], [first[1]], color=colour, s=14, zorder=3)
    ax.scatter([last[0]], [last[1]], color=colour, marker="*", s=60, zorder=3)
    boxes[a] = ax.add_patch(Polygon(np.zeros((4, 2)), closed=True, facecolor=colour, edgecolor="k", lw=0.4,
                                    alpha=0.9, zorder=4))
    (trails[a],) = ax.plot([], [], color=colour, lw=1.0, alpha=0.7, zorder=2)
  pts = trajectories[np.asarray(agents, int)][observed[np.asarray(agents, int)]] if agents else np.zeros((0, 2))
  if len(pts):  # frame the agents, with room for the map around them
    lo, hi = pts.min(0) - 25.0, pts.max(0) + 25.0
    half = max(hi - lo) / 2
    mid = (lo + hi) / 2
    ax.set_xlim(mid[0] - half, mid[0] + half)
    ax.set_ylim(mid[1] - half, mid[1] + half)
  ax.set_aspect("equal")
  _legend(ax, valid, agent_type)
  clock = ax.text(0.02, 0.97, "", transform=ax.transAxes, fontsize=9, va="top")
  ax.set_title(title, fontsize=9)
  frames = list(range(0, trajectories.shape[1], frame_stride))

  def draw(t):
    for a in agents:
      seen = np.flatnonzero(observed[a, :t + 1])
      if not len(seen):  # not there yet
        boxes[a].set_visible(False)
        continue
      now = seen[-1]
      size = datatypes.AGENT_BOX_SIZE_M[datatypes.AGENT_TYPES[int(agent_type[a])]]
      boxes[a].set_xy(box_outline(trajectories[a, now], headings[a, now], size))
      boxes[a].set_visible(True)
      trails[a].set_data(trajectories[a, seen, 0], trajectories[a, seen, 1])
    clock.set_text(f"t = {(t + 1) * step_s:.1f} s")
    return [*boxes.values(), *trails.values(), clock]

  anim = animation.FuncAnimation(fig, draw, frames=frames, blit=False)
  path = Path(path)
  tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}.gif")  # atomic: never half a GIF under the final name
  try:
    anim.save(str(tmp), writer=animation.PillowWriter(fps=max(1, round(1.0 / (step_s * frame_stride)))), dpi=80)
    os.replace(tmp, path)
  except OSError as e:
    raise files.named_os_error(e, path) from e
  finally:
    plt.close(fig)
    tmp.unlink(missing_ok=True)
  return len(frames)
