"""Infilling throughput at the official model size.

  python benchmarks/infill.py [--batch_sizes 1,8] [--repeats 3] [--padding full|bucketed]

Prints one JSON object: for each batch size, compile time (first call) and scenes per second over
`--repeats` timed calls of the jit-compiled `tdiff_jax.infill` (mode "both"), plus XLA's memory
estimate. Random weights of the official infiller (128 wide, 8 heads, 2 attention layers per stage,
2 temporal layers, 64 Fourier bands, every polygon within 150 m; `--pl2pl_neighbors=k` bounds the map
encoder's polygon pairs to the k nearest) on the real AV2 maps of tests/data:
with `--padding full` A = 64 agents, all placed (initial state at the start of a lane centreline,
goal at its end) and P = 256 polygons; with `--padding bucketed` the scenes' own agents, trimmed to the
size buckets. The per-agent network is mapped over agents with `jax.vmap`; no hand-batched variant
is implemented, so none is compared.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from configs import infill as infill_config  # noqa: E402
from tdiff_jax import infilling, types  # noqa: E402
from tdiff_jax.data import av2_io, batches, scene as scene_lib  # noqa: E402
from tdiff_jax.train import trainer  # noqa: E402


def place_agents(scene: types.Scene, a: int) -> types.Scene:
  """All `a` agents valid: agent i starts at the first centreline point of lane i (cycling) and ends at its last."""
  k3 = scene.num_points // 3
  lanes = np.flatnonzero(scene.pl_valid & (scene.pl_type != types.POLYGON_TYPES.index("PEDESTRIAN")))
  pick = lanes[np.arange(a) % len(lanes)]
  centre = scene.pt_xy[pick, 2 * k3:]
  state = np.zeros((a, 2, 4), np.float32)
  state[:, 0, :2], state[:, 1, :2] = centre[:, 0], centre[:, -1]
  state[:, :, 2] = 8.0
  state[:, :, 3] = scene.pt_heading[pick, 2 * k3][:, None]
  return scene.replace(agent_state=state, agent_valid=np.ones(a, bool), agent_type=np.zeros(a, np.int32))


def main() -> None:
  parser = argparse.ArgumentParser()
  parser.add_argument("--batch_sizes", default="1,8")
  parser.add_argument("--repeats", type=int, default=3)
  parser.add_argument("--padding", default="full", choices=["full", "bucketed"])
  parser.add_argument("--pl2pl_neighbors", type=int, default=0,
                      help="polygon pairs in the map encoder: 0 = all within 150 m (official), k = the k nearest")
  args = parser.parse_args()
  config = infill_config.get_config("av2")
  config.model.pl2pl_neighbors = args.pl2pl_neighbors
  bucketed = args.padding == "bucketed"
  scenes = []
  for f in av2_io.list_scenario_folders(ROOT / "tests" / "data"):
    try:
      scene = scene_lib.load_scene(f, config.data.scene, require_agents=bucketed)[0]
    except av2_io.BadScenarioError:
      continue  # bucketed mode needs the agents: the 50-step test-split sample has none
    scenes.append(scene if bucketed else place_agents(scene, config.data.scene.max_agents))
  graphdef, params = trainer.split_model(trainer.create_model(config))
  result = {"device": jax.devices()[0].device_kind, "platform": jax.devices()[0].platform,
            "host": platform.processor() or platform.machine(), "host_cpus": os.cpu_count(), "jax": jax.__version__,
            "parameters": int(sum(x.size for x in jax.tree_util.tree_leaves(params))),
            "pl2pl_neighbors": args.pl2pl_neighbors, "runs": []}
  for bs in [int(b) for b in args.batch_sizes.split(",")]:
    batch = types.stack_scenes([scenes[i % len(scenes)] for i in range(bs)])
    if bucketed:
      batch = batches.crop_to_bucket(batch, config.data.agent_buckets, config.data.polygon_buckets)
    batch = jax.tree_util.tree_map(jnp.asarray, batch)
    heading = batch.agent_state[..., 0, 3]
    t0 = time.perf_counter()
    mem = infilling.infill.lower(graphdef, params, batch, heading, 0).compile().memory_analysis()
    jax.block_until_ready(infilling.infill(graphdef, params, batch, heading, 0))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(args.repeats):
      jax.block_until_ready(infilling.infill(graphdef, params, batch, heading, 0))
    dt = (time.perf_counter() - t0) / args.repeats
    need = mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes - mem.alias_size_in_bytes
    run = {"padding": args.padding, "batch_size": bs, "agents": int(batch.num_agents),
           "valid_agents_per_scene": float(np.asarray(batch.agent_valid).sum(-1).mean()),
           "polygons": int(batch.num_polygons), "compile_and_first_call_s": round(compile_s, 2),
           "seconds_per_call": round(dt, 4), "scenes_per_s": round(bs / dt, 2), "memory_gib": round(need / 2**30, 3)}
    result["runs"].append(run)
    print(json.dumps(run), file=sys.stderr)
  print(json.dumps(result))


if __name__ == "__main__":
  main()
