"""Where the time goes: one sampling call and one train step, broken down (docs/benchmarks.md).

  python benchmarks/breakdown.py [--config av2|default] [--batch 0|1] [--train_batch 0|1] [--notrain] [--trace_dir DIR]

Sampling (the model of `--config`, random weights, fixed batch `--batch` of the varied scene set of
`scene_set`, as `sample.py` runs it): wall time of the map encoding (`encode_maps`) and of one denoiser
step per batch of one size (`batches.sampler_batches`), unguided and guided (clearance, lane, off-road: the guidance's share is the
difference; also with the costs on the padded map geometry, as before `geometry.MapGeometry`), and,
from a `jax.profiler` trace of one DDIM-50 call, the XLA operations each network call executes, by kind
(`dot`/`ynn_fusion`: matrix products; other fusions: elementwise and reductions), their count and time.
Train step (the same model, fixed batch `--train_batch` cropped to its buckets as training crops it,
an all-pairs map encoder over the batch's packed polygons as training runs it): wall time of the step, of the map encoder's forward and backward pass alone, and the trace's
operations by kind.
Both traces are also broken down by the network's Python function that made each operation (`by_function`:
the compiled program's source stack frames, inclusive, top 16), e.g. how much of a train step is the grounded
attention's pairs or the map encoder's Fourier embeddings; the train step reads the map encoder's frozen
input side from a per-scene cache where the config freezes it, as training does.
Prints one JSON object. The trace needs XLA's per-operation events, so this script sets
`--xla_cpu_enable_xprof_traceme=true` in `XLA_FLAGS` before JAX starts.
"""

from __future__ import annotations

import collections
import glob
import os
import re
import sys
import tempfile
from pathlib import Path

os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_xprof_traceme=true").strip()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from absl import app, flags  # noqa: E402
from flax import nnx  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import common  # noqa: E402
from tdiff_jax import datatypes, diffusion, geometry, sampling  # noqa: E402
from tdiff_jax.data import batches  # noqa: E402
from tdiff_jax.train import trainer  # noqa: E402

FLAGS = flags.FLAGS
flags.DEFINE_enum("config", "av2", ["av2", "default"], "configs/hl.py variant")
flags.DEFINE_integer("batch", 1, "the sampling profile's fixed batch of 8 of the scene set (0: scenes 1 to 8, "
                     "1: 9 to 14, 1, 2)")
flags.DEFINE_integer("train_batch", 0, "the train step's batch (0: A = 16, P = 128 as training pads it)")
flags.DEFINE_string("trace_dir", "", "keep the traces here (default: a temporary folder)")
flags.DEFINE_integer("repeats", 5, "timed calls per measurement (the median is reported)")
flags.DEFINE_bool("train", True, "also break down a train step (--notrain: sampling only)")

GUIDED = ("clearance", "lane", "offroad")


def source_frames(hlo_text: str) -> dict[str, list[tuple[str, str, int]]]:
  """Each instruction of a compiled module's HLO text (`compiled.as_text()`) -> the Python call stack that
  made it, innermost first, as (file path, function, line) frames: the module's `FileNames`, `FunctionNames`,
  `FileLocations` and `StackFrames` tables, which the instructions' `stack_frame_id` metadata index."""
  tables: dict[str, dict[int, str]] = {"FileNames": {}, "FunctionNames": {}, "FileLocations": {}, "StackFrames": {}}
  section, frame_of = None, {}
  for line in hlo_text.splitlines():
    text = line.strip()
    if text in tables:
      section = text
    elif section and not text:
      section = None
    elif section:
      number, rest = text.split(" ", 1)
      tables[section][int(number)] = rest
    else:
      m = re.match(r"\s*(?:ROOT )?%([\w.\-]+) = .*stack_frame_id=(\d+)", line)
      if m:
        frame_of[m.group(1)] = int(m.group(2))
  field = lambda text, name: int(re.search(name + r"=(\d+)", text).group(1))  # noqa: E731
  locations = {}
  for i, text in tables["FileLocations"].items():
    file = tables["FileNames"].get(field(text, "file_name_id"), "?").strip('"')
    function = tables["FunctionNames"].get(field(text, "function_name_id"), "?").strip('"').split(".<locals>.")[-1]
    locations[i] = (file, function, field(text, "line"))

  def stack(frame: int) -> list[tuple[str, str, int]]:
    out, seen = [], set()
    while frame in tables["StackFrames"] and frame not in seen:
      seen.add(frame)
      text = tables["StackFrames"][frame]
      out.append(locations.get(field(text, "file_location_id"), ("?", "?", 0)))
      frame = field(text, "parent_frame_id") - 1   # printed one above the parent's number; 0: none
    return out

  return {name: stack(frame) for name, frame in frame_of.items()}


