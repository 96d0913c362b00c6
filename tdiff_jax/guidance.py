"""Guidance costs J on a high-level scenario, in metres (paper §III-C, eq. 3).

Every cost takes the denormalised state `[B, A, 2, 3]` (x, y in metres in the scene frame, speed in
m/s; token 0 initial, token 1 goal) and the batch's `datatypes.Scene` (map and agent masks), and returns a
scalar: the mean over valid entries, so padded agents never contribute and a scene without pairs or
agents gives 0, not NaN. Unlike the official code, every threshold is in metres (its collision
threshold was applied in normalised units).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tdiff_jax import datatypes

PEDESTRIAN = datatypes.AGENT_TYPES.index("pedestrian")
CROSSWALK = datatypes.POLYGON_TYPES.index("PEDESTRIAN")
CENTER = datatypes.POINT_SIDES.index("CENTER")


def _masked_mean(values: jax.Array, mask: jax.Array) -> jax.Array:
  return jnp.sum(jnp.where(mask, values, 0.0)) / jnp.maximum(jnp.sum(mask), 1)


def clearance(state: jax.Array, scene: datatypes.Scene, min_distance_m: float | jax.Array = 2.0) -> jax.Array:
  """Mean over valid ordered agent pairs and both tokens of relu(min_distance - centre distance)."""
  xy = state[..., :2]                                                  # [B, A, 2, 2]
  d = jnp.sqrt(jnp.sum((xy[:, :, None] - xy[:, None]) ** 2, -1) + 1e-9)  # [B, A, A, 2]
  a = scene.agent_valid.shape[-1]
  pair = scene.agent_valid[:, :, None] & scene.agent_valid[:, None, :] & ~jnp.eye(a, dtype=bool)
  return _masked_mean(jax.nn.relu(min_distance_m - d), pair[..., None] & jnp.ones(d.shape, bool))


def box_clearance(state: jax.Array, scene: datatypes.Scene, margin_m: float | jax.Array = 0.5) -> jax.Array:
  """Mean over valid agents and both tokens of how far the agent's box overlaps the others' along the lane.

  Each agent is a box of its type's size (`datatypes.AGENT_BOX_SIZE_M`) along its nearest lane. Pair (i, j)
  is seen in i's lane frame: with the centre offset (along, across) and L_ij, W_ij the pair's mean
  length and width plus `margin_m`, the boxes (taken as parallel) overlap where |along| < L_ij and
  |across| < W_ij; the cost is then L_ij - |along|, summed over the agent's overlaps: the push along
  the lane that separates them (a push across would move agents off their lanes, which is where the
  lane and off-road costs hold them). A centre-distance threshold cannot do this: 2 m lets two 4 m cars
  overlap nose to tail, 4 m pushes apart cars in neighbouring lanes.
  """
  xy = state[..., :2]                                                  # [B, A, 2, 2]
  heading = jax.lax.stop_gradient(lane_headings(xy, scene))            # [B, A, 2]
  size = jnp.asarray([datatypes.AGENT_BOX_SIZE_M[t] for t in datatypes.AGENT_TYPES], jnp.float32)[scene.agent_type]
  reach = (size[:, :, None] + size[:, None, :]) / 2.0 + margin_m        # [B, A, A, 2] length, width
  d = xy[:, None] - xy[:, :, None]                                     # [B, A, A, 2 tokens, 2] j - i
  c, s = jnp.cos(heading)[:, :, None], jnp.sin(heading)[:, :, None]    # [B, A, 1, 2]
  along = jnp.abs(c * d[..., 0] + s * d[..., 1])
  across = jax.lax.stop_gradient(jnp.abs(c * d[..., 1] - s * d[..., 0]))
  overlap = jnp.where(across < reach[..., None, 1], jax.nn.relu(reach[..., None, 0] - along), 0.0)
  a = scene.agent_valid.shape[-1]
  pair = scene.agent_valid[:, :, None] & scene.agent_valid[:, None, :] & ~jnp.eye(a, dtype=bool)
  per_agent = jnp.sum(jnp.where(pair[..., None], overlap, 0.0), axis=2)   # [B, A, 2]
  return _masked_mean(per_agent, scene.agent_valid[..., None] & jnp.ones(per_agent.shape, bool))


def centerline_points(scene: datatypes.Scene) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Lane centreline points `[B, P*K', 2]`, their headings and validity (crosswalks excluded)."""
  lane = scene.pl_valid & (scene.pl_type != CROSSWALK)
  mask = scene.pt_valid & (scene.pt_side == CENTER) & lane[..., None]
  b = mask.shape[0]
  return scene.pt_xy.reshape(b, -1, 2), scene.pt_heading.reshape(b, -1), mask.reshape(b, -1)


