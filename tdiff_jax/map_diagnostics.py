"""Does an HL checkpoint use its map? `python -m tdiff_jax.map_diagnostics [--hl_workdir=workdirs/hl]`.

Two measurements on a split's scenes (default: the workdir's synthetic validation split):

* **One-step denoising per noise level.** The ground truth is noised to step t (a fixed seed) and the
  model's one-step estimate x0_hat(x_t, t) is scored: mean position error (m) and official off-road
  rate of road users. Next to it the best map-blind estimate, E[x0 | x_t] = sqrt(alpha_bar_t) x_t
  under the unit-variance prior of the normalised state: a model that learned the map beats it. Also
  the part of the error across the lane (perpendicular to the centreline nearest the true position)
  and the distance to the nearest lane centreline (the strict convention's near-edge distance and
  lateral deviation), next to the ground truth's own: how precisely the estimate puts agents on their
  lanes. And the error's 10th, 50th and 90th percentiles over road users' tokens: whether a mean comes
  from a few outliers or from a broad imprecision. And the speeds: the share of moving agents' tokens
  (ground truth at least 1 m/s, the speed histograms' first bin) whose estimate is below 1 m/s, and of
  stopped ones estimated at 1 m/s or more.
* **Map sensitivity.** The same noise is sampled (DDIM-50, unguided) on each scene's own map and on
  the next scene's map; the mean distance between the two samples' positions (m) says how much the
  map steers the result.

Prints Markdown and writes `map_diagnostics.json` to --out (default <hl workdir>/eval).
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from absl import flags
from flax import nnx

from tdiff_jax import checkpoint, cli, datatypes, diffusion, evaluate, files, metrics, sampling
from tdiff_jax.data import av2_io, batches, scene_builder
from tdiff_jax.data.normalize import denormalize_state, normalized_state
from tdiff_jax.models import grounding

STEPS = (1, 10, 30, 100, 200, 300, 500)
PERCENTILES = (10, 50, 90)
STOPPED_MPS = 1.0   # a token slower than this counts as stopped (the speed histograms' first bin)



def _lane_directions(xy: jax.Array, scene: datatypes.Scene) -> jax.Array:
  """`[B, A, 2]` direction (cos, sin) of the lane centreline nearest each position `[B, A, 2]` (m)."""
  feats, dist, _ = grounding.relation_features(xy, grounding.centerlines(scene))
  nearest = jnp.argmin(jnp.where(scene.lane_polygons[:, None], dist, jnp.inf), -1)[..., None, None]
  return jnp.take_along_axis(feats[..., grounding.DIRECTION], nearest, axis=2)[..., 0, :]


def _offroad_and_error(xy: jax.Array, scene: datatypes.Scene, lane_direction: jax.Array) -> tuple[jax.Array, ...]:
  """Sums over road users and both tokens of official off-road, position error, distance to the nearest
  lane centreline (the strict near-edge distance) and error across the lane (m); their count.
  `lane_direction` `[B, A, 2, 2]`: the direction of the lane nearest each true position."""
  road = scene.road_users
  off = err = lateral = across = 0.0
  for tok in range(2):
    acc = metrics.state_accumulators(xy[..., tok, :], scene.agent_state[..., tok, 2], scene.agent_state[..., tok, 3], scene)
    off = off + acc["official/offroad_sum"]
    lateral = lateral + acc["strict/near_edge_sum"]
    d = xy[..., tok, :] - scene.agent_state[..., tok, :2]
    u = lane_direction[..., tok, :]
    err = err + jnp.sum(jnp.where(road, jnp.linalg.norm(d, axis=-1), 0.0))
    across = across + jnp.sum(jnp.where(road, jnp.abs(u[..., 0] * d[..., 1] - u[..., 1] * d[..., 0]), 0.0))
  return off, err, 2.0 * jnp.sum(road), lateral, across


def noised_ground_truth(sched: diffusion.Schedule, norm, batch: datatypes.Scene, t: int,
                        key: jax.Array) -> tuple[jax.Array, jax.Array]:
  """The batch's ground truth as the normalised model state, noised to step t: the steps `[B]` and x_t
  `[B, A, 2, F]` (noise from `key`)."""
  x0 = normalized_state(batch, norm)
  tt = jnp.full(x0.shape[:1], t)
  return tt, diffusion.q_sample(sched, x0, tt, jax.random.normal(key, x0.shape))


def diagnose(hl_workdir: Path | str, data: Path | str, max_scenes: int = 64, batch_size: int = 8) -> dict:
  m = checkpoint.load_checkpoint(hl_workdir, task="hl")
  data_config = m.config.data
  folders = av2_io.map_folders(data)[: max_scenes or None]
  scenes, skipped = [], 0
  for folder in folders:
    try:
      scenes.append(scene_builder.load_scene(folder, data_config.scene)[0])
    except av2_io.BadScenarioError:
      skipped += 1
  if not scenes:
    raise ValueError(f"{data}: no usable scenario")

  @jax.jit
  def one_step(params, batch, t, key):
    model = nnx.merge(m.graphdef, params)
    tt, x_t = noised_ground_truth(m.sched, m.norm, batch, t, key)
    ctx = model.encode_map(batch, m.norm)
    eps, _ = model.denoise(ctx, x_t, m.sched.betas[tt], m.sched.alpha_bars[tt], batch.agent_type, batch.agent_valid,
                           lane_pull=m.lane_pull)
    x0_hat = diffusion.x0_from_eps(m.sched, x_t, tt, eps)
    blind = jnp.sqrt(m.sched.alpha_bars[t]) * x_t
    estimate = denormalize_state(x0_hat, batch.frame_scale, m.norm)                          # [B, A, 2, F] m, m/s
    xy = {"model": estimate[..., :2], "blind": denormalize_state(blind, batch.frame_scale, m.norm)[..., :2]}
    truth = batch.agent_state[..., :2]
    lane = jnp.stack([_lane_directions(truth[..., tok, :], batch) for tok in range(2)], -2)    # [B, A, 2, 2]
    gt_lateral = _offroad_and_error(truth, batch, lane)[3]
    errors = [jnp.linalg.norm(xy[k] - truth, axis=-1) for k in ("model", "blind")]           # [B, A, 2] m each
    moving = batch.agent_state[..., 2] >= STOPPED_MPS                                          # [B, A, 2]
    slow = estimate[..., 2] < STOPPED_MPS
    valid = batch.agent_valid[..., None]
    speed_counts = jnp.stack([jnp.sum(valid & moving & slow), jnp.sum(valid & moving),
                              jnp.sum(valid & ~moving & ~slow), jnp.sum(valid & ~moving)])
    return (_offroad_and_error(xy["model"], batch, lane), _offroad_and_error(xy["blind"], batch, lane), gt_lateral,
            errors, speed_counts)

  per_t = {t: np.zeros((2, 5)) for t in STEPS}
  speed_counts = {t: np.zeros(4) for t in STEPS}   # moving estimated stopped, moving, stopped estimated moving, stopped
  token_errors = {t: ([], []) for t in STEPS}   # each road user token's error (m): model, map-blind
  gt_lateral = 0.0
  moved, moved_n = 0.0, 0
  for c in range(0, len(scenes), batch_size):
    chunk = scenes[c:c + batch_size]
    batch = batches.crop_to_bucket(datatypes.stack_scenes(chunk), data_config.agent_buckets, data_config.polygon_buckets)
    batch = jax.tree_util.tree_map(jnp.asarray, batch)
    road = np.asarray(batch.road_users)
    for t in STEPS:
      *res, lateral, errors, counts = jax.device_get(one_step(m.params, batch, t, jax.random.key(c * 1000 + t)))
      per_t[t] += np.array([[float(v) for v in r] for r in res])
      speed_counts[t] += np.asarray(counts, np.float64)
      for acc, err in zip(token_errors[t], errors):
        acc.append(np.asarray(err)[road].ravel())
      gt_lateral += float(lateral) if t == STEPS[0] else 0.0
    if len(chunk) > 1:
      key = jax.random.key(c)
      cond = batch.replace(agent_state=jnp.zeros_like(batch.agent_state))
      own = sampling.sample(m.graphdef, m.params, cond, m.norm, m.sched, key, lane_pull=m.lane_pull)
      other = sampling.sample(m.graphdef, m.params, evaluate.with_next_map(cond), m.norm, m.sched, key,
                              lane_pull=m.lane_pull)
      d = np.linalg.norm(np.asarray(own.state[..., :2] - other.state[..., :2]), axis=-1)   # [B, A, 2]
      valid = np.asarray(batch.agent_valid)[..., None] & np.ones(d.shape, bool)
      moved += float(d[valid].sum())
      moved_n += int(valid.sum())
  rows = {}
  for t, ((off, err, n, lat, across), (boff, berr, bn, blat, bacross)) in per_t.items():
    rows[str(t)] = {"noise_m": float(np.sqrt(1 - float(m.sched.alpha_bars[t])) * float(np.mean(m.norm.std[:2]))
                                     * float(scenes[0].frame_scale)),
                    "model_error_m": err / max(n, 1), "model_offroad_pct": 100 * off / max(n, 1),
                    "model_across_m": across / max(n, 1), "model_to_centreline_m": lat / max(n, 1),
                    "blind_error_m": berr / max(bn, 1), "blind_offroad_pct": 100 * boff / max(bn, 1),
                    "blind_across_m": bacross / max(bn, 1), "blind_to_centreline_m": blat / max(bn, 1),
                    "moving_estimated_stopped_pct": 100 * speed_counts[t][0] / max(speed_counts[t][1], 1),
                    "stopped_estimated_moving_pct": 100 * speed_counts[t][2] / max(speed_counts[t][3], 1)}
    for name, parts in zip(("model", "blind"), token_errors[t]):
      errs = np.concatenate(parts) if parts else np.zeros(0)
      rows[str(t)][f"{name}_error_percentiles_m"] = (
          {str(q): float(np.percentile(errs, q)) for q in PERCENTILES} if errs.size else {})
  road_tokens = per_t[STEPS[0]][0, 2]
  return {"hl_checkpoint": {"workdir": str(hl_workdir), "step": m.record["step"]}, "data": str(data),
          "scenes": len(scenes), "skipped": skipped, "one_step": rows,
          "gt_to_centreline_m": gt_lateral / max(road_tokens, 1),
          "map_sensitivity_m": moved / max(moved_n, 1)}


def to_markdown(r: dict) -> str:
  lines = [f"Map diagnostics of `{r['hl_checkpoint']['workdir']}` (step {r['hl_checkpoint']['step']}) on "
           f"{r['scenes']} scenes of `{r['data']}`.", "",
           "Errors and distances are means over road users' tokens (m); across: the error's part perpendicular to",
           "the lane nearest the true position; to centreline: distance to the nearest lane centreline (ground",
           f"truth: {r['gt_to_centreline_m']:.2f} m).", "",
           "| t | noise (m) | x0_hat error | x0_hat across | x0_hat to centreline | x0_hat off-road (%) | "
           "map-blind error | map-blind across | map-blind to centreline | map-blind off-road (%) |",
           "|---|---|---|---|---|---|---|---|---|---|"]
  for t, row in r["one_step"].items():
    lines.append(f"| {t} | {row['noise_m']:.1f} | {row['model_error_m']:.2f} | {row['model_across_m']:.2f} | "
                 f"{row['model_to_centreline_m']:.2f} | {row['model_offroad_pct']:.1f} | "
                 f"{row['blind_error_m']:.2f} | {row['blind_across_m']:.2f} | {row['blind_to_centreline_m']:.2f} | "
                 f"{row['blind_offroad_pct']:.1f} |")
  lines += ["", "Spread of the position error over road users' tokens (m; percentiles "
            f"{' / '.join(map(str, PERCENTILES))}): a mean set by a few outliers or a broad imprecision.", "",
            "| t | x0_hat error | map-blind error |", "|---|---|---|"]
  for t, row in r["one_step"].items():
    spread = [" / ".join(f"{v:.2f}" for v in row[f"{name}_error_percentiles_m"].values()) or "-"
              for name in ("model", "blind")]
    lines.append(f"| {t} | {spread[0]} | {spread[1]} |")
  lines += ["", f"Speeds: the share of moving tokens (ground truth >= {STOPPED_MPS:g} m/s) whose x0_hat is slower, and of "
            "stopped ones whose x0_hat is not.", "", "| t | moving estimated stopped (%) | stopped estimated moving (%) |",
            "|---|---|---|"]
  lines += [f"| {t} | {row['moving_estimated_stopped_pct']:.1f} | {row['stopped_estimated_moving_pct']:.1f} |"
            for t, row in r["one_step"].items()]
  lines += ["", f"Map sensitivity: the same noise sampled on another scene's map moves agents by "
            f"{r['map_sensitivity_m']:.1f} m on average."]
  return "\n".join(lines) + "\n"


def define_flags(values: flags.FlagValues) -> None:
  flags.DEFINE_string("hl_workdir", "workdirs/hl", "HL training workdir", flag_values=values)
  flags.DEFINE_string("data", None, "folder of scenario folders (default <hl_workdir>/synthetic/val)",
                      flag_values=values)
  flags.DEFINE_string("out", None, "output folder (default <hl_workdir>/eval)", flag_values=values)
  flags.DEFINE_integer("max_scenes", 64, "scenes to use (0: all)", lower_bound=0, flag_values=values)
  flags.DEFINE_integer("batch_size", 8, "scenes per batch", lower_bound=1, flag_values=values)


def run(f: flags.FlagValues, args: list[str]) -> None:
  cli.no_arguments(args)
  checkpoint.quiet_orbax_logging()
  workdir = files.user_path(f.hl_workdir)
  data = files.user_path(f.data) if f.data else workdir / "synthetic" / "val"
  out = files.user_path(f.out) if f.out else workdir / "eval"
  try:
    result = diagnose(workdir, data, f.max_scenes, f.batch_size)
    out.mkdir(parents=True, exist_ok=True)
    files.atomic_write_text(out / "map_diagnostics.json", json.dumps(result, indent=1))
  except (OSError, ValueError) as e:
    raise SystemExit(f"map_diagnostics: {e}") from None
  print(to_markdown(result), end="")


main = cli.entry_point(define_flags, run)


if __name__ == "__main__":
  main()
