"""The lane pull: a sampling-time step on the grounded denoiser's position estimate, parameter-free.

With `across_m=d` > 0 the final position estimate (x̂⁰, in metres) of every moving road user's token
(speed estimate at least 1 m/s; not pedestrians) is moved across its lane onto the nearest lane centreline
(not crosswalks) whose direction agrees with its heading estimate (within 60 degrees), when that
centreline is at most d metres away across it; along the lane it stays. With `clearance_m=c` > 0 a token
is not pulled where that would bring it nearer than c metres to another agent's token of the same kind
(initial or goal, at its pulled or its own place) than it was before: two agents side by side between two
lanes are not both put on one centreline. With `end_m=e` > 0 a token past the end (or before the start) of
that centreline, at most e metres along it, is also moved back onto its end: the network, short of
training, drives agents past the end of lanes that leave the map, where the data has none. With
`route_m=r` > 0 a goal token goes onto the nearest lane its heading agrees with that its agent's initial
lane leads to along the lane graph within the next 6 s (successors and lane changes), from at most r
metres across; with no such lane within r the pull is as without. With `still_m=s` > 0 a still road user's
token (speed estimate under 1 m/s) more than s metres from its nearest lane centreline (of any direction)
moves towards it to s metres: the data keeps a road user only near a lane (within 4 m of a centreline or
2 m of a boundary), and the network, trained on junction worlds, stands agents 4 to 10 m from every lane of
real maps whose drivable areas reach far beyond them. `still_m` acts at sampling only: the objective passes
the pull without it (`LanePull.for_objective`), so the network is not taught to leave that step to it and
a checkpoint's weights do not depend on it.

A `LanePull` is the grounded denoiser's `position_step` (`GroundedDenoiser.denoise`): the sampler
(`sampling.sample(lane_pull=...)`) and the training objective pass it, so any grounded checkpoint samples
with or without it (`LoadedModel.lane_pull`: the one it was trained with, the config's `lane_pull`
section; docs/research_log.md for how each part was measured).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import ml_collections

from tdiff_jax import datatypes
from tdiff_jax.data.normalize import denormalize_speed
from tdiff_jax.models import grounding
from tdiff_jax.models.grounded_denoiser import ROUTE_BACKWARD_M, GroundedConfig
from tdiff_jax.models.paper_denoiser import HLContext

# A lane agrees with a heading within 60 degrees; below this speed a heading says little.
AGREE_COS = 0.5
MIN_MPS = 1.0
# `route_m`: a goal is 6 s (AV2 steps 50 -> 109) after the initial state; a route to it is at most what the
# agent's faster speed covers in that time, plus this slack (and, as the denoiser's routes, goes at most
# `ROUTE_BACKWARD_M` backwards).
ROUTE_HORIZON_S = 6.0
ROUTE_SLACK_M = 10.0


@dataclasses.dataclass(frozen=True)
class LanePull:
  """The lane pull's settings (module docstring), in metres; 0 turns a part off, `across_m=0` the pull."""

  across_m: float = 0.0     # estimates at most this far across a lane their heading agrees with go onto it
  clearance_m: float = 0.0  # ... not where that would bring two agents' tokens nearer than this
  end_m: float = 0.0        # ... and back onto the lane's end from at most this far past it
  route_m: float = 0.0      # ... goals onto lanes their initial lane leads to, from at most this far
  still_m: float = 0.0      # still road users' estimates at most this far from their nearest lane (sampling)

  def __post_init__(self):
    for name, value in dataclasses.asdict(self).items():
      if value < 0:
        raise ValueError(f"lane_pull.{name} must be >= 0 (0: off), got {value}")
      if name != "across_m" and value and not self.across_m:
        raise ValueError(f"lane_pull.{name} needs lane_pull.across_m > 0")

  @staticmethod
  def check(cfg) -> None:
    """Raises ValueError when a model of config `cfg` has no position estimate to pull."""
    if not isinstance(cfg, GroundedConfig):
      raise ValueError("the lane pull needs model.denoiser='grounded' (the lane is the one the grounded "
                       "denoiser's heading estimate agrees with)")

  @classmethod
  def from_config(cls, c: ml_collections.ConfigDict) -> "LanePull | None":
    """The config's `lane_pull` section; None when off (or absent)."""
    pull = cls(**{k: float(v) for k, v in c.get("lane_pull", {}).items()})
    return pull if pull.across_m else None

  def for_objective(self) -> "LanePull":
    """The pull the training objective passes: this one without the sampling-only `still_m`."""
    return dataclasses.replace(self, still_m=0.0)

  def __call__(self, ctx: HLContext, position_m: jax.Array, estimate: jax.Array, agent_type: jax.Array,
               agent_valid: jax.Array) -> jax.Array:
    """`[B, A, 2, 2]` (m): `position_m` with each moving road user's token moved across its lane onto the
    nearest lane centreline that agrees with its heading, from at most `across_m` across, and onto its end
    from at most `end_m` past it, and each still road user's to at most `still_m` from its nearest lane
    centreline (module docstring). `estimate`: `[B, A, 2, 3]` the final speed (normalised)
    and heading (cos, sin) estimates; `agent_type`, `agent_valid` `[B, A]` (pedestrians stay where they are)."""
    b, a = position_m.shape[:2]
    feats, dist, arc = grounding.relation_features(position_m.reshape(b, 2 * a, 2), ctx.lines)   # [B, 2A, P, .]
    lane = feats[..., grounding.DIRECTION]
    heading = estimate[..., 1:3].reshape(b, 2 * a, 1, 2)
    heading = heading / jnp.sqrt(jnp.sum(heading ** 2, -1, keepdims=True) + 1e-12)
    disp = feats[..., :2] * grounding.FEATURE_SCALE_M                  # to the nearest centreline point
    along = jnp.sum(disp * lane, -1, keepdims=True) * lane              # nonzero only past a centreline's end
    across = disp - along                                               # its part across the lane
    step = across
    if self.end_m > 0:                                         # and back onto the end from at most e past it
      step = jnp.where(jnp.sum(along ** 2, -1, keepdims=True) <= self.end_m ** 2, disp, across)
    agrees = ctx.lanes[:, None] & (jnp.sum(heading * lane, -1) > AGREE_COS) & (dist < 1e3)
    across2 = jnp.sum(across ** 2, -1)
    ok = agrees & (across2 <= self.across_m ** 2)
    mps = denormalize_speed(estimate[..., 0], ctx.norm)
    road_user = jnp.broadcast_to((agent_type != datatypes.PEDESTRIAN)[:, :, None], (b, a, 2)).reshape(b, 2 * a)
    moving = (mps.reshape(b, 2 * a) >= MIN_MPS) & road_user
    if self.route_m > 0:
      ok = _prefer_routed_goals(ctx, ok, agrees & (across2 <= self.route_m ** 2), moving,
                                mps.reshape(b, 2 * a), dist, arc)
    nearest = jnp.argmin(jnp.where(ok, dist, jnp.inf), axis=-1)[..., None, None]   # [B, 2A, 1, 1]
    move = jnp.take_along_axis(step, nearest, axis=2)[:, :, 0]                    # [B, 2A, 2]
    pulled = ok.any(-1) & moving
    if self.still_m > 0:   # a still road user's token towards its nearest lane centreline, to still_m from it
      lane_dist = jnp.where(ctx.lanes[:, None] & (dist < 1e3), dist, jnp.inf)                # [B, 2A, P]
      nearest_lane = jnp.argmin(lane_dist, axis=-1)[..., None, None]
      to_lane = jnp.take_along_axis(disp, nearest_lane, axis=2)[:, :, 0]                      # [B, 2A, 2]
      far = jnp.sqrt(jnp.sum(to_lane ** 2, -1, keepdims=True) + 1e-12)
      held = road_user & ~moving & (far[..., 0] > self.still_m) & jnp.isfinite(lane_dist).any(-1)
      move = jnp.where(held[..., None], to_lane * (1.0 - self.still_m / far), move)
      pulled = pulled | held
    moved = position_m + jnp.where(pulled[..., None], move, 0.0).reshape(b, a, 2, 2)
    if self.clearance_m > 0:
      # A token is not pulled where it would end nearer than c to another token of its kind, at that one's
      # pulled or its own place, than before: no pair then ends nearer than min(c, their distance before).
      def distance(p, q):                                               # [B, A, 2, 2] each -> [B, 2, A, A]
        p, q = jnp.swapaxes(p, 1, 2), jnp.swapaxes(q, 1, 2)
        return jnp.sqrt(jnp.sum((p[:, :, :, None] - q[:, :, None]) ** 2, -1) + 1e-12)
      before = distance(position_m, position_m)
      pair = (agent_valid[:, :, None] & agent_valid[:, None, :] & ~jnp.eye(a, dtype=bool))[:, None]
      crowded = jnp.zeros_like(pair)
      for after in (distance(moved, moved), distance(moved, position_m)):
        crowded = crowded | (pair & (after < self.clearance_m) & (after < before))
      moved = jnp.where(jnp.swapaxes(crowded.any(-1), 1, 2)[..., None], position_m, moved)
    return moved


