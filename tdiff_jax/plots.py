"""Charts of numbers: Table I's distributions and rates (from `evaluate`'s result) and training curves.

* `distribution_figures`: per distribution metric and endpoint, the ground-truth and model histograms
  overlaid on the metric's own bins (`metrics.HISTOGRAMS`), each as the share of its agents per bin,
  with the JS value in the title.
* `rate_figure`: collision, off-road and near-edge of ground truth, the model and, when evaluated,
  the guided model, initial and goal side by side.
* `training_curves`: a workdir's `metrics.jsonl` (train and validation losses, learning rate, steps/s).

Top-down pictures of scenes live in `viz`; both draw with matplotlib's Agg backend (files only).
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from tdiff_jax import metrics  # noqa: E402

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
