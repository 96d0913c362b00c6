"""The host process's memory: transparent huge pages for glibc's malloc, where XLA's CPU runtime allocates.

XLA's CPU runtime allocates a call's temporary buffers afresh on every call, and glibc serves blocks
that large with new memory mappings, whose pages the kernel faults in and zeroes 4 KiB at a time: 190 MB
of page faults (46,600 faults) per forward and backward pass of one Fourier embedding of 23,040 map
points. glibc's tunable `glibc.malloc.hugetlb=1` (glibc 2.35 and later) has malloc ask the kernel for
transparent huge pages (2 MiB) instead: a few hundred faults per call. A train step, one call with
large temporaries, gains most (README, Benchmarks: command 1's training 9 % more steps per second,
14 % in a shorter run, the same losses to the last digit, since only where the memory comes from changes); a sampler
(one call for all its steps) and the packed infiller (many small buffers, and occasional stalls while
the kernel gathers free huge pages) gain little or nothing, so only training uses it.

Tunables are read when a process starts, so `use_huge_pages` starts the command again, the same way,
with the tunable added to `GLIBC_TUNABLES`; `train.py` and `benchmarks/train_step.py` call it first
thing. It does nothing where it cannot help (not Linux, glibc older than 2.35, transparent huge pages
`never`), where the tunable is set already, or with `TDIFF_JAX_HUGE_PAGES=0` in the environment.
Scripts of your own get the same by starting Python with `GLIBC_TUNABLES=glibc.malloc.hugetlb=1`.

Memory maps: XLA's CPU runtime keeps each compiled program's kernels in memory mappings of their own,
about 1,370 for one of the CPU default's guided samplers (one agent bucket, a throwaway count of
`/proc/self/maps`), and Linux refuses a process more than `vm.max_map_count` (65,530 by default): a batch
job that compiles a few dozen sampler shapes (scenes of many sizes) then dies inside LLVM ("Unable to
allocate section memory"). `drop_compiled_near_map_limit` drops every compiled program (`jax.clear_caches`;
they compile again when next called) once the process holds more than `MAP_SHARE` of the limit;
`sampling.sample_grouped` calls it after each call that compiled something, `evaluate` and `sample.py` once a batch.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

SWITCH = "TDIFF_JAX_HUGE_PAGES"      # "0": leave the allocator alone
TUNABLE = "glibc.malloc.hugetlb=1"
_THP_MODE = Path("/sys/kernel/mm/transparent_hugepage/enabled")
_MAP_LIMIT = Path("/proc/sys/vm/max_map_count")
# Compiled programs are dropped above this share of the limit: the rest leaves room for the twenty-odd
# programs one more batch may compile before the next check.
MAP_SHARE = 0.6


def huge_pages_available() -> bool:
  """Whether glibc's malloc can be told to use transparent huge pages here: Linux, glibc 2.35 or later,
  and the kernel's transparent huge pages not `never`."""
  if not sys.platform.startswith("linux"):
    return False
  try:
    name, version = os.confstr("CS_GNU_LIBC_VERSION").split()
    major, minor = (int(v) for v in version.split(".")[:2])
    mode = _THP_MODE.read_text()
  except (ValueError, OSError, AttributeError):
    return False
  return name == "glibc" and (major, minor) >= (2, 35) and "[never]" not in mode


def use_huge_pages() -> None:
  """Run this process's command again (same interpreter, arguments and environment) with
  `glibc.malloc.hugetlb=1` added to `GLIBC_TUNABLES`, unless it is set already, `TDIFF_JAX_HUGE_PAGES=0`,
  or `huge_pages_available()` is False; then it returns and nothing changes. Call it before any work:
  the current process is replaced."""
  tunables = os.environ.get("GLIBC_TUNABLES", "")
  if ("glibc.malloc.hugetlb" in tunables or os.environ.get(SWITCH, "1") == "0" or not sys.executable
      or not huge_pages_available()):
    return
  env = dict(os.environ, GLIBC_TUNABLES=":".join(t for t in (tunables, TUNABLE) if t))
  sys.stdout.flush()
  sys.stderr.flush()
  try:
    os.execve(sys.executable, sys.orig_argv, env)
  except OSError as e:  # the command goes on as it is, only slower
    print(f"tdiff_jax.host: could not start the command again with {TUNABLE} ({e}); going on without it",
          file=sys.stderr)


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
