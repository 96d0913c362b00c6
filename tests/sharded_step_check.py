"""Run in a subprocess with 4 fake CPU devices: one train step on a 4-device mesh vs on 1 device.

Prints JSON {"devices": n, "max_abs_diff": d}.
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


def main(cache_dir: str) -> None:
  config = hl_config.get_config("tiny")
  ds = batches.load_split(cache_dir, "train", config.data.scene)
  batch = batches.crop_to_bucket(next(batches.BatchIterator(ds, 4, seed=0)), config.data.agent_buckets,
                                 config.data.polygon_buckets)
  consts = trainer.Constants(trainer.norm_stats(config, ds.manifest), diffusion.schedule_from_config(config.diffusion))
  graphdef, params = models.split_model(models.create_model(config))
  flat, tx, init = trainer.init_flat_state(config, params)  # the step training runs
  step = trainer.make_train_step(graphdef, tx, config, flat)
  results = []
  for devices in (jax.devices()[:1], jax.devices()):
    mesh = Mesh(np.array(devices), ("data",), axis_types=(jax.sharding.AxisType.Auto,))
    rep, shard = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec("data"))
    state = jax.device_put(init, rep)
    fn = jax.jit(step, out_shardings=(rep, rep))
    new, metrics = fn(state, jax.device_put(batch, shard), jax.device_put(consts, rep))
    assert len(new.params.sharding.device_set) == len(devices)
    results.append(jax.device_get((new.params, metrics["loss"])))
  diff = max(float(np.max(np.abs(a - b))) for a, b in zip(jax.tree_util.tree_leaves(results[0]),
                                                             jax.tree_util.tree_leaves(results[1])))
  print(json.dumps({"devices": jax.device_count(), "max_abs_diff": diff}))


if __name__ == "__main__":
  main(sys.argv[1])
