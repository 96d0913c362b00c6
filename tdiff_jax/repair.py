"""Complete scenarios whose agents stay apart and on the road: sample, infill, resample the faulty agents.

The HL model places states; the infiller connects them. Two states can be fine while the 6 s between
them are not (paths cross, a turn cuts a corner). `sample_complete` therefore judges the infilled
trajectories and resamples only the agents at fault, every other agent held (the sampler's inpainting:
`fixed_state`/`fixed_mask`), for up to `repair_rounds` rounds:

1. sample the HL states (`sampling.sample`) and infill them (`infilling.infill_batch`);
2. `faults`: each agent whose box overlaps another's at some step, and each road user whose centre
   leaves the drivable area at some step (what `audit` reads back from the written AV2 folders);
3. resample the faulty agents given the others (a scene without faults held whole), infill again, and
   keep each scene's new sample where it has fewer faulty agents than before; repeat from 2.

Round r draws from the scene's key folded with r, so a scene's result depends on its own key only, and
`repair_rounds=0` is the sampler alone. How it was chosen and what it measures: docs/research_log.md.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Callable

import jax
import jax.numpy as jnp
import numpy as np
from absl import logging
from flax import struct

from tdiff_jax import datatypes, geometry, infilling, sampling

if TYPE_CHECKING:
  from tdiff_jax import checkpoint
  from tdiff_jax.models.map_encoder import MapContext

# The command lines' default: up to 6 rounds after `sampling.DEFAULT` (docs/sampling.md; 0: the sampler alone).
DEFAULT_REPAIR_ROUNDS = 6


@struct.dataclass
class CompleteSample:
  """A batch of complete scenarios: the HL sample, its infilled trajectories and what is still wrong."""

  hl: sampling.HLSample   # [B, A, ...]
  trajectory: jax.Array   # [B, A, H, 2] metres, scene frame, AV2 steps 50..109
  overlap: jax.Array      # [B, A] the agent's box overlaps another's at some step
  offroad: jax.Array      # [B, A] a road user's centre leaves the drivable area at some step
  resampled: jax.Array    # [B, A] int32: rounds in which the agent was resampled and the result kept
  judged: jax.Array       # [B, A] bool: agents the caller's `judge` finds wrong (none without one)

  def badness(self) -> np.ndarray:
    """`[B]` how far each scene is from done, smaller better: judged agents first (one outweighs every
    fault), then agents at fault. Host-level numpy."""
    judged = np.asarray(self.judged)
    return judged.sum(-1) * (judged.shape[-1] + 1) + np.asarray(self.overlap | self.offroad).sum(-1)


def motion_headings(xy: jax.Array, initial_heading: jax.Array) -> jax.Array:
  """`[B, A, H]` headings of trajectories `[B, A, H, 2]` as the AV2 files get them (`data.av2_export`):
  the direction of each step's motion, held from `initial_heading` `[B, A]` while a step moves less than
  `datatypes.STOPPED_STEP_M`."""
  step = jnp.diff(xy, axis=2, prepend=xy[:, :, :1])
  moving = jnp.hypot(step[..., 0], step[..., 1]) > datatypes.STOPPED_STEP_M
  angle = jnp.arctan2(step[..., 1], step[..., 0])

  def hold(current, inputs):
    m, a = inputs
    current = jnp.where(m, a, current)
    return current, current

  _, heading = jax.lax.scan(hold, jnp.asarray(initial_heading, xy.dtype),
                            (jnp.moveaxis(moving, -1, 0), jnp.moveaxis(angle, -1, 0)))
  return jnp.moveaxis(heading, 0, -1)


@jax.jit
def faults(xy: jax.Array, valid: jax.Array, initial_heading: jax.Array, agent_type: jax.Array,
           map_geometry: geometry.MapGeometry) -> tuple[jax.Array, jax.Array]:
  """`(overlap, offroad)`, each `[B, A]`, of trajectories `xy` `[B, A, H, 2]` (scene frame) of the agents
  `valid` `[B, A]`: an agent's type-sized box (`datatypes.AGENT_BOX_SIZE_M`, along `motion_headings`)
  overlaps another's at some step (separating axes); a road user's (not a pedestrian's) centre is
  outside every drivable area of its map (`map_geometry`, `[B]`) at some step. The same tests as
  `audit.check_scenario` on the written files."""
  heading = motion_headings(xy, initial_heading)                               # [B, A, H]
  size = geometry.box_sizes(agent_type)                                        # [B, A, 2]
  pairs = geometry.pair_mask(valid)                                            # [B, A, A]

  def scene_overlap(args):   # one scene at a time: the per-step pair tests of a batch are large
    xy_s, heading_s, size_s, pairs_s = args
    xy_t, heading_t = jnp.swapaxes(xy_s, 0, 1), jnp.swapaxes(heading_s, 0, 1)  # [H, A, ...]
    corners = geometry.box_corners(xy_t, heading_t, size_s[None])                # [H, A, 4, 2]
    hit = geometry.boxes_overlap(corners, heading_t) & pairs_s[None]             # [H, A, A]
    return hit.any((0, 2))

  overlap = jax.lax.map(scene_overlap, (xy, heading, size, pairs))
  road = valid & (agent_type != datatypes.PEDESTRIAN) & map_geometry.edge_valid.any(-1)[:, None]
  inside = geometry.inside_drivable_area(xy, map_geometry)                     # [B, A, H]
  offroad = road & ~inside.all(-1)
  return overlap & valid, offroad


def encode_batch(hl: checkpoint.LoadedModel, scene: datatypes.Scene) -> tuple[MapContext, geometry.MapGeometry]:
  """What every sampler call on `scene` reads of its maps, computed once: the HL model's map encodings
  (`sampling.encode_maps`, at the model's polygon buckets) and the maps' geometry (valid entries only).
  Call it outside `jit`."""
  return (sampling.encode_maps(hl.graphdef, hl.params, scene, hl.norm, hl.config.data.polygon_buckets),
          geometry.map_geometry(scene, *geometry.compact_sizes(scene)))


def sample_states(hl: checkpoint.LoadedModel, scene: datatypes.Scene, key: jax.Array,
                  options: sampling.SamplerOptions = sampling.DEFAULT,
                  guidance_params: sampling.GuidanceParams | None = None,
                  maps: tuple[MapContext, geometry.MapGeometry] | None = None) -> sampling.HLSample:
  """`sampling.sample` of a loaded HL model with its lane pull over `scene`'s maps `encode_batch(hl, scene)`
  (or given as `maps`)."""
  context, geom = encode_batch(hl, scene) if maps is None else maps
  return sampling.sample(hl.graphdef, hl.params, scene, hl.norm, hl.sched, key, options, guidance_params,
                         map_context=context, map_geometry=geom, lane_pull=hl.lane_pull)


def sample_complete(hl: checkpoint.LoadedModel, infiller: checkpoint.LoadedModel, scene: datatypes.Scene,
                    key: jax.Array, options: sampling.SamplerOptions = sampling.DEFAULT,
                    guidance_params: sampling.GuidanceParams | None = None, *, mode: int | jax.Array = 0,
                    repair_rounds: int = DEFAULT_REPAIR_ROUNDS, infill_key: jax.Array | None = None,
                    maps: tuple[MapContext, geometry.MapGeometry] | None = None,
                    judge: Callable[[sampling.HLSample], np.ndarray] | None = None,
                    hold: Callable[[sampling.HLSample, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
                    fixed_state: jax.Array | None = None, fixed_mask: jax.Array | None = None) -> CompleteSample:
  """Complete scenarios for the valid agents of `scene` `[B, ...]` (see the module docstring).

  Args:
    hl, infiller: loaded models (`checkpoint.load_checkpoint`), the HL model with its lane pull.
    scene: the maps and the agents to place (`agent_type`, `agent_valid`), as `sampling.sample`; padded to
      its largest scene (`data.batches.sampler_batches` cuts batches of one size).
    key: one key, or `[B]` keys (one per scene, `sampling.keys_at`); round r uses each scene's key folded with r.
    options, guidance_params: the HL sampler's (`sampling.SamplerOptions`), every round.
    mode: the infiller's hard-constraint mode id (`infilling.MODES`; 0, "both", pins both states).
    repair_rounds: rounds of resampling the faulty agents (0: the sampler and the infiller alone).
    infill_key: a stochastic infiller's noise, one key or `[B]` keys (as `infilling.infill`).
    maps: `encode_batch(hl, scene)`, when the caller has it; computed here otherwise.
    judge: more agents at fault, `[B, A]` bool of an HL sample (host-level numpy), e.g. those missing their
      scenario spec (`spec.violating_agents`): resampled as the faulty ones, and a scene keeps a new sample
      where it has fewer of them, or as many and fewer faulty agents.
    hold: more tokens to hold from the next round on, given the best sample so far and its judged agents
      (`[B, A]`): `(state [B, A, 2, 4], mask [B, A, 2])`, e.g. goals that make a judged agent's maneuver.
    fixed_state, fixed_mask: tokens held in every round (the sampler's inpainting): `[B, A, 2, 4]` (x, y,
      speed, heading) where `[B, A, 2]` is true; a held token is never resampled.
  Host-level (it decides on the host which agents to resample): call it outside `jit`.
  """
  if repair_rounds < 0:
    raise ValueError(f"repair_rounds must be >= 0, got {repair_rounds}")
  num = scene.agent_valid.shape[0]
  keys = sampling.scene_keys(key, num)
  infill_keys = None if infill_key is None else sampling.scene_keys(infill_key, num)
  context, geom = encode_batch(hl, scene) if maps is None else maps   # once for every round
  at_fault = lambda c: int(np.asarray(c.overlap | c.offroad | c.judged).sum())   # noqa: E731
  # Round 0 holds nothing; round r resamples the agents still at fault, every other agent held. Every round
  # samples the whole batch (scenes without faults held whole): one compiled program per shape serves all.
  user_mask = np.zeros(scene.agent_valid.shape + (2,), bool) if fixed_mask is None else np.asarray(fixed_mask, bool)
  user_state = jnp.zeros(scene.agent_valid.shape + (2, 4), jnp.float32) if fixed_state is None else jnp.asarray(
      fixed_state, jnp.float32)
  fixed_state = user_state
  bad = np.ones(scene.agent_valid.shape, bool)
  best = None
  for round_ in range(repair_rounds + 1):
    if not bad.any():
      break
    t0 = time.perf_counter()
    fold = lambda ks: jax.vmap(lambda k: jax.random.fold_in(k, round_))(ks) if round_ else ks   # noqa: E731,B023
    held = user_mask | ~bad[..., None]
    fixed_mask = jnp.asarray(held)
    fixed_state = jnp.where(jnp.asarray(user_mask)[..., None], user_state, fixed_state)
    out = sampling.sample(hl.graphdef, hl.params, scene, hl.norm, hl.sched, fold(keys), options, guidance_params,
                          fixed_state, fixed_mask, map_context=context, map_geometry=geom, lane_pull=hl.lane_pull)
    placed = scene.replace(agent_state=jnp.concatenate([out.state, out.heading[..., None]], -1))
    traj = infilling.infill_batch(infiller.graphdef, infiller.params, placed, out.heading[..., 0], mode,
                                  None if infill_keys is None else fold(infill_keys),
                                  polygon_buckets=infiller.config.data.polygon_buckets)
    overlap, offroad = faults(traj, scene.agent_valid, out.heading[..., 0], scene.agent_type, geom)
    judged = np.zeros(overlap.shape, bool) if judge is None else np.asarray(judge(out), bool)
    new = CompleteSample(out, traj, overlap, offroad, jnp.zeros(overlap.shape, jnp.int32), judged)
    if best is None:
      best, fixed_state = new, placed.agent_state
      logging.info("sampled and infilled %d scenes: %d agents at fault (%.1f s)", num, at_fault(best),
                   time.perf_counter() - t0)
    else:
      better = new.badness() < best.badness()           # [B] scenes that keep the new sample
      new = new.replace(resampled=best.resampled + jnp.asarray(bad, jnp.int32))
      pick = lambda n, o: jnp.where(better.reshape((-1,) + (1,) * (n.ndim - 1)), n, o)   # noqa: E731,B023
      best, fixed_state = jax.tree_util.tree_map(pick, new, best), pick(placed.agent_state, fixed_state)
      logging.info("repair round %d: %d of %d scenes resampled, %d kept; %d agents still at fault (%.1f s)", round_,
                   int(bad.any(-1).sum()), num, int(better.sum()), at_fault(best), time.perf_counter() - t0)
    if hold is not None:
      more_state, more_mask = hold(best.hl, np.asarray(best.judged))
      user_state = jnp.where(jnp.asarray(more_mask)[..., None], jnp.asarray(more_state, jnp.float32), user_state)
      user_mask = user_mask | np.asarray(more_mask, bool)
    bad = np.asarray(best.overlap | best.offroad | best.judged)
  return best
