"""Realism metrics of high-level scenarios (paper §V-B, Table I), under two conventions.

Everything is computed for one endpoint at a time (token 0 initial, token 1 goal) from positions in
metres, speeds, headings, agent types and masks, jit-able, masked, with no Python loop over agents.
`state_accumulators` turns a batch into sums, counts and histogram counts; accumulators of many
batches add up (`add`), so distributions are pooled over a whole split; `summarize` turns a model's
and the ground truth's accumulators into the table's numbers.

Conventions (every printed number says which):

**official**: the official code's (reference notes §5), so numbers sit next to the paper's Table I.
* Collision: another agent's centre within 2 m (1 m for a pedestrian-pedestrian pair; PathDiffuser's
  rule, which the official code's pedestrian exception intends). Rate over all agents.
* Off-road: no centreline point (crosswalk centrelines included) within 4 m.
* Near. edge: mean distance to the nearest centreline point.
  The official code measures to the raw JSON centreline vertices, about 2 m apart; our polylines are
  resampled to 10 points (11 m apart on a 100 m lane), so each centreline segment is subdivided
  `OFFICIAL_POINT_SUBDIVISIONS` times to give points at a similar spacing.
* JSD: Jensen-Shannon *distance* (sqrt of the divergence, natural log) between normalised histograms;
  values outside the bins are dropped (`torch.histc`). Bins: speed 50 on [0, 50] m/s; lateral deviation
  (distance to the nearest centreline point) 30 on [0, 3] m; local density (distances to the up to 5
  nearest agents, pooled) 150 on [0, 150] m; nearest distance 250 on [0, 250] m, 0 for an agent alone.

**strict**: closer to other scene-generation work (WOSAC, Scenario Dreamer).
* Collision: oriented bounding boxes overlap (separating-axis test) with the `datatypes.AGENT_BOX_SIZE_M`
  table (length x width; AV2 has no sizes; the values of av2's visualiser and ScenarioNet's AV2 converter).
* Off-road: the centre lies outside every drivable-area polygon. Agents outside the map crop (the
  bounding box of the map's points) are excluded from it and counted (`outside_map`).
* Near. edge and lateral deviation: distance to the nearest lane centreline *segment* (crosswalks
  excluded).
* JSD: Jensen-Shannon *divergence* (natural log), the same bins, out-of-range values clipped into the
  end bins; an agent alone has no nearest distance or density (excluded).

Map metrics (off-road, near. edge, lateral deviation) are taken over road users (every type but
pedestrians, who walk on sidewalks; the official code keeps vehicles only); collisions and the
distributions of speed, density and nearest distance over all agents.

Infilling metrics (Table II): `displacement_errors` (ADE, FDE) and `summarize_displacement_errors` (per
hard-constraint mode, with the miss rate at 2 m); `tdiff_jax.infilling.infill_errors` runs the infiller
in every mode and feeds them.

Edge cases: a scene with no agents adds nothing; one agent alone never collides; a histogram with no
mass gives a JSD of NaN (printed as "n/a"), as does a rate with no agents.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from tdiff_jax import datatypes, geometry
from tdiff_jax.datatypes import CENTER, CROSSWALK, PEDESTRIAN

CONVENTIONS = ("official", "strict")

OFFICIAL_COLLISION_M = 2.0
OFFICIAL_PEDESTRIAN_COLLISION_M = 1.0
OFFICIAL_OFFROAD_M = 4.0
DENSITY_NEIGHBOURS = 5
OFFICIAL_POINT_SUBDIVISIONS = 4

# name -> (bins, upper edge); every histogram starts at 0.
HISTOGRAMS = {"speed": (50, 50.0), "lateral_deviation": (30, 3.0), "local_density": (150, 150.0),
              "nearest_distance": (250, 250.0)}
RATES = ("collision", "offroad", "near_edge")


def _histogram(values: jax.Array, mask: jax.Array, name: str, clip: bool) -> jax.Array:
  """Counts `[bins]` of the masked values; out of range dropped (official) or clipped (strict)."""
  bins, top = HISTOGRAMS[name]
  width = top / bins
  idx = jnp.floor(values / width).astype(jnp.int32)
  if clip:
    idx = jnp.clip(idx, 0, bins - 1)
  else:  # torch.histc includes the upper edge in the last bin
    idx = jnp.where(values == top, bins - 1, idx)
    mask = mask & (values >= 0) & (idx < bins)
  return jnp.zeros(bins, jnp.float32).at[jnp.clip(idx, 0, bins - 1).reshape(-1)].add(
      mask.reshape(-1).astype(jnp.float32))


def _map_distances(xy: jax.Array, scene: datatypes.Scene) -> tuple[jax.Array, jax.Array]:
  """Per agent `[B, A]`: distance to the nearest centreline point (crosswalks included, official) and
  to the nearest lane-centreline segment (crosswalks excluded, strict); inf without any.

  Both come from one projection onto every centreline segment: the segment distance clamps the
  projection to [0, 1]; the point distance rounds it to the nearest of the segment's subdivision
  points (on a line, the nearest of a set of points is the one nearest the projection).
  """
  b = xy.shape[0]
  centre = scene.centerline_points_mask                                     # [B, P, K]
  in_seg = centre[..., 1:] & centre[..., :-1]                               # [B, P, K-1]
  lane = scene.lane_polygons[..., None]
  start = scene.pt_xy[:, :, :-1].reshape(b, 1, -1, 2)
  seg = scene.pt_xy[:, :, 1:].reshape(b, 1, -1, 2) - start
  q = xy[:, :, None]                                                        # [B, A, 1, 2]
  t = geometry.segment_fraction(q[..., 0], q[..., 1], start[..., 0], start[..., 1], seg[..., 0], seg[..., 1])
  s = OFFICIAL_POINT_SUBDIVISIONS
  dist = lambda tt: jnp.sqrt(jnp.sum((start + tt[..., None] * seg - q) ** 2, -1) + 1e-12)  # noqa: E731
  d_pt = jnp.where(in_seg.reshape(b, 1, -1), dist(jnp.round(t * s) / s), jnp.inf).min(-1)
  d_seg = jnp.where((in_seg & lane).reshape(b, 1, -1), dist(t), jnp.inf).min(-1)
  return d_pt, d_seg


def _inside_map(xy: jax.Array, scene: datatypes.Scene) -> jax.Array:
  """`[B, A]`: inside the bounding box of the map's points (the map crop)."""
  b = xy.shape[0]
  pts = jnp.concatenate([scene.pt_xy.reshape(b, -1, 2), scene.da_xy.reshape(b, -1, 2)], 1)
  ok = jnp.concatenate([scene.pt_valid.reshape(b, -1), scene.da_valid.reshape(b, -1)], 1)[..., None]
  lo = jnp.where(ok, pts, jnp.inf).min(1)
  hi = jnp.where(ok, pts, -jnp.inf).max(1)
  return jnp.all((xy >= lo[:, None]) & (xy <= hi[:, None]), -1)


