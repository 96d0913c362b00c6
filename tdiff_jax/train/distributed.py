"""Several processes (hosts) training one model: `jax.distributed` and the few helpers around it.

The same `python train.py ...` runs on every host. `initialize` connects the processes: explicitly
(coordinator address, process count and index, e.g. from flags) or, under a cluster manager JAX
detects (SLURM, Open MPI), from its environment. After it, `jax.devices()` lists every process's
devices: the trainer's data mesh spans them all, each process reads only its share of every global
batch (`local_to_global`), orbax saves and restores checkpoints across processes, and only the
primary process (index 0) prepares data, logs and writes metrics. With one process all of this is a
no-op, so the single-machine path is the same code.

On one CPU host, `use_cpu_cores` splits the CPU into one JAX device per core before anything touches a
device (`train.cpu_devices`): the same data-parallel mesh then runs each device's share of the batch on
its own core. A train step's many small XLA operations leave the second core of a single device mostly
idle (README, "Training the HL generator").
"""

from __future__ import annotations

import os

import jax
from jax.experimental import multihost_utils

# Environment variables under which a launcher starts several tasks that JAX can connect by itself.
_CLUSTER_SIZE_VARS = ("SLURM_NTASKS", "OMPI_COMM_WORLD_SIZE")


def multi_process_requested(coordinator_address: str | None = None, num_processes: int | None = None,
                            process_id: int | None = None) -> bool:
  """Whether `initialize` with these arguments (or this environment) connects several processes."""
  if any(v not in (None, "") for v in (coordinator_address, num_processes, process_id)):
    return True
  return any(int(os.environ.get(v, "1") or 1) > 1 for v in _CLUSTER_SIZE_VARS)


def available_cores() -> int:
  """The CPU cores this process may run on (its affinity mask where the OS has one)."""
  try:
    return len(os.sched_getaffinity(0))
  except (AttributeError, OSError):
    return os.cpu_count() or 1


def cpu_device_count(requested: int, batch_size: int, cores: int | None = None) -> int:
  """How many CPU devices `use_cpu_cores` makes: `requested` (> 0) as given; 0, one per core this
  process may use, lowered to the largest count that divides `batch_size` (the mesh splits every batch
  evenly)."""
  if requested < 0:
    raise ValueError(f"config.train.cpu_devices must be >= 0 (0: one per core), got {requested}")
  if requested > 0:
    return requested
  n = max(1, min(available_cores() if cores is None else cores, batch_size))
  while batch_size % n:
    n -= 1
  return n


def use_cpu_cores(requested: int, batch_size: int) -> int | None:
  """Splits the host CPU into `cpu_device_count(requested, batch_size)` JAX devices; returns the count,
  or None where it leaves JAX's own setting (the user set `JAX_NUM_CPU_DEVICES` or XLA's
  `--xla_force_host_platform_device_count`, or JAX's backends are already running). Only the CPU
  platform reads it: an accelerator's devices are unchanged. Call before anything touches a device."""
  n = cpu_device_count(requested, batch_size)
  if "JAX_NUM_CPU_DEVICES" in os.environ or "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
    return None
  try:
    jax.config.update("jax_num_cpu_devices", n)
  except RuntimeError:  # JAX's backends are already running: their devices stay as they are
    return None
  return n


def initialize(coordinator_address: str | None = None, num_processes: int | None = None,
               process_id: int | None = None) -> bool:
  """Connects this process to the others; returns whether it runs with several processes.

  Explicit arguments win (all three are needed, e.g. `localhost:12355`, 2, 0); without them, a
  SLURM or Open MPI job of several tasks is detected by JAX; otherwise nothing happens (one process).
  Call before anything touches a JAX device.
  """
  given = [coordinator_address, num_processes, process_id]
  if not multi_process_requested(*given):
    return False
  if any(v not in (None, "") for v in given):
    if any(v in (None, "") for v in given):
      raise ValueError("multi-process training needs all of --coordinator_address, --num_processes and "
                       f"--process_id (got {coordinator_address!r}, {num_processes!r}, {process_id!r})")
    if not 0 <= int(process_id) < int(num_processes):
      raise ValueError(f"--process_id={process_id} must be in [0, --num_processes={num_processes})")
    jax.distributed.initialize(coordinator_address, int(num_processes), int(process_id))
  else:
    jax.distributed.initialize()  # the cluster's own environment says who is who
  return jax.process_count() > 1


def is_primary() -> bool:
  """Whether this process logs, writes metrics and prepares data (process 0)."""
  return jax.process_index() == 0


def barrier(name: str) -> None:
  """Waits until every process reaches the barrier of this name (no-op with one process)."""
  if jax.process_count() > 1:
    multihost_utils.sync_global_devices(name)


def local_to_global(tree, sharding: jax.sharding.Sharding):
  """This process's share of a batch (numpy, leading axis) -> global arrays split along `sharding`.

  Every process passes its own rows; the global batch is their concatenation in process order."""
  return jax.tree_util.tree_map(lambda x: jax.make_array_from_process_local_data(sharding, x), tree)
