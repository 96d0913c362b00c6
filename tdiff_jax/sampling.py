"""Guided reverse sampling of high-level scenarios: one jit, a `lax.scan` over the diffusion steps.

`sample(graphdef, params, scene, norm, sched, key, ...)` is a pure function. `graphdef`, `options`
and `custom_cost` are static (one compile per shape and option set); params, the scene (map
conditioning and the agents to place: `agent_type`, `agent_valid`), guidance weights, fixed states
and the key are traced, so it composes with a caller's `jax.jit` and `jax.vmap`. The map is encoded
once per call, not per step. Its core, `sample_with(denoise_fn, scene, ...)`, runs the same reverse
process over any function `(x_t, t) -> eps` (another model, a stand-in in a test); `sample` binds the
HL model's map encoding and denoiser into one.

Options (`SamplerOptions`, static):
* `method`: "ddim" (deterministic, eta = 0; stride 10 = 50 network calls, the official default),
  "ddpm" (ancestral, every step: 500 calls) or "dpmpp2m" (DPM-Solver++(2M), a second-order multistep
  solver on the data prediction: `solver_steps` network calls at steps evenly spaced in log-SNR,
  deterministic; docs/research_log.md for its quality). `solver_max_noise` > 0: the calls after the first
  are spaced from that noise-to-signal ratio down, not from T (`diffusion.solver_timesteps`; `UNGUIDED`:
  11 calls from 12).
* `restarts`: restart sampling (Xu et al. 2023, "Restart sampling for improving generative
  processes"): after the method's steps, `restarts` times, the sample is noised again (fresh noise) to
  the method's last step and that step runs again, a self-conditioned model reading the sample as its
  previous estimate. Each restart lets the model mend the errors its last call leaves; `restarts` more
  network calls. 0 (the default here) is off; `DEFAULT` and `UNGUIDED` run 4.
* `final_cost_steps` (with guidance costs): after the last network call, this many more of official
  guidance's steps on the sample itself: each a gradient step of the weighted costs, clamped per element
  (no network call, fixed tokens held). What the last guided call leaves of box overlaps and off-road
  ends is cheap to remove there. 0 (the default here) is off; `DEFAULT` runs 5.
* `self_condition_max_t`: a self-conditioned model (the grounded denoiser) gets the previous step's x0
  estimate at steps t <= this only (default 50; at every step its agents crowd onto the same lane points).
* `costs`: which guidance terms are on, from `guidance.COSTS` plus "custom" (a caller's cost) and "spec" (a
  scenario spec's cost, `spec.cost`, on `GuidanceParams.spec`). Each scene
  is guided by its own costs, computed on it alone (`total_cost`), so its guidance does not depend on
  the other scenes of its batch.
* `guidance`: "official" (each step takes one gradient step of J on x0_hat, clamped per element, with
  x0_hat clipped to [-3, 3]; no gradient through the network; with goal offsets the step is taken on the
  goal's absolute position, `normalize.absolute_goals`) or "paper" (eq. 3: the noise estimate
  is shifted by the gradient of J(x0_hat(x_t)) with respect to x_t, through the denoiser; we use the
  sign that lowers J, eps + scale sqrt(1 - abar_t) grad J, as in classifier guidance with log p = -J;
  one denoiser pass per step: the noise estimate and the gradient come from one `jax.vjp`).

`clip_x0` (default 3): x0_hat is clipped to +-clip_x0 (normalised units, i.e. standard deviations of the
training data) at every step. The official code clips only when guided; without clipping, errors of an
imperfect denoiser at high noise (alpha_bar_T ~ 3e-6) can throw agents kilometres off the map. `None`
reproduces the official unguided update.

Inpainting: `fixed_state` `[B, A, 2, 3]` (x, y in metres in the scene frame, speed in m/s) where
`fixed_mask` `[B, A, 2]` is true is imposed on x_t at every step (forward-noised to the step's level)
and returned exactly. With goal offsets (`NormStats.goal_offset`), a goal fixed alone is imposed as its
offset from the current estimate of the initial state, so it too is kept in metres. With headings in
the state (`NormStats.heading`), `fixed_state` `[B, A, 2, 4]` also fixes the heading (rad); with 3
features the fixed tokens' headings are sampled.

Speeds are magnitudes: a diffusion model can put a stopped agent's speed a little below zero, which
the official code returns as it is (and its speed metric then drops). `HLSample.state` holds such
speeds as 0 and `HLSample.negative_speed` marks where that happened (fixed tokens are never changed);
`HLSample.normalized` keeps the model's own state. `evaluate` reports the share.

Headings: each endpoint takes the direction of travel of the nearest lane centreline point (lanes are
directed in AV2; crosswalks and other polygon sides are never used), or, when the model's state holds
headings (`NormStats.heading`), the model's own.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx, struct

from tdiff_jax import cpu_products, datatypes, diffusion, geometry, guidance, static_args
from tdiff_jax import spec as spec_lib
from tdiff_jax.data.normalize import (NormStats, absolute_goals, denormalize_heading, denormalize_state,
                                      normalized_state, offset_goals)
from tdiff_jax.models import map_encoder
from tdiff_jax.lane_pull import LanePull
from tdiff_jax.models.map_encoder import MapContext, PackedPolygons, encode_batch


METHODS = ("ddim", "ddpm", "dpmpp2m")


@dataclasses.dataclass(frozen=True)
class SamplerOptions:
  """The sampler's static options (one compile per set): the reverse process and the guidance costs."""

  method: str = "ddim"
  stride: int = 10
  costs: tuple[str, ...] = ()
  guidance: str = "official"
  clip_x0: float | None = 3.0
  solver_steps: int = 15
  # dpmpp2m: > 0, the calls after the first start at this noise-to-signal ratio sigma / alpha (data standard
  # deviations) instead of spreading from T (`diffusion.solver_timesteps`); 0: from T.
  solver_max_noise: float = 0.0
  # A self-conditioned model (the grounded denoiser) reads its previous estimate at steps t <= this only:
  # at every step its agents crowd onto the same lane points.
  self_condition_max_t: int = 50
  restarts: int = 0  # the last step runs again this many times on the renoised sample
  # Guided: after the last network call, this many more official guidance steps on the sample itself (no
  # network call): each a gradient step of the costs, clamped per element as the guided steps are.
  final_cost_steps: int = 0

  def network_calls(self, num_steps: int) -> int:
    """Denoiser calls per sample (guidance in "paper" mode adds one backward pass per call)."""
    if self.method == "ddim":
      steps = len(diffusion.ddim_timesteps(num_steps, self.stride))
    else:
      steps = self.solver_steps if self.method == "dpmpp2m" else num_steps
    return steps + self.restarts

  def describe(self) -> str:
    """E.g. "ddim stride 10", "dpmpp2m 15 steps", "ddpm"."""
    if self.method == "ddim":
      out = f"ddim stride {self.stride}"
    elif self.method == "dpmpp2m":
      out = f"dpmpp2m {self.solver_steps} steps"
      out += f", from noise {self.solver_max_noise:g}" if self.solver_max_noise else ""
    else:
      out = "ddpm"
    out += f", {self.restarts} restarts" if self.restarts else ""
    return out + (f", {self.final_cost_steps} final cost steps" if self.final_cost_steps else "")

  def __post_init__(self):
    if self.method not in METHODS:
      raise ValueError(f"sampler method {self.method!r}: choose from {METHODS}")
    if self.method == "dpmpp2m" and self.solver_steps < 2:
      raise ValueError(f"solver_steps must be >= 2, got {self.solver_steps}")
    if self.solver_max_noise < 0:
      raise ValueError(f"solver_max_noise must be >= 0 (0: from T), got {self.solver_max_noise}")
    if self.self_condition_max_t < 0:
      raise ValueError(f"self_condition_max_t must be >= 0, got {self.self_condition_max_t}")
    if self.restarts < 0:
      raise ValueError(f"restarts must be >= 0, got {self.restarts}")
    if self.guidance not in ("official", "paper"):
      raise ValueError(f"guidance {self.guidance!r}: choose 'official' or 'paper'")
    if self.final_cost_steps < 0 or (self.final_cost_steps and not self.costs):
      raise ValueError(f"final_cost_steps must be >= 0 and needs guidance costs, got {self.final_cost_steps} "
                       f"with costs {self.costs}")
    unknown = set(self.costs) - set(guidance.COSTS) - {"custom", "spec"}
    if unknown:
      raise ValueError(f"unknown guidance costs {sorted(unknown)}; choose from "
                       f"{sorted(guidance.COSTS) + ['custom', 'spec']}")