def state_accumulators(xy: jax.Array, speed: jax.Array, heading: jax.Array, scene: datatypes.Scene,
                       valid: jax.Array | None = None) -> dict:
  """Sums, counts and histograms of one endpoint of a batch, for both conventions.

  Args:
    xy: `[B, A, 2]` positions (m, scene frame). speed: `[B, A]` m/s. heading: `[B, A]` rad (boxes).
    scene: the batch's scenes (map, `agent_type`; `agent_valid` unless `valid` is given).
    valid: `[B, A]` which agents exist (default `scene.agent_valid`).
  Returns a flat dict of float32 arrays: `{convention}/{metric}_sum`, `..._count`, `{convention}/hist_{name}`
  and `strict/outside_map`.
  """
  valid = scene.agent_valid if valid is None else valid
  agent_type = scene.agent_type
  a = valid.shape[-1]
  f32 = lambda x: jnp.sum(x.astype(jnp.float32))  # noqa: E731
  road = valid & (agent_type != PEDESTRIAN)  # `scene.road_users` unless `valid` is given
  out = {}

  # Pairs.
  pair = geometry.pair_mask(valid)
  d = jnp.sqrt(jnp.sum((xy[:, :, None] - xy[:, None]) ** 2, -1) + 1e-12)     # [B, A, A]
  ped_pair = (agent_type == PEDESTRIAN)[:, :, None] & (agent_type == PEDESTRIAN)[:, None, :]
  limit = jnp.where(ped_pair, OFFICIAL_PEDESTRIAN_COLLISION_M, OFFICIAL_COLLISION_M)
  hit_official = (pair & (d < limit)).any(-1)
  corners = geometry.box_corners(xy, heading, geometry.box_sizes(agent_type))
  hit_strict = (pair & geometry.boxes_overlap(corners, heading)).any(-1)
  for conv, hit in (("official", hit_official), ("strict", hit_strict)):
    out[f"{conv}/collision_sum"] = f32(hit & valid)
    out[f"{conv}/collision_count"] = f32(valid)

  # Map.
  d_pt, d_seg = _map_distances(xy, scene)
  off_official = road & ~(d_pt <= OFFICIAL_OFFROAD_M)
  has_area = scene.da_valid.any(axis=(-1, -2))[:, None]
  inside_map = _inside_map(xy, scene)
  judged = road & inside_map & has_area
  off_strict = judged & ~geometry.inside_drivable_area(xy, scene)
  out["official/offroad_sum"], out["official/offroad_count"] = f32(off_official), f32(road)
  out["strict/offroad_sum"], out["strict/offroad_count"] = f32(off_strict), f32(judged)
  out["strict/outside_map"] = f32(road & ~inside_map)
  for conv, dist in (("official", d_pt), ("strict", d_seg)):
    ok = road & jnp.isfinite(dist)
    out[f"{conv}/near_edge_sum"] = jnp.sum(jnp.where(ok, dist, 0.0))
    out[f"{conv}/near_edge_count"] = f32(ok)

  # Distributions.
  d_other = jnp.where(pair, d, jnp.inf)
  nearest = d_other.min(-1)
  alone = valid & ~pair.any(-1)
  k = min(DENSITY_NEIGHBOURS, max(a - 1, 1))
  neg, _ = jax.lax.top_k(-d_other, k)
  knn, knn_ok = -neg, jnp.isfinite(neg) & valid[..., None]
  for conv, clip in (("official", False), ("strict", True)):
    out[f"{conv}/hist_speed"] = _histogram(speed, valid, "speed", clip)
    lat = d_pt if conv == "official" else d_seg
    out[f"{conv}/hist_lateral_deviation"] = _histogram(lat, road & jnp.isfinite(lat), "lateral_deviation", clip)
    out[f"{conv}/hist_local_density"] = _histogram(jnp.where(knn_ok, knn, 0.0), knn_ok, "local_density", clip)
  out["official/hist_nearest_distance"] = _histogram(jnp.where(alone, 0.0, jnp.where(valid, nearest, 0.0)), valid,
                                                     "nearest_distance", False)
  out["strict/hist_nearest_distance"] = _histogram(jnp.where(valid & ~alone, nearest, 0.0), valid & ~alone,
                                                   "nearest_distance", True)
  return out


