"""HL sampling throughput on the varied scene set of the official timings, beside the official figures.

  python benchmarks/sampling.py [--modes ddim50,ddim50_guided,ddpm500,dpmpp2m15] [--batch_sizes 1,8]
      [--repeats 3] [--config av2|default] [--scenes varied|real] [--maps per_scene|batch] [--agent_buckets 4,8,12,16,24,32,40,48,64]
      [--polygon_buckets 64,96,128,192,256] [--matmul_dtype bfloat16] [--save_samples PATH.npz]
      [--num_layers 3] [--fourier_tables 0]

The 14 scenes of `common.OFFICIAL_TIMING_SET` (the agent and polygon counts of the real scenes the
official code was timed on), batch 1 each scene once, batch 8 the 16 scenes of two fixed batches in set
order (scenes 1 to 8, then 9 to 14 and 1 to 2) (`--scenes real`: the 3 real scenes of tests/data the
official DDPM-500 figure was measured on, each alone at batch 1, repeated to the batch size otherwise,
each copy's map moved by a millimetre so that it is encoded, not shared). The scenes are sampled as
`sample.py` and `evaluate` sample them: cut into batches of at most the batch size of one agent bucket
(`data.batches.sampler_batches`: cropped to their largest map, padded to 1, 2, 4, 8 scenes), each one
`sample` call with its maps encoded once (`sampling.encode_maps`) and the geometry of their valid entries
(`geometry.compact_sizes`), both timed with the call, or with `--maps batch` the maps encoded inside `sample`
on the padded batch. Random
weights of the model of `--config` (`av2`: the paper's, its map encoder's Fourier embeddings interpolated from
tables as the config sets, `--fourier_tables 0`: exact; `default`: the grounded CPU default). Every
shape is compiled first (compile time reported apart); then the whole set is timed `--repeats` times
and the median is reported, with XLA's memory estimate of the largest call and the share of padded
(agent, polygon) pairs. Prints one JSON object; each run has our scenes/s, the official figure, the
ratio and the issue's target. The official figures were measured once on a 2-core CPU like the
development machine; `dpmpp2m15` (15 network calls), `dpmpp2m15r4` (the same with 4 restarts of
its last call, 19 calls) and `dpmpp2m11n12r4`
(11 calls, the 10 after the first from noise-to-signal ratio 12, and 4 restarts, 15 calls: the command
lines' unguided default), and its 12-call variants `dpmpp2m8n12r4` (8 calls, 4 restarts) and
`dpmpp2m11n12r1` (11 calls, 1 restart) are compared with the official DDIM-50, the quality they match or
pass (docs/research_log.md); `ddim50r4_guided` (54 calls) and `ddim50r4f5_guided` (the same and 5 final cost steps: the
guided default) with the official guided DDIM-50.
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
sys.path.insert(0, str(ROOT / "benchmarks"))

import common  # noqa: E402
from common import MODES, OFFICIAL, TARGET_RATIO, batches_of  # noqa: E402
from tdiff_jax import geometry, host, sampling  # noqa: E402
from tdiff_jax.data import batches  # noqa: E402


FLAGS = flags.FLAGS
flags.DEFINE_list("modes", ["ddim50", "ddim50_guided", "ddpm500", "dpmpp2m15"], f"from {sorted(MODES)}")
flags.DEFINE_list("batch_sizes", ["1", "8"], "batch sizes (8: the two fixed batches of the set)")
flags.DEFINE_integer("repeats", 3, "timed passes over the set (the median is reported)")
flags.DEFINE_enum("config", "av2", ["av2", "default"], "configs/hl.py variant")
flags.DEFINE_enum("scenes", "varied", ["varied", "real"], "varied: the 14-scene set; real: the 3 real scenes of "
                  "tests/data (the official DDPM-500 figure's), batch 1 each alone, larger batches one batch of them "
                  "repeated, each copy's map moved by 1 mm so that it is encoded, as the official code encodes it")
flags.DEFINE_enum("maps", "per_scene", ["per_scene", "batch"], "map encoding: each map once over its own polygons "
                  "(sampling.encode_maps, as sample.py), or inside `sample` on the padded batch")
flags.DEFINE_list("agent_buckets", [], "override the config's sampler agent buckets (data.sampler_agent_buckets), "
                  "e.g. 8,16,32,64 (the training batches')")
flags.DEFINE_enum("matmul_dtype", "float32", ["float32", "bfloat16"], "bfloat16: matrix products with bfloat16 "
                  "operands and float32 accumulation (common.set_matmul_dtype: every product on an accelerator, the 2-D "
                  "ones on the CPU; a numerics experiment); float32: true float32 products, on a GPU too")
flags.DEFINE_string("save_samples", "", "write the last timed pass's sampled states (m, m/s; zeros for padded "
                    "agents), one array per mode and batch size, to this .npz, to compare two runs' samples")
flags.DEFINE_list("polygon_buckets", [], "override the config's polygon buckets")
flags.DEFINE_integer("num_layers", 0, "denoiser layers (0: the config's)")
flags.DEFINE_integer("fourier_tables", -1, "the map encoder's slowly varying Fourier embeddings interpolated from "
                     "this many values per input (model.fourier_tables; 0: exact; -1: the config's)")


def main(argv: list[str]) -> None:
  del argv
  args = FLAGS
  matmul_dtype = common.set_matmul_dtype(args.matmul_dtype)  # before the model is built
  overrides = {**({"num_layers": args.num_layers} if args.num_layers else {}),
               **({"fourier_tables": args.fourier_tables} if args.fourier_tables >= 0 else {})}
  setup = common.hl_setup(args.config, overrides or None)
  scenes, graphdef, params, sched, norm = (setup[k] for k in ("scenes", "graphdef", "params", "sched", "norm"))
  varied = args.scenes == "varied"
  if not varied:
    scenes = common.official_real_scenes(setup["config"].data.scene)
  a_buckets = tuple(int(x) for x in args.agent_buckets) if args.agent_buckets else setup["a_buckets"]
  p_buckets = tuple(int(x) for x in args.polygon_buckets) if args.polygon_buckets else setup["p_buckets"]
  result = {**common.machine(), "config": args.config, "scene_set": ([list(c) for c in common.OFFICIAL_TIMING_SET] if varied else
                                                            "the real AV2 samples of tests/data (repeats' maps moved by 1 mm)"),
            "matmul_dtype": matmul_dtype, "maps": args.maps, "agent_buckets": list(a_buckets), "polygon_buckets": list(p_buckets),
            "num_layers": int(setup["config"].model.num_layers),
            "fourier_tables": int(setup["config"].model.get("fourier_tables", 0)), "runs": []}

  def call(b, key, options):   # as sample.py: the maps encoded once, the geometry of their valid entries
    maps = sampling.encode_maps(graphdef, params, b, norm, p_buckets) if args.maps == "per_scene" else None
    geom = geometry.map_geometry(b, *geometry.compact_sizes(b))
    return sampling.sample(graphdef, params, b, norm, sched, key, options, map_context=maps, map_geometry=geom,
                           lane_pull=setup["lane_pull"])

  saved = {}
  for name in args.modes:
    options = MODES[name]
    for bs in [int(b) for b in args.batch_sizes]:
      host.drop_compiled_near_map_limit()   # as sample.py between batches: each shape's program holds memory maps
      calls, n_scenes = [], 0
      pool = [s for chunk in batches_of(scenes, bs, varied) for s in chunk]   # the set's scenes at this batch size
      for positions, b in batches.sampler_batches(pool, bs, a_buckets, p_buckets):   # cut as sample.py cuts them
        calls.append(jax.tree_util.tree_map(jnp.asarray, b))
        n_scenes += len(positions)
      real = sum(float((np.asarray(b.agent_valid).sum(-1) * np.asarray(b.pl_valid).sum(-1)).sum()) for b in calls)
      shapes = [(b.agent_valid.shape[0], b.num_agents, b.num_polygons) for b in calls]
      padded = sum(n * a * p for n, a, p in shapes)
      mem = 0
      for b in calls:  # XLA's memory estimate of each shape 
        maps = sampling.encode_maps(graphdef, params, b, norm, p_buckets) if args.maps == "per_scene" else None
        lowered = sampling.sample.lower(graphdef, params, b, norm, sched, jax.random.key(0), options,
                                        map_context=maps, lane_pull=setup["lane_pull"])
        m = lowered.compile().memory_analysis()
        mem = max(mem, m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes - m.alias_size_in_bytes)

      last_pass = []

      def one_pass(r, calls=calls, options=options, last_pass=last_pass):
        last_pass.clear()
        for i, b in enumerate(calls):
          out = jax.block_until_ready(call(b, jax.random.key(max(r, 0) * 100 + i), options))
          if args.save_samples:   # the copy to the host only when asked for
            last_pass.append(np.asarray(jnp.where(out.valid[..., None, None], out.state, 0.0)).reshape(-1))
      timing = common.time_passes(one_pass, args.repeats)
      compile_s, dt = timing["compile_and_first_pass_s"], timing["median_pass_s"]
      ours = n_scenes / dt
      # The official DDIM figures were measured on the 14 scenes, DDPM-500 on the 3 real ones.
      official = OFFICIAL.get((name, bs)) if varied or name == "ddpm500" else None
      run = {"mode": name, "batch_size": bs, "network_calls": options.network_calls(sched.num_steps),
             "scenes": n_scenes, "calls": len(calls),
             "shapes": sorted(set(shapes)), "sampler_calls": len(shapes),
             "padded_pair_share": round(1.0 - real / padded, 3),
             "compile_s": round(compile_s, 1), "seconds_per_set": round(dt, 3), "scenes_per_s": round(ours, 2),
             "official_scenes_per_s": official, "ratio": round(ours / official, 2) if official else None,
             "target_ratio": TARGET_RATIO[name] if official else None, "memory_gib": round(mem / 2**30, 3),
             "peak_rss_mb": timing["peak_rss_mb"]}
      result["runs"].append(run)
      common.progress(run)
      if args.save_samples:
        saved[f"{name}_batch{bs}"] = np.concatenate(last_pass)
  if args.save_samples:
    np.savez(args.save_samples, **saved)
  common.report(result)


if __name__ == "__main__":
  app.run(main)
