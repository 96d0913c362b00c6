"""Planar geometry on scenes, in metres (scene frame): the one home of what guidance, the metrics, the
models and the pictures share.

Every function is jit-able, works on JAX or numpy inputs and keeps padded entries out through the
scene's masks (`datatypes.Scene.road_users`, `lane_polygons`, `centerline_points_mask`).
Shapes: B scenes, A agents, P polygons, K points per polygon, D drivable-area rings of V vertices.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

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


def segment_fraction(q: jax.Array, start: jax.Array, seg: jax.Array) -> jax.Array:
  """Where the foot of each point `q` on segment `start + u seg` lies, u in [0, 1] (broadcasting `[..., 2]`)."""
  return jnp.clip(jnp.sum((q - start) * seg, -1) / jnp.maximum(jnp.sum(seg * seg, -1), 1e-9), 0.0, 1.0)


def centerline_points(scene: datatypes.Scene) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Lane centreline points `[B, P*K, 2]`, their headings `[B, P*K]` and validity (crosswalks excluded)."""
  mask = scene.centerline_points_mask & scene.lane_polygons[..., None]
  b = mask.shape[0]
  return scene.pt_xy.reshape(b, -1, 2), scene.pt_heading.reshape(b, -1), mask.reshape(b, -1)


def lane_headings(xy: jax.Array, scene: datatypes.Scene) -> jax.Array:
  """`[B, ..., 2]` positions -> `[B, ...]` heading of the nearest lane centreline point (0 if none)."""
  pts, heads, mask = centerline_points(scene)
  b = xy.shape[0]
  q = xy.reshape(b, -1, 1, 2)
  d2 = jnp.where(mask[:, None], jnp.sum((q - pts[:, None]) ** 2, -1), jnp.inf)      # [B, N, M]
  h = jnp.take_along_axis(heads, jnp.argmin(d2, axis=-1), axis=-1)
  return jnp.where(mask.any(-1)[:, None], h, 0.0).reshape(xy.shape[:-1])


def drivable_edges(scene: datatypes.Scene) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Drivable-area edges `[B, D, V, 2]` (start, end) and their validity (rings are stored open)."""
  start, valid = scene.da_xy, scene.da_valid
  n = valid.sum(-1, keepdims=True)                                   # vertices per ring
  nxt = (jnp.arange(valid.shape[-1]) + 1) % jnp.maximum(n, 1)       # wrap to the ring's first vertex
  end = jnp.take_along_axis(start, nxt[..., None], axis=-2)
  return start, end, valid


def inside_drivable_area(xy: jax.Array, scene: datatypes.Scene) -> jax.Array:
  """`[B, ..., 2]` points -> bool: inside any drivable-area polygon (even-odd ray casting)."""
  start, end, valid = drivable_edges(scene)
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
  start, end, valid = drivable_edges(scene)
  b = xy.shape[0]
  q = xy.reshape(b, -1, 1, 1, 2)
  s, e = start[:, None], end[:, None]
  seg = e - s
  t = segment_fraction(q, s, seg)
  d = jnp.sqrt(jnp.sum((s + t[..., None] * seg - q) ** 2, -1) + 1e-9)
  d = jnp.where(valid[:, None], d, 1e6).min(axis=(-1, -2))
  return d.reshape(xy.shape[:-1])
