"""Every picture the project draws, the one module that imports matplotlib (Agg backend: files only).

Scenes: top-down pictures of generated scenarios, in the style of the paper's Figs. 5 and 7, and animations.

Map: drivable area in light grey, lane centrelines in grey, crosswalks hatched. Agents: the initial
state as a dot, the goal as a star, and a line pairing them (Fig. 5) or, when trajectories are
given, the infilled trajectory (Fig. 7); one colour per agent type. `animate_scenario` moves each
agent as an oriented box of its type's size along its trajectory over the 6 s (an animated GIF
written by matplotlib's animation module with Pillow; no ffmpeg needed).

Charts of numbers: Table I's distributions and rates (from `evaluate`'s result) and training curves.
* `distribution_figures`: per distribution metric and endpoint, the ground-truth and model histograms
  overlaid on the metric's own bins (`metrics.HISTOGRAMS`), each as the share of its agents per bin,
  with the JS value in the title.
* `rate_figure`: collision, off-road and near-edge of ground truth, the model and, when evaluated,
  the guided model, initial and goal side by side.
* `training_curves`: a workdir's `metrics.jsonl` (train and validation losses, learning rate, steps/s).
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from tdiff_jax import datatypes, files, geometry, metrics  # noqa: E402

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
                     path: Path | str, title: str = "", trajectories: np.ndarray | None = None,
                     labels: dict[int, str] | None = None) -> None:
  """One scene (see `draw_hl_scenario`) to a PNG. `labels`: names written beside agents (row -> name), e.g. a
  spec's agents; the view then centres on them."""
  fig, ax = plt.subplots(figsize=(7, 7))
  draw_hl_scenario(ax, scene, state, valid, agent_type, title, trajectories)
  if labels:
    for a, name in labels.items():
      ax.annotate(name, state[a, 0, :2], xytext=(4, 4), textcoords="offset points", fontsize=8, weight="bold",
                  zorder=4)
    points = np.concatenate([state[list(labels), :, :2].reshape(-1, 2)]
                            + ([trajectories[list(labels)].reshape(-1, 2)] if trajectories is not None else []))
    centre, half = (points.max(0) + points.min(0)) / 2, max(30.0, float(np.ptp(points, 0).max()) / 2 + 15.0)
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
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
  corners = np.asarray(geometry.box_corners(trajectories, headings, geometry.box_sizes(agent_type)[:, None]))
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
      boxes[a].set_xy(corners[a, now])
      boxes[a].set_visible(True)
      trails[a].set_data(trajectories[a, seen, 0], trajectories[a, seen, 1])
    clock.set_text(f"t = {(t + 1) * step_s:.1f} s")
    return [*boxes.values(), *trails.values(), clock]

  anim = animation.FuncAnimation(fig, draw, frames=frames, blit=False)
  try:
    with files.atomic_path(path) as tmp:  # never half a GIF under the final name
      anim.save(str(tmp), writer=animation.PillowWriter(fps=max(1, round(1.0 / (step_s * frame_stride)))), dpi=80)
  finally:
    plt.close(fig)
  return len(frames)


# ---- charts of numbers ------------------------------------------------------------------------

ENDPOINTS = ("initial", "goal")
# Row keys of a Table I endpoint in `evaluate`'s result, and how the charts name them.
ROWS = {"GT": "ground truth", "model": "model", "guided": "model, guided"}
ROW_COLOURS = {"GT": "0.35", "model": "tab:blue", "guided": "tab:orange"}
METRIC_LABELS = {"speed": "speed (m/s)", "lateral_deviation": "distance to the nearest lane point (m)",
                 "local_density": "distance to the 5 nearest agents (m)",
                 "nearest_distance": "distance to the nearest agent (m)"}


def draw_distribution(ax, name: str, gt_counts, model_counts, title: str = "") -> dict:
  """Overlays the two histograms of metric `name` (counts on its `metrics.HISTOGRAMS` bins) as shares.

  Returns {"edges" `[bins + 1]`, "gt", "model": the bar heights drawn (`[bins]`, counts / their sum)}."""
  bins, top = metrics.HISTOGRAMS[name]
  edges = np.linspace(0.0, top, bins + 1)
  drawn = {"edges": edges}
  for who, counts, style in (("gt", gt_counts, dict(color=ROW_COLOURS["GT"], alpha=0.45, label="ground truth")),
                             ("model", model_counts, dict(color=ROW_COLOURS["model"], alpha=0.45, label="model"))):
    counts = np.asarray(counts, np.float64)
    share = counts / counts.sum() if counts.sum() > 0 else counts
    ax.bar(edges[:-1], share, width=np.diff(edges), align="edge", **style)
    drawn[who] = share
  used = np.flatnonzero((np.asarray(gt_counts) + np.asarray(model_counts)) > 0)
  if len(used):  # the bins with mass, not the whole range (nearest distance goes to 250 m)
    ax.set_xlim(0.0, edges[min(used.max() + 2, bins)])
  ax.set_xlabel(METRIC_LABELS[name], fontsize=8)
  ax.set_ylabel("share of agents", fontsize=8)
  ax.tick_params(labelsize=7)
  ax.legend(fontsize=7)
  ax.set_title(title, fontsize=9)
  return drawn


