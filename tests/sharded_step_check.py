"""Run in a subprocess with 4 fake CPU devices: one train step on a 4-device mesh vs on 1 device, of the
tiny config with an all-pairs map encoder: on four devices its polygons packed as training packs them,
each device's slice of the batch apart (`trainer.packed_polygons`), against the dense `[B, P, P]` grid
on one. (The tiny config's own step, dense grids, sharded over one device per core: the train command's
test compares its losses with one device's.)

Prints JSON {"devices": n, "packed_max_abs_diff": d, "packed_shards": s}.
"""

import json
import os
import sys

os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
os.environ["JAX_PLATFORMS"] = "cpu"

import jax  # noqa: E402
import numpy as np  # noqa: E402
from jax.sharding import Mesh, NamedSharding, PartitionSpec  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from configs import hl as hl_config  # noqa: E402
from tdiff_jax import diffusion, models  # noqa: E402
from tdiff_jax.data import batches  # noqa: E402
from tdiff_jax.train import trainer  # noqa: E402


def _one_step(config, cache_dir: str, mesh_devices: list, packing: str):
  """The params and loss after one train step from the same initial state, on a mesh of `mesh_devices`;
  `packing`: "none" (dense grids) or "sharded" (a list per device, as training packs them)."""
  ds = batches.load_split(cache_dir, "train", config.data.scene)
  batch = batches.crop_to_bucket(next(batches.BatchIterator(ds, 4, seed=0)), config.data.agent_buckets,
                                 config.data.polygon_buckets)
  consts = trainer.Constants(trainer.norm_stats(config, ds.manifest), diffusion.schedule_from_config(config.diffusion))
  graphdef, params = models.split_model(models.create_model(config))
  flat, tx, init = trainer.init_flat_state(config, params)  # the step training runs
  step = trainer.make_train_step(graphdef, tx, config, flat)
  mesh = Mesh(np.array(mesh_devices), ("data",), axis_types=(jax.sharding.AxisType.Auto,))
  rep, shard = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec("data"))
  packed = None
  if packing == "sharded":  # what training passes on this process's devices
    packed = trainer.packed_polygons(config, batch, shard)
  state = jax.device_put(init, rep)
  fn = jax.jit(step, out_shardings=(rep, rep))
  new, metrics = fn(state, jax.device_put(batch, shard), jax.device_put(consts, rep), packed)
  assert len(new.params.sharding.device_set) == len(mesh_devices)
  return jax.device_get((new.params, metrics["loss"])), (packed.shards if packed is not None else 0)


def _max_diff(a, b) -> float:
  return max(float(np.max(np.abs(x - y))) for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))


def main(cache_dir: str) -> None:
  config = hl_config.get_config("tiny")
  config.model.pl2pl_neighbors = 0   # all pairs: what training packs
  dense, _ = _one_step(config, cache_dir, jax.devices()[:1], "none")
  packed_four, shards = _one_step(config, cache_dir, jax.devices(), "sharded")
  print(json.dumps({"devices": jax.device_count(), "packed_max_abs_diff": _max_diff(dense, packed_four),
                    "packed_shards": shards}))


if __name__ == "__main__":
  main(sys.argv[1])
