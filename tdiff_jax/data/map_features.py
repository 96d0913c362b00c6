"""Map polygons of an AV2 map as fixed-shape arrays.

Choices (see DESIGN.md; the official code's are in the reference notes §1.7):
* One polygon per lane segment, two per crosswalk (one per walking direction), lanes first (sorted by
  id), then crosswalks (sorted by id, forward then reverse).
* Each polygon has three polylines, left boundary, right boundary and centreline, each resampled to
  `points_per_polyline` points evenly spaced by arc length (the official code keeps the raw vertices,
  a ragged count). Lane centrelines come from the JSON `centerline` field like the official code; a
  lane without it falls back to av2's interpolated centreline.
* A crosswalk's centreline is the midpoint line of its two edges; for each direction the edge on the
  left of the walking direction is the left boundary.
* Degenerate elements are dropped and counted (the manifest reports them): a lane or crosswalk with a
  boundary or centreline of zero length (a single point, or all points equal) has no direction or width
  to encode, and a drivable area with fewer than three distinct vertices encloses nothing.
* When a map has more polygons than the cap, the polygons whose centreline comes closest to the scene
  origin are kept (a crosswalk's two directions tie, so they are kept or dropped together); the
  number dropped is returned. Valid polygons are packed first, closest first.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from tdiff_jax import datatypes
from tdiff_jax.data import av2_io

_MARK_INDEX = {name: i for i, name in enumerate(datatypes.POINT_TYPES)}
_POLY_TYPE_INDEX = {name: i for i, name in enumerate(datatypes.POLYGON_TYPES)}
_EDGE_INDEX = {name: i for i, name in enumerate(datatypes.EDGE_TYPES)}


@dataclasses.dataclass
class Polygon:
  """One map polygon in city metres, before resampling."""

  left: np.ndarray    # [N, 2]
  right: np.ndarray   # [M, 2]
  center: np.ndarray  # [C, 2]
  pl_type: int
  intersection: int
  left_mark: int
  right_mark: int
  lane_id: int | None  # None for crosswalks
  source_id: int       # the AV2 lane or crosswalk id


def resample_polyline(xy: np.ndarray, n: int) -> np.ndarray:
  """[N, 2] -> [n, 2] points evenly spaced by arc length, ends kept. Degenerate lines repeat."""
  xy = np.asarray(xy, np.float64)
  if len(xy) == 1:
    return np.repeat(xy, n, axis=0)
  seg = np.linalg.norm(np.diff(xy, axis=0), axis=-1)
  cum = np.concatenate([[0.0], np.cumsum(seg)])
  if cum[-1] <= 0:
    return np.repeat(xy[:1], n, axis=0)
  s = np.linspace(0.0, cum[-1], n)
  return np.stack([np.interp(s, cum, xy[:, 0]), np.interp(s, cum, xy[:, 1])], axis=-1)


def resample_polylines(lines: list[np.ndarray], n: int) -> np.ndarray:
  """Vectorised `resample_polyline` over many polylines: list of `[N_i, 2]` -> `[M, n, 2]`."""
  if not lines:
    return np.zeros((0, n, 2))
  lengths = np.array([len(l) for l in lines])
  pts = np.concatenate(lines).astype(np.float64)
  starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
  seg = np.linalg.norm(np.diff(pts, axis=0), axis=-1)
  seg[starts[1:] - 1] = 0.0  # no segment between the end of one polyline and the next
  cum = np.concatenate([[0.0], np.cumsum(seg)])
  cum_local = cum - np.repeat(cum[starts], lengths)
  total = cum_local[starts + lengths - 1]  # [M]
  # Offset each polyline's arc length so one sorted array serves a single searchsorted.
  big = float(total.max()) + 1.0
  line = np.repeat(np.arange(len(lines)), lengths)
  key = cum_local + line * big
  target = np.linspace(0.0, 1.0, n)[None] * total[:, None]  # [M, n]
  tkey = target + (np.arange(len(lines)) * big)[:, None]
  hi = np.searchsorted(key, tkey.ravel(), side="left").reshape(target.shape)
  hi = np.clip(hi, starts[:, None] + 1, (starts + lengths - 1)[:, None])
  hi = np.maximum(hi, starts[:, None])  # single-point polylines
  lo = np.maximum(hi - 1, starts[:, None])
  span = key[hi] - key[lo]
  w = np.where(span > 0, (tkey - key[lo]) / np.where(span > 0, span, 1.0), 0.0)
  w = np.clip(w, 0.0, 1.0)[..., None]
  return pts[lo] * (1 - w) + pts[hi] * w


def _has_length(xy: np.ndarray) -> bool:
  """Whether a polyline `[N, 2]` has two distinct points (a direction and a length)."""
  xy = np.asarray(xy)
  if len(xy) < 2:
    return False
  (x0, y0), (x1, y1) = xy[0].tolist(), xy[-1].tolist()
  if (x1 - x0) ** 2 + (y1 - y0) ** 2 > 1e-12:  # the common case, without array arithmetic
    return True
  d = xy - xy[0]
  return bool((np.einsum("ij,ij->i", d, d) > 1e-12).any())  # a point more than 1e-6 m from the first


def is_degenerate(poly: "Polygon") -> bool:
  """A polygon whose left boundary, right boundary or centreline has zero length."""
  return not (_has_length(poly.left) and _has_length(poly.right) and _has_length(poly.center))


def polyline_headings(xy: np.ndarray) -> np.ndarray:
  """[..., n, 2] -> [..., n] tangent directions (central differences, one-sided at the ends)."""
  d = np.gradient(xy, axis=-2)
  return np.arctan2(d[..., 1], d[..., 0])


def lane_polygons(raw: av2_io.RawScenario) -> list[Polygon]:
  """The map's lanes by id, each with the JSON centreline (av2's inferred one where the JSON has none)."""
  out = []
  polylines = raw.polylines
  for lane_id in sorted(raw.lanes):
    lane = raw.lanes[lane_id]
    center = polylines.lane_center.get(lane_id)
    if center is None or len(center) < 2:
      center = raw.static_map.get_lane_segment_centerline(lane_id)[:, :2]
    out.append(Polygon(
        left=polylines.lane_left[lane_id],
        right=polylines.lane_right[lane_id],
        center=np.asarray(center, np.float64),
        pl_type=_POLY_TYPE_INDEX[lane.lane_type],
        intersection=1 if lane.is_intersection else 0,
        left_mark=_MARK_INDEX[lane.left_mark_type],
        right_mark=_MARK_INDEX[lane.right_mark_type],
        lane_id=lane_id,
        source_id=lane_id,
    ))
  return out


def crosswalk_polygons(polylines: av2_io.MapPolylines) -> list[Polygon]:
  out = []
  for pc_id in sorted(polylines.crosswalk_edges):
    e1, e2 = polylines.crosswalk_edges[pc_id]
    if np.dot(e1[-1] - e1[0], e2[-1] - e2[0]) < 0:  # av2 says "nominally" parallel; make sure
      e2 = e2[::-1]
    n = max(2, int(np.ceil(np.linalg.norm(e1[-1] - e1[0]) / 2.0)) + 1)  # ~2 m spacing, as lanes
    center = 0.5 * (resample_polyline(e1, n) + resample_polyline(e2, n))
    forward = center[-1] - center[0]
    offset = e1.mean(0) - center.mean(0)
    e1_is_left = forward[0] * offset[1] - forward[1] * offset[0] > 0
    left, right = (e1, e2) if e1_is_left else (e2, e1)
    cw = _POLY_TYPE_INDEX["PEDESTRIAN"]
    mark = _MARK_INDEX["CROSSWALK"]
    na = datatypes.INTERSECTION_FLAGS.index("NOT_APPLICABLE")
    out.append(Polygon(left, right, center, cw, na, mark, mark, None, pc_id))
    # Walking the other way swaps the sides.
    out.append(Polygon(right[::-1], left[::-1], center[::-1], cw, na, mark, mark, None, pc_id))
  return out


def map_polygons(raw: av2_io.RawScenario) -> tuple[list[Polygon], int]:
  """The map's lanes and crosswalks, degenerate ones dropped, and the number of AV2 elements dropped
  (a crosswalk counts once, though it gives two polygons)."""
  lanes = lane_polygons(raw)
  good_lanes = [p for p in lanes if not is_degenerate(p)]
  crosswalks = crosswalk_polygons(raw.polylines)
  good_crosswalks = [p for p in crosswalks if not is_degenerate(p)]
  dropped = len(lanes) - len(good_lanes) + (len(crosswalks) - len(good_crosswalks)) // 2
  return good_lanes + good_crosswalks, dropped


def map_bounds(polylines: av2_io.MapPolylines) -> tuple[np.ndarray, np.ndarray]:
  """`[2]` lower and upper corners of the bounding box of every map element (lane boundaries, crosswalk
  edges, drivable areas), city metres."""
  pts = [*polylines.lane_left.values(), *polylines.lane_right.values(),
         *(e for edges in polylines.crosswalk_edges.values() for e in edges), *polylines.drivable_areas.values()]
  if not pts:
    raise ValueError("map has no elements")
  pts = np.concatenate(pts)
  return pts.min(0), pts.max(0)


def map_crop_center(polylines: av2_io.MapPolylines) -> np.ndarray:
  """[2] centre of the map's bounding box (`map_bounds`): the scene origin (DESIGN.md)."""
  lo, hi = map_bounds(polylines)
  return 0.5 * (lo + hi)