# The network's code: what `op_breakdown` attributes operations to.
NETWORK_SOURCES = re.compile(r"tdiff_jax/(models/|geometry\.py)")


def op_breakdown(fn, trace_dir: str, calls_per_run: int, hlo_text: str | None = None, top_functions: int = 16) -> dict:
  """XLA operations executed by one run of `fn` (traced), by kind: count and milliseconds per call. With
  the compiled program's `hlo_text`, also by the network's function that made them (`source_frames`,
  functions of `tdiff_jax/models/` and `tdiff_jax/geometry.py`): milliseconds per call of the operations
  under each function (inclusive: a function's callees count towards it), the `top_functions` largest;
  "(elsewhere)": operations made outside the network (the loss, the optimiser, the sampler's update),
  "(no source)": XLA's own (e.g. the first level of its tree reductions, the gradients' transposes)."""
  jax.block_until_ready(fn())
  jax.profiler.start_trace(trace_dir)
  jax.block_until_ready(fn())
  jax.profiler.stop_trace()
  from jax.profiler import ProfileData  # the trace reader that ships with jaxlib

  path = sorted(glob.glob(f"{trace_dir}/**/*.xplane.pb", recursive=True), key=os.path.getmtime)[-1]
  frames = source_frames(hlo_text) if hlo_text else {}
  time_ns, count, by_function = collections.Counter(), collections.Counter(), collections.Counter()
  for plane in ProfileData.from_file(path).planes:
    for line in plane.lines:
      if "XLAEigen" not in line.name:  # XLA's worker threads: one event per executed operation
        continue
      for event in line.events:
        name = event.name
        if name.startswith(("end:", "ThunkExecutor", "while", "call", "conditional")):
          continue  # bookkeeping, or a loop/call whose body's operations are counted themselves
        kind = re.sub(r"\.\d+$", "", name)
        kind = "matrix product" if kind in ("dot", "ynn_fusion", "xnn_fusion", "onednn") else kind
        time_ns[kind] += event.duration_ns
        count[kind] += 1
        if hlo_text:
          stack = frames.get(name, [])
          functions = {f"{file.split('tdiff_jax/')[-1]}:{function}" for file, function, _ in stack
                       if NETWORK_SOURCES.search(file)}
          for function in functions or {"(no source)" if not stack else "(elsewhere)"}:
            by_function[function] += event.duration_ns
  total = sum(time_ns.values())
  top = [{"kind": k, "ops_per_call": round(count[k] / calls_per_run, 1), "ms_per_call": round(v / 1e6 / calls_per_run, 3),
          "share": round(v / total, 3)} for k, v in time_ns.most_common(8)]
  out = {"ops_per_call": round(sum(count.values()) / calls_per_run, 1),
         "op_ms_per_call": round(total / 1e6 / calls_per_run, 3), "top_kinds": top}
  if hlo_text:
    out["by_function"] = [{"function": k, "ms_per_call": round(v / 1e6 / calls_per_run, 3), "share": round(v / total, 3)}
                          for k, v in by_function.most_common(top_functions)]
  return out