def _prefer_routed_goals(ctx: HLContext, ok: jax.Array, ok_routed: jax.Array, moving: jax.Array, mps: jax.Array,
                         dist: jax.Array, arc: jax.Array) -> jax.Array:
  """`ok` `[B, 2A, P]` (the lanes each token may be pulled onto) with each goal's replaced by the lanes
  of `ok_routed` (those within `route_m`) that its initial token's lane leads to, where it has
  one: by a route at most `ROUTE_BACKWARD_M` backwards and at most as long as the faster of the agent's
  speed estimates covers in `ROUTE_HORIZON_S`, plus `ROUTE_SLACK_M` (the opposite lane, reached only
  round a junction, is no goal for the next 6 s). The initial token's lane is the one its pull puts it
  on or, not pulled, its nearest lane. `moving` `[B, 2A]` says which tokens are pulled, `mps` `[B, 2A]`
  their speed estimates (m/s); dist and arc `[B, 2A, P]` (m) from `grounding.relation_features`."""
  b, q, p = dist.shape
  initial = lambda x: x.reshape(b, q // 2, 2, *x.shape[2:])[:, :, 0]  # noqa: E731  [B, A, ...]
  ok0, dist0, arc0 = initial(ok), initial(dist), initial(arc)
  pulled = ok0.any(-1) & initial(moving)
  lane_dist = jnp.where(ctx.lanes[:, None] & (dist0 < 1e3), dist0, jnp.inf)
  lane0 = jnp.where(pulled, jnp.argmin(jnp.where(ok0, dist0, jnp.inf), -1), jnp.argmin(lane_dist, -1))   # [B, A]
  start_arc = jnp.take_along_axis(arc0, lane0[..., None], -1)                                             # [B, A, 1]
  route = jnp.take_along_axis(ctx.routes, lane0[..., None], axis=1) - start_arc + arc[:, 1::2]            # [B, A, P]
  reach = ROUTE_HORIZON_S * jnp.max(mps.reshape(b, q // 2, 2), -1, keepdims=True) + ROUTE_SLACK_M        # [B, A, 1]
  routed = ((route >= -ROUTE_BACKWARD_M) & (route <= reach)
            & jnp.isfinite(lane_dist).any(-1, keepdims=True))
  narrowed = ok_routed[:, 1::2] & routed
  goal_ok = jnp.where(narrowed.any(-1, keepdims=True), narrowed, ok[:, 1::2])
  return jnp.stack([ok0, goal_ok], axis=2).reshape(b, q, p)