def near_lane_points(polygons: list[Polygon]) -> tuple[np.ndarray, np.ndarray]:
  """Raw boundary points and centreline points of all polygons, for the in-lane agent test."""
  boundary = np.concatenate([np.concatenate([p.left, p.right]) for p in polygons])
  center = np.concatenate([p.center for p in polygons])
  return boundary, center


def encode_polygons(polygons: list[Polygon], origin: np.ndarray, max_polygons: int,
                    points_per_polyline: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
  """Resamples, orders by distance to the origin, caps and pads the polygons.

  Returns the `pl_*` and `pt_*` arrays of `datatypes.Scene` (positions relative to `origin`) and the
  indices into `polygons` of the kept rows, in row order.
  """
  n = points_per_polyline
  p_cap, k = max_polygons, 3 * n
  num = len(polygons)
  lines = [line for poly in polygons for line in (poly.left, poly.right, poly.center)]
  pts = resample_polylines(lines, n).reshape(num, 3, n, 2) - origin
  dist = np.linalg.norm(pts[:, 2], axis=-1).min(-1) if num else np.zeros(0)
  order = np.argsort(dist, kind="stable")[:p_cap]
  m = len(order)

  out = {
      "pl_xy": np.zeros((p_cap, 2), np.float32),
      "pl_heading": np.zeros((p_cap,), np.float32),
      "pl_type": np.zeros((p_cap,), np.int32),
      "pl_intersection": np.zeros((p_cap,), np.int32),
      "pl_valid": np.zeros((p_cap,), bool),
      "pt_xy": np.zeros((p_cap, k, 2), np.float32),
      "pt_heading": np.zeros((p_cap, k), np.float32),
      "pt_type": np.zeros((p_cap, k), np.int32),
      "pt_side": np.zeros((p_cap, k), np.int32),
      "pt_valid": np.zeros((p_cap, k), bool),
  }
  if m == 0:
    return out, order
  sel = pts[order]  # [m, 3, n, 2]
  center = sel[:, 2]
  out["pl_xy"][:m] = center[:, 0]
  d0 = center[:, 1] - center[:, 0]
  out["pl_heading"][:m] = np.arctan2(d0[:, 1], d0[:, 0])
  out["pl_valid"][:m] = True
  out["pt_xy"][:m] = sel.reshape(m, k, 2)
  out["pt_heading"][:m] = polyline_headings(sel).reshape(m, k)
  out["pt_valid"][:m] = True
  out["pt_side"][:m] = np.repeat(np.arange(3), n)[None]
  centre_mark = _MARK_INDEX["CENTERLINE"]
  kept = [polygons[i] for i in order]
  out["pl_type"][:m] = [poly.pl_type for poly in kept]
  out["pl_intersection"][:m] = [poly.intersection for poly in kept]
  marks = np.array([(poly.left_mark, poly.right_mark, centre_mark) for poly in kept])       # [m, 3]
  out["pt_type"][:m] = np.repeat(marks, n, axis=1)
  return out, order


def topology(row_lane_ids: list[int | None], lanes: dict[int, av2_io.LaneAttributes],
             max_polygons: int) -> np.ndarray:
  """[P, P] int8 `pl_edge` between kept rows (lane id per row, None for crosswalks).

  References to lanes that were not kept, or that lie outside the map crop, are dropped.
  """
  edge = np.zeros((max_polygons, max_polygons), np.int8)
  row_of = {lane_id: r for r, lane_id in enumerate(row_lane_ids) if lane_id is not None}
  for r, lane_id in enumerate(row_lane_ids):
    if lane_id is None:
      continue
    lane = lanes[lane_id]
    relations = [(j, "PRED") for j in lane.predecessors] + [(j, "SUCC") for j in lane.successors]
    if lane.left_neighbor_id is not None:
      relations.append((lane.left_neighbor_id, "LEFT"))
    if lane.right_neighbor_id is not None:
      relations.append((lane.right_neighbor_id, "RIGHT"))
    for other, kind in relations:
      c = row_of.get(other)
      if c is not None:
        edge[r, c] = _EDGE_INDEX[kind]
  return edge


def _three_distinct_vertices(ring: np.ndarray) -> bool:
  """Whether `ring` `[N, 2]` has at least three distinct vertices at the micrometre: what
  `len(np.unique(np.round(ring, 6), axis=0)) >= 3` says, without its sort of the rows."""
  r = np.round(ring, 6)
  if not np.isfinite(r).all():  # NaN rows: leave their counting to np.unique
    return len(np.unique(r, axis=0)) >= 3
  other = (r != r[0]).any(-1)                              # rows unlike the first
  if not other.any():
    return False
  return bool((other & (r != r[np.argmax(other)]).any(-1)).any())   # and unlike the first other one


def encode_drivable_areas(polylines: av2_io.MapPolylines, origin: np.ndarray, max_areas: int,
                          max_vertices: int) -> tuple[dict[str, np.ndarray], int, int, int]:
  """Drivable-area polygons as `[D, V, 2]` open rings relative to `origin`.

  Rings longer than `max_vertices` are resampled evenly along their perimeter; areas beyond the cap
  are dropped farthest first; rings with fewer than three distinct vertices are dropped as degenerate.
  Returns the arrays, the number dropped by the cap, the number resampled and the number degenerate.
  """
  rings, degenerate = [], 0
  for da_id in sorted(polylines.drivable_areas):
    ring = polylines.drivable_areas[da_id] - origin
    ring = np.concatenate([ring, ring[:1]])  # closed, as av2's DrivableArea holds it
    if len(ring) > 1 and np.allclose(ring[0], ring[-1]):
      ring = ring[:-1]  # we store it open
    if not _three_distinct_vertices(ring):
      degenerate += 1
      continue
    rings.append(ring)
  dist = np.array([np.linalg.norm(r, axis=-1).min() for r in rings]) if rings else np.zeros(0)
  order = np.argsort(dist, kind="stable")[:max_areas]
  dropped = len(rings) - len(order)
  resampled = 0
  xy = np.zeros((max_areas, max_vertices, 2), np.float32)
  valid = np.zeros((max_areas, max_vertices), bool)
  for row, i in enumerate(order):
    ring = rings[i]
    if len(ring) > max_vertices:
      closed = np.concatenate([ring, ring[:1]])
      ring = resample_polyline(closed, max_vertices + 1)[:-1]
      resampled += 1
    xy[row, :len(ring)] = ring
    valid[row, :len(ring)] = True
  return {"da_xy": xy, "da_valid": valid}, dropped, resampled, degenerate