def add(acc: dict | None, new: dict) -> dict:
  """Adds two accumulator dicts (numpy, on the host)."""
  new = {k: np.asarray(v, np.float64) for k, v in new.items()}
  if acc is None:
    return new
  return {k: acc[k] + new[k] for k in acc}


def js_divergence_terms(p: np.ndarray, q: np.ndarray) -> np.ndarray:
  """Each bin's term of the Jensen-Shannon divergence (natural log) of two non-empty histograms (normalised
  here): 0.5 p log(p / m) + 0.5 q log(q / m), m their mixture; the terms sum to `js_divergence`."""
  p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
  p, q = p / p.sum(), q / q.sum()
  m = 0.5 * (p + q)
  kl = lambda x: np.where(x > 0, x * np.log(np.where(x > 0, x, 1.0) / np.where(m > 0, m, 1.0)), 0.0)  # noqa: E731
  return 0.5 * kl(p) + 0.5 * kl(q)


def js_divergence(p: np.ndarray, q: np.ndarray) -> float:
  """Jensen-Shannon divergence (natural log) of two histograms (normalised here); NaN if either is empty."""
  if np.sum(p) <= 0 or np.sum(q) <= 0:
    return float("nan")
  return max(float(np.sum(js_divergence_terms(p, q))), 0.0)


