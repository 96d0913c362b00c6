"""The host process's compiled programs: dropped before Linux's per-process memory-map limit.

Memory maps: XLA's CPU runtime keeps each compiled program's kernels in memory mappings of their own,
about 1,370 for one of the CPU default's guided samplers (one agent bucket, a throwaway count of
`/proc/self/maps`), and Linux refuses a process more than `vm.max_map_count` (65,530 by default): a batch
job that compiles a few dozen sampler shapes (scenes of many sizes) then dies inside LLVM ("Unable to
allocate section memory"). `drop_compiled_near_map_limit` drops every compiled program (`jax.clear_caches`;
they compile again when next called) once the process holds more than `MAP_SHARE` of the limit;
`evaluate` and `sample.py` call it once a batch. A run over scenes of many sizes compiles a program per
batch shape (`data.batches.sampler_batches`: agent bucket x polygon bucket x 1, 2, 4 or 8 scenes) for
the sampler, the infiller and the repair's checks: a whole AV2 split meets more than the limit holds.
"""

from __future__ import annotations

import sys
from pathlib import Path

_MAP_LIMIT = Path("/proc/sys/vm/max_map_count")
# Compiled programs are dropped above this share of the limit: the rest leaves room for the twenty-odd
# programs one more batch may compile before the next check.
MAP_SHARE = 0.6


def memory_maps() -> tuple[int, int] | None:
  """(memory mappings this process holds, the kernel's per-process limit `vm.max_map_count`), or None
  where they cannot be read (not Linux)."""
  try:
    limit = int(_MAP_LIMIT.read_text())
    with open("/proc/self/maps", "rb") as f:
      return f.read().count(b"\n"), limit
  except (OSError, ValueError):
    return None


def drop_compiled_near_map_limit(share: float = MAP_SHARE) -> bool:
  """Drops every compiled JAX program (`jax.clear_caches()`) when this process holds more than `share`
  of its memory-map limit (`memory_maps`), saying so on standard error; returns whether it did. The
  programs compile again when next called, so results do not change; without it, a process that keeps
  compiling new shapes aborts once the limit is reached (module docstring)."""
  maps = memory_maps()
  if maps is None or maps[0] <= share * maps[1]:
    return False
  import jax

  jax.clear_caches()
  after = memory_maps()
  print(f"tdiff_jax: dropped the compiled programs (they compile again when needed): this process held "
        f"{maps[0]} memory maps of the {maps[1]} Linux allows it (vm.max_map_count), {after[0] if after else '?'} "
        "after", file=sys.stderr)
  return True
