"""Infilling throughput on the varied scene set of the official timings, beside the official figure.

  python benchmarks/infill.py [--batch_sizes 1,8] [--repeats 3] [--scenes varied|real] [--agents packed|padded]
      [--maps per_scene|batch]
      [--matmul_dtype float32|bfloat16]
      [--pl2pl_neighbors 0] [--fourier_tables 0]

The 14 scenes of `common.OFFICIAL_TIMING_SET` (the agent and polygon counts of the real scenes the
official code was timed on; vehicles placed along lane centrelines), batch 1 each scene once, batch 8 as
two fixed batches in set order, each trimmed to its size bucket as `sample.py` does (`--scenes real`: the
3 real scenes of tests/data the official figure was measured on, repeated to the batch size, each copy's
map moved by a millimetre so that it is encoded, not shared). Random weights of
the official infiller (128 wide, 8 heads, 2 attention layers per stage, 2 temporal layers, 64 Fourier
bands; every polygon pair within 150 m, or with `--pl2pl_neighbors=k` the k nearest; its relation
embeddings interpolated from tables as `configs/infill.py:av2` sets, `--fourier_tables 0`: exact), mode "both".
By default each batch is infilled as `sample.py` infills it: its maps encoded once, then one call over
the batch's valid agents and their real (agent, polygon) and (agent, agent) pairs, packed into lists
(`infilling.infill_packed`, timed with the call). With `--agents padded`, one `infill` call on the padded
batch, with the maps encoded apart (`--maps per_scene`, `infilling.encode_maps`) or the padded batch's map encoded inside
`infill` (`--maps batch`). Every shape is compiled first (compile time apart), the whole set is timed `--repeats` times
and the median reported, then the maps' encoding alone the same way (`map_encoding_seconds_per_set`: the
rest of a pass is the per-agent network). The official figure (22.8 scenes/s at batch 8) was measured once on the 3 real
scenes of tests/data on a 2-core CPU like the development machine. Prints one JSON object.
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
from configs import infill as infill_config  # noqa: E402
from tdiff_jax import datatypes, infilling  # noqa: E402
from tdiff_jax.data import batches  # noqa: E402
from tdiff_jax import models  # noqa: E402

OFFICIAL = {8: 22.8}  # scenes/s, official PyTorch infiller, 2-core CPU
TARGET_RATIO = 2.0


FLAGS = flags.FLAGS
flags.DEFINE_list("batch_sizes", ["1", "8"], "batch sizes (8: the two fixed batches of the set)")
flags.DEFINE_integer("repeats", 3, "timed passes over the set (the median is reported)")
flags.DEFINE_enum("agents", "packed", ["packed", "padded"], "packed: the batch's valid agents and pairs "
                  "listed (infilling.infill_packed, as sample.py runs it); padded: one call on the padded batch")
flags.DEFINE_enum("maps", "per_scene", ["per_scene", "batch"], "with --agents padded, map encoding: each scene at its "
                  "own size, or padded")
flags.DEFINE_enum("matmul_dtype", "float32", ["float32", "bfloat16"], "bfloat16: matrix products with bfloat16 "
                  "operands and float32 accumulation (common.set_matmul_dtype); float32: true float32 products")
flags.DEFINE_enum("scenes", "varied", ["varied", "real"], "varied: the 14-scene set; real: the 3 real scenes of "
                  "tests/data repeated to the batch size (the official figure's scenes; each copy's map encoded, "
                  "as the official code encodes it)")
flags.DEFINE_integer("fourier_tables", -1, "the relation embeddings interpolated from this many values per input "
                     "(model.fourier_tables; 0: exact; -1: the config's)")
flags.DEFINE_integer("pl2pl_neighbors", 0, "polygon pairs in the map encoder: 0 = all within 150 m (official), "
                     "k = the k nearest")


def main(argv: list[str]) -> None:
  del argv
  args = FLAGS
  matmul_dtype = common.set_matmul_dtype(args.matmul_dtype)  # before the model is built
  config = infill_config.get_config("av2")
  config.model.pl2pl_neighbors = args.pl2pl_neighbors
  if args.fourier_tables >= 0:
    config.model.fourier_tables = args.fourier_tables
  varied = args.scenes == "varied"
  scenes = common.timing_scenes(config.data.scene) if varied else common.official_real_scenes(config.data.scene)
  graphdef, params = models.split_model(models.create_model(config))
  a_buckets, p_buckets = config.data.agent_buckets, config.data.polygon_buckets
  result = {**common.machine(), "parameters": int(sum(x.size for x in jax.tree_util.tree_leaves(params))),
            "matmul_dtype": matmul_dtype, "agents": args.agents, "maps": args.maps,
            "pl2pl_neighbors": args.pl2pl_neighbors,
            "fourier_tables": int(config.model.fourier_tables),
            "scene_set": ([list(c) for c in common.OFFICIAL_TIMING_SET] if varied else
                          "the real AV2 samples of tests/data, repeated to the batch size (each copy's map moved by 1 mm)"),
            "runs": []}

  def call(b):
    if args.agents == "packed":
      return infilling.infill_packed(graphdef, params, b, b.agent_state[..., 0, 3], 0, polygon_buckets=p_buckets)
    maps = infilling.encode_maps(graphdef, params, b, p_buckets) if args.maps == "per_scene" else None
    return infilling.infill(graphdef, params, b, b.agent_state[..., 0, 3], 0, map_context=maps)

  for bs in [int(b) for b in args.batch_sizes]:
    if not varied:  # each real scene alone, or one batch of them, each copy's map encoded as the official code does
      chunks = [[s] for s in scenes] if bs == 1 else [common.repeated(scenes, bs, distinct_maps=True)]
    elif bs == 8:
      chunks = [[scenes[i] for i in idx] for idx in common.BATCHES_OF_8]
    else:
      chunks = [[scenes[(k + i) % len(scenes)] for i in range(bs)] for k in range(0, len(scenes), bs)]
    calls = [jax.tree_util.tree_map(jnp.asarray, batches.crop_to_bucket(datatypes.stack_scenes(c), a_buckets, p_buckets))
             for c in chunks]
    n_scenes = sum(len(c) for c in chunks)
    def one_pass(_, calls=calls):
      for b in calls:
        jax.block_until_ready(call(b))
    timing = common.time_passes(one_pass, args.repeats)
    # The map encoding alone (each call's `encode_maps`, already compiled): the rest is the per-agent network.
    maps_pass = lambda _, calls=calls: [jax.block_until_ready(infilling.encode_maps(graphdef, params, b, p_buckets))  # noqa: E731
                                        for b in calls]
    maps_s = common.time_passes(maps_pass, args.repeats)["median_pass_s"]
    ours = n_scenes / timing["median_pass_s"]
    official = OFFICIAL.get(bs)
    run = {"batch_size": bs, "scenes": n_scenes, "calls": len(calls),
           "shapes": sorted({(int(b.agent_valid.shape[0]), b.num_agents, b.num_polygons) for b in calls}),
           "compile_and_first_pass_s": timing["compile_and_first_pass_s"],
           "seconds_per_set": round(timing["median_pass_s"], 3), "map_encoding_seconds_per_set": round(maps_s, 3),
           "peak_rss_mb": timing["peak_rss_mb"],
           "scenes_per_s": round(ours, 2), "official_scenes_per_s": official,
           "ratio": round(ours / official, 2) if official else None, "target_ratio": TARGET_RATIO if official else None}
    result["runs"].append(run)
    common.progress(run)
  common.report(result)


if __name__ == "__main__":
  app.run(main)