# The named samplers. What `python sample.py` and `evaluate` run (docs/sampling.md for how each setting was
# measured): guided by the paths between the states (boxes apart, on the road), DDIM-50 (stride 10 of the
# paper's T = 500), its last call run again four times (restarts) and five steps of the costs alone after it.
DEFAULT = SamplerOptions("ddim", stride=10, costs=("paths", "path_offroad"), restarts=4, final_cost_steps=5)
# What `--guidance=` runs: DPM-Solver++(2M), 11 calls (the 10 after the first from noise-to-signal ratio 12
# down; the linear schedule's T is at 584) and 4 restarts: closer to the model's own distribution (DDPM-500)
# than DDIM-50, in a third of the calls.
UNGUIDED = SamplerOptions("dpmpp2m", stride=1, solver_steps=11, solver_max_noise=12.0, restarts=4)
# The paper's (and the official code's) sampler: DDIM-50, unguided.
PAPER = SamplerOptions("ddim", stride=10)


@struct.dataclass
class GuidanceParams:
  """Traced guidance settings: scale, the official per-element clamp, per-cost weights, thresholds (m)."""

  scale: jax.Array | float = 1.0
  clamp: jax.Array | float = 1.0
  weights: dict = dataclasses.field(default_factory=lambda: {"clearance": 1.0, "boxes": 1.0, "lane": 0.1,
                                                             "offroad": 1.0, "paths": 1.0, "path_offroad": 1.0,
                                                             "custom": 1.0, "spec": 0.02})
  clearance_m: jax.Array | float = 2.0
  lane_m: jax.Array | float = 2.0
  box_margin_m: jax.Array | float = 0.5
  path_margin_m: jax.Array | float = 0.3
  spec: spec_lib.SpecArrays | None = None   # the "spec" cost's scenario spec, `[B, A]` (`spec.arrays`)



