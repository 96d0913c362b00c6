"""Where along the sampler an HL checkpoint's agents find their lanes: every network call's x0 estimate scored.

  python experiments/sampler_trajectory.py HL_WORKDIR [--solver_steps=11] [--solver_max_noise=12] [--restarts=0]
      [--restart_steps=1]

Samples every scene of the checkpoint's validation split (batches of 8, keys as `evaluate`'s) with
DPM-Solver++(2M) (`--restarts`: restart sampling, `sampling.SamplerOptions.restarts`) and scores, after
each network call, the call's x0 estimate (clipped as the sampler clips it) as if it were the sample:
  * goal reachability (`metrics.goal_reachability`, and why the others are not reachable);
  * the median and 75th percentile distance of road users' endpoints to the nearest lane centreline
    whose direction agrees with their heading, and the share beyond half a lane (1.75 m);
  * the median distance each road user's endpoint moves from this call's estimate to the next call's.
The last call's estimate is the sample (the solver's last step returns it). Prints one line per call
(docs/learning_the_map.md, "Restart sampling"). An experiment, not part of the library.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from goal_given_initial import lane_geometry, validation_batches  # noqa: E402
from tdiff_jax import checkpoint, datatypes, diffusion, metrics, sampling  # noqa: E402
from tdiff_jax.data.normalize import denormalize_heading, denormalize_state  # noqa: E402


def main(argv: list[str]) -> None:
  if len(argv) < 2 or argv[1].startswith("--"):
    raise SystemExit(__doc__)
  workdir = Path(argv[1])
  flags = dict(a[2:].split("=", 1) for a in argv[2:] if a.startswith("--"))
  options = sampling.SamplerOptions(method="dpmpp2m",
                                    solver_steps=int(flags.get("solver_steps", sampling.DEFAULT_SOLVER_STEPS)),
                                    solver_max_noise=float(flags.get("solver_max_noise",
                                                                     sampling.DEFAULT_SOLVER_MAX_NOISE)),
                                    restarts=int(flags.get("restarts", 0)),
                                    restart_steps=int(flags.get("restart_steps", 1)))
  hl = checkpoint.load_checkpoint(workdir, task="hl")
  if not hl.norm.heading:
    raise SystemExit(f"{workdir}: this experiment scores the model's own headings (model.heading_state)")
  sched, norm, data = hl.sched, hl.norm, hl.config.data
  steps = np.asarray(diffusion.solver_timesteps(sched, options.solver_steps, options.solver_max_noise))
  labels = [f"t={t}" for t in steps] + [f"restart {r + 1}, t={t}" for r in range(options.restarts)
                                         for t in steps[-options.restart_steps:]]
  records: list[np.ndarray] = []

  @jax.jit
  def run(params, scene, key):
    model = nnx.merge(hl.graphdef, params)
    ctx = model.encode_map(scene, norm)

    def denoise_fn(x, t, x0_prev=None, has_prev=None):
      eps, _ = model.denoise(ctx, x, sched.betas[t], sched.alpha_bars[t], scene.agent_type, scene.agent_valid,
                             x0_prev=x0_prev, has_prev=has_prev)
      x0 = jnp.clip(diffusion.x0_from_eps(sched, x, t, eps), -options.clip_x0, options.clip_x0)
      jax.debug.callback(lambda v: records.append(np.asarray(v)), x0, ordered=True)
      return eps

    return sampling.sample_with(denoise_fn, scene, norm, sched, key, options,
                                self_conditioned=model.cfg.self_condition)

  n_calls = len(labels)
  reach = [dict.fromkeys(metrics.REACHABILITY_COUNTS, 0) for _ in range(n_calls)]
  dist = [[] for _ in range(n_calls)]
  moves = [[] for _ in range(n_calls - 1)]
  for chunk, batch, key in validation_batches(workdir, data):
    conditioning = batch.replace(agent_state=jnp.zeros_like(batch.agent_state))
    records.clear()
    out = run(hl.params, conditioning, key)
    jax.block_until_ready(out)
    if len(records) != n_calls:
      raise SystemExit(f"expected {n_calls} network calls, recorded {len(records)}")
    states = [np.asarray(denormalize_state(jnp.asarray(x0), batch.frame_scale, norm)) for x0 in records]
    headings = [np.asarray(denormalize_heading(jnp.asarray(x0))) for x0 in records]
    host = jax.device_get(batch)
    for i in range(len(chunk)):
      one = jax.tree_util.tree_map(lambda x: x[i], host)  # noqa: B023
      graph = metrics._lane_graph(one)
      if not len(graph[0]):
        continue
      road = np.asarray(one.agent_valid) & (np.asarray(one.agent_type) != datatypes.PEDESTRIAN)
      for k in range(n_calls):
        d, _, _ = lane_geometry(states[k][i], headings[k][i], one, graph)
        dist[k].append(d.ravel())
        for name, v in metrics.goal_reachability(states[k][i], one).items():
          reach[k][name] += v
        if k + 1 < n_calls:
          step = states[k + 1][i][road, :, :2] - states[k][i][road, :, :2]
          moves[k].append(np.linalg.norm(step, axis=-1).ravel())
  print(f"{workdir} ({options.describe()}, {options.network_calls(sched.num_steps)} network calls)")
  print("| call | reachable (%) | to consistent centreline, median / p75 (m) | beyond 1.75 m (%) | "
        "moves to the next estimate, median (m) | " + " / ".join(metrics.REACHABILITY_FAILURES) + " |")
  print("|---|---|---|---|---|---|")
  for k in range(n_calls):
    d = np.concatenate(dist[k])
    d = d[np.isfinite(d)]
    move = f"{np.median(np.concatenate(moves[k])):.2f}" if k + 1 < n_calls else "-"
    print(f"| {labels[k]} | {metrics.reachability_pct(reach[k]):.1f} | {np.median(d):.2f} / {np.percentile(d, 75):.2f} "
          f"| {100 * np.mean(d > 1.75):.1f} | {move} | "
          + " / ".join(str(reach[k][name]) for name in metrics.REACHABILITY_FAILURES) + " |")


if __name__ == "__main__":
  main(sys.argv)
