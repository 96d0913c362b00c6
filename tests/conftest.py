"""Shared fixtures over the real AV2 samples in tests/data (see tests/data/NOTICE.md); their paths and
the mixed dataset builder are in `tests/av2_samples.py`."""

from __future__ import annotations

import collections
import gc
import os
from pathlib import Path

import jax
import pytest

from tests.av2_samples import DATA, make_mixed_dataset
from tests.tiny import build_tiny_cache

# Most of the tests' time is XLA:CPU compiling many small programs, which it does faster without LLVM's
# optimisation passes and with its elemental emitters instead of the MLIR fusion emitters
# (`tests/test_sampling.py` alone, at optimisation level 0: 261 s with the fusion emitters, 174 s without);
# the tiny models run fast either way. Each test worker has a core of its own (`-n auto`), so XLA's
# threads for one program's operations and code generation only contend with the other worker (the suite
# on 2 cores, one run each: 10 min 45 s with them, 10 min 2 s without). Set before any backend starts,
# so the commands the tests run inherit them too; TDIFF_TEST_XLA_OPT=1 keeps XLA's defaults.
if not os.environ.get("TDIFF_TEST_XLA_OPT"):
  os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0"
                             " --xla_cpu_use_fusion_emitters=false --xla_cpu_multi_thread_eigen=false"
                             " --xla_cpu_parallel_codegen_split_count=1").strip()

# A persistent compilation cache shared by the session and the commands it runs makes repeated runs
# faster, but it is opt-in (`TDIFF_TEST_COMPILE_CACHE=<dir>`): writing XLA:CPU executables to it has
# crashed a cold-cache run of the whole suite (a segmentation fault inside jax's cache writer). The
# command lines' own cache (`cli.use_compilation_cache`, on by default) is off in the tests but where a
# test turns it on, so no test writes to the user's cache folder.
os.environ["TDIFF_JAX_COMPILATION_CACHE"] = "0"
if os.environ.get("TDIFF_TEST_COMPILE_CACHE"):
  os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ["TDIFF_TEST_COMPILE_CACHE"]   # for subprocesses
  os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0.5"
  jax.config.update("jax_compilation_cache_dir", os.environ["TDIFF_TEST_COMPILE_CACHE"])
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


# Programs compiled in this process, by jitted function ("jit(sample)"): JAX's public monitoring events.
_COMPILES: collections.Counter = collections.Counter()
jax.monitoring.register_event_duration_secs_listener(
    lambda event, duration, **kw: _COMPILES.update([kw.get("fun_name")])
    if event == "/jax/core/compile/jaxpr_to_mlir_module_duration" else None)


@pytest.fixture
def compiles() -> collections.Counter:
  """How many programs each jitted function has compiled in this process so far, by name ("jit(sample)"):
  read it before and after a call to count the call's compiles."""
  return _COMPILES


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
  """Drops jax's compiled programs after each test module. XLA:CPU maps about 13 memory regions per
  compiled program and never unmaps them while the program is cached: one worker running
  `test_sampling.py` reaches 54,000 of Linux's default 65,530 (`vm.max_map_count`), and the next module's
  compiles then crash the worker inside XLA (a segmentation fault or an abort). Cleared, it is back to
  about 1,700."""
  yield
  jax.clear_caches()
  gc.collect()


@pytest.fixture(scope="session")
def real_dir() -> Path:
  return DATA


@pytest.fixture(scope="session")
def mixed_dataset(tmp_path_factory):
  root = tmp_path_factory.mktemp("mixed")
  return root, make_mixed_dataset(root)


@pytest.fixture(scope="session")
def mixed_cache(mixed_dataset, tmp_path_factory):
  from tdiff_jax.data import preprocess
  root, _ = mixed_dataset
  out = tmp_path_factory.mktemp("cache")
  manifest = preprocess.preprocess(root, out, workers=1, shard_size=3, progress=False)
  return out, manifest


@pytest.fixture(scope="session")
def tiny_cache(tmp_path_factory) -> Path:
  """The tiny HL config's preprocessed synthetic worlds (`tests.tiny`), built once per worker."""
  return build_tiny_cache(tmp_path_factory.mktemp("tiny"))
