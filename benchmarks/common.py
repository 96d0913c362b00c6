"""What every benchmark shares: the machine's description, timing and peak memory. Each benchmark
prints one JSON object on stdout (progress lines on stderr), with the official figure and the ratio
beside ours where the official code was timed."""

from __future__ import annotations

import datetime
import json
import os
import platform
import resource
import statistics
import sys
import time
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from tdiff_jax import datatypes, sampling
from tdiff_jax.data import av2_io, scene_builder, synthetic
from tdiff_jax.lane_pull import LanePull


def machine() -> dict:
  """The device and host a figure was measured on."""
  import jax

  d = jax.devices()[0]
  return {"date": datetime.date.today().isoformat(),
          "device": d.device_kind, "platform": d.platform, "host": platform.processor() or platform.machine(),
          "cpu": cpu_model(), **cpu_generation(),
          "host_cpus": os.cpu_count(), "python": platform.python_version(), "jax": jax.__version__,
          # the sampler's and infiller's products: XLA's own kernels, or YNNPACK's (tdiff_jax/cpu_products.py)
          "ynn_products": os.environ.get("TDIFF_JAX_YNN_PRODUCTS", "0") == "1"}


def _cpuinfo() -> dict[str, str]:
  """The first processor's fields of Linux's /proc/cpuinfo (it holds every field the others repeat);
  empty where there is none."""
  fields = {}
  try:
    for line in open("/proc/cpuinfo"):
      key, _, value = line.partition(":")
      if not key.strip():
        break  # the blank line after the first processor's block
      fields.setdefault(key.strip(), value.strip())
  except OSError:
    pass
  return fields


def cpu_model() -> str:
  """The CPU's model name (Linux's /proc/cpuinfo), else the platform's processor string."""
  return _cpuinfo().get("model name") or platform.processor() or platform.machine()


# Vector extensions that decide which kernels XLA's CPU backend can use (and the bfloat16 and AMX products).
CPU_FEATURES = ("avx2", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16")


def cpu_generation() -> dict:
  """What tells two CPUs of one model name apart (virtual machines often report only "AMD EPYC"):
  `cpu_id`, the vendor's family and model numbers (Linux's /proc/cpuinfo; e.g. AMD family 25 model 1 is
  Zen 3, 25 model 17 Zen 4, 26 Zen 5), and `cpu_features`, which of `CPU_FEATURES` it has. Empty where
  /proc/cpuinfo does not give the family."""
  fields = _cpuinfo()
  if "cpu family" not in fields:
    return {}
  flags = set(fields.get("flags", "").split())
  return {"cpu_id": f"{fields.get('vendor_id', '?')} family {fields['cpu family']} model {fields.get('model', '?')}",
          "cpu_features": [f for f in CPU_FEATURES if f in flags]}


def norm_stats(config, scenes):
  """The model state's normalisation for `config` (goal offsets and headings as its model asks), from
  `scenes` (a list of `datatypes.Scene`) as the trainer computes it from a training split."""
  import numpy as np
  from tdiff_jax import datatypes
  from tdiff_jax.data import normalize
  from tdiff_jax.train import trainer

  d = datatypes.stack_scenes(scenes).to_dict()
  args = (np.asarray(d["agent_state"]), np.asarray(d["agent_valid"]), np.asarray(d["frame_scale"]))
  manifest = {"normalization": normalize.normalization_stats(*args),
              "goal_offset_normalization": normalize.offset_stats(*args)}
  return trainer.norm_stats(config, manifest)


def hl_setup(variant: str, model_overrides: dict | None = None) -> dict:
  """What an HL benchmark starts from: the config of `configs/hl.py:variant` (its `model` block updated
  with `model_overrides`), its sampler's agent buckets and its polygon buckets, the varied scene set (`timing_scenes`), the model with random weights split into
  (graphdef, params), the diffusion schedule and the normalisation from the scene set."""
  from configs import hl as hl_config
  from tdiff_jax import diffusion, models
  from tdiff_jax.data import batches

  config = hl_config.get_config(variant)
  config.model.update(model_overrides or {})
  scenes = timing_scenes(config.data.scene)
  graphdef, params = models.split_model(models.create_model(config))
  return {"config": config, "a_buckets": batches.sampler_agent_buckets(config.data), "p_buckets": config.data.polygon_buckets,
          "scenes": scenes, "graphdef": graphdef, "params": params,
          "sched": diffusion.schedule_from_config(config.diffusion), "norm": norm_stats(config, scenes),
          "lane_pull": LanePull.from_config(config)}


def scene_split(scenes: list):
  """The benchmark's scenes (one data config's caps) as a training split (`batches.SceneDataset`), for
  `trainer.map_inputs_cache`."""
  import numpy as np

  from tdiff_jax import datatypes
  from tdiff_jax.data import batches
  return batches.SceneDataset(datatypes.stack_scenes(scenes), np.array([f"scene_{i}" for i in range(len(scenes))]),
                              manifest={}, split="benchmark")


def median_s(fn: Callable[[], object], repeats: int) -> float:
  """Median wall time (s) of `repeats` calls of `fn` (jax results awaited), after one untimed call."""
  import jax

  jax.block_until_ready(fn())
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - t0)
  return statistics.median(times)