@struct.dataclass
class HLSample:
  """A sampled high-level scenario. State: x, y (m, scene frame), speed (m/s) per token."""

  state: jax.Array       # [B, A, 2, 3]
  heading: jax.Array     # [B, A, 2] rad: the model's (`NormStats.heading`) or the nearest lane centreline's
  city_xy: jax.Array     # [B, A, 2, 2] city-frame metres
  normalized: jax.Array  # [B, A, 2, F] the model's state
  valid: jax.Array       # [B, A]
  negative_speed: jax.Array  # [B, A, 2] the model's speed was below zero; `state` holds 0 there



# Each scene is guided by its own costs, J = sum_b J_b / GUIDANCE_REFERENCE_SCENES: the strength the official
# code (whose costs are means over a whole batch) gives a scene in a batch of this many equal-sized scenes,
# and the batch size the default weights were measured at, now the same in any batch.
GUIDANCE_REFERENCE_SCENES = 8


def total_cost(x0: jax.Array, scene: datatypes.Scene, norm: NormStats, options: SamplerOptions, g: GuidanceParams,
               custom_cost: Callable | None, map_geometry: geometry.MapGeometry | None = None) -> jax.Array:
  """`[B]`: each scene's weighted sum of the enabled costs on its denormalised x0 (metres).

  Every cost is computed on the scene alone (a batch of one; the costs are means over the scene's own
  agents), so a scene's guidance does not depend on the other scenes of its batch, as the official
  code's batch means did (a 1-scene batch got 8 times the push of a scene in a batch of 8).
  `map_geometry`: the scene's `geometry.MapGeometry` (built from the scene when not given)."""
  geom = geometry.map_geometry(scene) if map_geometry is None else map_geometry

  def one_scene(x0_one: jax.Array, scene_one: datatypes.Scene, geom_one: geometry.MapGeometry,
                spec_one: spec_lib.SpecArrays | None) -> jax.Array:
    scene_one, geom_one = jax.tree_util.tree_map(lambda x: x[None], (scene_one, geom_one))
    state = denormalize_state(x0_one[None], scene_one.frame_scale, norm)
    if any(name in guidance.PATH_COSTS for name in options.costs):   # as `HLSample.heading`, held: the paths
      # move through positions and speeds (an angle's gradient is undefined where its (cos, sin) is 0)
      heading = jax.lax.stop_gradient(denormalize_heading(x0_one[None]) if norm.heading else
                                      geometry.lane_headings(state[..., :2], geom_one))
    out = 0.0
    for name in options.costs:
      if name == "clearance":
        c = guidance.clearance(state, scene_one, g.clearance_m)
      elif name == "boxes":
        c = guidance.box_clearance(state, scene_one, g.box_margin_m, map_geometry=geom_one)
      elif name == "lane":
        c = guidance.lane_distance(state, scene_one, g.lane_m, map_geometry=geom_one)
      elif name == "offroad":
        c = guidance.offroad(state, scene_one, map_geometry=geom_one)
      elif name == "paths":
        c = guidance.path_overlap(state, heading, scene_one, g.path_margin_m)
      elif name == "path_offroad":
        c = guidance.path_offroad(state, heading, scene_one, map_geometry=geom_one)
      elif name == "spec":
        if spec_one is None:
          raise ValueError("options.costs has 'spec' but guidance_params.spec is None (`spec.arrays`)")
        if norm.heading:   # the model's headings move with the cost; else the lanes' (held)
          direction = x0_one[None, ..., 3:5] / jnp.sqrt(jnp.sum(x0_one[None, ..., 3:5] ** 2, -1, keepdims=True) + 1e-6)
        else:
          h = jax.lax.stop_gradient(geometry.lane_headings(state[..., :2], geom_one))
          direction = jnp.stack([jnp.cos(h), jnp.sin(h)], -1)
        c = spec_lib.cost(state, direction, scene_one, spec_one)
      else:
        if custom_cost is None:
          raise ValueError("options.costs has 'custom' but no custom_cost was passed")
        c = custom_cost(state, scene_one)
      out = out + g.weights[name] * c
    return out

  return jax.vmap(one_scene)(x0, scene, geom, g.spec)


