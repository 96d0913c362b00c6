"""The grounded high-level (HL) denoiser: the paper's, with its map attention grounded in metres (the default).

Beyond the paper (docs/training.md; docs/research_log.md for how each part was measured). On top of
`paper_denoiser.PaperDenoiser`'s layers:
* Grounded map attention: the differential map attention of every layer also sees, for each (token,
  polygon) pair, where the polygon's centreline lies seen from the token's current position estimate, in
  metres (`grounding.relation_features`), embedded into its keys and values, with a per-head
  -log(1 + distance) bias; each token attends to its `grounded_neighbors` nearest polygons (0: all). Each
  pair also gets the length of the shortest route along the directed lane graph (successors and lane
  changes, `grounding.lane_routes`) from the initial to the goal position if this token were on this
  polygon and the other token on one of its nearest lanes (which lanes lead where, which the geometry
  alone does not show), and the heading estimate's dot and cross product with the centreline's direction
  at the nearest point (along or against the lane).
* x0 prediction: the network predicts the clean state and returns the equivalent epsilon, so samplers
  and losses are unchanged. The first position and heading estimate is E[x0 | x_t] = sqrt(alpha_bar_t) x_t
  (or the previous estimate, below); each layer moves it by a learned offset (positions in units of 10 m,
  along the scene axes and along and across the agent's heading estimate), so later layers look at the
  lanes near where the agent is going; the heads give the last estimate plus an offset. Each token also
  reads its displacement to the agent's other token in the agent's frame. The speed is sqrt(alpha_bar) x_t
  + sqrt(1 - alpha_bar) F (the c_skip and c_out of the unit-variance normalised speed), so a stopped
  agent stays stopped at low noise.
* The state `[x, y, s, cos, sin]` holds the heading; the goal position is diffused as its offset from the
  initial position (`data.normalize`; `NormStats.offset_mean/offset_std`); the grounded geometry works on
  positions in metres.
* The noise level enters as log(alpha_bar / (1 - alpha_bar)) with Fourier periods from 1 to 64.
* Self-conditioning (Chen et al. 2023, "Analog Bits"): the denoiser also reads a previous estimate of x0
  (the sampler's last step's; in training its own first pass on the same x_t, for half the scenes),
  embedded and added to each token's state embedding with a flag saying whether there is one; that
  estimate is also where the position and heading estimates start.
* Training (`hl_objective`): min-SNR-5 loss weights, noise levels drawn in proportion to them, and
  staged draws: each drawn training sample is, with equal probability, both tokens at
  one noise level (the paper), the initial token at t with the goal's pure noise, or the goal token at t
  given the clean initial state; the denoiser takes a noise level per scene (`[B]`) or per token time
  (`[B, 2]`).
* `position_step`: a step the caller applies to the final position estimate in metres before it becomes
  epsilon (the sampler's and the objective's lane pull, `lane_pull.LanePull`); the network has none.

Shapes: B scenes, A agents, P polygons, D width; states `[B, A, 2, 5]`.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, ClassVar

import jax
import jax.numpy as jnp
from flax import nnx

from tdiff_jax.data.normalize import positions_from_metres, positions_to_metres
from tdiff_jax.models import grounding, layers
from tdiff_jax.models.paper_denoiser import HLContext, PaperConfig, PaperDenoiser, per_token

HEADING_FEATURES = 2  # each pair's heading . lane direction and heading x lane direction
# The noise-level input of a clean token (t = 0, staged): log-SNR is infinite there; this is beyond
# t = 1's (about 9.2) and the Fourier periods' range.
CLEAN_LOG_SNR = 16.0
# One unit of a position offset output, in metres.
POSITION_STEP_M = 10.0
# The route features: the other token's lanes a route may start or end on (its nearest few, within this of
# its nearest, so overlapping lanes in junctions all count), and how far back a route may go.
ROUTE_CANDIDATES = 4
ROUTE_CANDIDATE_M = 0.5
ROUTE_BACKWARD_M = 2.0


@dataclasses.dataclass(frozen=True)
class GroundedConfig(PaperConfig):
  """The grounded denoiser (`model.denoiser="grounded"`): the paper's sizes and its nearest polygons."""

  state_dim: ClassVar[int] = 5
  heading_state: ClassVar[bool] = True
  goal_offset: ClassVar[bool] = True
  self_condition: ClassVar[bool] = True
  staged_noise: ClassVar[bool] = True
  loss_weighting: ClassVar[str] = "min_snr"  # the x0 error weighted by min(SNR_t, 5): what x0 prediction needs
  t_sampling: ClassVar[str] = "importance"   # t drawn in proportion to that weight

  grounded_neighbors: int = 0  # attention to the k nearest polygons of each token (0: all)


