"""Statistics of AV2 data: of scenario folders, to set synthetic worlds beside real AV2, and of a
training split, for samplers that place agents like the training data (`training_agent_stats`).

  python -m tdiff_jax.data.stats DIR [DIR ...]

prints one JSON object per directory: scenes read and skipped, tracks per scenario, kept agents per
scene (by the default selection) and by type, initial speed of kept agents, the goal's offset from the
initial position (per-axis std and length), lanes, crosswalks and polygons per map, lane length.
"""

from __future__ import annotations

import collections
import json
from pathlib import Path

import numpy as np

from tdiff_jax import cli, datatypes
from tdiff_jax.data import av2_io, map_features, normalize
from tdiff_jax.data import config as config_lib
from tdiff_jax.data import scene_builder


def _summary(values) -> dict[str, float]:
  v = np.asarray(values, np.float64)
  if v.size == 0:
    return {}
  return {"min": round(float(v.min()), 2), "median": round(float(np.median(v)), 2),
          "mean": round(float(v.mean()), 2), "max": round(float(v.max()), 2)}


def _vector_summary(rows: list) -> dict:
  """Per-axis mean and std (x, y) and the length's summary of `[N, 2]` vectors (m)."""
  v = np.concatenate(rows).astype(np.float64) if rows else np.zeros((0, 2))
  if not len(v):
    return {}
  return {"mean_xy": np.round(v.mean(0), 3).tolist(), "std_xy": np.round(v.std(0), 2).tolist(),
          "length": _summary(np.linalg.norm(v, axis=-1))}


def training_agent_stats(source, max_pairs: int = 4000) -> dict:
  """What a sampler needs to place agents like the training data: (polygons, agents) pairs per scene
  (a seeded subset of at most `max_pairs`) and the frequency of each agent type.

  `source`: a split from `batches.open_split` or `batches.load_split` (no scene is read).
  """
  polys, agents = np.asarray(source.num_polygons), np.asarray(source.num_agents)
  pick = np.random.default_rng(0).permutation(len(polys))[:max_pairs]
  counts = np.asarray(source.manifest["splits"][source.split]["agent_type_counts"], np.float64)
  return {"polygons_agents": [[int(polys[i]), int(agents[i])] for i in sorted(pick)],
          "type_frequency": (counts / max(counts.sum(), 1)).tolist()}


def folder_stats(folders: list[Path], config=None) -> dict:
  config = config_lib.scene_config(config)
  tracks, kept, lanes, crosswalks, polygons, lane_len = [], [], [], [], [], []
  speeds, vehicle_speeds, offsets = [], [], []
  by_type = collections.Counter()
  skipped = {}
  for folder in folders:
    try:
      raw = av2_io.read_scenario_folder(folder)
      scene, _ = scene_builder.build_scene(raw, config)
    except av2_io.BadScenarioError as e:
      skipped[folder.name] = e.reason
      continue
    n = int(scene.agent_valid.sum())
    tracks.append(raw.tracks.num_tracks)
    kept.append(n)
    s0 = scene.agent_state[:n, 0, 2]
    t = scene.agent_type[:n]
    speeds += s0.tolist()
    vehicle_speeds += s0[t == 0].tolist()
    state = scene.agent_state[:n]
    offsets.append(state[:, 1, :2] - state[:, 0, :2])
    by_type.update(datatypes.AGENT_TYPES[i] for i in t)
    lanes.append(len(raw.lanes))
    crosswalks.append(len(raw.polylines.crosswalk_edges))
    polygons.append(int(scene.pl_valid.sum()))
    lane_len += [float(np.linalg.norm(np.diff(p.center, axis=0), axis=-1).sum())
                 for p in map_features.lane_polygons(raw)]
  return {
      "scenes": len(kept), "skipped": skipped,
      "tracks_per_scenario": _summary(tracks),
      "kept_agents_per_scene": _summary(kept),
      "kept_agents_by_type": dict(sorted(by_type.items())),
      "initial_speed_mps": _summary(speeds),
      "initial_speed_below_1mps": round(float(np.mean(np.asarray(speeds) < 1.0)), 2) if speeds else None,
      "vehicle_initial_speed_mps": _summary(vehicle_speeds),
      "goal_offset_m": _vector_summary(offsets),
      "lanes_per_map": _summary(lanes),
      "crosswalks_per_map": _summary(crosswalks),
      "polygons_per_map": _summary(polygons),
      "lane_length_m": _summary(lane_len),
  }


def define_flags(values) -> None:  # positional arguments only
  del values


def run(f, args: list[str]) -> None:
  del f
  if not args:
    raise SystemExit("usage: python -m tdiff_jax.data.stats DIR [DIR ...]")
  for d in args:
    print(json.dumps({"dir": d, **folder_stats(av2_io.list_scenario_folders(d))}))


main = cli.entry_point(define_flags, run)  # `python -m tdiff_jax.data.stats DIR...` or `main(["DIR", ...])`


if __name__ == "__main__":
  main()
