"""HL train-step throughput at the paper's model size (or, `--config default`, command 1's model).

  python benchmarks/train_step.py [--config av2|default] [--batch_sizes 8,32] [--steps 5] [--pl2pl_neighbors 0]

Prints one JSON object with a run per mode and batch size: compile time, train steps/s and scenes/s
over `--steps` timed steps (after a warm-up step, blocking on the result), and memory (XLA's buffer
assignment for the step: arguments + outputs + temporaries; on a GPU also the device's peak). The model
is the paper's (128 wide, 3 denoiser layers, 8 heads, 1 map layer, 64 Fourier bands, 16 latents, all
polygon pairs within 150 m) and the scenes are the real AV2 samples of tests/data. Mode `padded` pads
them to A = 64 agents and P = 256 polygons, the worst case the caps allow; mode `bucketed` trims the
padding to the size buckets as training does (for these scenes A = 16, P = 128). A run that would not
fit in a CPU host's memory is reported as skipped.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import jax
import numpy as np
from absl import app, flags

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
import common  # noqa: E402

from configs import hl as hl_config  # noqa: E402
from tdiff_jax import datatypes, diffusion, models  # noqa: E402
from tdiff_jax.data import av2_io, batches, normalize, scene_builder  # noqa: E402
from tdiff_jax.train import trainer  # noqa: E402


def real_scenes(config) -> list[datatypes.Scene]:
  out = []
  for folder in av2_io.list_scenario_folders(ROOT / "tests" / "data"):
    try:
      out.append(scene_builder.load_scene(folder, config.data.scene)[0])
    except av2_io.BadScenarioError:
      pass
  return out


# Official PyTorch train steps/s at batch 8 on the same 3 real scenes (paper model, 2-core CPU, measured once).
OFFICIAL_STEPS_PER_S = {8: 1.43}
TARGET_RATIO = 1.5

FLAGS = flags.FLAGS
flags.DEFINE_list("batch_sizes", ["8", "32"], "batch sizes")
flags.DEFINE_integer("steps", 5, "timed steps per run")
flags.DEFINE_integer("pl2pl_neighbors", -1, "0: all polygon pairs (the paper's; the av2 config's); -1: the config's")
flags.DEFINE_enum("config", "av2", ["av2", "default"], "configs/hl.py variant (default: command 1's model and recipe)")
flags.DEFINE_list("modes", ["bucketed", "padded"], "bucketed: padding trimmed to the size buckets, as in training; "
                  "padded: A = 64, P = 256")


def main(argv: list[str]) -> None:
  del argv
  args = FLAGS

  config = hl_config.get_config(args.config)  # av2: the paper's model and schedule
  if args.pl2pl_neighbors >= 0:
    config.model.pl2pl_neighbors = args.pl2pl_neighbors
  scenes = real_scenes(config)
  stacked = datatypes.stack_scenes(scenes).to_dict()
  stats = normalize.normalization_stats(stacked["agent_state"], stacked["agent_valid"], stacked["frame_scale"])
  consts = trainer.Constants(normalize.NormStats(np.float32(stats["mean"]), np.float32(stats["std"])),
                             diffusion.schedule_from_config(config.diffusion))
  graphdef, params = models.split_model(models.create_model(config))
  result = {
      **common.machine(), "model": config.model.to_dict(), "parameters": int(sum(x.size for x in jax.tree_util.tree_leaves(params))),
      "scenes": "the real AV2 samples of tests/data, repeated to the batch size", "runs": [],
  }
  ram = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
  for mode in args.modes:
    for bs in [int(b) for b in args.batch_sizes]:
      idx = np.arange(bs) % len(scenes)
      batch = datatypes.Scene.from_dict({k: v[idx] for k, v in stacked.items()})
      if mode == "bucketed":  # as training does: trim padding to the smallest bucket
        batch = batches.crop_to_bucket(batch, config.data.agent_buckets, config.data.polygon_buckets)
      run = {"mode": mode, "batch_size": bs, "agents": batch.num_agents, "polygons": batch.num_polygons}
      # The step training runs (parameters as one vector); the state is donated: a fresh copy.
      flat, tx, state = trainer.init_flat_state(config, jax.tree_util.tree_map(np.array, params))
      batch = jax.device_put(batch)
      t0 = time.perf_counter()
      compiled = trainer.jit_train_step(graphdef, tx, config, flat=flat).lower(state, batch, consts).compile()
      run["compile_s"] = round(time.perf_counter() - t0, 2)
      mem = compiled.memory_analysis()
      need = mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes - mem.alias_size_in_bytes
      run["memory_gib"] = round(need / 2**30, 2)  # XLA's buffer assignment: arguments + outputs + temporaries
      if jax.devices()[0].platform == "cpu" and need > 0.8 * ram:
        run["skipped"] = f"needs {need / 2**30:.1f} GiB, this host has {ram / 2**30:.1f} GiB"
      else:
        state, metrics = compiled(state, batch, consts)
        jax.block_until_ready(metrics)
        t0 = time.perf_counter()
        for _ in range(args.steps):
          state, metrics = compiled(state, batch, consts)
        jax.block_until_ready((state, metrics))
        dt = (time.perf_counter() - t0) / args.steps
        run.update(steps_per_s=round(1 / dt, 4), scenes_per_s=round(bs / dt, 3), peak_rss_mb=round(common.peak_rss_mb(), 1))
        official = OFFICIAL_STEPS_PER_S.get(bs) if args.config == "av2" and mode == "bucketed" else None
        if official:  # like for like: the paper's model, padding trimmed as the official graph has none
          run.update(official_steps_per_s=official, ratio=round(1 / dt / official, 3), target_ratio=TARGET_RATIO)
        stats = jax.devices()[0].memory_stats() or {}
        if "peak_bytes_in_use" in stats:
          run["device_peak_gib"] = round(stats["peak_bytes_in_use"] / 2**30, 2)
      result["runs"].append(run)
      common.progress(run)
  common.report(result)


if __name__ == "__main__":
  app.run(main)