@functools.partial(cpu_products.jit, static_argnames=("graphdef",))
def _encode_map_batch(graphdef: nnx.GraphDef, params, scene: datatypes.Scene, norm: NormStats,
                      packed: PackedPolygons | None) -> MapContext:
  return nnx.merge(graphdef, params).map_encoder(scene, norm.mean[:2], norm.std[:2], packed=packed)


def encode_maps(graphdef: nnx.GraphDef, params, scene: datatypes.Scene, norm: NormStats,
                polygon_buckets: Sequence[int]) -> MapContext:
  """The HL model's map encoding of a batch, maps shared by several scenes encoded once: the same context
  as encoding the padded batch, for a fraction of the work. Pass it to `sample(map_context=...)`. An
  all-pairs encoder computes the batch's distinct maps in one call over their valid polygons and pairs
  only (`map_encoder.encode_distinct`, `pack_polygons`); one that keeps the k nearest polygons encodes
  each scene alone at its own polygon bucket (`map_encoder.encode_per_scene`). Call it outside `jit`."""
  radius_m, neighbors = static_args.read_once(graphdef, params, map_encoder.pair_settings)
  pack = lambda maps: map_encoder.packing_for(maps, radius_m, neighbors)  # noqa: E731
  return encode_batch(lambda maps: _encode_map_batch(graphdef, params, maps, norm, pack(maps)), scene,
                      polygon_buckets, all_pairs=neighbors <= 0)


def scene_keys(key: jax.Array, num_scenes: int) -> jax.Array:
  """`[B]` keys, one per scene: `key` itself when it already holds `num_scenes` keys, else
  `fold_in(key, b)` for scene b.

  The sampler draws each scene's noise from its own key, `[A, 2, 3]` at a time, and a draw of more
  agents extends a draw of fewer (threefry keys are partitionable; tested), so a scene's sample depends
  neither on the other scenes of its batch nor on its padding (`data.batches.sampler_batches` relies on it)."""
  key = jnp.asarray(key)
  if not jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):  # a raw uint32 key (`jax.random.PRNGKey`)
    key = jax.random.wrap_key_data(key)
  if key.ndim == 1:
    if key.shape[0] != num_scenes:
      raise ValueError(f"{key.shape[0]} keys for {num_scenes} scenes")
    return key
  return keys_at(key, np.arange(num_scenes))


