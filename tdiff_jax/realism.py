"""The realism score of complete scenarios: the sim-agents meta-metric, as the 2025 Scenario Generation
challenge computes it (objects pooled), for 6-second trajectories at 10 Hz on AV2 maps.

For one map, N generated scenarios (high-level states, then trajectories) give, per feature, a histogram
of their values pooled over the scenarios, their objects and their steps, smoothed with `PSEUDOCOUNT` in
every bin. The logged scenario of that map is scored by the mean log-likelihood of its values under the
histogram; the feature's score is the exponential of that (1 when the generated scenarios put all their
mass where the logged values fall), and the meta-metric is the weighted sum of the feature scores
(`FEATURES`' weights). A split's numbers are the means over its maps.

Features (per object and step unless said; `trajectory_features`):
* linear speed and acceleration, angular speed and acceleration: central differences of the positions and
  headings (a step is valid when its neighbours are), as the challenge's kinematics;
* distance to the nearest object: between boxes with rounded corners (the challenge's rounding factor
  0.7), negative when they overlap; an object alone gets a large distance (the top bin);
* collision indication (per object): a distance below 0 at any step;
* time to collision with the object followed (ahead, heading within 75 degrees, laterally overlapping;
  within 10 degrees when the overlap is under 0.5 m), at constant speeds, capped at 5 s;
* distance to the road edge: the most off-road box corner's signed distance to the drivable area's
  boundary (negative inside it); road users (not pedestrians) on maps with a drivable area;
* off-road indication (per object): that distance above 0 at any step.

AV2 has no object sizes: the boxes are `datatypes.AGENT_BOX_SIZE_M`'s (as the strict Table I metrics). It
has no headings between the two states either: a step's heading is the direction of its central
displacement when the object moves at least `MOVING_MPS`, else the last such heading (the initial
state's before the object first moves), for logged and generated trajectories alike. AV2 motion
forecasting has no traffic-light states: the challenge's traffic-light violation term (weight 0.05) is
left out and the other weights renormalised.

Also here: `constant_velocity` (the floor any trajectory model must beat) and `draw_diversity` (how a
stochastic infiller's draws for one high-level scenario differ). `tdiff_jax.evaluate` makes the rows.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from tdiff_jax import datatypes, geometry

DT = 0.1                  # seconds per step (AV2 at 10 Hz)
MOVING_MPS = 1.0          # below this speed a step keeps its last heading
PSEUDOCOUNT = 0.1         # additive smoothing of every histogram bin
CORNER_ROUNDING = 0.7     # boxes' corners rounded by this share of half their smaller side
FAR_M = 1e4               # distance to the nearest object of an object alone
MAX_TTC_S = 5.0
FOLLOW_MAX_HEADING = math.radians(75.0)
FOLLOW_MAX_HEADING_SMALL_OVERLAP = math.radians(10.0)
SMALL_OVERLAP_M = 0.5


class Feature(NamedTuple):
  low: float            # histogram range (values outside go to the end bins); None for an indication
  high: float
  bins: int
  weight: float         # the challenge's weight (before renormalising without traffic lights)


# The 2025 scenario-generation configuration; the two indications are Bernoulli (2 bins: no, yes).
FEATURES = {
    "linear_speed": Feature(0.0, 25.0, 10, 0.05),
    "linear_acceleration": Feature(-12.0, 12.0, 11, 0.05),
    "angular_speed": Feature(-0.628, 0.628, 11, 0.05),
    "angular_acceleration": Feature(-3.14, 3.14, 11, 0.05),
    "distance_to_nearest_object": Feature(-5.0, 40.0, 10, 0.10),
    "collision": Feature(None, None, 2, 0.25),
    "time_to_collision": Feature(0.0, 5.0, 10, 0.10),
    "distance_to_road_edge": Feature(-20.0, 40.0, 10, 0.05),
    "offroad": Feature(None, None, 2, 0.25),
}
TRAFFIC_LIGHT_WEIGHT = 0.05   # left out (AV2 has no signal states); the rest sum to 0.95


def _wrap(angle: jax.Array) -> jax.Array:
  return (angle + jnp.pi) % (2 * jnp.pi) - jnp.pi


def _central_diff(x: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array]:
  """`[..., T]` -> half the difference of each step's neighbours `[..., T]` and its validity (the ends
  and steps next to an invalid one are invalid)."""
  d = (x[..., 2:] - x[..., :-2]) / 2
  ok = valid[..., 2:] & valid[..., :-2]
  pad = [(0, 0)] * (x.ndim - 1) + [(1, 1)]
  return jnp.pad(d, pad), jnp.pad(ok, pad)


def motion_headings(xy: jax.Array, valid: jax.Array, initial_heading: jax.Array) -> jax.Array:
  """`[..., T]` headings of trajectories `xy` `[..., T, 2]`: the direction of each step's central
  displacement (one-sided at the ends) where the object moves at least `MOVING_MPS`, else the last such
  heading before it, else `initial_heading` `[...]`."""
  fwd = jnp.concatenate([xy[..., 1:, :], xy[..., -1:, :]], -2)
  bwd = jnp.concatenate([xy[..., :1, :], xy[..., :-1, :]], -2)
  ok = valid & jnp.concatenate([valid[..., 1:], valid[..., -1:]], -1) & jnp.concatenate(
      [valid[..., :1], valid[..., :-1]], -1)
  d = fwd - bwd
  steps = jnp.full(valid.shape[-1], 2.0).at[0].set(1.0).at[-1].set(1.0)   # the ends' differences span one step
  moving = ok & (jnp.sqrt(jnp.sum(d * d, -1)) >= MOVING_MPS * DT * steps)
  raw = jnp.arctan2(d[..., 1], d[..., 0])
  t = jnp.arange(valid.shape[-1])
  last = jax.lax.cummax(jnp.where(moving, t, -1), axis=valid.ndim - 1)
  held = jnp.take_along_axis(raw, jnp.maximum(last, 0), axis=-1)
  return jnp.where(last >= 0, held, initial_heading[..., None])


def kinematics(xy: jax.Array, heading: jax.Array, valid: jax.Array) -> dict:
  """Linear speed (m/s) and acceleration (m/s^2), angular speed (rad/s) and acceleration (rad/s^2) of
  `[..., T, 2]` positions and `[..., T]` headings: name -> (values, valid) `[..., T]`."""
  dx, speed_ok = _central_diff(xy[..., 0], valid)
  dy, _ = _central_diff(xy[..., 1], valid)
  speed = jnp.sqrt(dx * dx + dy * dy) / DT
  accel, accel_ok = _central_diff(speed, speed_ok)
  # Headings wrap: twice the central difference wrapped, then halved (the acute change per step).
  dh, _ = _central_diff(heading, valid)
  dh = _wrap(2 * dh) / 2
  d2h, _ = _central_diff(dh, speed_ok)
  d2h = _wrap(2 * d2h) / 2
  return {"linear_speed": (speed, speed_ok), "linear_acceleration": (accel / DT, accel_ok),
          "angular_speed": (dh / DT, speed_ok), "angular_acceleration": (d2h / DT ** 2, accel_ok)}


def _vertex_edge_sq_distance(p: jax.Array, q: jax.Array) -> jax.Array:
  """Smallest squared distance from the 4 corners of boxes `p` `[..., 4, 2]` to the 4 edges of boxes `q`
  (x and y apart: on a trailing axis of 2, XLA's CPU loops do not vectorise)."""
  px, py = p[..., :, None, 0], p[..., :, None, 1]                              # [..., 4, 1]
  sx, sy = q[..., None, :, 0], q[..., None, :, 1]                              # [..., 1, 4]
  ux, uy = jnp.roll(q[..., 0], -1, -1)[..., None, :] - sx, jnp.roll(q[..., 1], -1, -1)[..., None, :] - sy
  t = geometry.segment_fraction(px, py, sx, sy, ux, uy)
  fx, fy = px - sx - t * ux, py - sy - t * uy
  return (fx * fx + fy * fy).min((-1, -2))


def box_signed_distance(p: jax.Array, q: jax.Array) -> jax.Array:
  """Signed distance between boxes (convex quadrilaterals, corners in order) `p` and `q` `[..., 4, 2]`:
  the gap between them when apart, minus the depth of their overlap (the smallest shift that separates
  them) when they overlap."""
  # Axes: the two edge normals of each box; the overlap of the boxes' projections on each.
  edges = jnp.concatenate([p[..., 1:3, :] - p[..., 0:2, :], q[..., 1:3, :] - q[..., 0:2, :]], -2)
  axes = edges / jnp.sqrt(jnp.sum(edges * edges, -1, keepdims=True) + 1e-12)   # [..., 4, 2]
  project = lambda c: axes[..., :, None, 0] * c[..., None, :, 0] + axes[..., :, None, 1] * c[..., None, :, 1]  # noqa: E731
  pp, pq = project(p), project(q)                                              # [..., 4 axes, 4 corners]
  overlap = jnp.minimum(pp.max(-1), pq.max(-1)) - jnp.maximum(pp.min(-1), pq.min(-1))   # [..., 4]
  gap_sq = jnp.minimum(_vertex_edge_sq_distance(p, q), _vertex_edge_sq_distance(q, p))
  return jnp.where(jnp.all(overlap > 0, -1), -overlap.min(-1), jnp.sqrt(gap_sq + 1e-12))


def distance_to_nearest_object(xy: jax.Array, heading: jax.Array, size: jax.Array, valid: jax.Array) -> jax.Array:
  """`[B, A, T]` signed distance (m) from each object's box to the nearest other valid object's, boxes with
  corners rounded by `CORNER_ROUNDING`; `FAR_M` for an object alone. `xy` `[B, A, T, 2]`, `heading` and
  `valid` `[B, A, T]`, `size` `[B, A, 2]` (length, width)."""
  shrink = CORNER_ROUNDING * size.min(-1) / 2                                  # [B, A]
  core = geometry.box_corners(xy, heading, (size - 2 * shrink[..., None])[:, :, None])   # [B, A, T, 4, 2]
  # Each unordered pair once (the distance is symmetric), then the smallest per object of either end.
  a = xy.shape[1]
  i, j = np.triu_indices(a, k=1)
  d = box_signed_distance(core[:, i], core[:, j]) - shrink[:, i, None] - shrink[:, j, None]   # [B, pairs, T]
  d = jnp.where(valid[:, i] & valid[:, j], d, FAR_M)
  nearest = jnp.full(valid.shape, FAR_M, d.dtype)
  return nearest.at[:, i].min(d).at[:, j].min(d)


def time_to_collision(xy: jax.Array, heading: jax.Array, speed: jax.Array, size: jax.Array,
                      valid: jax.Array) -> jax.Array:
  """`[B, A, T]` seconds until each object reaches the object it follows at their current speeds, capped
  at `MAX_TTC_S` (also when it follows none or is not closing in). Followed: ahead of it, its heading
  within `FOLLOW_MAX_HEADING` and overlapping it laterally (within `FOLLOW_MAX_HEADING_SMALL_OVERLAP` when
  the overlap is under `SMALL_OVERLAP_M`); the nearest such. Shapes as `distance_to_nearest_object`, `speed`
  `[B, A, T]`."""
  rel = geometry.rotate(xy[:, None] - xy[:, :, None], -heading[:, :, None])     # [B, i, j, T, 2] in i's frame
  yaw = jnp.abs(_wrap(heading[:, None] - heading[:, :, None]))                  # [B, i, j, T]
  cos, sin = jnp.abs(jnp.cos(yaw)), jnp.abs(jnp.sin(yaw))
  length_j, width_j = size[:, None, :, None, 0], size[:, None, :, None, 1]
  long_gap = rel[..., 0] - size[:, :, None, None, 0] / 2 - (length_j * cos + width_j * sin) / 2
  lateral = jnp.abs(rel[..., 1]) - size[:, :, None, None, 1] / 2 - (length_j * sin + width_j * cos) / 2
  a = xy.shape[1]
  follows = (valid[:, :, None] & valid[:, None] & ~jnp.eye(a, dtype=bool)[None, :, :, None]
             & (long_gap > 0) & (yaw <= FOLLOW_MAX_HEADING) & (lateral < 0)
             & ((lateral < -SMALL_OVERLAP_M) | (yaw <= FOLLOW_MAX_HEADING_SMALL_OVERLAP)))
  gap = jnp.where(follows, long_gap, jnp.inf)
  ahead = jnp.argmin(gap, axis=2)                                               # [B, A, T]
  gap = jnp.take_along_axis(gap, ahead[:, :, None], axis=2)[:, :, 0]
  speed_ahead = jnp.take_along_axis(jnp.broadcast_to(speed[:, None], follows.shape), ahead[:, :, None], axis=2)
  closing = speed - speed_ahead[:, :, 0]
  ttc = jnp.where(jnp.isfinite(gap) & (closing > 0), gap / jnp.where(closing > 0, closing, 1.0), MAX_TTC_S)
  return jnp.minimum(ttc, MAX_TTC_S)


def distance_to_road_edge(xy: jax.Array, heading: jax.Array, size: jax.Array,
                          map_geometry: geometry.MapGeometry) -> jax.Array:
  """`[B, A, T]` the largest signed distance (m) of a box corner to the drivable area's boundary:
  negative when the whole box is inside it, positive by how far its most off-road corner is outside."""
  corners = geometry.box_corners(xy, heading, size[:, :, None])                  # [B, A, T, 4, 2]
  inside = geometry.inside_drivable_area(corners, map_geometry)
  d = geometry.distance_to_drivable_boundary(corners, map_geometry)
  return jnp.where(inside, -d, d).max(-1)


@jax.jit
def trajectory_features(xy: jax.Array, valid: jax.Array, initial_heading: jax.Array, agent_type: jax.Array,
                        map_geometry: geometry.MapGeometry) -> dict:
  """Every feature of `FEATURES` of a batch of scenarios: name -> (values, valid), `[B, A, T]` per step or
  `[B, A]` for the two indications.

  Args:
    xy: `[B, A, T, 2]` positions (m, scene frame) at 10 Hz. valid: `[B, A, T]` which exist.
    initial_heading: `[B, A]` (rad) the heading before an object first moves (`motion_headings`).
    agent_type: `[B, A]` (boxes; pedestrians have no road-edge features).
    map_geometry: the scenarios' maps (`geometry.map_geometry`), `[B]`.
  """
  valid = jnp.asarray(valid, bool)
  heading = motion_headings(xy, valid, initial_heading)
  out = kinematics(xy, heading, valid)
  size = geometry.box_sizes(agent_type)
  exists = valid.any(-1)
  nearest = distance_to_nearest_object(xy, heading, size, valid)
  out["distance_to_nearest_object"] = (nearest, valid)
  out["collision"] = ((valid & (nearest < 0)).any(-1), exists)
  speed = jnp.where(out["linear_speed"][1], out["linear_speed"][0], 0.0)
  out["time_to_collision"] = (time_to_collision(xy, heading, speed, size, valid), valid)
  road = valid & (agent_type != datatypes.PEDESTRIAN)[..., None] & map_geometry.edge_valid.any(-1)[:, None, None]
  edge = distance_to_road_edge(xy, heading, size, map_geometry)
  out["distance_to_road_edge"] = (edge, road)
  out["offroad"] = ((road & (edge > 0)).any(-1), road.any(-1))
  return out


def _bins(name: str, values: jax.Array) -> jax.Array:
  f = FEATURES[name]
  if f.low is None:
    return values.astype(jnp.int32)
  width = (f.high - f.low) / f.bins
  return jnp.clip(jnp.floor((values - f.low) / width), 0, f.bins - 1).astype(jnp.int32)


def histograms(features: dict) -> dict:
  """Per scenario, each feature's counts `[B, bins]` of its valid values (out of range in the end bins)."""
  out = {}
  for name, (values, valid) in features.items():
    b = values.shape[0]
    onehot = jax.nn.one_hot(_bins(name, values), FEATURES[name].bins) * valid[..., None]
    out[name] = onehot.reshape(b, -1, FEATURES[name].bins).sum(1)
  return out


@jax.jit
def log_likelihoods(counts: dict, features: dict) -> dict:
  """Per scenario, each feature's summed log-likelihood and count of its valid values under the smoothed,
  normalised histograms `counts` (`[B, bins]`, e.g. N generated scenarios' summed): name -> (sum, count) `[B]`."""
  out = {}
  for name, (values, valid) in features.items():
    c = counts[name] + PSEUDOCOUNT
    log_p = jnp.log(c / c.sum(-1, keepdims=True))                            # [B, bins]
    b = values.shape[0]
    idx = _bins(name, values).reshape(b, -1)
    ll = jnp.take_along_axis(log_p, idx, axis=-1)
    ok = valid.reshape(b, -1)
    out[name] = (jnp.sum(jnp.where(ok, ll, 0.0), -1), ok.sum(-1).astype(jnp.float32))
  return out


def scores(log_likelihood: dict) -> dict:
  """Per map, each feature's score exp(mean log-likelihood) and the meta-metric, from `log_likelihoods`
  sums and counts (numpy `[M]`; NaN for a feature the map's logged scenario has no value of, and the
  meta-metric then weighs the others): name -> `[M]`, plus "meta"."""
  out, weighted, weights = {}, 0.0, 0.0
  for name, (total, count) in log_likelihood.items():
    total, count = np.asarray(total, np.float64), np.asarray(count, np.float64)
    score = np.where(count > 0, np.exp(total / np.maximum(count, 1)), np.nan)
    out[name] = score
    w = FEATURES[name].weight
    weighted = weighted + np.where(np.isnan(score), 0.0, w * score)
    weights = weights + np.where(np.isnan(score), 0.0, w)
  out["meta"] = np.where(weights > 0, weighted / np.maximum(weights, 1e-12), np.nan)
  return out


def summarize(per_map: dict) -> dict:
  """A table row: each feature's and the meta-metric's mean over the maps that have it, and the map count."""
  row = {name: float(np.nanmean(v)) if np.isfinite(v).any() else float("nan") for name, v in per_map.items()}
  row["maps"] = int(len(per_map["meta"]))
  return row


def constant_velocity(initial_state: jax.Array, horizon: int = datatypes.HORIZON) -> jax.Array:
  """`[..., horizon, 2]` positions of objects keeping their initial speed and heading from `initial_state`
  `[..., 4]` (x, y, speed, heading): the floor any trajectory model must beat."""
  k = jnp.arange(horizon, dtype=jnp.float32) * DT
  step = initial_state[..., 2:3] * jnp.stack([jnp.cos(initial_state[..., 3]), jnp.sin(initial_state[..., 3])], -1)
  return initial_state[..., None, :2] + k[:, None] * step[..., None, :]


@jax.jit
def scenario_histograms(xy: jax.Array, valid: jax.Array, initial_heading: jax.Array, agent_type: jax.Array,
                        map_geometry: geometry.MapGeometry) -> dict:
  """Each feature's counts `[B, bins]` per scenario (`histograms` of `trajectory_features`, same arguments),
  a few scenarios at a time so that the object pairs of a large batch fit in memory."""
  def one(args):
    one_batch = jax.tree_util.tree_map(lambda x: x[None], args)
    return jax.tree_util.tree_map(lambda x: x[0], histograms(trajectory_features(*one_batch)))
  return jax.lax.map(one, (xy, valid, initial_heading, agent_type, map_geometry), batch_size=8)


_SUCC = datatypes.EDGE_TYPES.index("SUCC")


def _nearest_lane(xy: jax.Array, scene: datatypes.Scene) -> jax.Array:
  """`[B, ...]` the polygon index of the lane centreline point nearest each point `xy` `[B, ..., 2]`."""
  pts, _, mask = geometry.centerline_points(scene)                       # [B, P x K/3, 2]
  b = xy.shape[0]
  d2 = jnp.where(mask[:, None], geometry.squared_distances(xy.reshape(b, -1, 2), pts), jnp.inf)
  per_polygon = pts.shape[1] // scene.pl_valid.shape[-1]
  return (jnp.argmin(d2, -1) // per_polygon).reshape(xy.shape[:-1])


@jax.jit
def draw_diversity(draws: jax.Array, scene: datatypes.Scene) -> dict:
  """How K trajectory draws for the same high-level scenario differ: sums and counts over the scenes'
  valid agents (`[K, B, A, H, 2]` draws of `scene`'s agents, `agent_state` the scenario's states).

  Returns {"pairwise_ade_sum", "agents", "fork_agents", "fork_multi_lane", "pinned_goal_error_max"}: the
  mean over pairs of draws of their mean distance per step, summed over agents; the agents whose
  initial position's nearest lane has two or more successors, and how many of them have draws whose
  nearest lane at the horizon's midpoint differs; the largest distance of a draw's last position from
  the goal state (0 when the goal is pinned)."""
  k = draws.shape[0]
  valid = scene.agent_valid
  dist = jnp.sqrt(jnp.sum((draws[:, None] - draws[None]) ** 2, -1) + 1e-12).mean(-1)    # [K, K, B, A]
  pairwise = dist.sum((0, 1)) / (k * (k - 1))
  lane0 = _nearest_lane(scene.agent_state[..., 0, :2], scene)                             # [B, A]
  successors = (scene.pl_edge == _SUCC).sum(-1)                                          # [B, P]
  at_fork = valid & (jnp.take_along_axis(successors, lane0, axis=1) >= 2)
  mid = draws[..., draws.shape[-2] // 2, :]                                              # [K, B, A, 2]
  mid_lane = jax.vmap(lambda xy: _nearest_lane(xy, scene))(mid)                          # [K, B, A]
  multi = (mid_lane != mid_lane[:1]).any(0)
  goal_error = jnp.sqrt(jnp.sum((draws[..., -1, :] - scene.agent_state[..., 1, :2]) ** 2, -1))
  return {"pairwise_ade_sum": jnp.sum(jnp.where(valid, pairwise, 0.0)), "agents": valid.sum(),
          "fork_agents": at_fork.sum(), "fork_multi_lane": (at_fork & multi).sum(),
          "pinned_goal_error_max": jnp.where(valid, goal_error, 0.0).max()}