def js_distance(p: np.ndarray, q: np.ndarray) -> float:
  """scipy's `jensenshannon` (natural log): the square root of the divergence."""
  return math.sqrt(js_divergence(p, q))


def summarize(acc: dict, reference: dict | None, convention: str) -> dict:
  """One Table I row: collision and off-road rates (%), near. edge (m) and, against `reference`
  (the ground truth's accumulators; None for the GT row), the four JSDs."""
  def rate(name, scale):
    count = acc[f"{convention}/{name}_count"]
    return float(scale * acc[f"{convention}/{name}_sum"] / count) if count > 0 else float("nan")

  row = {"collision_rate_pct": rate("collision", 100.0), "offroad_rate_pct": rate("offroad", 100.0),
         "near_edge_m": rate("near_edge", 1.0), "agents": int(acc[f"{convention}/collision_count"])}
  if convention == "strict":
    row["outside_map"] = int(acc["strict/outside_map"])
  jsd = js_distance if convention == "official" else js_divergence
  for name in HISTOGRAMS:
    row[f"jsd_{name}"] = (jsd(acc[f"{convention}/hist_{name}"], reference[f"{convention}/hist_{name}"])
                          if reference is not None else None)
  return row


# Goal reachability (the paper's claim of feasible initial/goal pairs). Host-side numpy, per scene.
HORIZON_S = 6.0             # AV2 steps 50 -> 109 at 10 Hz
REACH_SLACK_M = 10.0        # on top of the horizon times the faster endpoint speed
REACH_BACKWARD_M = 2.0      # a goal this far behind the start on the same lane still counts (stopped agents)
LANE_CANDIDATE_M = 0.5      # lanes within the nearest lane's distance + this are all candidates (overlaps)
ON_LANE_M = OFFICIAL_OFFROAD_M  # an endpoint farther than this from every lane is on no lane

_SUCC, _LEFT, _RIGHT = (datatypes.EDGE_TYPES.index(n) for n in ("SUCC", "LEFT", "RIGHT"))


def _lane_graph(scene) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
  """One scene's lanes: indices `[L]`, centreline points `[L, n, 2]` and validity, and the shortest
  path length `[L, L]` from the start of lane i to the start of lane j (successors cost lane i's length,
  lane changes to a left or right neighbour cost nothing; inf if unreachable)."""
  from scipy.sparse.csgraph import shortest_path

  lanes = np.flatnonzero(np.asarray(scene.pl_valid) & (np.asarray(scene.pl_type) != CROSSWALK))
  centre = (np.asarray(scene.pt_valid) & (np.asarray(scene.pt_side) == CENTER))[lanes]      # [L, K]
  pts = np.asarray(scene.pt_xy)[lanes]                                                     # [L, K, 2]
  seg = np.linalg.norm(np.diff(pts, axis=1), axis=-1) * (centre[:, 1:] & centre[:, :-1])
  length = seg.sum(-1)
  edge = np.asarray(scene.pl_edge)[np.ix_(lanes, lanes)]
  weights = np.where(edge == _SUCC, np.maximum(length[:, None], 1e-3),
                     np.where((edge == _LEFT) | (edge == _RIGHT), 1e-6, 0.0))   # 0 = no edge for scipy
  dist = shortest_path(weights, method="D", directed=True)
  return lanes, pts, centre, dist