def peak_rss_mb() -> float:
  """This process's peak resident memory so far (MB)."""
  return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # KiB on Linux


def time_passes(one_pass: Callable[[int], None], repeats: int) -> dict:
  """Runs `one_pass(r)` once to compile (timed apart), then `repeats` times; the median pass in seconds.

  `one_pass` must block until its results are ready (`jax.block_until_ready`)."""
  t0 = time.perf_counter()
  one_pass(-1)
  first = time.perf_counter() - t0
  times = []
  for r in range(repeats):
    t0 = time.perf_counter()
    one_pass(r)
    times.append(time.perf_counter() - t0)
  return {"compile_and_first_pass_s": round(first, 2), "median_pass_s": statistics.median(times),
          "passes_s": [round(t, 4) for t in times], "peak_rss_mb": round(peak_rss_mb(), 1)}


def progress(row: dict) -> None:
  print(json.dumps(row), file=sys.stderr)


def report(result: dict) -> None:
  print(json.dumps(result))


def set_matmul_dtype(name: str) -> str:
  """The matrix-product numerics of a benchmark ("float32" or "bfloat16"), set before the model is built;
  returns what was set, for the JSON. On an accelerator through `jax_default_matmul_precision` (every
  product, attention's too): "highest" for float32 (a GPU's default would take TF32 products), "bfloat16"
  (bfloat16 operands, float32 accumulation). The CPU ignores that setting: there only float32."""
  import jax

  if jax.devices()[0].platform != "cpu":
    precision = "highest" if name == "float32" else "bfloat16"
    jax.config.update("jax_default_matmul_precision", precision)
    return f"{name} (jax_default_matmul_precision={precision})"
  if name != "float32":
    raise SystemExit(f"--matmul_dtype={name}: the CPU computes float32 products only")
  return name


# The varied scene set.
# The varied scene set of the speed benchmarks: the sizes of the 14 real scenes the official code was timed on.
#
# The official timings (docs/benchmarks.md) ran on 14 real AV2 scenes, vehicles only, with these agent and
# polygon counts, batch 1 each scene once and batch 8 as two fixed batches in set order (scenes 1 to 8,
# then 9 to 14 and 1 to 2). `timing_scenes` rebuilds scenes of exactly those counts from the real AV2 maps
# of tests/data and synthetic worlds: each takes the smallest map with at least its polygon count (the
# 150-polygon scene, larger than any map at hand, is two maps side by side, 400 m apart), keeps its
# polygons nearest the origin up to the count, and places its vehicles on lane centrelines (agent i
# starts at the first point of lane i and ends at its last, at 8 m/s). Deterministic.

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