def lane_headings(xy: jax.Array, scene: datatypes.Scene) -> jax.Array:
  """`[B, ...,  2]` positions -> `[B, ...]` heading of the nearest lane centreline point (0 if none)."""
  pts, heads, mask = centerline_points(scene)
  b = xy.shape[0]
  q = xy.reshape(b, -1, 1, 2)
  d2 = jnp.where(mask[:, None], jnp.sum((q - pts[:, None]) ** 2, -1), jnp.inf)      # [B, N, M]
  h = jnp.take_along_axis(heads, jnp.argmin(d2, axis=-1), axis=-1)
  return jnp.where(mask.any(-1)[:, None], h, 0.0).reshape(xy.shape[:-1])


def lane_distance(state: jax.Array, scene: datatypes.Scene, max_distance_m: float | jax.Array = 2.0,
                  softmin_k: float = 10.0) -> jax.Array:
  """Mean relu(soft-min distance to a lane centreline point - max_distance) over road users' endpoints."""
  pts, _, pmask = centerline_points(scene)
  d = jnp.sqrt(jnp.sum((state[..., None, :2] - pts[:, None, None]) ** 2, -1) + 1e-9)  # [B, A, 2, N]
  d = jnp.where(pmask[:, None, None], d, 1e6)
  soft = -jax.nn.logsumexp(-softmin_k * d, axis=-1) / softmin_k
  road_user = scene.agent_valid & (scene.agent_type != PEDESTRIAN)
  return _masked_mean(jax.nn.relu(soft - max_distance_m), road_user[..., None] & jnp.ones(soft.shape, bool))


def _segments(scene: datatypes.Scene) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Drivable-area edges `[B, D, V, 2]` (start, end) and their validity (rings are stored open)."""
  start, valid = scene.da_xy, scene.da_valid
  n = valid.sum(-1, keepdims=True)                                   # vertices per ring
  nxt = (jnp.arange(valid.shape[-1]) + 1) % jnp.maximum(n, 1)       # wrap to the ring's first vertex
  end = jnp.take_along_axis(start, nxt[..., None], axis=-2)
  return start, end, valid


def inside_drivable_area(xy: jax.Array, scene: datatypes.Scene) -> jax.Array:
  """`[B, ..., 2]` points -> bool: inside any drivable-area polygon (even-odd ray casting)."""
  start, end, valid = _segments(scene)
  b = xy.shape[0]
  q = xy.reshape(b, -1, 1, 1, 2)
  s, e = start[:, None], end[:, None]
  crosses = ((s[..., 1] > q[..., 1]) != (e[..., 1] > q[..., 1]))
  x_at = s[..., 0] + (q[..., 1] - s[..., 1]) * (e[..., 0] - s[..., 0]) / jnp.where(
      e[..., 1] == s[..., 1], 1e-9, e[..., 1] - s[..., 1])
  hits = crosses & (q[..., 0] < x_at) & valid[:, None]
  inside = (jnp.sum(hits, -1) % 2 == 1).any(-1)
  return inside.reshape(xy.shape[:-1])


def distance_to_drivable_boundary(xy: jax.Array, scene: datatypes.Scene) -> jax.Array:
  """`[B, ..., 2]` -> distance (m) to the nearest drivable-area edge."""
  start, end, valid = _segments(scene)
  b = xy.shape[0]
  q = xy.reshape(b, -1, 1, 1, 2)
  s, e = start[:, None], end[:, None]
  seg = e - s
  t = jnp.clip(jnp.sum((q - s) * seg, -1) / jnp.maximum(jnp.sum(seg * seg, -1), 1e-9), 0.0, 1.0)
  d = jnp.sqrt(jnp.sum((s + t[..., None] * seg - q) ** 2, -1) + 1e-9)
  d = jnp.where(valid[:, None], d, 1e6).min(axis=(-1, -2))
  return d.reshape(xy.shape[:-1])


def offroad(state: jax.Array, scene: datatypes.Scene) -> jax.Array:
  """Mean distance outside the drivable area (0 inside) over road users' endpoints, in metres."""
  xy = state[..., :2]
  outside = ~inside_drivable_area(jax.lax.stop_gradient(xy), scene)
  dist = distance_to_drivable_boundary(xy, scene)
  has_area = scene.da_valid.any(axis=(-1, -2))[:, None, None]
  road_user = scene.agent_valid & (scene.agent_type != PEDESTRIAN)
  return _masked_mean(jnp.where(outside, dist, 0.0), road_user[..., None] & has_area & jnp.ones(dist.shape, bool))


COSTS = {"clearance": clearance, "boxes": box_clearance, "lane": lane_distance, "offroad": offroad}