def keys_at(key: jax.Array, indices) -> jax.Array:
  """`[B]` keys `fold_in(key, i)` for the `[B]` `indices`: e.g. the keys of a run's scenes i, whichever
  batch each falls in (a `key` argument of `sample`)."""
  return _fold_in_each(key, jnp.asarray(indices, jnp.uint32))


@jax.jit
def _fold_in_each(key: jax.Array, indices: jax.Array) -> jax.Array:
  # One call (eagerly, the vmap's trace cost about 1 ms a sampling call).
  return jax.vmap(lambda i: jax.random.fold_in(key, i))(indices)


def _split_each(keys: jax.Array, num: int) -> tuple[jax.Array, ...]:
  """`num` arrays of `[B]` keys, each scene's key split in `num`."""
  split = jax.vmap(lambda k: jax.random.split(k, num))(keys)                      # [B, num]
  return tuple(split[:, i] for i in range(num))


def _normal_each(keys: jax.Array, shape: tuple[int, ...]) -> jax.Array:
  """`[B, *shape]` standard normal noise, scene b's from its own key."""
  return jax.vmap(lambda k: jax.random.normal(k, shape))(keys)


# `denoise_fn(x_t, t) -> eps`: the noise prediction `[B, A, 2, 3]` for model states `x_t` `[B, A, 2, 3]` at
# integer steps `t` `[B]`, map and agents already bound (what `sample` builds from the HL model).
DenoiseFn = Callable[[jax.Array, jax.Array], jax.Array]