def _project(xy: np.ndarray, pts: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Distance `[N, L]` from points `[N, 2]` to each lane's centreline and the arc length of the foot."""
  start, end = pts[:, :-1], pts[:, 1:]                                       # [L, S, 2]
  ok = centre[:, 1:] & centre[:, :-1]
  u = end - start
  seg_len = np.linalg.norm(u, axis=-1)
  cum = np.concatenate([np.zeros_like(seg_len[:, :1]), np.cumsum(seg_len * ok, -1)[:, :-1]], -1)
  rel = xy[:, None, None] - start[None]                                      # [N, L, S, 2]
  t = np.clip(np.sum(rel * u, -1) / np.maximum(seg_len ** 2, 1e-9), 0.0, 1.0)
  d = np.linalg.norm(rel - t[..., None] * u, axis=-1)
  d = np.where(ok[None], d, np.inf)
  best = d.argmin(-1)                                                        # [N, L]
  dist = np.take_along_axis(d, best[..., None], -1)[..., 0]
  arc = np.take_along_axis(cum[None] + t * seg_len[None], best[..., None], -1)[..., 0]
  return dist, arc


REACHABILITY_COUNTS = ("reachable", "road_users", "pedestrians", "off_lane", "lane_width_off", "no_route", "behind",
                       "too_far")
REACHABILITY_FAILURES = REACHABILITY_COUNTS[3:]


def goal_reachability(state: np.ndarray, scene, valid: np.ndarray | None = None) -> dict:
  """Counts for one scene: road users whose goal lies on a lane reachable from their initial lane.

  Args:
    state: `[A, 2, >=3]` x, y (m, scene frame) and speed (m/s) of the initial and goal tokens.
    scene: one unbatched `datatypes.Scene` (numpy or JAX arrays).
    valid: `[A]` which agents exist (default `scene.agent_valid`).
  An agent counts as reachable when both endpoints lie within `ON_LANE_M` of a lane centreline and, for
  some pair of candidate lanes (every lane within `LANE_CANDIDATE_M` of the nearest, so overlapping
  lanes in junctions all count), the path along the directed lane graph (successors, lane changes)
  from the initial foot point to the goal's is between -`REACH_BACKWARD_M` and
  `HORIZON_S` x the faster endpoint speed + `REACH_SLACK_M`. Pedestrians are excluded and counted.
  Returns ints under `REACHABILITY_COUNTS`: "reachable", "road_users", "pedestrians" and why the other
  road users are not reachable, each counted once, in this order: "off_lane" (an endpoint farther than
  `ON_LANE_M` from every lane), "lane_width_off" (reachable if every lane within `ON_LANE_M` of each
  endpoint were a candidate: an endpoint on the neighbouring or opposite lane), "no_route" (no route
  between the candidate lanes), "behind" (every route puts the goal more than `REACH_BACKWARD_M` behind
  the start) and "too_far" (the rest: no route within the distance the speeds allow).
  """
  valid = np.asarray(scene.agent_valid if valid is None else valid, bool)
  agent_type = np.asarray(scene.agent_type)
  road = valid & (agent_type != PEDESTRIAN)
  out = dict.fromkeys(REACHABILITY_COUNTS, 0)
  out.update(road_users=int(road.sum()), pedestrians=int((valid & (agent_type == PEDESTRIAN)).sum()))
  if not road.any():
    return out
  state = np.asarray(state, np.float64)[road]
  lanes, pts, centre, path = _lane_graph(scene)
  if not len(lanes):
    out["off_lane"] = out["road_users"]
    return out
  d0, s0 = _project(state[:, 0, :2], pts, centre)                             # [N, L]
  d1, s1 = _project(state[:, 1, :2], pts, centre)
  on_lane = (d0.min(-1) <= ON_LANE_M) & (d1.min(-1) <= ON_LANE_M)
  c0 = d0 <= d0.min(-1, keepdims=True) + LANE_CANDIDATE_M                    # candidate lanes [N, L]
  c1 = d1 <= d1.min(-1, keepdims=True) + LANE_CANDIDATE_M
  along = path[None] - s0[:, :, None] + s1[:, None, :]                       # [N, L0, L1]
  limit = HORIZON_S * np.maximum(state[:, 0, 2], state[:, 1, 2]) + REACH_SLACK_M
  in_range = (along >= -REACH_BACKWARD_M) & (along <= limit[:, None, None])
  pair = c0[:, :, None] & c1[:, None, :]
  reach = on_lane & (in_range & pair).any(axis=(1, 2))
  # Why the others are not: the first reason that applies.
  near = (d0 <= ON_LANE_M)[:, :, None] & (d1 <= ON_LANE_M)[:, None, :]
  routed = np.isfinite(along) & pair
  lane_width_off = on_lane & ~reach & (in_range & near).any(axis=(1, 2))
  rest = on_lane & ~reach & ~lane_width_off
  no_route = rest & ~routed.any(axis=(1, 2))
  behind = rest & ~no_route & ~(routed & (along >= -REACH_BACKWARD_M)).any(axis=(1, 2))
  out.update(reachable=int(reach.sum()), off_lane=int((~on_lane).sum()), lane_width_off=int(lane_width_off.sum()),
             no_route=int(no_route.sum()), behind=int(behind.sum()), too_far=int((rest & ~no_route & ~behind).sum()))
  return out


def reachability_pct(counts: dict) -> float:
  """`goal_reachable_pct` of summed `goal_reachability` counts (NaN without road users)."""
  return 100.0 * counts["reachable"] / counts["road_users"] if counts["road_users"] else float("nan")


# Infilling (Table II).
MISS_THRESHOLD_M = 2.0


def displacement_errors(pred: jax.Array, target: jax.Array, valid: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
  """Per agent: ADE `[...]` (mean L2 error over valid steps), FDE (error at the last valid step) and
  whether it has any valid step. `pred`, `target` `[..., H, 2]`, `valid` `[..., H]`."""
  err = jnp.sqrt(jnp.sum((pred - target) ** 2, -1) + 1e-12)
  err = jnp.where(valid, err, 0.0)
  count = valid.sum(-1)
  ade = err.sum(-1) / jnp.maximum(count, 1)
  h = valid.shape[-1]
  last = h - 1 - jnp.argmax(valid[..., ::-1], axis=-1)
  fde = jnp.take_along_axis(err, last[..., None], axis=-1)[..., 0]
  return ade, jnp.where(count > 0, fde, 0.0), count > 0


def summarize_displacement_errors(ade, fde, valid, mode_names: tuple[str, ...]) -> dict:
  """Table II: ADE/FDE (m) and miss rate (%, FDE > 2 m) per infill mode from stacked
  `infilling.infill_errors` outputs (`ade`, `fde` `[M, N]`, `valid` `[N]`, any flat agent axis) and the M
  modes' names."""
  ade, fde, valid = np.asarray(ade), np.asarray(fde), np.asarray(valid, bool)
  n = int(valid.sum())
  table = {}
  for m, name in enumerate(mode_names):
    a, f = ade[m][valid], fde[m][valid]
    table[name] = {"ade_m": float(a.mean()) if n else float("nan"),
                   "fde_m": float(f.mean()) if n else float("nan"),
                   "miss_rate_pct": float(100.0 * (f > MISS_THRESHOLD_M).mean()) if n else float("nan"),
                   "agents": n}
  return table
