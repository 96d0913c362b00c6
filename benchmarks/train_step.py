"""HL train-step throughput at the paper's model size (or, `--config default`, command 1's model).

  python benchmarks/train_step.py [--config av2|default] [--scenes varied|real] [--batch_sizes 8,32]
      [--repeats 3] [--modes bucketed,padded] [--pl2pl_neighbors 0] [--fourier_tables 0] [--freeze_map_inputs 1] [--agent_buckets 8,16,32,48,64] [--polygon_buckets 64,96,128,160,192,256] [--lane_pull_m 0] [--nopacked] [--matmul_dtype bfloat16]

Prints one JSON object with a run per mode and batch size: compile time (every batch shape of the set,
before timing), train steps/s and scenes/s (the median of `--repeats` timed passes over the set, after a
warm-up pass, blocking on the result), the share of padded agent and polygon slots, and memory (XLA's
buffer assignment for the largest step: arguments + outputs + temporaries; on a GPU also the device's
peak). The model is the paper's (128 wide, 3 denoiser layers, 8 heads, 1 map layer, 64 Fourier bands,
16 latents, all polygon pairs within 150 m; its map encoder's Fourier embeddings interpolated from tables
as `configs/hl.py:av2` sets, `--fourier_tables 0`: exact).

Scenes: `varied` (default) is the set of the sampling benchmarks (`common.OFFICIAL_TIMING_SET`, the
agent and polygon counts of the 14 real scenes the official sampler was timed on), batch 8 as its two
fixed batches in set order (scenes 1 to 8, then 9 to 14 and 1 to 2), other batch sizes cycling through
the set; `real` is the 3 usable real AV2 samples of tests/data repeated to the batch size, the scenes
the official train step was timed on. Mode `bucketed` trims each batch's padding to its size bucket as
training does; `padded` pads to A = 64 agents and P = 256 polygons, the worst case the caps allow. A run
that would not fit in a CPU host's memory is reported as skipped. The official figure (batch 8, 3 real
scenes) is printed beside every bucketed batch-8 run of the paper model; on the varied set it is the
closest official figure there is, not a like-for-like one, and the run says so. As training does, an
all-pairs map encoder (the paper's) gets each batch's valid polygons and their pairs packed into lists
(`trainer.packed_polygons`; the run reports real, packed and dense slots); `--nopacked` times the
dense `[B, P, K]` and `[B, P, P]` grids instead. A frozen map encoder input side that is a constant of
each polygon (the CPU default's) is computed once per scene before the steps and read by them, as
training reads it (`trainer.map_inputs_cache`); the run says which.
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
import jax  # noqa: E402
import numpy as np  # noqa: E402
from absl import app, flags  # noqa: E402

import common  # noqa: E402

from configs import hl as hl_config  # noqa: E402
from tdiff_jax import datatypes, diffusion, models  # noqa: E402
from tdiff_jax.data import batches  # noqa: E402
from tdiff_jax.train import distributed, trainer  # noqa: E402
from jax.sharding import NamedSharding, PartitionSpec  # noqa: E402


# Official PyTorch train steps/s at batch 8 on the same 3 real scenes (paper model, 2-core CPU, measured once).
OFFICIAL_STEPS_PER_S = {8: 1.43}
TARGET_RATIO = 1.5

FLAGS = flags.FLAGS
flags.DEFINE_list("batch_sizes", ["8", "32"], "batch sizes (8 on the varied set: its two fixed batches)")
flags.DEFINE_integer("repeats", 3, "timed passes over the set (the median is reported)")
flags.DEFINE_integer("steps", 4, "with --scenes real: train steps per pass")
flags.DEFINE_enum("scenes", "varied", ["varied", "real"], "varied: the 14-scene set of the sampling benchmarks; "
                  "real: the 3 real samples of tests/data repeated (the official figure's scenes)")
flags.DEFINE_integer("pl2pl_neighbors", -1, "0: all polygon pairs (the paper's; the av2 config's); -1: the config's")
flags.DEFINE_integer("fourier_tables", -1, "the map encoder's slowly varying Fourier embeddings interpolated from "
                     "this many values per input (model.fourier_tables; 0: exact; -1: the config's)")
flags.DEFINE_float("lane_pull_m", -1.0, "the denoiser's lane pull (lane_pull.across_m; 0: off; -1: the config's)")
flags.DEFINE_integer("freeze_map_inputs", -1, "train.freeze_map_inputs: 1 the map encoder's input side and polygon "
                     "-> polygon relation embedding frozen, 0 trained; -1: the config's")
flags.DEFINE_list("agent_buckets", [], "data.agent_buckets (the batch's agents padded to the smallest that fits); "
                  "empty: the config's")
flags.DEFINE_list("polygon_buckets", [], "data.polygon_buckets; empty: the config's")
flags.DEFINE_enum("config", "av2", ["av2", "default"], "configs/hl.py variant (default: command 1's model and recipe)")
flags.DEFINE_integer("cpu_devices", -1, "train.cpu_devices: the CPU split into this many JAX devices, each batch "
                     "sharded over them, as train.py does (0: one per core); -1: the config's")
flags.DEFINE_bool("packed", True, "as training: an all-pairs map encoder gets each batch's valid polygons and "
                  "pairs packed into lists (--nopacked: the dense [B, P, P] grid, the previous step)")
flags.DEFINE_enum("matmul_dtype", "float32", ["float32", "bfloat16"], "bfloat16: the step's matrix products take "
                  "bfloat16 operands with float32 accumulation (`common.set_matmul_dtype`: every product on an accelerator, "
                  "the 2-D ones on the CPU; an experiment); float32: true float32 products, on a GPU too")
flags.DEFINE_list("modes", ["bucketed", "padded"], "bucketed: padding trimmed to the size buckets, as in training; "
                  "padded: A = 64, P = 256")


def scene_batches(scenes: list[datatypes.Scene], batch_size: int, varied: bool) -> list[list[datatypes.Scene]]:
  """The batches of one pass: the varied set's fixed batches of 8 (or the set cycled), or one batch of
  the real scenes repeated."""
  if not varied:
    return [common.repeated(scenes, batch_size)]
  if batch_size == 8:
    return [[scenes[i] for i in idx] for idx in common.BATCHES_OF_8]
  n = max(1, -(-len(scenes) // batch_size))
  return [[scenes[(k * batch_size + i) % len(scenes)] for i in range(batch_size)] for k in range(n)]


def main(argv: list[str]) -> None:
  del argv
  args = FLAGS

  config = hl_config.get_config(args.config)  # av2: the paper's model and schedule
  if args.cpu_devices >= 0:
    config.train.cpu_devices = args.cpu_devices
  # As train.py, before anything touches a device: every batch size must split evenly.
  distributed.use_cpu_cores(int(config.train.cpu_devices), math.gcd(*[int(b) for b in args.batch_sizes]))
  matmul_dtype = common.set_matmul_dtype(args.matmul_dtype)  # before the model is built
  if args.pl2pl_neighbors >= 0:
    config.model.pl2pl_neighbors = args.pl2pl_neighbors
  if args.fourier_tables >= 0:
    config.model.fourier_tables = args.fourier_tables
  if args.agent_buckets:
    config.data.agent_buckets = tuple(int(b) for b in args.agent_buckets)
  if args.polygon_buckets:
    config.data.polygon_buckets = tuple(int(b) for b in args.polygon_buckets)
  if args.freeze_map_inputs >= 0:
    config.train.freeze_map_inputs = bool(args.freeze_map_inputs)
  if args.lane_pull_m >= 0:  # 0: off with its options
    config.lane_pull.across_m = args.lane_pull_m
    if not args.lane_pull_m:
      config.lane_pull.update(dict(clearance_m=0.0, end_m=0.0, route_m=0.0))
  mesh = trainer.data_mesh()
  replicated, sharded = NamedSharding(mesh, PartitionSpec()), NamedSharding(mesh, PartitionSpec("data"))
  varied = args.scenes == "varied"
  scenes = common.timing_scenes(config.data.scene) if varied else common.official_real_scenes(config.data.scene)
  consts = trainer.Constants(common.norm_stats(config, scenes), diffusion.schedule_from_config(config.diffusion))
  graphdef, params = models.split_model(models.create_model(config))
  # As training: a frozen input side that is a constant of each polygon is computed once per scene, before
  # the steps, and each step reads its batch's rows (None: the step computes it).
  map_cache = trainer.map_inputs_cache(config, graphdef, params, consts.norm, common.scene_split(scenes))
  scene_index = {id(s): i for i, s in enumerate(scenes)}
  result = {
      **common.machine(), "devices": jax.device_count(), "matmul_dtype": matmul_dtype, "model": config.model.to_dict(), "train": config.train.to_dict(),
      "parameters": int(sum(x.size for x in jax.tree_util.tree_leaves(params))),
      "scenes": ("the varied set: " + str([list(c) for c in common.OFFICIAL_TIMING_SET]) + " (agents, polygons)"
                 if varied else "the real AV2 samples of tests/data, repeated to the batch size"), "runs": [],
  }
  ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
  for mode in args.modes:
    for bs in [int(b) for b in args.batch_sizes]:
      calls, inputs = [], []
      for chunk in scene_batches(scenes, bs, varied):
        batch = datatypes.stack_scenes(chunk)
        if mode == "bucketed":  # as training does: trim padding to the smallest bucket
          batch = batches.crop_to_bucket(batch, config.data.agent_buckets, config.data.polygon_buckets)
        calls.append(batch)
        inputs.append(None if map_cache is None else
                      map_cache.take(np.array([scene_index[id(s)] for s in chunk]), batch.num_polygons))
      shapes = sorted({(b.num_agents, b.num_polygons) for b in calls})
      slots = {"agents": sum(b.agent_valid.size for b in calls), "polygons": sum(b.pl_valid.size for b in calls)}
      run = {"mode": mode, "batch_size": bs, "batches_per_pass": len(calls), "shapes": shapes,
             "padded_agent_share": round(1 - sum(int(b.agent_valid.sum()) for b in calls) / slots["agents"], 3),
             "padded_polygon_share": round(1 - sum(int(b.pl_valid.sum()) for b in calls) / slots["polygons"], 3),
             "map_inputs": ("computed by the step" if map_cache is None else
                            "the frozen input side" + (" and polygon -> polygon relations" if
                                                       map_cache.pl2pl_relation is not None else "")
                            + " read from a per-scene cache, as training")}
      # The step training runs (parameters as one vector); the state is donated: a fresh copy.
      flat, tx, state = trainer.init_flat_state(config, jax.tree_util.tree_map(np.array, params))
      # As training: an all-pairs map encoder gets each batch's valid polygons and pairs, packed (on several
      # devices, each device's slice apart).
      packs = [trainer.packed_polygons(config, b, sharded) for b in calls] if args.packed else [None] * len(calls)
      if packs[0] is not None:
        run["packed"] = {"polygons": sum(int(p.polygon_valid.sum()) for p in packs),
                         "polygon_slots": sum(p.shards * p.shape[0] for p in packs),
                         "dense_polygon_slots": sum(b.pl_valid.size for b in calls),
                         "pairs": sum(int(p.valid.sum()) for p in packs),
                         "pair_slots": sum(p.shards * p.shape[1] for p in packs),
                         "dense_pair_slots": sum(b.pl_valid.size * b.num_polygons for b in calls)}
      # As training: the batch sharded over the mesh (one device: all of it), the state and constants replicated.
      calls = [jax.device_put(b, sharded) for b in calls]
      inputs = [None if m is None else jax.device_put(m, sharded) for m in inputs]
      state, run_consts = jax.device_put(state, replicated), jax.device_put(consts, replicated)
      step = trainer.jit_train_step(graphdef, tx, config, replicated=replicated, flat=flat)
      compiled, need = {}, 0
      shape_of = lambda b, p: (b.num_agents, b.num_polygons) + (p.shape if p is not None else ())  # noqa: E731
      t0 = time.perf_counter()
      for b, p, m in zip(calls, packs, inputs):
        key = shape_of(b, p)
        if key not in compiled:
          compiled[key] = step.lower(state, b, run_consts, p, m).compile()
          mem = compiled[key].memory_analysis()
          need = max(need, mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes
                     - mem.alias_size_in_bytes)
      run["compile_s"] = round(time.perf_counter() - t0, 2)
      run["memory_gib"] = round(need / 2**30, 2)  # XLA's buffer assignment: arguments + outputs + temporaries
      if jax.devices()[0].platform == "cpu" and need > 0.8 * ram:
        run["skipped"] = f"needs {need / 2**30:.1f} GiB, this host has {ram / 2**30:.1f} GiB"
      else:
        steps_per_batch = 1 if varied else args.steps
        holder = {"state": state}

        def one_pass(r, calls=calls, packs=packs, inputs=inputs, compiled=compiled, holder=holder,
                     steps_per_batch=steps_per_batch, run_consts=run_consts):
          del r
          for b, p, m in zip(calls, packs, inputs):
            for _ in range(steps_per_batch):
              holder["state"], metrics = compiled[shape_of(b, p)](holder["state"], b, run_consts, p, m)
          jax.block_until_ready((holder["state"], metrics))

        timing = common.time_passes(one_pass, args.repeats)
        steps = len(calls) * steps_per_batch
        dt = timing["median_pass_s"] / steps
        run.update(steps_per_s=round(1 / dt, 4), scenes_per_s=round(bs / dt, 3), steps_per_pass=steps,
                   passes_s=timing["passes_s"], peak_rss_mb=timing["peak_rss_mb"])
        official = OFFICIAL_STEPS_PER_S.get(bs) if args.config == "av2" and mode == "bucketed" else None
        if official:  # the paper's model, padding trimmed as the official graph has none
          run.update(official_steps_per_s=official, ratio=round(1 / dt / official, 3), target_ratio=TARGET_RATIO,
                     official_scenes="the 3 real scenes of tests/data" + (" (not this set)" if varied else ""))
        stats = jax.devices()[0].memory_stats() or {}
        if "peak_bytes_in_use" in stats:
          run["device_peak_gib"] = round(stats["peak_bytes_in_use"] / 2**30, 2)
      result["runs"].append(run)
      common.progress(run)
  common.report(result)


if __name__ == "__main__":
  app.run(main)