def main(argv: list[str]) -> None:
  del argv
  args = FLAGS
  setup = common.hl_setup(args.config)
  config, a_buckets, p_buckets, scenes = setup["config"], setup["a_buckets"], setup["p_buckets"], setup["scenes"]
  graphdef, params, sched, norm = setup["graphdef"], setup["params"], setup["sched"], setup["norm"]

  def fixed_batch(i: int) -> datatypes.Scene:
    chunk = datatypes.stack_scenes([scenes[j] for j in common.BATCHES_OF_8[i]])
    return jax.tree_util.tree_map(jnp.asarray, batches.crop_to_bucket(chunk, a_buckets, p_buckets))

  batch = fixed_batch(args.batch)
  trace_root = args.trace_dir or tempfile.mkdtemp(prefix="tdiff-profile-")
  result = {**common.machine(), "config": args.config, "batch": [list(common.OFFICIAL_TIMING_SET[i])
                                                                   for i in common.BATCHES_OF_8[args.batch]]}

  # Sampling: the map encoding, then one denoiser step per batch of one size (`batches.sampler_batches`), unguided and guided.
  model = nnx.merge(graphdef, params)
  encode_s = common.median_s(lambda: sampling.encode_maps(graphdef, params, batch, norm, p_buckets), args.repeats)

  @jax.jit
  def one_step(params, ctx, x, t, group):
    m = nnx.merge(graphdef, params)
    tt = jnp.full((x.shape[0],), t)
    return m.denoise(ctx, x, sched.betas[tt], sched.alpha_bars[tt], group.agent_type, group.agent_valid)[0]

  @jax.jit
  def guided_step(params, ctx, x, t, group, geom):
    opts = sampling.SamplerOptions("ddim", 10, GUIDED)
    eps = one_step(params, ctx, x, t, group)
    x0 = diffusion.x0_from_eps(sched, x, t, eps)
    grad = jax.grad(lambda z: sampling.total_cost(z, group, norm, opts, sampling.GuidanceParams(), None,
                                                  geom).sum())(x0)
    return x0 - grad

  counts = np.asarray(batch.agent_valid).sum(-1)
  groups, step_ms, guided_ms, padded_ms = [], 0.0, 0.0, 0.0
  # The batch's scenes as sample.py samples them: cut into batches of one size (`batches.sampler_batches`).
  for _, group in batches.sampler_batches([scenes[j] for j in common.BATCHES_OF_8[args.batch]], 8, a_buckets, p_buckets):
    group = jax.tree_util.tree_map(jnp.asarray, group)
    geometry_sizes = geometry.compact_sizes(group)
    geom = geometry.map_geometry(group, *geometry_sizes)
    padded_geom = geometry.map_geometry(group)  # the padded rings and points, what every step used before
    ctx = model.encode_map(group, norm)
    x = jax.random.normal(jax.random.key(0), group.agent_valid.shape + (2, norm.state_dim))
    unguided = common.median_s(lambda: one_step(params, ctx, x, 100, group), 4 * args.repeats)  # noqa: B023
    guided = common.median_s(lambda: guided_step(params, ctx, x, 100, group, geom), 4 * args.repeats)  # noqa: B023
    padded = common.median_s(lambda: guided_step(params, ctx, x, 100, group, padded_geom), 4 * args.repeats)  # noqa: B023
    groups.append({"scenes": group.agent_valid.shape[0], "agents": group.num_agents, "polygons": group.num_polygons,
                   "step_ms": round(1e3 * unguided, 2), "guided_step_ms": round(1e3 * guided, 2),
                   "guided_step_padded_geometry_ms": round(1e3 * padded, 2)})
    step_ms, guided_ms, padded_ms = step_ms + 1e3 * unguided, guided_ms + 1e3 * guided, padded_ms + 1e3 * padded
  calls = len(diffusion.ddim_timesteps(sched.num_steps, 10))
  result["sampling"] = {
      "map_encoding_ms": round(1e3 * encode_s, 1), "groups": groups,
      "ddim50_estimate_ms": {"map_encoding": round(1e3 * encode_s, 1), "denoiser_steps": round(calls * step_ms, 1),
                             "guidance": round(calls * (guided_ms - step_ms), 1),
                             "guidance_on_padded_geometry": round(calls * (padded_ms - step_ms), 1)},
  }
  first = jax.tree_util.tree_map(lambda x: x[:1], batch)
  first = first.crop(num_agents=datatypes.bucket_size(int(counts[0]), a_buckets),
                     num_polygons=datatypes.bucket_size(int(np.asarray(first.pl_valid).sum()), p_buckets))
  opts = sampling.SamplerOptions("ddim", 10)
  first_maps = sampling.encode_maps(graphdef, params, first, norm, p_buckets)
  sample_args = (graphdef, params, first, norm, sched, jax.random.key(0), opts)
  sample_hlo = sampling.sample.lower(*sample_args, map_context=first_maps, lane_pull=setup["lane_pull"]).compile().as_text()
  result["sampling"]["trace_one_scene_ddim50"] = {
      "agents": first.num_agents, "polygons": first.num_polygons,
      "per_network_call": op_breakdown(lambda: sampling.sample(*sample_args, map_context=first_maps, lane_pull=setup["lane_pull"]),
                                       f"{trace_root}/sample", calls, sample_hlo)}
  common.progress(result["sampling"])
  if not args.train:
    common.report(result)
    return

  # Train step: the whole step, and the map encoder's forward and backward pass alone.
  batch = fixed_batch(args.train_batch)
  consts = trainer.Constants(common.norm_stats(config, [scenes[j] for j in common.BATCHES_OF_8[args.train_batch]]),
                             sched)
  flat, tx, state = trainer.init_flat_state(config, jax.tree_util.tree_map(np.array, params))
  packed = trainer.packed_polygons(config, batch)   # as training: an all-pairs encoder's packed polygons
  # As training: a frozen input side that is a constant of each polygon read from a per-scene cache.
  indices = np.array(common.BATCHES_OF_8[args.train_batch])
  cache = trainer.map_inputs_cache(config, graphdef, params, consts.norm, common.scene_split(scenes))
  map_inputs = None if cache is None else cache.take(indices, batch.num_polygons)
  step = trainer.jit_train_step(graphdef, tx, config, flat=flat).lower(state, batch, consts, packed,
                                                                        map_inputs).compile()
  holder = {"state": state}

  def train_once():
    holder["state"], metrics = step(holder["state"], batch, consts, packed, map_inputs)
    return metrics

  @jax.jit
  def encoder_fwd_bwd(params, scene, packed, map_inputs):
    def loss(p):
      encoder = nnx.merge(graphdef, p).map_encoder
      return jnp.sum(encoder(scene, norm.mean[:2], norm.std[:2], packed=packed, inputs=map_inputs).polygons ** 2)
    return jax.grad(loss)(params)

  step_s = common.median_s(train_once, 3)
  encoder_s = common.median_s(lambda: encoder_fwd_bwd(params, batch, packed, map_inputs), 3)
  result["train_step"] = {"agents": batch.num_agents, "polygons": batch.num_polygons,
                          "map_inputs": "read from a per-scene cache, as training" if cache is not None
                          else "computed by the step",
                          "step_ms": round(1e3 * step_s, 1), "map_encoder_fwd_bwd_ms": round(1e3 * encoder_s, 1),
                          "map_encoder_share": round(encoder_s / step_s, 3),
                          "ops": op_breakdown(train_once, f"{trace_root}/train", 1, step.as_text())}
  common.progress(result["train_step"])
  common.report(result)


if __name__ == "__main__":
  app.run(main)