def sample_with(denoise_fn: DenoiseFn, scene: datatypes.Scene, norm: NormStats, sched: diffusion.Schedule,
                key: jax.Array, options: SamplerOptions = SamplerOptions(),
                guidance_params: GuidanceParams | None = None, fixed_state: jax.Array | None = None,
                fixed_mask: jax.Array | None = None, custom_cost: Callable | None = None,
                map_geometry: geometry.MapGeometry | None = None, self_conditioned: bool = False) -> HLSample:
  """The reverse process over any denoiser: `sample` with `denoise_fn` in place of the HL model.

  Pure and not jitted (call it inside a caller's `jax.jit`; `options` and the function are static
  there). The update rules are `diffusion.ddim_step`, `diffusion.ddpm_step` and
  `diffusion.dpmpp_2m_step`, applied to the clipped (and, with guidance, corrected) x0 prediction.
  `map_geometry`: the scene's `geometry.MapGeometry` for the guidance costs and the headings, e.g. with
  only its valid entries (`geometry.map_geometry(scene, *geometry.compact_sizes(scene))`, outside jit);
  built from the whole padded scene when not given. The same samples either way.
  `self_conditioned` (static): `denoise_fn(x_t, t, x0_prev, has_prev)` also reads the previous step's x0
  estimate `[B, A, 2, F]` (after clipping and guidance), where `has_prev` `[B]`: false at the first step
  and at steps t > `options.self_condition_max_t`.
  """
  g = guidance_params if guidance_params is not None else GuidanceParams()
  valid = scene.agent_valid
  b, a = valid.shape
  if options.method == "ddim":
    steps = diffusion.ddim_timesteps(sched.num_steps, options.stride)
  elif options.method == "dpmpp2m":
    steps = diffusion.solver_timesteps(sched, options.solver_steps, options.solver_max_noise)
  else:
    steps = np.arange(sched.num_steps, 0, -1)
  steps = jnp.asarray(steps)
  prev = jnp.append(steps[1:], 0)
  guided = bool(options.costs)
  geom = geometry.map_geometry(scene) if map_geometry is None else map_geometry  # once per call, not per step

  def to_model(state):  # [B, A, 2, 4] metres, m/s and rad -> the model state
    return normalized_state(scene.replace(agent_state=state), norm)

  def with_fixed(x0):  # x0 with the fixed tokens set, in metres: exact also for a goal fixed alone
    free = denormalize_state(x0, scene.frame_scale, norm)
    free = jnp.concatenate([free, denormalize_heading(x0)[..., None] if norm.heading else jnp.zeros_like(free[..., :1])], -1)
    fixed = fixed_state if fixed_state.shape[-1] == 4 else jnp.concatenate([fixed_state, free[..., 3:]], -1)
    x = to_model(jnp.where(fixed_mask[..., None], fixed, free))
    if norm.heading and fixed_state.shape[-1] == 3:  # headings not given: the model's, as they are
      x = jnp.concatenate([x[..., :3], x0[..., 3:]], -1)
    return x

  if fixed_state is not None:
    if fixed_state.shape[-1] not in (3, 4):
      raise ValueError(f"fixed_state has {fixed_state.shape[-1]} features per token: 3 (x, y, speed) or 4 (and heading)")
    fixed_mask = jnp.ones((b, a, 2), bool) if fixed_mask is None else fixed_mask
  live = valid[..., None, None]

  def cost(x0):
    return jnp.sum(total_cost(x0, scene, norm, options, g, custom_cost, geom)) / GUIDANCE_REFERENCE_SCENES

  def cost_step(x0, active):
    # The step is taken on absolute positions (`absolute_goals`): with goal offsets, a goal's own
    # gradient would otherwise be scaled by the offsets' statistics and summed into its initial state's.
    # Held tokens take no step (a held initial state's would move its goal, with goal offsets).
    xa = absolute_goals(jax.lax.stop_gradient(x0), norm, scene.frame_scale)
    step = jnp.clip(g.scale * jax.grad(lambda y: cost(offset_goals(y, norm, scene.frame_scale)))(xa), -g.clamp,
                    g.clamp)
    return offset_goals(jnp.clip(xa - jnp.where(active, step, 0.0), -3.0, 3.0), norm, scene.frame_scale)

  every_token = jnp.ones((1, 1, 2, 1), bool)

  def restart(carry):  # restart sampling: the sample noised again to the last step's level
    x, keys, _, h = carry
    keys, k_restart = _split_each(keys, 2)
    x0 = with_fixed(x) if fixed_state is not None else x
    x_t = diffusion.q_sample(sched, x0, jnp.full((b,), steps[-1]), _normal_each(k_restart, x.shape[1:]))
    return jnp.where(live, x_t, 0.0), keys, x0, jnp.zeros_like(h)

  def step(carry, ts):  # one scan, so the network is compiled once: the steps, then the restarts of the last
    t, tp, restarting = ts
    if options.restarts:
      carry = jax.lax.cond(restarting, restart, lambda c: c, carry)
    x, keys, x0_last, h_last = carry
    keys, k_noise, k_fix = _split_each(keys, 3)
    t_b, tp_b = jnp.full((b,), t), jnp.full((b,), tp)
    # A self-conditioned model also reads its previous estimate, at steps t <= self_condition_max_t after the first.
    previous = (x0_last, jnp.full((b,), (t < steps[0]) & (t <= options.self_condition_max_t))) if self_conditioned else ()
    if guided and options.guidance == "paper":  # one pass: the denoiser's output and its vjp
      def eps_and_x0(xx):
        eps = denoise_fn(xx, t_b, *previous)
        return eps, diffusion.x0_from_eps(sched, xx, t_b, eps)
      (eps, x0_of_x), pullback = jax.vjp(eps_and_x0, x)
      grad_x0 = jax.grad(cost)(x0_of_x)
      (grad,) = pullback((jnp.zeros_like(eps), grad_x0))
      abar = diffusion.alpha_bar_at(sched, t_b, x)
      eps = eps + g.scale * jnp.sqrt(1.0 - abar) * grad
    else:
      eps = denoise_fn(x, t_b, *previous)
    x0 = diffusion.x0_from_eps(sched, x, t_b, eps)
    if guided and options.guidance == "official":
      x0 = cost_step(x0, every_token)
    if options.clip_x0 is not None:
      x0 = jnp.clip(x0, -options.clip_x0, options.clip_x0)
    h = h_last
    if options.method == "ddim":
      x_prev = diffusion.ddim_step(sched, x0, eps, t_b, tp_b)
    elif options.method == "dpmpp2m":
      x_prev, h = diffusion.dpmpp_2m_step(sched, x, t_b, tp_b, x0, x0_last, h_last)
    else:
      x_prev = diffusion.ddpm_step(sched, x0, x, t, _normal_each(k_noise, x.shape[1:]))
    if fixed_state is not None:  # impose the fixed tokens at the next step's noise level
      x_prev = jnp.where(fixed_mask[..., None], diffusion.q_sample(
          sched, with_fixed(x0), tp_b, _normal_each(k_fix, x.shape[1:])), x_prev)
    return (jnp.where(live, x_prev, 0.0), keys, x0, h), None

  keys, k_init = _split_each(scene_keys(key, b), 2)
  x = jnp.where(live, _normal_each(k_init, (a, 2, norm.state_dim)), 0.0)
  carry = (x, keys, jnp.zeros_like(x), jnp.zeros((b, 1, 1, 1), x.dtype))
  n = len(steps)
  schedule = (jnp.append(steps, jnp.full(options.restarts, steps[-1])),
              jnp.append(prev, jnp.full(options.restarts, prev[-1])), jnp.arange(n + options.restarts) >= n)
  (x, keys, *_), _ = jax.lax.scan(step, carry, schedule)
  if options.final_cost_steps:  # the guided steps' cost descent, on the sample itself; fixed tokens stay
    free = ~fixed_mask[..., None] if fixed_state is not None else every_token
    x, _ = jax.lax.scan(lambda xx, _: (jnp.where(live, cost_step(xx, free), 0.0), None), x, None,
                        length=options.final_cost_steps)
  if fixed_state is not None:
    x = with_fixed(x)
  state = denormalize_state(x, scene.frame_scale, norm)
  state = jnp.where(live, state, 0.0)
  negative_speed = valid[..., None] & (state[..., 2] < 0.0)
  if fixed_state is not None:
    negative_speed = negative_speed & ~fixed_mask
  state = state.at[..., 2].set(jnp.where(negative_speed, 0.0, state[..., 2]))
  heading = denormalize_heading(x) if norm.heading else geometry.lane_headings(state[..., :2], geom)
  heading = jnp.where(valid[..., None], heading, 0.0)
  city = datatypes.to_city(scene, state[..., :2])
  return HLSample(state, heading, jnp.where(live, city, 0.0), x, valid, negative_speed)


