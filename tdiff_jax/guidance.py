"""Guidance costs J on a high-level scenario, in metres (paper §III-C, eq. 3), on its states and, for the
trajectory-level costs (`PATH_COSTS`), on the 6 s between them.

Every cost takes the denormalised state `[B, A, 2, 3]` (x, y in metres in the scene frame, speed in
m/s; token 0 initial, token 1 goal) and the batch's `datatypes.Scene` (map and agent masks), and returns a
scalar: the mean over valid entries, so padded agents never contribute and a scene without pairs or
agents gives 0, not NaN. Unlike the official code, every threshold is in metres (its collision
threshold was applied in normalised units). The map costs also take the scene's precomputed
`geometry.MapGeometry` (`map_geometry`; built from the scene when not given): the sampler builds it once per
call with only the valid edges and lane points, and the costs are the same.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from tdiff_jax import datatypes, geometry

def clearance(state: jax.Array, scene: datatypes.Scene, min_distance_m: float | jax.Array = 2.0) -> jax.Array:
  """Mean over valid ordered agent pairs and both tokens of relu(min_distance - centre distance)."""
  xy = state[..., :2]                                                  # [B, A, 2, 2]
  d = jnp.sqrt(jnp.sum((xy[:, :, None] - xy[:, None]) ** 2, -1) + 1e-9)  # [B, A, A, 2]
  return geometry.masked_mean(jax.nn.relu(min_distance_m - d), geometry.pair_mask(scene.agent_valid)[..., None])


def box_clearance(state: jax.Array, scene: datatypes.Scene, margin_m: float | jax.Array = 0.5,
                  map_geometry: geometry.MapGeometry | None = None) -> jax.Array:
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
  heading = jax.lax.stop_gradient(geometry.lane_headings(xy, scene if map_geometry is None else map_geometry))
  size = geometry.box_sizes(scene.agent_type)
  reach = (size[:, :, None] + size[:, None, :]) / 2.0 + margin_m        # [B, A, A, 2] length, width
  d = xy[:, None] - xy[:, :, None]                                     # [B, A, A, 2 tokens, 2] j - i
  c, s = jnp.cos(heading)[:, :, None], jnp.sin(heading)[:, :, None]    # [B, A, 1, 2]
  along = jnp.abs(c * d[..., 0] + s * d[..., 1])
  across = jax.lax.stop_gradient(jnp.abs(c * d[..., 1] - s * d[..., 0]))
  overlap = jnp.where(across < reach[..., None, 1], jax.nn.relu(reach[..., None, 0] - along), 0.0)
  pair = geometry.pair_mask(scene.agent_valid)
  per_agent = jnp.sum(jnp.where(pair[..., None], overlap, 0.0), axis=2)   # [B, A, 2]
  return geometry.masked_mean(per_agent, scene.agent_valid[..., None])


def lane_distance(state: jax.Array, scene: datatypes.Scene, max_distance_m: float | jax.Array = 2.0,
                  softmin_k: float = 10.0, map_geometry: geometry.MapGeometry | None = None) -> jax.Array:
  """Mean relu(soft-min distance to a lane centreline point - max_distance) over road users' endpoints."""
  geom = geometry.map_geometry(scene) if map_geometry is None else map_geometry
  pts, pmask = geom.lane_xy, geom.lane_valid
  b, a = state.shape[:2]
  d2 = geometry.squared_distances(state[..., :2].reshape(b, 2 * a, 2), pts).reshape(b, a, 2, -1)   # [B, A, 2, N]
  d = jnp.where(pmask[:, None, None], jnp.sqrt(d2 + 1e-9), 1e6)
  soft = -jax.nn.logsumexp(-softmin_k * d, axis=-1) / softmin_k
  return geometry.masked_mean(jax.nn.relu(soft - max_distance_m), scene.road_users[..., None])


def _mean_outside(xy: jax.Array, scene: datatypes.Scene, map_geometry: geometry.MapGeometry | None) -> jax.Array:
  """Mean distance outside the drivable area (0 inside) over road users' points `xy` `[B, A, N, 2]`, in metres."""
  geom = geometry.map_geometry(scene) if map_geometry is None else map_geometry
  outside = ~geometry.inside_drivable_area(jax.lax.stop_gradient(xy), geom)
  dist = geometry.distance_to_drivable_boundary(xy, geom)
  has_area = geom.edge_valid.any(axis=-1)[:, None, None]
  return geometry.masked_mean(jnp.where(outside, dist, 0.0), scene.road_users[..., None] & has_area)


