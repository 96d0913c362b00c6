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

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import common  # noqa: E402
from tdiff_jax import datatypes, evaluate  # noqa: E402
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


FLAGS = flags.FLAGS
flags.DEFINE_list("batch_sizes", ["1", "8", "32"], "batch sizes")
flags.DEFINE_integer("repeats", 5, "timed calls per batch size (the median is reported)")


def main(argv: list[str]) -> None:
  del argv
  args = FLAGS
  config = config_lib.default_data_config()
  rng = np.random.default_rng(0)
  scenes = [place_agents(scene_builder.load_scene(f, config, require_agents=False)[0], config.max_agents, rng)
            for f in av2_io.list_scenario_folders(ROOT / "tests" / "data")]
  result = {**common.machine(), "agents": config.max_agents, "polygons": config.max_polygons, "runs": []}
  for bs in [int(b) for b in args.batch_sizes]:
    batch = jax.tree_util.tree_map(jnp.asarray, datatypes.stack_scenes([scenes[i % len(scenes)] for i in range(bs)]))
    generated = batch.agent_state[..., :3] + 1.0     # stands in for a sample: other positions and speeds
    heading = batch.agent_state[..., 3]
    timing = common.time_passes(
        lambda _, g=generated, h=heading, b=batch: jax.block_until_ready(evaluate.batch_metrics(g, h, b)), args.repeats)
    dt = timing["median_pass_s"]
    run = {"batch_size": bs, "compile_and_first_call_s": timing["compile_and_first_pass_s"],
           "seconds_per_call": round(dt, 4), "scenes_per_s": round(bs / dt, 1), "peak_rss_mb": timing["peak_rss_mb"]}
    result["runs"].append(run)
    common.progress(run)
  common.report(result)


if __name__ == "__main__":
  app.run(main)