@dataclasses.dataclass(frozen=True)
class GroundedPairs:
  """The (token, polygon) pairs of the grounded map attention: all P polygons or K nearest per token."""

  relation: jax.Array          # [B, 2A, K, D] embedded relative geometry
  bias: jax.Array              # [B, 2A, K] -log(1 + distance in m)
  mask: jax.Array              # [B, 2A, K]
  index: jax.Array | None      # [B, 2A, K] polygon indices (None: K = P, all polygons)


# `position_step(ctx, position_m [B, A, 2, 2], estimate [B, A, 2, 3], agent_type, agent_valid) -> position_m`:
# a step on the final position estimate (m), given the speed (normalised) and heading (cos, sin) estimates.
PositionStep = Callable[[HLContext, jax.Array, jax.Array, jax.Array, jax.Array], jax.Array]


class GroundedDenoiser(PaperDenoiser):
  """The grounded denoiser (module docstring)."""

  MAP_INPUTS: ClassVar[str] = "metric"
  GROUNDED: ClassVar[bool] = True

  def _noise_freqs(self) -> jax.Array:
    return layers.log_spaced_freqs(1, self.cfg.num_freq_bands, 1.0, 64.0)

  def _create_layer_extras(self, rngs: nnx.Rngs) -> None:
    d, n = self.cfg.dim, self.cfg.num_layers
    num_features = grounding.NUM_FEATURES + grounding.NUM_ROUTE_FEATURES + HEADING_FEATURES
    self.relation_emb = nnx.List([nnx.Linear(num_features, d, rngs=rngs), nnx.LayerNorm(d, rngs=rngs),
                                  nnx.Linear(d, d, rngs=rngs)])
    # per-layer refinements of the position and heading estimates, starting at zero
    self.position_updates = nnx.List([nnx.Linear(d, 2, kernel_init=nnx.initializers.zeros, rngs=rngs)
                                      for _ in range(n)])
    self.heading_updates = nnx.List([nnx.Linear(d, 2, kernel_init=nnx.initializers.zeros, rngs=rngs)
                                     for _ in range(n)])

  def _create_head_extras(self, rngs: nnx.Rngs) -> None:
    d, n = self.cfg.dim, self.cfg.num_layers
    self.heading_head = nnx.List([nnx.Linear(d, d, rngs=rngs), nnx.Linear(d, 4, rngs=rngs)])
    # the previous x0 estimate and whether there is one
    self.previous_in = nnx.Linear(self.cfg.state_dim + 1, d, rngs=rngs)
    # the other token's displacement in the agent's frame, and position updates along and across the
    # agent's heading (per layer and the head's), zero at first
    self.frame_emb = nnx.List([nnx.Linear(4, d, rngs=rngs), nnx.LayerNorm(d, rngs=rngs), nnx.Linear(d, d, rngs=rngs)])
    self.frame_updates = nnx.List([nnx.Linear(d, 2, kernel_init=nnx.initializers.zeros, rngs=rngs)
                                   for _ in range(n)])
    self.frame_head = nnx.Linear(d, 4, kernel_init=nnx.initializers.zeros, rngs=rngs)

  def encode_map(self, scene, norm, key=None, map_context=None, packed=None, map_inputs=None) -> HLContext:
    """`PaperDenoiser.encode_map` with the centrelines and the lane graph's route lengths
    (`grounding.lane_routes`)."""
    ctx = super().encode_map(scene, norm, key, map_context, packed, map_inputs)
    lines = grounding.centerlines(scene)
    return ctx.replace(lines=lines, routes=grounding.lane_routes(scene, lines))

  def _pairs(self, ctx: HLContext, position_m: jax.Array, heading: jax.Array) -> GroundedPairs:
    """The grounded attention's pairs for token positions `[B, A, 2, 2]` (m) and heading estimates
    `[B, A, 2, 2]` (cos, sin; not unit vectors: their length says how sure)."""
    b, a = position_m.shape[:2]
    feats, dist, arc = grounding.relation_features(jax.lax.stop_gradient(position_m).reshape(b, 2 * a, 2),
                                                   ctx.lines)
    # along (+1) or against (-1) the lane, and how far across
    h = jax.lax.stop_gradient(heading).reshape(b, 2 * a, 1, 2)
    lane = feats[..., grounding.DIRECTION]                                          # [B, 2A, P, 2]
    feats = jnp.concatenate([feats, jnp.sum(h * lane, -1, keepdims=True),
                             (h[..., 0] * lane[..., 1] - h[..., 1] * lane[..., 0])[..., None]], -1)
    valid = jnp.broadcast_to(ctx.map.valid[:, None], dist.shape)                  # [B, 2A, P]
    # Ties (each crosswalk is stored twice, once per direction) are broken by the polygon's heading,
    # at the millimetre, so the choice never depends on the polygons' order.
    tie = 1e-3 * (layers.wrap_angle(ctx.heading) + jnp.pi) / (2 * jnp.pi)           # [B, P]
    order = -jnp.where(valid, dist + tie[:, None], jnp.inf)
    feats = jnp.concatenate([feats, self._route_features(ctx, order, dist, arc)], -1)
    index = None
    k = self.cfg.grounded_neighbors
    if 0 < k < dist.shape[-1]:  # the k nearest polygons of each token
      _, index = jax.lax.top_k(order, k)
      pick = lambda x: jnp.take_along_axis(x, index.reshape(index.shape + (1,) * (x.ndim - 3)), axis=2)  # noqa: E731
      feats, dist, valid = pick(feats), pick(dist), pick(valid)
    lin1, norm, lin2 = self.relation_emb
    return GroundedPairs(lin2(jax.nn.relu(norm(lin1(feats)))), -jnp.log1p(dist), valid, index)

  def _route_features(self, ctx: HLContext, order: jax.Array, dist: jax.Array, arc: jax.Array) -> jax.Array:
    """`[B, 2A, P, 3]` route features of every (token, polygon) pair (`grounding.route_features`).

    For token (a, t) and polygon j: the shortest route (m) along the lane graph from the agent's initial
    position to its goal, with token t's foot point on j and the other token's on one of its
    `ROUTE_CANDIDATES` nearest polygons (those within `ROUTE_CANDIDATE_M` of its nearest): the shortest
    route that goes at most `ROUTE_BACKWARD_M` backwards, inf if none.
    Args: order `[B, 2A, P]` (larger = nearer, -inf for padded polygons), dist and arc `[B, 2A, P]` (m).
    """
    b, q, p = dist.shape
    a = q // 2
    _, near = jax.lax.top_k(order, min(ROUTE_CANDIDATES, p))                      # [B, 2A, C]
    near_dist = jnp.take_along_axis(dist, near, -1)
    near_arc = jnp.take_along_axis(arc, near, -1)
    candidate = (near_dist <= near_dist[..., :1] + ROUTE_CANDIDATE_M) & jnp.isfinite(
        jnp.take_along_axis(order, near, -1))
    swap = lambda x: x.reshape(b, a, 2, -1)[:, :, ::-1].reshape(b, q, -1)  # noqa: E731  the other token's
    other, other_arc, other_ok = swap(near), swap(near_arc), swap(candidate)      # [B, 2A, C]
    rows = jnp.arange(b)[:, None, None, None]
    polygon = jnp.arange(p)[None, None, :, None]                                  # [1, 1, P, 1]
    is_goal = jnp.tile(jnp.arange(2) == 1, a)[None, :, None, None]                # [1, 2A, 1, 1]
    # initial token on polygon j: route j -> other's lane; goal token on j: other's lane -> j
    start = jnp.where(is_goal, other[:, :, None, :], polygon)
    end = jnp.where(is_goal, polygon, other[:, :, None, :])
    start_arc = jnp.where(is_goal, other_arc[:, :, None, :], arc[..., None])
    end_arc = jnp.where(is_goal, arc[..., None], other_arc[:, :, None, :])
    route = ctx.routes[rows, start, end] - start_arc + end_arc                   # [B, 2A, P, C]
    route = jnp.where(other_ok[:, :, None, :] & (route >= -ROUTE_BACKWARD_M), route, jnp.inf)
    return grounding.route_features(route.min(-1))

  @staticmethod
  def _displacement(position_m: jax.Array, emb: nnx.List, frame: jax.Array) -> jax.Array:
    """`[B, A, 2, D]`: each token's displacement to its agent's other token, from `[B, A, 2, 2]` m, along and
    across the agent's heading (`frame`, `_agent_frame`), embedded by `emb`."""
    d = jax.lax.stop_gradient(position_m[:, :, ::-1] - position_m)
    dist = jnp.sqrt(jnp.sum(d * d, -1, keepdims=True) + 1e-12)
    local = GroundedDenoiser._to_frame(d, frame)
    feats = jnp.concatenate([local / grounding.FEATURE_SCALE_M, dist / grounding.FEATURE_SCALE_M, jnp.log1p(dist)], -1)
    lin1, norm, lin2 = emb
    return lin2(jax.nn.relu(norm(lin1(feats))))

  @staticmethod
  def _unit_heading(heading: jax.Array) -> jax.Array:
    """Heading estimates `[..., 2]` (not unit: shrunk by the noise) as unit (cos, sin); no gradient."""
    h = jax.lax.stop_gradient(heading)
    return h * jax.lax.rsqrt(jnp.sum(h * h, -1, keepdims=True) + 1e-4)

  @staticmethod
  def _agent_frame(heading: jax.Array) -> jax.Array:
    """`[B, A, 1, 2]` the unit (cos, sin) of each agent's heading estimate at its initial token, from the
    heading estimates `[B, A, 2, 2]`; held fixed for the gradient."""
    return GroundedDenoiser._unit_heading(heading[:, :, :1])

  @staticmethod
  def _to_world(local: jax.Array, frame: jax.Array) -> jax.Array:
    """(along, across) the agent's heading `[B, A, 2, 2]` -> (x, y) in the scene frame."""
    c, s = frame[..., :1], frame[..., 1:]
    return jnp.concatenate([c * local[..., :1] - s * local[..., 1:], s * local[..., :1] + c * local[..., 1:]], -1)

  @staticmethod
  def _to_frame(xy: jax.Array, frame: jax.Array) -> jax.Array:
    """(x, y) in the scene frame `[B, A, 2, 2]` -> (along, across) the agent's heading: `_to_world`'s inverse."""
    c, s = frame[..., :1], frame[..., 1:]
    return jnp.concatenate([c * xy[..., :1] + s * xy[..., 1:], -s * xy[..., :1] + c * xy[..., 1:]], -1)


  def denoise(self, ctx: HLContext, x_t: jax.Array, beta_t: jax.Array, alpha_bar_t: jax.Array,
              agent_type: jax.Array, agent_valid: jax.Array, agent_id: jax.Array | None = None,
              self_only: jax.Array | None = None, key: jax.Array | None = None, x0_prev: jax.Array | None = None,
              has_prev: jax.Array | None = None, position_step: PositionStep | None = None
              ) -> tuple[jax.Array, list[jax.Array]]:
    """epsilon `[B, A, 2, 5]` (zero for padded agents) and the map attention `[B, H, 2A, P]` per layer.

    Args: as `PaperDenoiser.denoise` (alpha_bar_t = 1 for a clean token, whose epsilon is then x_t less the
      network's x0 estimate, so that x0 from it is x_t exactly), and
      x0_prev: `[B, A, 2, 5]` the previous estimate of x0 (the sampler's last step's, or in training the
        network's own first pass, without gradient), where `has_prev` `[B]` (default: all scenes when
        x0_prev is given, none when not); it is also the first position and heading estimate.
      position_step: a step on the final position estimate (module docstring); None: none.
    """
    b, a = agent_valid.shape
    sqrt_ab = per_token(jnp.sqrt(alpha_bar_t))
    sqrt_1m = per_token(jnp.sqrt(1.0 - alpha_bar_t))
    if has_prev is None:
      has_prev = jnp.full((b,), x0_prev is not None)
    prev = jnp.where(has_prev[:, None, None, None], x0_prev, 0.0) if x0_prev is not None else jnp.zeros_like(x_t)
    flag = jnp.broadcast_to(has_prev[:, None, None, None].astype(x_t.dtype), x_t.shape[:3] + (1,))
    state = self.state_in(x_t) + self.previous_in(jnp.concatenate([prev, flag], -1))
    # E[x0 | x_t] under the unit-variance prior, or the previous estimate
    start = jnp.where(has_prev[:, None, None, None], prev, sqrt_ab * x_t)
    m0 = self._tokens(state, agent_type, agent_id)                         # [B, A, 2, D]
    log_snr = jnp.minimum(jnp.log(alpha_bar_t) - jnp.log1p(-alpha_bar_t), CLEAN_LOG_SNR)
    noise = per_token(self.noise_emb(log_snr[..., None]), feature_axis=True)  # [B, 1, 1 or 2, D]
    social = self._social_mask(agent_valid, self_only)
    position = positions_to_metres(start[..., :2], ctx.frame_scale, ctx.norm)   # [B, A, 2, 2] m
    heading = start[..., 3:5]
    x, m_sum, maps = m0, m0, []
    for i, layer in enumerate(self.layers):
      pairs = self._pairs(ctx, position, heading)
      frame = self._agent_frame(heading)
      extra = self._displacement(position, self.frame_emb, frame)
      x, w = layer(x + noise + extra, ctx.map, social, layers.fold(key, i), pairs, ctx.map_kv[i])
      m_sum, maps = m_sum + x, maps + [w]
      update = self.position_updates[i](x) + self._to_world(self.frame_updates[i](x), frame)
      position = position + POSITION_STEP_M * update
      heading = heading + self.heading_updates[i](x)
    h = self._trunk(m_sum)
    pos_hidden = jax.nn.relu(self.pos_head[0](h))
    pos = self.pos_head[1](pos_hidden).reshape(b, a, 2, 2)
    # plus an offset along and across the agent's heading
    pos = pos + self._to_world(self.frame_head(pos_hidden).reshape(b, a, 2, 2), self._agent_frame(heading))
    speed = self.speed_head[1](jax.nn.relu(self.speed_head[0](h)))[..., None]   # [B, A, 2, 1]
    direction = heading + self.heading_head[1](jax.nn.relu(self.heading_head[0](h))).reshape(b, a, 2, 2)
    speed = jnp.concatenate([speed, direction], -1)                     # [B, A, 2, 3]
    speed = speed.at[..., :1].set(sqrt_ab * x_t[..., 2:3] + sqrt_1m * speed[..., :1])
    metres = position + POSITION_STEP_M * pos
    if position_step is not None:
      metres = position_step(ctx, metres, speed, agent_type, agent_valid)
    x0 = jnp.concatenate([positions_from_metres(metres, ctx.frame_scale, ctx.norm), speed], axis=-1)
    out = (x_t - sqrt_ab * x0) / jnp.where(sqrt_1m > 0.0, sqrt_1m, 1.0)
    return jnp.where(agent_valid[:, :, None, None], out, 0.0), maps