def distribution_figures(result: dict, out_dir: Path | str, convention: str = "official") -> list[Path]:
  """`dist_<metric>_<endpoint>.png` for each distribution metric and endpoint; returns the paths."""
  out_dir = Path(out_dir)
  hist = result["histograms"][convention]
  jsd_name = "JS distance" if convention == "official" else "JS divergence"
  paths = []
  for name in metrics.HISTOGRAMS:
    for e in ENDPOINTS:
      jsd = result["table_i"][convention][e]["model"][f"jsd_{name}"]
      fig, ax = plt.subplots(figsize=(5.0, 3.4))
      draw_distribution(ax, name, hist[e]["GT"][name], hist[e]["model"][name],
                        f"{name.replace('_', ' ')}, {e} states: {jsd_name} {_num(jsd)}")
      fig.tight_layout()
      path = out_dir / f"dist_{name}_{e}.png"
      fig.savefig(path, dpi=90)
      plt.close(fig)
      paths.append(path)
  return paths


def realism_figure(realism_result: dict, path: Path | str) -> Path:
  """Each realism feature's histograms (`evaluate`'s "realism" result; shares of its values) for the logged
  scenarios and every generated row, with the row's feature score."""
  features = realism_result["features"]
  hist = realism_result["histograms"]
  rows = list(realism_result["rows"])
  fig, axes = plt.subplots(3, 3, figsize=(12.0, 8.4))
  colours = dict(zip(rows, ["0.35", "tab:green", "tab:purple", "tab:blue", "tab:red", "tab:orange"]))
  for ax, (name, f) in zip(axes.ravel(), features.items()):
    width = 0.8 / len(rows)
    for j, row in enumerate(rows):
      counts = np.asarray(hist[row][name], np.float64)
      share = counts / counts.sum() if counts.sum() > 0 else counts
      score = realism_result["rows"][row][name]
      ax.bar(np.arange(f["bins"]) + (j - (len(rows) - 1) / 2) * width, share, width, color=colours[row],
             label=f"{row} ({_num(score, 2)})")
    if f["low"] is None:
      ax.set_xticks([0, 1], ["no", "yes"], fontsize=7)
    else:
      edges = np.linspace(f["low"], f["high"], f["bins"] + 1)
      ax.set_xticks(np.arange(f["bins"] + 1) - 0.5, [f"{e:.3g}" for e in edges], fontsize=6, rotation=45)
    ax.set_title(name.replace("_", " "), fontsize=9)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=6)
  fig.suptitle("Realism features: shares of values per bin (feature score in brackets)", fontsize=10)
  fig.tight_layout()
  fig.savefig(path, dpi=80)
  plt.close(fig)
  return Path(path)


def rate_figure(result: dict, path: Path | str, convention: str = "official") -> Path:
  """Collision (%), off-road (%) and near edge (m) per row of Table I, initial and goal."""
  table = result["table_i"][convention]
  rows = [r for r in ROWS if r in table["initial"]]
  fig, axes = plt.subplots(1, 3, figsize=(10.5, 3.2))
  for ax, (key, label) in zip(axes, (("collision_rate_pct", "collision (%)"), ("offroad_rate_pct", "off-road (%)"),
                                     ("near_edge_m", "nearest edge (m)"))):
    width = 0.8 / len(rows)
    for j, row in enumerate(rows):
      values = [table[e][row][key] for e in ENDPOINTS]
      bars = ax.bar(np.arange(len(ENDPOINTS)) + (j - (len(rows) - 1) / 2) * width, values, width,
                    color=ROW_COLOURS[row], label=ROWS[row])
      ax.bar_label(bars, labels=[_num(v, 1) for v in values], fontsize=6)
    ax.set_xticks(np.arange(len(ENDPOINTS)), ENDPOINTS, fontsize=8)
    ax.set_title(label, fontsize=9)
    ax.tick_params(labelsize=7)
  axes[0].legend(fontsize=7)
  fig.suptitle(f"Table I common-sense metrics ({convention} convention)", fontsize=9)
  fig.tight_layout()
  fig.savefig(path, dpi=90)
  plt.close(fig)
  return Path(path)


def training_curves(rows: list[dict], path: Path | str, title: str = "") -> Path:
  """Losses, learning rate and throughput of `metrics.jsonl` rows against the step."""
  def series(key):
    pts = [(r["step"], r[key]) for r in rows if isinstance(r.get(key), (int, float)) and math.isfinite(r[key])]
    return np.array(pts, np.float64).reshape(-1, 2)

  fig, axes = plt.subplots(2, 2, figsize=(10, 6.5))
  panels = ((axes[0, 0], "loss", (("loss", "train"), ("val_loss", "validation, parameters"),
                                  ("val_ema_loss", "validation, EMA"))),
            (axes[0, 1], "gradient norm", (("grad_norm", "train"),)),
            (axes[1, 0], "learning rate", (("lr", "learning rate"),)),
            (axes[1, 1], "throughput (steps/s)", (("steps_per_s", "steps/s"),)))
  for ax, name, keys in panels:
    for key, label in keys:
      pts = series(key)
      if len(pts):
        ax.plot(pts[:, 0], pts[:, 1], marker="o" if key.startswith("val") else None, ms=3, lw=1.2, label=label)
    if name == "loss":
      ax.set_yscale("log")
      ax.legend(fontsize=7)
    ax.set_title(name, fontsize=9)
    ax.set_xlabel("step", fontsize=8)
    ax.tick_params(labelsize=7)
  if title:
    fig.suptitle(title, fontsize=9)
  fig.tight_layout()
  fig.savefig(path, dpi=90)
  plt.close(fig)
  return Path(path)


def _num(x, digits: int = 3) -> str:
  return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"
