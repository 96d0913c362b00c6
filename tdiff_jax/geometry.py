"""Planar geometry on scenes, in metres (scene frame): the one home of what guidance, the metrics, the
models and the pictures share.

Every function is jit-able, works on JAX or numpy inputs and keeps padded entries out through the
scene's masks (`datatypes.Scene.road_users`, `lane_polygons`, `centerline_points_mask`).
Shapes: B scenes, A agents, P polygons, K points per polygon, D drivable-area rings of V vertices.

The map queries (`lane_headings`, `inside_drivable_area`, `distance_to_drivable_boundary`) take a scene
or its `MapGeometry`: the drivable-area edges and lane centreline points as flat lists. Built once per
sampling call with `map_geometry(scene, *compact_sizes(scene))`, the lists hold only the valid entries
(in power-of-two buckets) instead of the scene's padded `[D, V]` rings and `[P, K]` points, where most
entries are padding (an AV2 map has 100 to 450 drivable-area vertices of the 4096 slots; only the
centre third of a polygon's K points can be a centreline point), so the
guidance costs evaluated at every step do a fraction of the work and give the same values.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from tdiff_jax import datatypes


def masked_mean(values: jax.Array, mask: jax.Array) -> jax.Array:
  """Mean of `values` where `mask` (broadcast to the values); 0, not NaN, when nothing is masked in."""
  mask = jnp.broadcast_to(mask, values.shape)
  return jnp.sum(jnp.where(mask, values, 0.0)) / jnp.maximum(jnp.sum(mask), 1)


def pair_mask(valid: jax.Array) -> jax.Array:
  """`[..., A]` validity -> `[..., A, A]` ordered pairs (i, j) of valid agents with i != j."""
  a = valid.shape[-1]
  return valid[..., :, None] & valid[..., None, :] & ~jnp.eye(a, dtype=bool)


def rotate(xy: jax.Array, angle: jax.Array) -> jax.Array:
  """`[..., 2]` vectors turned counter-clockwise by `angle` `[...]` (rad)."""
  c, s = jnp.cos(angle), jnp.sin(angle)
  return jnp.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], -1)


def box_sizes(agent_type: jax.Array) -> jax.Array:
  """`[...]` agent types -> `[..., 2]` box length and width (m), `datatypes.AGENT_BOX_SIZE_M`."""
  sizes = jnp.asarray([datatypes.AGENT_BOX_SIZE_M[t] for t in datatypes.AGENT_TYPES], jnp.float32)
  return sizes[agent_type]


def box_corners(xy: jax.Array, heading: jax.Array, size: jax.Array) -> jax.Array:
  """`[..., 4, 2]` corners (in order around the box) of boxes of `size` `[..., 2]` (length, width)
  centred at `xy` `[..., 2]` with their length along `heading` `[...]`."""
  signs = jnp.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], jnp.float32)
  local = signs * (jnp.asarray(size, jnp.float32) / 2.0)[..., None, :]     # [..., 4, 2]
  return xy[..., None, :] + rotate(local, jnp.asarray(heading)[..., None])


def boxes_overlap(corners: jax.Array, heading: jax.Array) -> jax.Array:
  """Pairwise oriented-box overlap `[..., A, A]` by the separating-axis theorem (touching counts).

  `corners` `[..., A, 4, 2]` from `box_corners`, `heading` `[..., A]` the boxes' orientations."""
  axes = jnp.stack([jnp.cos(heading), jnp.sin(heading), -jnp.sin(heading), jnp.cos(heading)], -1)
  axes = axes.reshape(heading.shape + (2, 2))                             # [..., A, 2 axes, 2]
  a = axes.shape[-3]
  full = axes.shape[:-3] + (a, a, 2, 2)
  # Candidate axes of pair (i, j): i's two and j's two.
  pair_axes = jnp.concatenate([jnp.broadcast_to(axes[..., :, None, :, :], full),
                               jnp.broadcast_to(axes[..., None, :, :, :], full)], axis=-2)  # [..., A, A, 4, 2]
  proj_i = jnp.einsum("...ijkd,...icd->...ijkc", pair_axes, corners)      # [..., A, A, 4, 4 corners]
  proj_j = jnp.einsum("...ijkd,...jcd->...ijkc", pair_axes, corners)
  separated = (proj_i.max(-1) < proj_j.min(-1)) | (proj_j.max(-1) < proj_i.min(-1))
  return ~separated.any(-1)


