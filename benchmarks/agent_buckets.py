"""The grouped sampler at two or more sets of agent buckets, timed interleaved, beside the official figures.

  python benchmarks/agent_buckets.py [--config av2|default] [--modes ddim50,dpmpp2m15] [--batch_sizes 1,8]
      [--buckets 8,16,32,64 --buckets 4,8,12,16,24,32,40,48,64] [--repeats 15]

What `data.sampler_agent_buckets` buys: `sampling.sample_grouped` (as `sample.py` and `evaluate` sample on a
CPU) over the varied scene set of `benchmarks/sampling.py` (`scene_set`, `sampler_modes`: batch 1 each scene once, batch 8
the two fixed batches in set order, each batch cropped to the training batches' buckets as `evaluate`
crops it), its scenes grouped by each `--buckets` in turn (default: the training batches' 8, 16, 32, 64
against the config's sampler buckets). Separate processes run minutes apart on a 2-core virtual machine
differ by 10 % and more, more than the effect measured here; so every shape is compiled first, then each
pass over the set takes every bucket set once, one after the other, `--repeats` times, and each set's
median pass and its quartiles are reported. Random weights of the model of `--config`. Prints one JSON
object: per mode, batch size and bucket set, the median scenes/s, the official figure and the ratio,
the sampler calls per pass and their share of padded (agent, polygon) pairs.
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import common  # noqa: E402
import sampler_modes  # noqa: E402
from tdiff_jax import datatypes, sampling  # noqa: E402
from tdiff_jax.data import batches  # noqa: E402

FLAGS = flags.FLAGS
flags.DEFINE_enum("config", "av2", ["av2", "default"], "configs/hl.py variant")
flags.DEFINE_list("modes", ["ddim50", "dpmpp2m15"], f"from {sorted(sampler_modes.MODES)}")
flags.DEFINE_list("batch_sizes", ["1", "8"], "batch sizes (8: the two fixed batches of the set)")
flags.DEFINE_multi_string("buckets", [], "a set of agent buckets, e.g. 8,16,32,64; repeat the flag for each "
                          "(default: the training batches' and the config's sampler buckets)")
flags.DEFINE_integer("repeats", 15, "interleaved passes over the set (each bucket set once per pass)")


def main(argv: list[str]) -> None:
  del argv
  args = FLAGS
  setup = common.hl_setup(args.config)
  scenes, graphdef, params, sched, norm = (setup[k] for k in ("scenes", "graphdef", "params", "sched", "norm"))
  config, p_buckets = setup["config"], setup["p_buckets"]
  train_buckets = tuple(config.data.agent_buckets)
  bucket_sets = ([tuple(int(x) for x in b.split(",")) for b in args.buckets] if args.buckets
                 else [train_buckets, batches.sampler_agent_buckets(config.data)])
  result = {**common.machine(), "config": args.config, "repeats": args.repeats,
            "bucket_sets": [list(b) for b in bucket_sets], "polygon_buckets": list(p_buckets), "runs": []}
  for name in args.modes:
    options = sampler_modes.MODES[name]
    for bs in [int(b) for b in args.batch_sizes]:
      calls = [jax.tree_util.tree_map(jnp.asarray, batches.crop_to_bucket(datatypes.stack_scenes(chunk), train_buckets,
                                                                           p_buckets))
               for chunk in sampler_modes.batches_of(scenes, bs)]
      n_scenes = sum(int(b.agent_valid.shape[0]) for b in calls)
      real = sum(float((np.asarray(b.agent_valid).sum(-1) * np.asarray(b.pl_valid).sum(-1)).sum()) for b in calls)

      def one_pass(buckets, calls=calls, options=options):
        for i, b in enumerate(calls):
          jax.block_until_ready(sampling.sample_grouped(graphdef, params, b, norm, sched, jax.random.key(i), options,
                                                        agent_buckets=buckets, polygon_buckets=p_buckets))

      compile_s = {}
      for buckets in bucket_sets:   # every shape compiled first
        t0 = time.perf_counter()
        one_pass(buckets)
        compile_s[buckets] = time.perf_counter() - t0
      times = {buckets: [] for buckets in bucket_sets}
      for _ in range(args.repeats):
        for buckets in bucket_sets:
          t0 = time.perf_counter()
          one_pass(buckets)
          times[buckets].append(time.perf_counter() - t0)
      official = sampler_modes.OFFICIAL.get((name, bs))
      for buckets in bucket_sets:
        t = sorted(times[buckets])
        q = len(t) // 4
        shapes = [s for b in calls for s in sampler_modes.sampled_shapes(b, buckets, p_buckets, True)]
        ours = n_scenes / statistics.median(t)
        run = {"mode": name, "batch_size": bs, "agent_buckets": list(buckets), "sampler_calls": len(shapes),
               "padded_pair_share": round(1.0 - real / sum(n * a * p for n, a, p in shapes), 3),
               "compile_and_first_pass_s": round(compile_s[buckets], 1),
               "median_pass_s": round(statistics.median(t), 4), "quartile_pass_s": [round(t[q], 4), round(t[-q - 1], 4)],
               "scenes_per_s": round(ours, 2), "official_scenes_per_s": official,
               "ratio": round(ours / official, 2) if official else None,
               "target_ratio": sampler_modes.TARGET_RATIO[name] if official else None}
        result["runs"].append(run)
        common.progress(run)
  common.report(result)


if __name__ == "__main__":
  app.run(main)
