"""HL sampling throughput at the paper's model size.

  python benchmarks/sampling.py [--batch_sizes 1,8] [--repeats 2]

Prints one JSON object: for DDIM-50 unguided, DDIM-50 guided (official variant: clearance, lane and
off-road costs) and DDPM-500, at each batch size: compile time (first call) and scenes per second over
`--repeats` timed calls, plus XLA's memory estimate for the call. Random weights of the paper's model
(128 wide, 3 layers, 8 heads, 64 Fourier bands) on the real AV2 maps of tests/data: with `--padding full`
padded to A = 64 agents (all placed) and P = 256 polygons; with `--padding bucketed` the scenes' own
agents, trimmed to the size buckets as `sample.py` does.
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

from configs import hl as hl_config  # noqa: E402
from tdiff_jax import sampling, types  # noqa: E402
from tdiff_jax.data import av2_io, batches, scene as scene_lib  # noqa: E402
from tdiff_jax.hl_objective import NormStats  # noqa: E402
from tdiff_jax.train import trainer  # noqa: E402


def main() -> None:
  parser = argparse.ArgumentParser()
  parser.add_argument("--batch_sizes", default="1,8")
  parser.add_argument("--repeats", type=int, default=2)
  parser.add_argument("--modes", default="ddim50,ddim50_guided,ddpm500")
  parser.add_argument("--padding", default="full", choices=["full", "bucketed"],
                      help="full: A = 64 agents (all placed), P = 256; bucketed: the real scenes' own agents, "
                           "padding trimmed to the size buckets (like for like with the official code)")
  args = parser.parse_args()
  config = hl_config.get_config("av2")
  bucketed = args.padding == "bucketed"
  scenes = []
  for f in av2_io.list_scenario_folders(ROOT / "tests" / "data"):
    try:
      scenes.append(scene_lib.load_scene(f, config.data.scene, require_agents=bucketed)[0])
    except av2_io.BadScenarioError:
      pass  # bucketed mode needs the agents: the 50-step test-split sample has none
  a = config.data.scene.max_agents
  graphdef, params = trainer.split_model(trainer.create_model(config))
  sched = trainer.make_schedule(config)
  norm = NormStats(jnp.array([0.0, 0.0, -0.7]), jnp.array([0.35, 0.35, 0.3]))
  modes = {"ddim50": sampling.SamplerOptions("ddim", 10),
           "ddim50_guided": sampling.SamplerOptions("ddim", 10, ("clearance", "lane", "offroad")),
           "ddpm500": sampling.SamplerOptions("ddpm", 1)}
  result = {"device": jax.devices()[0].device_kind, "platform": jax.devices()[0].platform,
            "host": platform.processor() or platform.machine(), "host_cpus": os.cpu_count(),
            "jax": jax.__version__, "agents": a, "polygons": config.data.scene.max_polygons, "runs": []}
  for name in args.modes.split(","):
    for bs in [int(b) for b in args.batch_sizes.split(",")]:
      chosen = [scenes[i % len(scenes)] for i in range(bs)]
      batch = types.stack_scenes(chosen)
      if bucketed:
        batch = batches.crop_to_bucket(batch, config.data.agent_buckets, config.data.polygon_buckets)
      else:
        batch = batch.replace(agent_valid=np.ones((bs, a), bool), agent_type=np.zeros((bs, a), np.int32))
      batch = jax.tree_util.tree_map(jnp.asarray, batch)
      def call(key, batch=batch, options=modes[name]):
        return sampling.sample(graphdef, params, batch, norm, sched, key, options)
      t0 = time.perf_counter()
      lowered = sampling.sample.lower(graphdef, params, batch, norm, sched, jax.random.PRNGKey(0), modes[name])
      mem = lowered.compile().memory_analysis()
      jax.block_until_ready(call(jax.random.PRNGKey(0)))
      compile_s = time.perf_counter() - t0
      t0 = time.perf_counter()
      for r in range(args.repeats):
        jax.block_until_ready(call(jax.random.PRNGKey(r + 1)))
      dt = (time.perf_counter() - t0) / args.repeats
      need = mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes - mem.alias_size_in_bytes
      run = {"mode": name, "padding": args.padding, "agents": int(batch.num_agents), "polygons": int(batch.num_polygons),
             "valid_agents_per_scene": float(np.asarray(batch.agent_valid).sum(-1).mean()), "batch_size": bs, "compile_and_first_call_s": round(compile_s, 2), "seconds_per_call": round(dt, 3),
             "scenes_per_s": round(bs / dt, 3), "memory_gib": round(need / 2**30, 3)}
      result["runs"].append(run)
      print(json.dumps(run), file=sys.stderr)
  print(json.dumps(result))


if __name__ == "__main__":
  main()