@functools.partial(cpu_products.jit, static_argnames=("graphdef", "options", "custom_cost", "lane_pull"))
def sample(graphdef: nnx.GraphDef, params, scene: datatypes.Scene, norm: NormStats, sched: diffusion.Schedule,
           key: jax.Array, options: SamplerOptions = SamplerOptions(), guidance_params: GuidanceParams | None = None,
           fixed_state: jax.Array | None = None, fixed_mask: jax.Array | None = None,
           custom_cost: Callable | None = None, map_context: MapContext | None = None,
           map_geometry: geometry.MapGeometry | None = None, lane_pull: LanePull | None = None) -> HLSample:
  """Samples initial and goal states for the valid agents of each scene with the HL model; see the
  module docstring. The map is encoded once (or given as `map_context`, from `encode_maps`), then
  `sample_with` runs the reverse process over the model's denoiser (`map_geometry`: see there).
  `lane_pull` (static): the lane pull on the grounded denoiser's position estimate at every call
  (`lane_pull.LanePull`; a checkpoint's is `LoadedModel.lane_pull`); None: none."""
  model = nnx.merge(graphdef, params)
  ctx = model.encode_map(scene, norm, map_context=map_context)
  step = {}
  if lane_pull is not None:
    lane_pull.check(model.cfg)
    step = {"position_step": lane_pull}

  def denoise_fn(x, t, x0_prev=None, has_prev=None):
    previous = {"x0_prev": x0_prev, "has_prev": has_prev} if model.cfg.self_condition else {}
    eps, _ = model.denoise(ctx, x, sched.betas[t], sched.alpha_bars[t], scene.agent_type, scene.agent_valid,
                           **previous, **step)
    return eps

  return sample_with(denoise_fn, scene, norm, sched, key, options, guidance_params, fixed_state, fixed_mask,
                     custom_cost, map_geometry, self_conditioned=model.cfg.self_condition)
