"""Where an HL checkpoint's unreachable endpoints lie, and how precise its last denoiser calls are.

  python experiments/endpoint_failures.py HL_WORKDIR

Two measurements on the checkpoint's validation split (docs/learning_the_map.md, "Where the off-lane
endpoints lie"):
  * The default sampler's samples (batches of 8, keys as `evaluate`'s; DPM-Solver++(2M), the command
    lines' calls and start level, and 4 restarts) beside the ground truth: of the road users' endpoints
    farther than `metrics.ON_LANE_M` from every lane centreline (reachability's "off lane"), how many
    have their nearest centreline point at the end of a lane without successors (past a dead end) or
    within 10 m of the map's bounding box; and how many initial states on a lane have less road ahead of them along the lane
    graph (the farthest lane end a route reaches) than the straight distance to their own goal minus
    2 m: agents placed where the map ends before their goal.
  * The one-step estimate of noised ground truth at t = 1, 3, 10, 30 (as `map_diagnostics`), read once
    without a previous estimate and then twice more, each pass reading the last pass's estimate as
    self-conditioning does in the sampler: the median position error (m) of each pass against the
    noisy input's own (sqrt(alpha_bar) x_t).
An experiment, not part of the library.
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

from goal_given_initial import validation_batches  # noqa: E402
from tdiff_jax import checkpoint, datatypes, diffusion, map_diagnostics, metrics, sampling  # noqa: E402
from tdiff_jax.data.normalize import denormalize_state  # noqa: E402

MAP_EDGE_M = 10.0     # "near the map's edge": within this of the bounding box of the map's points
DEAD_END_M = 0.5      # a foot within this of a lane's end is at the end
PASSES = 3
STEPS = (1, 3, 10, 30)


def endpoint_rows(state: np.ndarray, scene) -> list[tuple]:
  """Per road user of one scene: (distance to the nearest centreline, its foot past a dead end, near the map's
  edge) for each endpoint, and (road ahead of the initial state, distance to the goal) in metres."""
  lanes, pts, centre, path = metrics._lane_graph(scene)
  if not len(lanes):
    return []
  ok = centre[:, 1:] & centre[:, :-1]
  length = (np.linalg.norm(np.diff(pts, axis=1), axis=-1) * ok).sum(-1)                  # [L]
  edge = np.asarray(scene.pl_edge)[np.ix_(lanes, lanes)]
  has_successor = (edge == metrics._SUCC).any(1)
  farthest = np.where(np.isfinite(path), path + length[None], -np.inf).max(1)           # [L] from the lane's start
  xy_all = np.asarray(scene.pt_xy)[np.asarray(scene.pt_valid)]
  lo, hi = xy_all.min(0), xy_all.max(0)
  road = np.asarray(scene.agent_valid) & (np.asarray(scene.agent_type) != datatypes.PEDESTRIAN)
  rows = []
  for a in np.flatnonzero(road):
    xy = np.asarray(state[a, :, :2], np.float64)
    dist, arc = metrics._project(xy, pts, centre)                                        # [2, L]
    nearest = dist.argmin(-1)
    dead = [not has_successor[nearest[k]] and arc[k, nearest[k]] >= length[nearest[k]] - DEAD_END_M for k in range(2)]
    edge_m = [min((xy[k] - lo).min(), (hi - xy[k]).min()) for k in range(2)]
    candidates = dist[0] <= dist[0].min() + metrics.LANE_CANDIDATE_M
    ahead = np.where(candidates, farthest - arc[0], -np.inf).max()
    rows.append((dist.min(-1), dead, edge_m, ahead, float(np.linalg.norm(xy[1] - xy[0]))))
  return rows


def summarize(who: str, rows: list[tuple]) -> None:
  dist = np.array([r[0] for r in rows])
  dead = np.array([r[1] for r in rows])
  edge_m = np.array([r[2] for r in rows])
  ahead = np.array([r[3] for r in rows])
  chord = np.array([r[4] for r in rows])
  off = dist > metrics.ON_LANE_M
  for k, name in enumerate(("initial", "goal")):
    print(f"  {who}, {name} states: {len(rows)} road users, {off[:, k].sum()} off every lane; of those "
          f"{dead[off[:, k], k].sum()} past a dead end, {(edge_m[off[:, k], k] < MAP_EDGE_M).sum()} within "
          f"{MAP_EDGE_M:.0f} m of the map's edge")
  on = ~off[:, 0]
  short = on & (ahead < chord - 2.0)
  print(f"  {who}: initial states on a lane with less road ahead than the distance to their goal - 2 m: "
        f"{short.sum()} of {on.sum()}; road ahead, 5th / 25th / 50th percentile: "
        + " / ".join(f"{v:.0f}" for v in np.percentile(ahead[on], [5, 25, 50])) + " m")


def main(argv: list[str]) -> None:
  if len(argv) != 2:
    raise SystemExit(__doc__)
  workdir = Path(argv[1])
  hl = checkpoint.load_checkpoint(workdir, task="hl")
  options = sampling.SamplerOptions(method="dpmpp2m", solver_steps=sampling.DEFAULT_SOLVER_STEPS,
                                    solver_max_noise=sampling.DEFAULT_SOLVER_MAX_NOISE,
                                    restarts=sampling.DEFAULT_RESTARTS)
  rows = {"ground truth": [], "samples": []}
  errors = {t: [] for t in STEPS}

  @jax.jit
  def passes(params, batch, t, key):
    model = nnx.merge(hl.graphdef, params)
    tt, x_t = map_diagnostics.noised_ground_truth(hl.sched, hl.norm, batch, t, key)
    ctx = model.encode_map(batch, hl.norm)
    previous, out = None, []
    for _ in range(PASSES if model.cfg.self_condition else 1):
      eps, _ = model.denoise(ctx, x_t, hl.sched.betas[tt], hl.sched.alpha_bars[tt], batch.agent_type,
                             batch.agent_valid, x0_prev=previous)
      previous = jnp.clip(diffusion.x0_from_eps(hl.sched, x_t, tt, eps), -options.clip_x0, options.clip_x0)
      out.append(previous)
    out.append(jnp.sqrt(hl.sched.alpha_bars[t]) * x_t)          # the noisy input's own estimate
    truth = batch.agent_state[..., :2]
    return jnp.stack([jnp.linalg.norm(denormalize_state(x, batch.frame_scale, hl.norm)[..., :2] - truth, axis=-1)
                      for x in out])                                                    # [passes + 1, B, A, 2]

  for c, (chunk, batch, key) in enumerate(validation_batches(workdir, hl.config.data)):
    conditioning = batch.replace(agent_state=jnp.zeros_like(batch.agent_state))
    out = sampling.sample(hl.graphdef, hl.params, conditioning, hl.norm, hl.sched, key, options)
    state = np.asarray(out.state)
    host = jax.device_get(batch)
    for i in range(len(chunk)):
      one = jax.tree_util.tree_map(lambda x: x[i], host)  # noqa: B023
      rows["ground truth"] += endpoint_rows(np.asarray(one.agent_state), one)
      rows["samples"] += endpoint_rows(state[i], one)
    road = np.asarray(batch.road_users)
    for t in STEPS:
      err = np.asarray(passes(hl.params, batch, t, jax.random.key(1000 * c + t)))
      errors[t].append(err[:, road])
  print(f"{workdir} ({options.describe()})")
  for who, r in rows.items():
    summarize(who, r)
  print("One-step estimates of noised ground truth, median position error over road users' endpoints (m):")
  for t in STEPS:
    e = np.concatenate(errors[t], 1)
    cells = ", ".join(f"pass {k + 1} {np.median(e[k]):.2f}" for k in range(len(e) - 1))
    print(f"  t = {t}: {cells}; the noisy input {np.median(e[-1]):.2f}")


if __name__ == "__main__":
  main(sys.argv)
