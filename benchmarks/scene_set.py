"""The varied scene set of the speed benchmarks: the sizes of the 14 real scenes the official code was timed on.

The official timings (README, Benchmarks) ran on 14 real AV2 scenes, vehicles only, with these agent and
polygon counts, batch 1 each scene once and batch 8 as two fixed batches in set order (scenes 1 to 8,
then 9 to 14 and 1 to 2). `timing_scenes` rebuilds scenes of exactly those counts from the real AV2 maps
of tests/data and synthetic worlds: each takes the smallest map with at least its polygon count (the
150-polygon scene, larger than any map at hand, is two maps side by side, 400 m apart), keeps its
polygons nearest the origin up to the count, and places its vehicles on lane centrelines (agent i
starts at the first point of lane i and ends at its last, at 8 m/s). Deterministic.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from tdiff_jax import datatypes
from tdiff_jax.data import av2_io, scene_builder, synthetic

ROOT = Path(__file__).resolve().parent.parent
# (vehicles, polygons) of the 14 real scenes the official code was timed on, in set order.
OFFICIAL_TIMING_SET = ((4, 71), (2, 65), (9, 83), (14, 39), (3, 53), (6, 51), (6, 38), (2, 110), (7, 69),
                       (8, 44), (33, 79), (19, 104), (11, 36), (12, 150))
BATCHES_OF_8 = (tuple(range(0, 8)), tuple(range(8, 14)) + (0, 1))
_SYNTHETIC_MAPS = 12  # synthetic worlds in the pool of maps (seed 0, indices 0..11)
_SIDE_BY_SIDE_M = 400.0


def _map_pool(data_config) -> list[datatypes.Scene]:
  pool = []
  for folder in av2_io.list_scenario_folders(ROOT / "tests" / "data"):
    pool.append(scene_builder.load_scene(folder, data_config, require_agents=False)[0])
  with tempfile.TemporaryDirectory() as tmp:
    for i in range(_SYNTHETIC_MAPS):
      folder = synthetic.write_scenario(synthetic.generate_scenario(0, i), Path(tmp))
      pool.append(scene_builder.load_scene(folder, data_config, require_agents=False)[0])
  return sorted(pool, key=lambda s: int(s.pl_valid.sum()))


def _with_polygons(scene: datatypes.Scene, extra: datatypes.Scene, shift: np.ndarray) -> datatypes.Scene:
  """`scene` with the valid polygons of `extra` (moved by `shift` metres) appended, up to the cap."""
  d, e = scene.to_dict(), extra.to_dict()
  n, m = int(scene.pl_valid.sum()), int(extra.pl_valid.sum())
  m = min(m, scene.num_polygons - n)
  for name in datatypes.POLYGON_FIELDS:
    d[name] = d[name].copy()
    d[name][n:n + m] = e[name][:m]
  d["pl_xy"][n:n + m] += shift
  d["pt_xy"][n:n + m] += shift
  d["pl_edge"] = d["pl_edge"].copy()
  d["pl_edge"][n:n + m, n:n + m] = e["pl_edge"][:m, :m]
  return datatypes.Scene.from_dict(d)


def _keep_polygons(scene: datatypes.Scene, p: int) -> datatypes.Scene:
  d = scene.to_dict()
  for name in datatypes.POLYGON_FIELDS:
    d[name] = d[name].copy()
    d[name][p:] = 0
  d["pl_edge"] = d["pl_edge"].copy()
  d["pl_edge"][p:] = 0
  d["pl_edge"][:, p:] = 0
  return datatypes.Scene.from_dict(d)


def place_vehicles(scene: datatypes.Scene, n: int) -> datatypes.Scene:
  """`n` valid vehicles: agent i from the first to the last centreline point of lane i (cycling)."""
  k3 = scene.num_points // 3
  lanes = np.flatnonzero(scene.pl_valid & (scene.pl_type != datatypes.POLYGON_TYPES.index("PEDESTRIAN")))
  pick = lanes[np.arange(n) % len(lanes)]
  centre = scene.pt_xy[pick, 2 * k3:]
  a_cap = scene.num_agents
  state = np.zeros((a_cap, 2, 4), np.float32)
  state[:n, 0, :2], state[:n, 1, :2] = centre[:, 0], centre[:, -1]
  state[:n, :, 2] = 8.0
  state[:n, :, 3] = scene.pt_heading[pick, 2 * k3][:, None]
  future = np.zeros_like(scene.agent_future)
  steps = np.linspace(0.0, 1.0, future.shape[1])[None, :, None]
  future[:n] = centre[:, :1] * (1 - steps) + centre[:, -1:] * steps
  future_valid = np.zeros_like(scene.agent_future_valid)
  future_valid[:n] = True
  return scene.replace(agent_state=state, agent_valid=np.arange(a_cap) < n,
                       agent_type=np.zeros(a_cap, np.int32), agent_future=future.astype(np.float32),
                       agent_future_valid=future_valid)


def timing_scenes(data_config) -> list[datatypes.Scene]:
  """The 14 scenes of `OFFICIAL_TIMING_SET`, in set order, padded to the data config's caps."""
  pool = _map_pool(data_config)
  counts = [int(s.pl_valid.sum()) for s in pool]
  out = []
  for n, p in OFFICIAL_TIMING_SET:
    fits = [i for i, c in enumerate(counts) if c >= p]
    if fits:
      scene = pool[fits[0]]
    else:  # two of the largest maps side by side
      scene = _with_polygons(pool[-1], pool[-2], np.array([_SIDE_BY_SIDE_M, 0.0], np.float32))
    scene = place_vehicles(_keep_polygons(scene, p), n)
    scene.validate()
    assert int(scene.pl_valid.sum()) == p and int(scene.agent_valid.sum()) == n
    out.append(scene)
  return out


def official_real_scenes(data_config) -> list[datatypes.Scene]:
  """The real AV2 scenes of tests/data that load (the three the official train step, infiller and DDPM-500
  were timed on, repeated to the batch size), with the agents `data_config` keeps."""
  out = []
  for folder in av2_io.list_scenario_folders(ROOT / "tests" / "data"):
    try:
      out.append(scene_builder.load_scene(folder, data_config)[0])
    except av2_io.BadScenarioError:
      pass
  return out


def repeated(scenes: list[datatypes.Scene], batch_size: int, distinct_maps: bool = False) -> list[datatypes.Scene]:
  """`scenes` cycled to `batch_size`; `distinct_maps`: each repeat's map moved by a millimetre per repeat, so
  that map encoders that encode each distinct map once (`map_encoder.encode_distinct`) encode every copy,
  as the official code does."""
  out = []
  for i in range(batch_size):
    scene, k = scenes[i % len(scenes)], i // len(scenes)
    if distinct_maps and k:
      d = scene.to_dict()
      d["pl_xy"] = d["pl_xy"] + np.float32(1e-3 * k)
      d["pt_xy"] = d["pt_xy"] + np.float32(1e-3 * k)
      scene = datatypes.Scene.from_dict(d)
    out.append(scene)
  return out
