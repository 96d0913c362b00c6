"""Where each agent token stands relative to each polygon, in metres: the grounded map attention's input.

The paper's denoiser sees the map only through polygon embeddings that encode absolute positions; with
the training budgets of this project it never learns to put agents on lanes (docs/training.md). The grounded denoiser instead tells every (token, polygon) pair where the polygon's centreline
is seen from the token's current position estimate, QCNet-style: the displacement to the nearest point
of the polygon's centreline segments and the centreline's direction there. `lane_routes` adds the
map's topology: the length of the shortest path along the directed lane graph between any two lanes,
so that a token can also be told how far along the lanes its agent's other token lies.

Shapes: B scenes, Q query tokens, P polygons, S centreline segments per polygon.
"""

from __future__ import annotations


import jax
import jax.numpy as jnp
from flax import struct

from tdiff_jax import datatypes, geometry

# Distances enter the features divided by this (metres): lane widths and offsets become O(1).
FEATURE_SCALE_M = 10.0
NUM_FEATURES = 8
DIRECTION = slice(6, 8)  # where `relation_features` holds the centreline's direction (cos, sin)
NUM_ROUTE_FEATURES = 3
_SUCC, _LEFT, _RIGHT = (datatypes.EDGE_TYPES.index(n) for n in ("SUCC", "LEFT", "RIGHT"))


@struct.dataclass
class Centerlines:
  """Each polygon's centreline as segments, in metres (scene frame)."""

  start: jax.Array      # [B, P, S, 2]
  end: jax.Array        # [B, P, S, 2]
  valid: jax.Array      # [B, P, S]
  arc_start: jax.Array  # [B, P, S] arc length of each segment's start along its centreline (m)



def centerlines(scene: datatypes.Scene) -> Centerlines:
  """The segments between consecutive valid centre points of each polygon (lanes and crosswalks): the
  centre polyline's K/3 - 1 segments only (the other polylines' would be masked out at every query)."""
  line = scene.centerline_slice
  centre = scene.centerline_points_mask[..., line] & scene.pl_valid[..., None]    # [B, P, K/3]
  valid = centre[..., :-1] & centre[..., 1:]
  xy = scene.pt_xy[..., line, :]
  start, end = xy[..., :-1, :], xy[..., 1:, :]
  length = jnp.where(valid, jnp.sqrt(jnp.sum((end - start) ** 2, -1)), 0.0)
  return Centerlines(start, end, valid, jnp.cumsum(length, -1) - length)


def lane_routes(scene: datatypes.Scene, lines: Centerlines) -> jax.Array:
  """`[B, P, P]` length (m) of the shortest path from the start of lane i to the start of lane j.

  The directed lane graph of `scene.pl_edge`: a successor costs lane i's length, a change to the left or
  right neighbour costs nothing; inf where j cannot be reached; 0 on the diagonal (crosswalks and padded
  polygons reach only themselves). All-pairs shortest paths by Floyd-Warshall, P min-plus updates.
  """
  p = scene.pl_edge.shape[-1]
  length = jnp.sum(jnp.where(lines.valid, jnp.sqrt(jnp.sum((lines.end - lines.start) ** 2, -1)), 0.0), -1)
  lane = scene.lane_polygons                                 # [B, P]
  both = lane[:, :, None] & lane[:, None, :]
  edge = scene.pl_edge
  cost = jnp.where(edge == _SUCC, length[:, :, None], jnp.where((edge == _LEFT) | (edge == _RIGHT), 0.0, jnp.inf))
  cost = jnp.where(both, cost, jnp.inf)
  cost = jnp.where(jnp.eye(p, dtype=bool), 0.0, cost)

  def relax(k, d):
    through = jax.lax.dynamic_slice_in_dim(d, k, 1, axis=2) + jax.lax.dynamic_slice_in_dim(d, k, 1, axis=1)
    return jnp.minimum(d, through)

  return jax.lax.fori_loop(0, p, relax, cost)