# The sampler modes of the sampling benchmarks, their official figures and targets, and the varied set's batches.

MODES = {"ddim50": sampling.SamplerOptions("ddim", 10),
         "ddim50_guided": sampling.SamplerOptions("ddim", 10, ("clearance", "lane", "offroad")),
         "ddpm500": sampling.SamplerOptions("ddpm", 1),
         "dpmpp2m15": sampling.SamplerOptions("dpmpp2m", solver_steps=15),
         # The command lines' unguided default of earlier releases: 15 solver calls and 4 restarts of the last (19).
         "dpmpp2m15r4": sampling.SamplerOptions("dpmpp2m", solver_steps=15, restarts=4),
         # The command lines' unguided default: the same low-noise steps without the four calls above noise 12
         # (T is at 584): 11 calls and 4 restarts (15).
         "dpmpp2m11n12r4": sampling.SamplerOptions("dpmpp2m", solver_steps=11, solver_max_noise=12.0, restarts=4),
         # Two 12-call variants of it (docs/sampling.md): 8 solver calls and 4 restarts, or 11 and 1 restart.
         "dpmpp2m8n12r4": sampling.SamplerOptions("dpmpp2m", solver_steps=8, solver_max_noise=12.0, restarts=4),
         "dpmpp2m11n12r1": sampling.SamplerOptions("dpmpp2m", solver_steps=11, solver_max_noise=12.0, restarts=1),
         # The previous guided default: DDIM-50 and 4 restarts of its last call (54 calls).
         "ddim50r4_guided": sampling.SamplerOptions("ddim", 10, ("clearance", "lane", "offroad"), restarts=4),
         # The command lines' guided default: the same and 5 final cost steps (54 calls).
         "ddim50r4f5_guided": sampling.SamplerOptions("ddim", 10, ("clearance", "lane", "offroad"), restarts=4,
                                                      final_cost_steps=sampling.DEFAULT.final_cost_steps)}
# Official scenes/s on a 2-core CPU (docs/benchmarks.md) and the targets, by (mode, batch size).
# DDPM-500 was timed on the 3 real scenes of tests/data; the few-step solvers are held to the official DDIM-50
# (10x), the guided defaults to the official guided DDIM-50 (4x).
FEW_STEP = ("dpmpp2m15", "dpmpp2m15r4", "dpmpp2m11n12r4", "dpmpp2m8n12r4", "dpmpp2m11n12r1")
GUIDED_DEFAULTS = ("ddim50r4_guided", "ddim50r4f5_guided")
OFFICIAL = {("ddim50", 1): 4.11, ("ddim50", 8): 6.34, ("ddim50_guided", 8): 4.56, ("ddpm500", 8): 0.81,
            **{(m, b): {1: 4.11, 8: 6.34}[b] for m in FEW_STEP for b in (1, 8)},
            **{(m, 8): 4.56 for m in GUIDED_DEFAULTS}}
TARGET_RATIO = {"ddim50": 5.0, "ddim50_guided": 4.0, "ddpm500": 5.0, **{m: 10.0 for m in FEW_STEP},
                **{m: 4.0 for m in GUIDED_DEFAULTS}}


def batches_of(scenes: list[datatypes.Scene], batch_size: int, varied: bool = True) -> list[list[datatypes.Scene]]:
  if not varied:  # the real scenes: each alone, or one batch of them repeated, each copy's map encoded
    return [[s] for s in scenes] if batch_size == 1 else [repeated(scenes, batch_size, distinct_maps=True)]
  if batch_size == 1:
    return [[s] for s in scenes]
  if batch_size == 8:
    return [[scenes[i] for i in idx] for idx in BATCHES_OF_8]
  return [[scenes[(k + i) % len(scenes)] for i in range(batch_size)] for k in range(0, len(scenes), batch_size)]
