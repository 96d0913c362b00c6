"""Why grouped sampling runs its groups on host threads: per-scene costs, and two calls side by side.

  python benchmarks/side_by_side.py [--config av2|default] [--repeats 5]

For each scene of the varied set (`scene_set`, alone, cropped to its buckets, the model of `--config`
with random weights): the map encoding (`sampling.encode_maps`) and one DDIM-50 call on that encoding
(`sampling.sample`), in ms, median of `--repeats`; the DDIM-50 call divided by its 50 network calls is
a denoiser step at that agent bucket. Then the largest scene's DDIM-50 call twice: one call after the
other from one thread (the reference), and the two calls made from two host threads
(`sampling.run_concurrently`), which is what `sample_grouped` now does with a batch's groups. Prints
one JSON object; `ratio` is the reference's time over the side-by-side time (2 = the second core did
a whole call's work). Run it pinned to one core (`taskset -c 0`) to see what the second core buys.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
from absl import app, flags

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import common  # noqa: E402
import scene_set  # noqa: E402
from tdiff_jax import datatypes, sampling  # noqa: E402
from tdiff_jax.data import batches  # noqa: E402

FLAGS = flags.FLAGS
flags.DEFINE_enum("config", "av2", ["av2", "default"], "configs/hl.py variant")
flags.DEFINE_integer("repeats", 5, "timed calls per measurement (the median is reported)")


def median_ms(fn, repeats: int) -> float:
  return round(1e3 * common.median_s(fn, repeats), 1)


def main(argv: list[str]) -> None:
  del argv
  args = FLAGS
  setup = common.hl_setup(args.config)
  a_buckets, p_buckets, scenes = setup["a_buckets"], setup["p_buckets"], setup["scenes"]
  graphdef, params, sched, norm = setup["graphdef"], setup["params"], setup["sched"], setup["norm"]
  options = sampling.SamplerOptions("ddim", 10)
  calls = options.network_calls(sched.num_steps)
  result = {**common.machine(), "config": args.config, "workers": sampling.default_workers(), "scenes": []}

  def prepared(scene):
    one = jax.tree_util.tree_map(jnp.asarray, batches.crop_to_bucket(datatypes.stack_scenes([scene]), a_buckets,
                                                                      p_buckets))
    return one, sampling.encode_maps(graphdef, params, one, norm, p_buckets)

  def ddim50(one, maps):
    return sampling.sample(graphdef, params, one, norm, sched, jax.random.key(0), options, map_context=maps)

  for scene, (agents, polygons) in zip(scenes, scene_set.OFFICIAL_TIMING_SET):
    one, maps = prepared(scene)
    encode_ms = median_ms(lambda: sampling.encode_maps(graphdef, params, one, norm, p_buckets), args.repeats)  # noqa: B023
    sample_ms = median_ms(lambda: ddim50(one, maps), args.repeats)  # noqa: B023
    row = {"agents": agents, "polygons": polygons, "agent_bucket": one.num_agents, "polygon_bucket": one.num_polygons,
           "map_encoding_ms": encode_ms, "ddim50_call_ms": sample_ms, "step_ms": round(sample_ms / calls, 2)}
    result["scenes"].append(row)
    common.progress(row)
  total_encode = sum(r["map_encoding_ms"] for r in result["scenes"])
  total = total_encode + sum(r["ddim50_call_ms"] for r in result["scenes"])
  result["map_encoding_share_ddim50_batch1"] = round(total_encode / total, 3)

  largest = max(range(len(scenes)), key=lambda i: scene_set.OFFICIAL_TIMING_SET[i][0])
  one, maps = prepared(scenes[largest])
  call = lambda: ddim50(one, maps)  # noqa: E731
  one_after_other = median_ms(lambda: [jax.block_until_ready(call()) for _ in range(2)], args.repeats)
  side_by_side = median_ms(lambda: sampling.run_concurrently([call, call], [1, 1], workers=2), args.repeats)
  result["two_ddim50_calls_largest_scene"] = {
      "agents": scene_set.OFFICIAL_TIMING_SET[largest][0], "ours_side_by_side_ms": side_by_side,
      "reference_one_after_other_ms": one_after_other, "ratio": round(one_after_other / side_by_side, 2)}
  common.report(result)


if __name__ == "__main__":
  app.run(main)