def relation_features(xy: jax.Array, lines: Centerlines) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Features `[B, Q, P, 8]` of each polygon seen from each query position, distances `[B, Q, P]` (m)
  and the arc length `[B, Q, P]` (m) of the nearest point along the polygon's centreline.

  Args:
    xy: `[B, Q, 2]` query positions in metres (scene frame).
  Features: displacement to the nearest centreline point (dx, dy), the same in the centreline's frame
  (along, across), distance (all / 10 m), log(1 + distance in m), and the centreline direction (cos,
  sin). A polygon without a centreline segment gets distance 1e4 m.
  """
  # Coordinates apart (x and y arrays, not a trailing axis of 2): XLA's CPU backend turns each sum over a
  # trailing axis of 2 into a small product kernel; as plain elementwise work the function and its
  # gradient (the lane pull's) run about 2 and 5 times as fast, the same numbers to float rounding. The
  # segments on a leading axis: the nearest one's argmin and the picks of its values (sums over a one-hot
  # mask) reduce over whole [B, Q, P] slices, vectorised, where over a trailing axis of S XLA's CPU backend
  # runs them (an arg-reduction, a gather per value) one element at a time: the same numbers, 3x as fast.
  seg = lambda a: jnp.moveaxis(a, 2, 0)[:, :, None]                              # noqa: E731  [S, B, 1, P]
  px, py = xy[..., 0][None, :, :, None], xy[..., 1][None, :, :, None]            # [1, B, Q, 1]
  sx, sy = seg(lines.start[..., 0]), seg(lines.start[..., 1])
  ux, uy = seg(lines.end[..., 0]) - sx, seg(lines.end[..., 1]) - sy
  frac = geometry.segment_fraction(px, py, sx, sy, ux, uy)                       # [S, B, Q, P]
  foot_x, foot_y = sx + frac * ux, sy + frac * uy
  d2 = jnp.where(seg(lines.valid), (foot_x - px) ** 2 + (foot_y - py) ** 2, jnp.inf)
  nearest = jnp.argmin(d2, axis=0) == jnp.arange(d2.shape[0])[:, None, None, None]   # one-hot [S, B, Q, P]
  pick = lambda a: jnp.sum(jnp.where(nearest, a, 0.0), axis=0)                  # noqa: E731  [B, Q, P]
  arc = pick(seg(lines.arc_start) + frac * jnp.sqrt(ux * ux + uy * uy))
  foot_x, foot_y, cx, cy = pick(foot_x), pick(foot_y), pick(ux), pick(uy)
  dx, dy = foot_x - px[0], foot_y - py[0]                                        # [B, Q, P]
  norm = jnp.sqrt(cx * cx + cy * cy + 1e-12)
  cx, cy = cx / norm, cy / norm
  has_line = lines.valid.any(-1)[:, None]                                        # [B, 1, P]
  dx, dy = jnp.where(has_line, dx, 1e4), jnp.where(has_line, dy, 1e4)
  dist = jnp.sqrt(dx * dx + dy * dy + 1e-12)
  along = dx * cx + dy * cy
  across = cx * dy - cy * dx
  feats = jnp.stack([dx / FEATURE_SCALE_M, dy / FEATURE_SCALE_M, along / FEATURE_SCALE_M, across / FEATURE_SCALE_M,
                     dist / FEATURE_SCALE_M, jnp.log1p(dist), cx, cy], -1)
  feats = jnp.where(has_line[..., None], jnp.clip(feats, -100.0, 100.0), 0.0)
  return feats, dist, jnp.where(has_line, arc, 0.0)


def route_features(route_m: jax.Array) -> jax.Array:
  """`[..., 3]` from route lengths `[...]` (m, inf where there is none): whether there is a route, its
  length / 10 m (clipped to 300 m) and log(1 + length), zero without a route."""
  has = jnp.isfinite(route_m)
  r = jnp.where(has, route_m, 0.0)
  return jnp.stack([has.astype(r.dtype), jnp.clip(r, -300.0, 300.0) / FEATURE_SCALE_M,
                    jnp.log1p(jnp.maximum(r, 0.0))], -1)
