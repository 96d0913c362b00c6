"""What every benchmark shares: the machine's description, timing and peak memory. Each benchmark
prints one JSON object on stdout (progress lines on stderr), with the official figure and the ratio
beside ours where the official code was timed."""

from __future__ import annotations

import json
import os
import platform
import resource
import statistics
import sys
import time
from typing import Callable


def machine() -> dict:
  """The device and host a figure was measured on."""
  import jax

  d = jax.devices()[0]
  return {"device": d.device_kind, "platform": d.platform, "host": platform.processor() or platform.machine(),
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
  with `model_overrides`), its sampler's agent buckets and its polygon buckets, the varied scene set (`scene_set.timing_scenes`), the model with random weights split into
  (graphdef, params), the diffusion schedule and the normalisation from the scene set."""
  import scene_set
  from configs import hl as hl_config
  from tdiff_jax import diffusion, models
  from tdiff_jax.data import batches

  config = hl_config.get_config(variant)
  config.model.update(model_overrides or {})
  scenes = scene_set.timing_scenes(config.data.scene)
  graphdef, params = models.split_model(models.create_model(config))
  return {"config": config, "a_buckets": batches.sampler_agent_buckets(config.data), "p_buckets": config.data.polygon_buckets,
          "scenes": scenes, "graphdef": graphdef, "params": params,
          "sched": diffusion.schedule_from_config(config.diffusion), "norm": norm_stats(config, scenes)}


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