def squared_distances(q: jax.Array, p: jax.Array) -> jax.Array:
  """`[B, Q, 2]` and `[B, N, 2]` points -> `[B, Q, N]` squared distances, x and y apart (on a trailing
  axis of 2, XLA's CPU loops do not vectorise)."""
  dx = q[:, :, None, 0] - p[:, None, :, 0]
  dy = q[:, :, None, 1] - p[:, None, :, 1]
  return dx * dx + dy * dy


def segment_fraction(qx: jax.Array, qy: jax.Array, sx: jax.Array, sy: jax.Array, ux: jax.Array,
                     uy: jax.Array) -> jax.Array:
  """Where the foot of each point (qx, qy) on segment (sx, sy) + u (ux, uy) lies, u in [0, 1]; x and y
  apart, broadcasting (on a trailing axis of 2, XLA's CPU loops do not vectorise)."""
  return jnp.clip(((qx - sx) * ux + (qy - sy) * uy) / jnp.maximum(ux * ux + uy * uy, 1e-9), 0.0, 1.0)


def centerline_points(scene: datatypes.Scene) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Lane centreline points `[B, P*K/3, 2]`, their headings `[B, P*K/3]` and validity (crosswalks excluded)."""
  centre = scene.centerline_slice
  mask = scene.centerline_points_mask[..., centre] & scene.lane_polygons[..., None]
  b = mask.shape[0]
  return (scene.pt_xy[..., centre, :].reshape(b, -1, 2), scene.pt_heading[..., centre].reshape(b, -1),
          mask.reshape(b, -1))


@struct.dataclass
class MapGeometry:
  """A map's drivable-area edges and lane centreline points as flat lists with validity masks.

  Edges keep their ring (`edge_ring`), so inside/outside is decided per drivable-area polygon as on the
  rings; `num_rings` (static) is D of the scene they came from.
  """

  edge_start: jax.Array    # [B, E, 2] m
  edge_end: jax.Array      # [B, E, 2] m
  edge_ring: jax.Array     # [B, E] int32, the ring's row in the scene's `da_xy`
  edge_valid: jax.Array    # [B, E]
  lane_xy: jax.Array       # [B, N, 2] m, lane centreline points (crosswalks excluded)
  lane_heading: jax.Array  # [B, N] rad, the lane's direction of travel there
  lane_valid: jax.Array    # [B, N]
  num_rings: int = struct.field(pytree_node=False, default=1)


def _bucket(count: int, minimum: int = 16) -> int:
  return max(minimum, 1 << max(count - 1, 0).bit_length())


def compact_sizes(scene: datatypes.Scene) -> tuple[int, int]:
  """(E, N): the batch's most valid drivable-area edges and lane centreline points of a scene, each rounded
  up to a power of two (at least 16, at most the padded count), for `map_geometry`. Host-level (numpy)."""
  da_valid = np.asarray(scene.da_valid)
  lanes = (np.asarray(scene.centerline_points_mask)[..., scene.centerline_slice]
           & np.asarray(scene.lane_polygons)[..., None])
  b = da_valid.shape[0]
  edges = int(da_valid.reshape(b, -1).sum(-1).max(initial=0))
  points = int(lanes.reshape(b, -1).sum(-1).max(initial=0))
  return (min(_bucket(edges), da_valid[0].size), min(_bucket(points), lanes[0].size))


def _compact(valid: jax.Array, size: int | None, *arrays: jax.Array) -> tuple[jax.Array, ...]:
  """The first `size` entries of each `[B, M, ...]` array with the valid ones moved first, in order."""
  if size is None or size >= valid.shape[1]:
    return (valid, *arrays)
  order = jnp.argsort(~valid, axis=1, stable=True)[:, :size]
  take = lambda x: jnp.take_along_axis(x, order.reshape(order.shape + (1,) * (x.ndim - 2)), axis=1)  # noqa: E731
  return (take(valid), *(take(x) for x in arrays))


def map_geometry(scene: datatypes.Scene, num_edges: int | None = None,
                 num_lane_points: int | None = None) -> MapGeometry:
  """The scene's `MapGeometry`: all D x V edge and P x K/3 centre-point slots (None), or their valid entries
  first, cut to `num_edges` / `num_lane_points` (each at least the batch's valid count: `compact_sizes`)."""
  start, end, valid = drivable_edges(scene)
  b, d, v = valid.shape
  ring = jnp.broadcast_to(jnp.arange(d, dtype=jnp.int32)[:, None], (b, d, v))
  edge_valid, start, end, ring = _compact(jnp.reshape(valid, (b, -1)), num_edges, jnp.reshape(start, (b, -1, 2)),
                                          jnp.reshape(end, (b, -1, 2)), jnp.reshape(ring, (b, -1)))
  pts, heads, mask = centerline_points(scene)
  lane_valid, pts, heads = _compact(jnp.asarray(mask), num_lane_points, jnp.asarray(pts), jnp.asarray(heads))
  return MapGeometry(jnp.asarray(start), jnp.asarray(end), ring, edge_valid, pts, heads, lane_valid, num_rings=d)


def as_geometry(map_: "datatypes.Scene | MapGeometry") -> MapGeometry:
  return map_ if isinstance(map_, MapGeometry) else map_geometry(map_)


def lane_headings(xy: jax.Array, map_: "datatypes.Scene | MapGeometry") -> jax.Array:
  """`[B, ..., 2]` positions -> `[B, ...]` heading of the nearest lane centreline point (0 if none)."""
  geom = as_geometry(map_)
  pts, heads, mask = geom.lane_xy, geom.lane_heading, geom.lane_valid
  b = xy.shape[0]
  d2 = jnp.where(mask[:, None], squared_distances(xy.reshape(b, -1, 2), pts), jnp.inf)   # [B, Q, N]
  h = jnp.take_along_axis(heads, jnp.argmin(d2, axis=-1), axis=-1)
  return jnp.where(mask.any(-1)[:, None], h, 0.0).reshape(xy.shape[:-1])


def drivable_edges(scene: datatypes.Scene) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Drivable-area edges `[B, D, V, 2]` (start, end) and their validity (rings are stored open)."""
  start, valid = scene.da_xy, scene.da_valid
  n = valid.sum(-1, keepdims=True)                                   # vertices per ring
  nxt = (jnp.arange(valid.shape[-1]) + 1) % jnp.maximum(n, 1)       # wrap to the ring's first vertex
  end = jnp.take_along_axis(start, nxt[..., None], axis=-2)
  return start, end, valid


def inside_drivable_area(xy: jax.Array, map_: "datatypes.Scene | MapGeometry") -> jax.Array:
  """`[B, ..., 2]` points -> bool: inside any drivable-area polygon (even-odd ray casting per ring)."""
  geom = as_geometry(map_)
  b = xy.shape[0]
  q = xy.reshape(b, -1, 1, 2)
  s, e = geom.edge_start[:, None], geom.edge_end[:, None]                 # [B, 1, E, 2]
  crosses = ((s[..., 1] > q[..., 1]) != (e[..., 1] > q[..., 1]))
  x_at = s[..., 0] + (q[..., 1] - s[..., 1]) * (e[..., 0] - s[..., 0]) / jnp.where(
      e[..., 1] == s[..., 1], 1e-9, e[..., 1] - s[..., 1])
  hits = crosses & (q[..., 0] < x_at) & geom.edge_valid[:, None]         # [B, Q, E]
  per_ring = jax.vmap(lambda h, r: jax.ops.segment_sum(h.T, r, num_segments=geom.num_rings))(
      hits.astype(jnp.int32), geom.edge_ring)                              # [B, D, Q] crossings per ring
  inside = (per_ring % 2 == 1).any(1)
  return inside.reshape(xy.shape[:-1])


def distance_to_drivable_boundary(xy: jax.Array, map_: "datatypes.Scene | MapGeometry") -> jax.Array:
  """`[B, ..., 2]` -> distance (m) to the nearest drivable-area edge."""
  geom = as_geometry(map_)
  b = xy.shape[0]
  # x and y apart ([B, Q, E] each): on a trailing axis of 2, XLA's CPU loops run scalar (several times as slow).
  qx, qy = (xy[..., i].reshape(b, -1, 1) for i in (0, 1))
  sx, sy, ex, ey = (a[:, None, :, i] for a in (geom.edge_start, geom.edge_end) for i in (0, 1))  # [B, 1, E]
  ux, uy = ex - sx, ey - sy
  t = segment_fraction(qx, qy, sx, sy, ux, uy)
  px, py = sx + t * ux - qx, sy + t * uy - qy
  d = jnp.sqrt(px * px + py * py + 1e-9)
  d = jnp.where(geom.edge_valid[:, None], d, 1e6).min(axis=-1)
  return d.reshape(xy.shape[:-1])
