"""Goal reachability of an HL checkpoint's samples, free or given the ground truth's initial states.

  python experiments/goal_given_initial.py HL_WORKDIR [free|initial|resample] [--order=joint|staged] [--method=M]

Samples every scene of the checkpoint's validation split (batches of 8, key as `evaluate`'s) with the
default sampler (DPM-Solver++(2M), 15 calls), either freely or with each agent's initial state fixed to
the ground truth's (`sample(fixed_state=..., fixed_mask=...)`: inpainting, so only the goals are
sampled), or with them fixed to those of a free sample (`resample`: the goals sampled again given the
model's own initial states), and prints (docs/learning_the_map.md, "Staged noise levels"):
  * `goal_reachability` counts for the ground truth and the samples;
  * how far the road users' endpoints lie from the nearest lane centreline whose direction agrees
    with their heading (quartiles, 90th and 95th percentiles, the share beyond half a lane, 1.75 m);
  * the reachability of the samples with every endpoint moved onto the nearest centreline (any
    direction), then onto the nearest centreline that agrees with its heading (stopped agents: any):
    whether the unreachable goals are imprecise around the right lane or on a wrong one.
An experiment, not part of the library.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tdiff_jax import checkpoint, datatypes, metrics, sampling  # noqa: E402
from tdiff_jax.data import av2_io, batches, scene_builder  # noqa: E402
from tdiff_jax.datatypes import PEDESTRIAN  # noqa: E402
from tdiff_jax.evaluate import training_val_split  # noqa: E402

MOVING_MPS = 1.0  # below this an agent's heading says nothing about its lane
AGREE_COS = 0.5   # a lane agrees with a heading within 60 degrees


def _feet(xy: np.ndarray, pts: np.ndarray, centre: np.ndarray):
  """For points `[N, 2]`: the foot on every centreline segment `[N, L, S, 2]`, its distance (inf where
  the segment is not a centreline one) and the unit segment directions `[L, S, 2]`."""
  start, end = pts[:, :-1], pts[:, 1:]
  ok = centre[:, 1:] & centre[:, :-1]
  u = end - start
  rel = xy[:, None, None] - start[None]
  t = np.clip(np.sum(rel * u, -1) / np.maximum(np.sum(u * u, -1), 1e-9), 0.0, 1.0)
  foot = start[None] + t[..., None] * u
  dist = np.where(ok[None], np.linalg.norm(xy[:, None, None] - foot, axis=-1), np.inf)
  return foot, dist, u / np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-9)


def lane_geometry(state: np.ndarray, heading: np.ndarray, scene, lanes_pts_centre):
  """Per road user and endpoint: distance to the nearest heading-consistent centreline `[N, 2]`, and the
  state with endpoints snapped to the nearest centreline (any) and to the nearest consistent one."""
  _, pts, centre, _ = lanes_pts_centre
  road = np.asarray(scene.agent_valid) & (np.asarray(scene.agent_type) != PEDESTRIAN)
  any_snap, agree_snap = np.array(state, np.float64), np.array(state, np.float64)
  consistent = np.full((len(road), 2), np.inf)
  for tok in range(2):
    foot, dist, direction = _feet(np.asarray(state[:, tok, :2], np.float64), pts, centre)
    h = np.stack([np.cos(heading[:, tok]), np.sin(heading[:, tok])], -1)
    stopped = (np.asarray(state[:, tok, 2]) < MOVING_MPS)[:, None, None]
    agree = (np.sum(direction[None] * h[:, None, None], -1) > AGREE_COS) | stopped
    dist_agree = np.where(agree, dist, np.inf)
    dist_agree = np.where(np.isfinite(dist_agree).any((1, 2), keepdims=True), dist_agree, dist)
    n = len(road)
    flat_foot = foot.reshape(n, -1, 2)
    any_snap[:, tok, :2] = flat_foot[np.arange(n), dist.reshape(n, -1).argmin(-1)]
    agree_snap[:, tok, :2] = flat_foot[np.arange(n), dist_agree.reshape(n, -1).argmin(-1)]
    consistent[:, tok] = dist_agree.reshape(n, -1).min(-1)
  return consistent[road], any_snap, agree_snap


def validation_batches(workdir: Path, data):
  """The checkpoint's validation split in batches of 8 as `evaluate` samples them: yields the scenes
  (unbatched, for scoring), the batch cropped to its buckets, and the batch's sampling key."""
  folders = av2_io.map_folders(training_val_split(workdir))
  for c in range(0, len(folders), 8):
    chunk = [scene_builder.load_scene(f, data.scene)[0] for f in folders[c:c + 8]]
    batch = batches.crop_to_bucket(datatypes.stack_scenes(chunk), data.agent_buckets, data.polygon_buckets)
    yield chunk, jax.tree_util.tree_map(jnp.asarray, batch), jax.random.fold_in(jax.random.key(0), c // 8)


def main(argv: list[str]) -> None:
  if len(argv) < 2:
    raise SystemExit(__doc__)
  workdir = Path(argv[1])
  mode = argv[2] if len(argv) > 2 and not argv[2].startswith("--") else "free"
  flags = dict(a[2:].split("=", 1) for a in argv[2:] if a.startswith("--"))
  if mode not in ("free", "initial", "resample"):
    raise SystemExit(f"mode {mode!r}: free, initial or resample")
  options = sampling.SamplerOptions(method=flags.get("method", "dpmpp2m"), order=flags.get("order", "joint"))
  hl = checkpoint.load_checkpoint(workdir, task="hl")
  data = hl.config.data
  rows = ("gt", "model", "snapped to the nearest centreline", "snapped to the nearest consistent centreline")
  reach = {r: dict.fromkeys(metrics.REACHABILITY_COUNTS, 0) for r in rows}
  distances = {"gt": [], "model": []}
  for chunk, batch, key in validation_batches(workdir, data):
    fixed = {}
    if mode == "initial":
      mask = jnp.zeros(batch.agent_valid.shape + (2,), bool).at[..., 0].set(True) & batch.agent_valid[..., None]
      fixed = {"fixed_state": batch.agent_state, "fixed_mask": mask}
    conditioning = batch.replace(agent_state=jnp.zeros_like(batch.agent_state))
    if mode == "resample":  # a joint sample's initial states kept, its goals sampled again given them
      first = sampling.sample(hl.graphdef, hl.params, conditioning, hl.norm, hl.sched, key,
                              sampling.SamplerOptions(method=options.method))
      mask = jnp.zeros(batch.agent_valid.shape + (2,), bool).at[..., 0].set(True) & batch.agent_valid[..., None]
      fixed = {"fixed_state": jnp.concatenate([first.state, first.heading[..., None]], -1), "fixed_mask": mask}
      key = jax.random.fold_in(key, 1)
    out = sampling.sample(hl.graphdef, hl.params, conditioning, hl.norm, hl.sched, key, options, **fixed)
    host, state, heading = jax.device_get(batch), np.asarray(out.state), np.asarray(out.heading)
    for i in range(len(chunk)):
      one = jax.tree_util.tree_map(lambda x: x[i], host)  # noqa: B023
      graph = metrics._lane_graph(one)
      if not len(graph[0]):
        continue
      gt_dist, _, _ = lane_geometry(one.agent_state[..., :3], one.agent_state[..., 3], one, graph)
      dist, any_snap, agree_snap = lane_geometry(state[i], heading[i], one, graph)
      distances["gt"].append(gt_dist.ravel())
      distances["model"].append(dist.ravel())
      for row, st in zip(rows, (one.agent_state, state[i], any_snap, agree_snap)):
        for k, v in metrics.goal_reachability(st, one).items():
          reach[row][k] += v
  print(f"{workdir} ({mode}, {options.describe()}, order {options.order})")
  for row in rows:
    print(f"  reachable {metrics.reachability_pct(reach[row]):5.1f} %  {row}: "
          + ", ".join(f"{k} {reach[row][k]}" for k in metrics.REACHABILITY_COUNTS[1:]))
  for who, d in distances.items():
    d = np.concatenate(d)
    d = d[np.isfinite(d)]
    q = ", ".join(f"{np.percentile(d, p):.2f}" for p in (25, 50, 75, 90, 95))
    print(f"  {who}: distance to the nearest heading-consistent centreline (m), percentiles 25/50/75/90/95: {q}; "
          f"beyond 1.75 m: {100 * np.mean(d > 1.75):.1f} %")


if __name__ == "__main__":
  main(sys.argv)
