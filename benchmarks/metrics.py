"""Throughput of the full realism-metric suite at the default caps.

  python benchmarks/metrics.py [--batch_sizes 1,8,32] [--repeats 5]

Prints one JSON object: for each batch size, compile time and scenes per second of one jit-compiled
call that scores both endpoints of the generated and of the ground-truth states under both conventions
(collisions by centre distance and by oriented boxes, off-road by centreline points and by drivable-area
polygons, nearest-edge distances to points and to segments, and the eight histograms), as
`python -m tdiff_jax.evaluate` does per batch. Scenes: the real AV2 maps of tests/data at A = 64 agents
(all placed on lane centrelines, random offsets) and P = 256 polygons.
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

from tdiff_jax import evaluate, datatypes  # noqa: E402
from tdiff_jax.data import av2_io, config as config_lib, scene_builder  # noqa: E402


def place_agents(scene: datatypes.Scene, a: int, rng: np.random.Generator) -> datatypes.Scene:
  """`a` agents near random centreline points, random speeds and headings."""
  centre = scene.pt_valid & (scene.pt_side == datatypes.POINT_SIDES.index("CENTER"))
  p, k = np.nonzero(centre)
  pick = rng.integers(0, len(p), (a, 2))
  state = np.zeros((a, 2, 4), np.float32)
  state[..., :2] = scene.pt_xy[p[pick], k[pick]] + rng.normal(0, 1.5, (a, 2, 2))
  state[..., 2] = rng.uniform(0, 20, (a, 2))
  state[..., 3] = scene.pt_heading[p[pick], k[pick]]
  return scene.replace(agent_state=state, agent_valid=np.ones(a, bool),
                       agent_type=rng.integers(0, len(datatypes.AGENT_TYPES), a).astype(np.int32))


def main() -> None:
  parser = argparse.ArgumentParser()
  parser.add_argument("--batch_sizes", default="1,8,32")
  parser.add_argument("--repeats", type=int, default=5)
  args = parser.parse_args()
  config = config_lib.default_data_config()
  rng = np.random.default_rng(0)
  scenes = [place_agents(scene_builder.load_scene(f, config, require_agents=False)[0], config.max_agents, rng)
            for f in av2_io.list_scenario_folders(ROOT / "tests" / "data")]
  result = {"device": jax.devices()[0].device_kind, "platform": jax.devices()[0].platform,
            "host": platform.processor() or platform.machine(), "host_cpus": os.cpu_count(), "jax": jax.__version__,
            "agents": config.max_agents, "polygons": config.max_polygons, "runs": []}
  for bs in [int(b) for b in args.batch_sizes.split(",")]:
    batch = jax.tree_util.tree_map(jnp.asarray, datatypes.stack_scenes([scenes[i % len(scenes)] for i in range(bs)]))
    generated = batch.agent_state[..., :3] + 1.0     # stands in for a sample: other positions and speeds
    heading = batch.agent_state[..., 3]
    t0 = time.perf_counter()
    jax.block_until_ready(evaluate.batch_metrics(generated, heading, batch))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(args.repeats):
      jax.block_until_ready(evaluate.batch_metrics(generated, heading, batch))
    dt = (time.perf_counter() - t0) / args.repeats
    run = {"batch_size": bs, "compile_and_first_call_s": round(compile_s, 2), "seconds_per_call": round(dt, 4),
           "scenes_per_s": round(bs / dt, 1)}
    result["runs"].append(run)
    print(json.dumps(run), file=sys.stderr)
  print(json.dumps(result))


if __name__ == "__main__":
  main()