def offroad(state: jax.Array, scene: datatypes.Scene, map_geometry: geometry.MapGeometry | None = None) -> jax.Array:
  """Mean distance outside the drivable area (0 inside) over road users' endpoints, in metres."""
  return _mean_outside(state[..., :2], scene, map_geometry)


# The trajectory-level costs: on the 6 s between the two states, through a stand-in for the infilled path.
PATH_SECONDS = 6.0     # from the initial to the goal state (AV2 steps 50 to 109)
PATH_SAMPLES = 13      # points along each path (every 0.5 s)
PATH_DISKS = 3         # disks covering each box along its length


def hermite_paths(state: jax.Array, heading: jax.Array, num: int = PATH_SAMPLES) -> tuple[jax.Array, jax.Array]:
  """Positions `[B, A, num, 2]` and unit tangents along the cubic Hermite curve from each agent's initial to
  its goal state: the positions, and the velocities (speed times heading) at both ends over `PATH_SECONDS`.
  A differentiable stand-in for the infilled trajectory, which meets the same states.

  Args: state `[B, A, 2, 3]` (x, y in metres, speed in m/s; token 0 initial, 1 goal), heading `[B, A, 2]` (rad).
  """
  s = jnp.linspace(0.0, 1.0, num)[:, None]                                 # [num, 1]
  s2, s3 = s * s, s * s * s
  p0, p1 = state[..., 0, None, :2], state[..., 1, None, :2]                 # [B, A, 1, 2]
  direction = jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1)           # [B, A, 2, 2]
  m0 = (PATH_SECONDS * state[..., 0, 2:3] * direction[..., 0, :])[..., None, :]
  m1 = (PATH_SECONDS * state[..., 1, 2:3] * direction[..., 1, :])[..., None, :]
  xy = (2 * s3 - 3 * s2 + 1) * p0 + (s3 - 2 * s2 + s) * m0 + (3 * s2 - 2 * s3) * p1 + (s3 - s2) * m1
  tangent = (6 * s2 - 6 * s) * p0 + (3 * s2 - 4 * s + 1) * m0 + (6 * s - 6 * s2) * p1 + (3 * s2 - 2 * s) * m1
  chord = jnp.broadcast_to(p1 - p0, tangent.shape)
  tangent = jnp.where(jnp.sum(tangent ** 2, -1, keepdims=True) > 1e-6, tangent, chord)   # at rest: the chord
  norm = jnp.sqrt(jnp.sum(tangent ** 2, -1, keepdims=True) + 1e-12)
  return xy, jax.lax.stop_gradient(tangent / norm)


def path_overlap(state: jax.Array, heading: jax.Array, scene: datatypes.Scene, margin_m: float | jax.Array = 0.3
                 ) -> jax.Array:
  """Mean over valid agents of how deep their boxes overlap others' along the 6 s (`hermite_paths`): each
  box is `PATH_DISKS` disks of its width along its length, and each pair of disks closer than their radii
  plus `margin_m` at one of the path's times adds the shortfall, averaged over the times."""
  xy, tangent = hermite_paths(state, heading)                              # [B, A, K, 2]
  size = geometry.box_sizes(scene.agent_type)                              # [B, A, 2]
  offsets = jnp.linspace(-0.5, 0.5, PATH_DISKS) * (size[..., :1] - size[..., 1:])   # [B, A, D]
  disks = xy[..., None, :] + offsets[:, :, None, :, None] * tangent[..., None, :]  # [B, A, K, D, 2]
  radius = size[..., 1] / 2                                                # [B, A]
  d = disks[:, :, None, :, :, None] - disks[:, None, :, :, None, :]         # [B, A, A, K, D, D, 2]
  dist = jnp.sqrt(jnp.sum(d ** 2, -1) + 1e-9)
  reach = (radius[:, :, None] + radius[:, None, :] + margin_m)[..., None, None, None]
  short = jnp.sum(jax.nn.relu(reach - dist), axis=(-1, -2)).mean(-1)       # [B, A, A]
  per_agent = jnp.sum(jnp.where(geometry.pair_mask(scene.agent_valid), short, 0.0), -1)
  return geometry.masked_mean(per_agent, scene.agent_valid)


def path_offroad(state: jax.Array, heading: jax.Array, scene: datatypes.Scene,
                 map_geometry: geometry.MapGeometry | None = None) -> jax.Array:
  """Mean distance outside the drivable area over road users' `hermite_paths` points, in metres."""
  return _mean_outside(hermite_paths(state, heading)[0], scene, map_geometry)


COSTS = {"clearance": clearance, "boxes": box_clearance, "lane": lane_distance, "offroad": offroad,
         "paths": path_overlap, "path_offroad": path_offroad}
PATH_COSTS = ("paths", "path_offroad")   # these also take the states' headings
