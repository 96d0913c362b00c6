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
          "host_cpus": os.cpu_count(), "python": platform.python_version(), "jax": jax.__version__}


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
