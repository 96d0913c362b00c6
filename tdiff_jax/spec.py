"""Scenario specs: what must happen in a generated scenario, and whether a sample does it.

A spec (a YAML or JSON file, docs/specs.md) names constrained agents, each with a type and, optionally,
a maneuver, speed ranges, a region and a relation to another constrained agent; `others` says how many
unconstrained agents join them ("auto": the training statistics' count). Entry k of the expanded agents
(counts expanded in order) is agent k of every sample, so the first is the AV2 file's focal track.

Three views of one spec:
* `load` / `parse`: the file, checked whole before anything is compiled (`SpecError` names the key);
* `arrays`: per-agent arrays (`SpecArrays`, traced) that `cost` turns into a differentiable guidance cost on
  the sampler's x0 estimate (the "spec" cost of `sampling.SamplerOptions`), one compiled program for every spec;
* `check`: the exact predicates on a sample's initial and goal states (positions, speeds, headings), per
  named predicate ("ego.maneuver"), and `violating_agents`, the agents a redraw resamples.
`feasibility` says why a map cannot hold a spec (no junction for `region: intersection`, ...).

Meanings (metres, degrees, on the initial and goal states; a relation in the frame of `to`'s initial state,
x forward, y left): maneuver from the initial to the goal heading, left +45 to +135, right -135 to -45,
straight within 20 and moving at least 5 m, u_turn at least 150 either way, stationary moving at most 1 m;
region intersection, the initial state within 30 m of a lane flagged in an intersection, crosswalk within
3 m of a pedestrian crossing; relations ahead / behind (heading within 30, |y| <= 2, x within the distance
ahead / behind), left_lane / right_lane (heading within 30, y 2.5 to 5 on that side, |x| within the
distance), oncoming (heading within 30 of opposite, x within the distance ahead), crossing (heading 60 to
120 off, within the distance), cut_in (in the left or right lane ahead within the distance, and its goal
in `to`'s goal frame at |y| <= 1.5 and x > 0).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from tdiff_jax import datatypes

MANEUVERS = ("any", "left", "right", "straight", "u_turn", "stationary")
REGIONS = ("any", "intersection", "crosswalk")
RELATIONS = ("ahead", "behind", "left_lane", "right_lane", "oncoming", "crossing", "cut_in")
SPEC_KEYS = ("name", "agents", "others")
AGENT_KEYS = ("name", "type", "count", "maneuver", "speed", "region", "relation")
RELATION_KEYS = ("to", "kind", "distance")
SPEED_KEYS = ("initial", "goal")
NO_LIMIT = 1e4          # the upper end of an open range (finite: a cost's gradient stays defined)

INTERSECTION_M = 30.0   # region: intersection
CROSSWALK_M = 3.0       # region: crosswalk
SAME_HEADING = math.cos(math.radians(30))
TURN_SIN = math.sin(math.radians(45))
STRAIGHT_COS = math.cos(math.radians(20))
U_TURN_COS = math.cos(math.radians(150))
CROSSING_COS = math.cos(math.radians(60))
STRAIGHT_MIN_M = 5.0
STATIONARY_MAX_M = 1.0
LANE_Y_M = (2.5, 5.0)   # left_lane / right_lane / cut_in: |y| of the neighbouring lane
SAME_LANE_Y_M = 2.0     # ahead / behind
CUT_IN_GOAL_Y_M = 1.5


class SpecError(ValueError):
  """A spec that cannot be used: the message names the file and the key."""


@dataclasses.dataclass(frozen=True)
class Relation:
  to: int                          # the expanded index of the agent it relates to
  kind: str                        # RELATIONS
  distance: tuple[float, float]    # metres


@dataclasses.dataclass(frozen=True)
class SpecAgent:
  """One constrained agent of the expanded spec."""

  name: str
  type: int                                      # datatypes.AGENT_TYPES index
  maneuver: str = "any"
  speed: tuple[tuple[float, float] | None, tuple[float, float] | None] = (None, None)   # initial, goal (m/s)
  region: str = "any"
  relation: Relation | None = None


@dataclasses.dataclass(frozen=True)
class Spec:
  name: str
  agents: tuple[SpecAgent, ...]   # expanded: entry k is agent k of every sample
  others: int | None              # unconstrained agents; None: from the training statistics ("auto")
  source: str = ""

  def predicates(self) -> list[str]:
    """The named predicates `check` reports, e.g. "ego.maneuver", "oncoming#2.relation"."""
    out = []
    for k, a in enumerate(self.agents):
      label = self.label(k)
      out += [f"{label}.maneuver"] * (a.maneuver != "any")
      out += [f"{label}.speed"] * (a.speed != (None, None))
      out += [f"{label}.region"] * (a.region != "any")
      out += [f"{label}.relation"] * (a.relation is not None)
    return out

  def label(self, k: int) -> str:
    """Agent k's name, numbered where an entry's count repeats it ("oncoming#2")."""
    same = [j for j, a in enumerate(self.agents) if a.name == self.agents[k].name]
    return self.agents[k].name if len(same) == 1 else f"{self.agents[k].name}#{same.index(k) + 1}"


# ---- the file ----------------------------------------------------------------------------------


def load(path: Path | str, max_agents: int | None = None) -> Spec:
  """The spec in a YAML (.yaml, .yml) or JSON file; `max_agents`: the model's agent cap. Raises SpecError."""
  path = Path(path)
  try:
    text = path.read_text()
  except OSError as e:
    raise SpecError(f"{path}: cannot read the spec ({e.strerror or e})") from None
  try:
    if path.suffix.lower() == ".json":
      raw = json.loads(text)
    else:
      import yaml
      raw = yaml.safe_load(text)
  except Exception as e:  # yaml.YAMLError, json.JSONDecodeError: the parser's message says where
    raise SpecError(f"{path}: not valid {'JSON' if path.suffix.lower() == '.json' else 'YAML'}: {e}") from None
  return parse(raw, str(path), max_agents)


def parse(raw: Any, source: str = "spec", max_agents: int | None = None) -> Spec:
  """A spec from its parsed mapping (the file's keys); raises SpecError naming the first bad key."""
  def fail(key: str, problem: str):
    raise SpecError(f"{source}: {key}: {problem}")

  def mapping(value, key, allowed):
    if not isinstance(value, dict):
      fail(key, f"expected a mapping, got {type(value).__name__}")
    for k in value:
      if k not in allowed:
        fail(f"{key}.{k}" if key else str(k), f"unknown key; choose from {', '.join(allowed)}")
    return value

  def choice(value, key, options):
    if value not in options:
      fail(key, f"unknown value {value!r}; choose from {', '.join(options)}")
    return value

  def number_range(value, key):
    if (not isinstance(value, (list, tuple)) or len(value) != 2
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)):
      fail(key, f"expected [low, high] in numbers, got {value!r}")
    lo, hi = float(value[0]), float(value[1])
    if lo < 0 or lo > hi:
      fail(key, f"empty or negative range [{value[0]}, {value[1]}]")
    return lo, hi

  raw = mapping(raw, "", SPEC_KEYS)
  name = raw.get("name", Path(source).stem)
  if not isinstance(name, str) or not name:
    fail("name", "expected a non-empty string")
  entries = raw.get("agents")
  if not isinstance(entries, list) or not entries:
    fail("agents", "expected a non-empty list of agents")
  names = []
  for i, entry in enumerate(entries):
    entry = mapping(entry, f"agents[{i}]", AGENT_KEYS)
    entry_name = entry.get("name", f"agent{i}")
    if not isinstance(entry_name, str) or not entry_name:
      fail(f"agents[{i}].name", "expected a non-empty string")
    if entry_name in names:
      fail(f"agents[{i}].name", f"{entry_name!r} names two entries")
    names.append(entry_name)
  first, counts = {}, []
  for i, entry in enumerate(entries):
    count = entry.get("count", 1)
    if not isinstance(count, int) or isinstance(count, bool) or count < 1:
      fail(f"agents[{i}].count", f"expected a whole number >= 1, got {count!r}")
    first[names[i]] = sum(counts)
    counts.append(count)
  agents = []
  for i, entry in enumerate(entries):
    key = f"agents[{i}]"
    if "type" not in entry:
      fail(f"{key}.type", f"missing; choose from {', '.join(datatypes.AGENT_TYPES)}")
    agent_type = datatypes.AGENT_TYPES.index(choice(entry["type"], f"{key}.type", datatypes.AGENT_TYPES))
    maneuver = choice(entry.get("maneuver", "any"), f"{key}.maneuver", MANEUVERS)
    region = choice(entry.get("region", "any"), f"{key}.region", REGIONS)
    speed = [None, None]
    if "speed" in entry:
      s = mapping(entry["speed"], f"{key}.speed", SPEED_KEYS)
      if not s:
        fail(f"{key}.speed", "give initial and/or goal")
      for t, token in enumerate(SPEED_KEYS):
        if token in s:
          speed[t] = number_range(s[token], f"{key}.speed.{token}")
    relation = None
    if "relation" in entry:
      r = mapping(entry["relation"], f"{key}.relation", RELATION_KEYS)
      for k in ("to", "kind"):
        if k not in r:
          fail(f"{key}.relation.{k}", "missing")
      to = r["to"]
      if to not in first:
        fail(f"{key}.relation.to", f"{to!r} names no agent; the agents are {', '.join(names)}")
      if to == names[i]:
        fail(f"{key}.relation.to", "an agent cannot relate to itself")
      if counts[names.index(to)] != 1:
        fail(f"{key}.relation.to", f"{to!r} has count {counts[names.index(to)]}: relate to an entry of count 1")
      kind = choice(r["kind"], f"{key}.relation.kind", RELATIONS)
      if "distance" not in r:
        fail(f"{key}.relation.distance", "missing: [low, high] in metres")
      relation = Relation(first[to], kind, number_range(r["distance"], f"{key}.relation.distance"))
    agents += [SpecAgent(names[i], agent_type, maneuver, tuple(speed), region, relation)] * counts[i]
  for i, a in enumerate(agents):   # relations must not go round in a circle (placed in their order)
    seen, k = {i}, a.relation.to if a.relation else None
    while k is not None:
      if k in seen:
        fail(f"agents[{names.index(a.name)}].relation.to", "the relations go round in a circle")
      seen.add(k)
      k = agents[k].relation.to if agents[k].relation else None
  others = raw.get("others", "auto")
  if others != "auto" and (not isinstance(others, int) or isinstance(others, bool) or others < 0):
    fail("others", f"expected auto or a whole number >= 0, got {others!r}")
  spec = Spec(name, tuple(agents), None if others == "auto" else others, source)
  if max_agents is not None:
    check_cap(spec, max_agents)
  return spec


def check_cap(spec: Spec, max_agents: int) -> None:
  """Raises SpecError when the spec places more agents than a model's cap `max_agents`."""
  n = len(spec.agents) + (spec.others or 0)
  if n > max_agents:
    key = "agents" if len(spec.agents) > max_agents else "others"
    raise SpecError(f"{spec.source}: {key}: {len(spec.agents)} constrained + {spec.others or 0} other agents: more "
                    f"than the model's cap of {max_agents} agents")


# ---- map geometry the predicates read ----------------------------------------------------------


def _region_points(scene: datatypes.Scene) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
  """`(intersection_xy [N, 2], intersection_valid [N], crosswalk_xy [M, 2], crosswalk_valid [M])` of one
  unbatched scene: centreline points of lanes in an intersection, and every point of the crossings."""
  centre = scene.centerline_slice
  in_junction = scene.lane_polygons & (scene.pl_intersection == 1)
  crossing = scene.pl_valid & (scene.pl_type == datatypes.CROSSWALK)
  return (scene.pt_xy[:, centre].reshape(-1, 2), (scene.pt_valid[:, centre] & in_junction[:, None]).reshape(-1),
          scene.pt_xy.reshape(-1, 2), (scene.pt_valid & crossing[:, None]).reshape(-1))


def _segments_distance(xy: np.ndarray, pts: np.ndarray, valid: np.ndarray) -> np.ndarray:
  """`[Q]` distance of points `xy` `[Q, 2]` to the polyline segments of `pts` `[P, K, 2]` (consecutive valid
  points of one polygon), inf where there are none."""
  a, b = pts[:, :-1], pts[:, 1:]
  seg = (valid[:, :-1] & valid[:, 1:]).reshape(-1)
  a, b = a.reshape(-1, 2)[seg], b.reshape(-1, 2)[seg]
  if not len(a):
    return np.full(len(xy), np.inf)
  ab = b - a
  t = np.clip(np.einsum("qsd,sd->qs", xy[:, None] - a[None], ab) / np.maximum((ab ** 2).sum(-1), 1e-12), 0, 1)
  nearest = a[None] + t[..., None] * ab[None]
  return np.sqrt(((xy[:, None] - nearest) ** 2).sum(-1)).min(-1)


def region_distances(xy: np.ndarray, scene: datatypes.Scene) -> dict[str, np.ndarray]:
  """`{"intersection": [Q], "crosswalk": [Q]}` metres from points `xy` `[Q, 2]` to the nearest lane
  centreline in an intersection and to the nearest pedestrian crossing (0 inside one), on one
  unbatched numpy scene."""
  sc = jax.tree_util.tree_map(np.asarray, scene)
  centre = sc.centerline_slice
  lanes = sc.lane_polygons & (sc.pl_intersection == 1)
  inter = _segments_distance(xy, sc.pt_xy[lanes][:, centre], sc.pt_valid[lanes][:, centre])
  crossings = sc.pl_valid & (sc.pl_type == datatypes.CROSSWALK)
  n = sc.num_points // datatypes.POLYLINES_PER_POLYGON
  cross = np.full(len(xy), np.inf)
  for p in np.flatnonzero(crossings):   # a crossing: its left edge then its right edge reversed, a ring
    left, right = sc.pt_xy[p, :n][sc.pt_valid[p, :n]], sc.pt_xy[p, n:2 * n][sc.pt_valid[p, n:2 * n]]
    ring = np.concatenate([left, right[::-1]])
    if len(ring) < 3:
      continue
    edge = _segments_distance(xy, np.concatenate([ring, ring[:1]])[None], np.ones((1, len(ring) + 1), bool))
    x, y = xy[:, 0:1], xy[:, 1:2]
    x0, y0, x1, y1 = ring[:, 0], ring[:, 1], np.roll(ring[:, 0], -1), np.roll(ring[:, 1], -1)
    crosses = ((y0 > y) != (y1 > y)) & (x < (x1 - x0) * (y - y0) / np.where(y1 == y0, 1e-12, y1 - y0) + x0)
    inside = crosses.sum(-1) % 2 == 1
    cross = np.minimum(cross, np.where(inside, 0.0, edge))
  return {"intersection": inter, "crosswalk": cross}


# ---- the exact predicates -----------------------------------------------------------------------


def _wrap_deg(angle_rad: np.ndarray) -> np.ndarray:
  return np.degrees((angle_rad + np.pi) % (2 * np.pi) - np.pi)


def _in(value, lo_hi) -> bool:
  return bool(lo_hi[0] <= value <= lo_hi[1])


def relation_holds(kind: str, distance: tuple[float, float], state: np.ndarray, heading: np.ndarray,
                   i: int, j: int) -> bool:
  """Whether agent i stands in relation `kind` to agent j; `state` `[A, 2, 3]`, `heading` `[A, 2]` (rad)."""
  c, s = math.cos(heading[j, 0]), math.sin(heading[j, 0])
  d = state[i, 0, :2] - state[j, 0, :2]
  x, y = c * d[0] + s * d[1], -s * d[0] + c * d[1]
  dh = abs(_wrap_deg(heading[i, 0] - heading[j, 0]))
  same = dh <= 30.0
  if kind == "ahead":
    return same and abs(y) <= SAME_LANE_Y_M and _in(x, distance)
  if kind == "behind":
    return same and abs(y) <= SAME_LANE_Y_M and _in(-x, distance)
  if kind in ("left_lane", "right_lane"):
    side = y if kind == "left_lane" else -y
    return same and _in(side, LANE_Y_M) and _in(abs(x), distance)
  if kind == "oncoming":
    return dh >= 150.0 and _in(x, distance)
  if kind == "crossing":
    return 60.0 <= dh <= 120.0 and _in(math.hypot(*d), distance)
  # cut_in
  c1, s1 = math.cos(heading[j, 1]), math.sin(heading[j, 1])
  d1 = state[i, 1, :2] - state[j, 1, :2]
  x1, y1 = c1 * d1[0] + s1 * d1[1], -s1 * d1[0] + c1 * d1[1]
  return same and _in(abs(y), LANE_Y_M) and _in(x, distance) and abs(y1) <= CUT_IN_GOAL_Y_M and x1 > 0.0


def maneuver_holds(maneuver: str, state: np.ndarray, heading: np.ndarray) -> bool:
  """Whether one agent's `state` `[2, 3]` and `heading` `[2]` make the maneuver."""
  dh = float(_wrap_deg(heading[1] - heading[0]))
  moved = float(np.hypot(*(state[1, :2] - state[0, :2])))
  return {"any": True, "left": 45.0 <= dh <= 135.0, "right": -135.0 <= dh <= -45.0,
          "straight": abs(dh) <= 20.0 and moved >= STRAIGHT_MIN_M, "u_turn": abs(dh) >= 150.0,
          "stationary": moved <= STATIONARY_MAX_M}[maneuver]


def check(spec: Spec, state: np.ndarray, heading: np.ndarray, scene: datatypes.Scene) -> dict[str, bool]:
  """The named predicates (`Spec.predicates`) of one sample: `state` `[A, 2, 3]` (x, y in metres in the scene
  frame, speed in m/s), `heading` `[A, 2]` (rad), constrained agent k in row k; `scene` unbatched."""
  state, heading = np.asarray(state, np.float64), np.asarray(heading, np.float64)
  k_all = len(spec.agents)
  regions = region_distances(state[:k_all, 0, :2], scene) if any(a.region != "any" for a in spec.agents) else None
  out = {}
  for k, a in enumerate(spec.agents):
    label = spec.label(k)
    if a.maneuver != "any":
      out[f"{label}.maneuver"] = maneuver_holds(a.maneuver, state[k], heading[k])
    if a.speed != (None, None):
      out[f"{label}.speed"] = all(r is None or _in(state[k, t, 2], r) for t, r in enumerate(a.speed))
    if a.region != "any":
      limit = INTERSECTION_M if a.region == "intersection" else CROSSWALK_M
      out[f"{label}.region"] = bool(regions[a.region][k] <= limit)
    if a.relation is not None:
      r = a.relation
      out[f"{label}.relation"] = relation_holds(r.kind, r.distance, state, heading, k, r.to)
  return out


def violating_agents(spec: Spec, predicates: dict[str, bool], num_agents: int) -> np.ndarray:
  """`[num_agents]` bool: the agents a redraw resamples for the failed `predicates` (`check`'s): the agent
  of each failed predicate, and for a failed relation also the agent it relates to."""
  bad = np.zeros(num_agents, bool)
  for k, a in enumerate(spec.agents):
    label = spec.label(k)
    for what in ("maneuver", "speed", "region", "relation"):
      if not predicates.get(f"{label}.{what}", True):
        bad[k] = True
        if what == "relation":
          bad[a.relation.to] = True
  return bad


# ---- where a spec can hold --------------------------------------------------------------------


def feasibility(spec: Spec, scene: datatypes.Scene) -> list[str]:
  """Why the map of `scene` (unbatched) cannot hold `spec`; empty when it can. Checked: a lane in an
  intersection (region: intersection), a pedestrian crossing (region: crosswalk), a lane path that turns
  by the maneuver's angle within 80 m (left, right, u_turn), lanes in opposite directions (oncoming),
  lanes at 60 to 120 degrees (crossing), and a lane beside a lane of the same direction (left_lane,
  right_lane, cut_in)."""
  sc = jax.tree_util.tree_map(np.asarray, scene)
  lanes = sc.lane_polygons
  centre = sc.centerline_slice
  reasons = []
  regions = {a.region for a in spec.agents}
  if "intersection" in regions and not (lanes & (sc.pl_intersection == 1)).any():
    reasons.append("region intersection: the map has no lane in an intersection")
  if "crosswalk" in regions and not (sc.pl_valid & (sc.pl_type == datatypes.CROSSWALK)).any():
    reasons.append("region crosswalk: the map has no pedestrian crossing")
  turns = {a.maneuver for a in spec.agents} & {"left", "right", "u_turn"}
  if turns:
    found = _turns(sc)
    reasons += [f"maneuver {m}: no lane path of the map turns that way within 80 m" for m in sorted(turns - found)]
  kinds = {a.relation.kind for a in spec.agents if a.relation is not None}
  heads = sc.pt_heading[lanes][:, centre][sc.pt_valid[lanes][:, centre]]   # every lane centreline point's
  if kinds & {"oncoming", "crossing"}:
    h = np.unique(np.round(np.degrees(heads) / 10.0) * 10.0)
    diff = np.abs(_wrap_deg(np.radians(h[:, None] - h[None])))
    if "oncoming" in kinds and not (diff >= 160).any():
      reasons.append("relation oncoming: the map has no lanes in opposite directions")
    if "crossing" in kinds and not ((diff >= 60) & (diff <= 120)).any():
      reasons.append("relation crossing: the map has no lanes that cross")
  if kinds & {"left_lane", "right_lane", "cut_in"}:
    edge = sc.pl_edge[np.ix_(lanes, lanes)]
    if not np.isin(edge, (datatypes.EDGE_TYPES.index("LEFT"), datatypes.EDGE_TYPES.index("RIGHT"))).any():
      reasons.append(f"relation {'/'.join(sorted(kinds & {'left_lane', 'right_lane', 'cut_in'}))}: the map has "
                     "no lane beside a lane of the same direction")
  return reasons


def _turns(sc: datatypes.Scene, reach_m: float = 80.0) -> set[str]:
  """The maneuvers (left, right, u_turn) some lane path of the map makes within `reach_m`: from each lane's
  start, along its successors (depth-first), the heading change at every centreline point."""
  centre = sc.centerline_slice
  lanes = np.flatnonzero(sc.lane_polygons)
  succ = datatypes.EDGE_TYPES.index("SUCC")
  found: set[str] = set()
  for start in lanes:
    h0 = None
    stack = [(start, 0.0, 0)]
    while stack and len(found) < 3:
      p, run, depth = stack.pop()
      pts, heads = sc.pt_xy[p, centre][sc.pt_valid[p, centre]], sc.pt_heading[p, centre][sc.pt_valid[p, centre]]
      if not len(pts):
        continue
      h0 = heads[0] if h0 is None else h0
      dh = _wrap_deg(heads - h0)
      found |= {"left"} if ((dh >= 45) & (dh <= 135)).any() else set()
      found |= {"right"} if ((dh <= -45) & (dh >= -135)).any() else set()
      found |= {"u_turn"} if (np.abs(dh) >= 150).any() else set()
      run += float(np.hypot(*np.diff(pts, axis=0).T).sum())
      if run < reach_m and depth < 6:
        stack += [(q, run, depth + 1) for q in np.flatnonzero(sc.pl_edge[p] == succ)]
  return found


# ---- initial states that hold the spec ---------------------------------------------------------

# Speeds (m/s) of a proposed initial state without a speed range, by agent type.
DEFAULT_SPEED = {"vehicle": (3.0, 12.0), "bus": (3.0, 10.0), "pedestrian": (0.8, 1.6), "cyclist": (2.0, 6.0),
                 "motorcyclist": (3.0, 12.0)}
LANE_TYPES = {"vehicle": ("VEHICLE", "BUS"), "bus": ("VEHICLE", "BUS"), "pedestrian": ("PEDESTRIAN",),
              "cyclist": ("BIKE", "VEHICLE"), "motorcyclist": ("VEHICLE", "BUS")}
POINT_SPACING_M = 1.0
SECONDS = 6.0   # from the initial to the goal state


@dataclasses.dataclass(frozen=True)
class _MapPoints:
  """Points every `POINT_SPACING_M` along the map's centrelines (lanes and crossings) of one scene."""

  xy: np.ndarray        # [N, 2]
  heading: np.ndarray   # [N] rad, the direction of travel
  polygon: np.ndarray   # [N] the polygon's row
  along: np.ndarray     # [N] metres from the polygon's first point
  ptype: np.ndarray     # [N] POLYGON_TYPES index
  length: np.ndarray    # [P] each polygon's centreline length


def _map_points(sc: datatypes.Scene) -> _MapPoints:
  centre = sc.centerline_slice
  xy, heading, polygon, along, ptype = [], [], [], [], []
  length = np.zeros(sc.num_polygons)
  for p in np.flatnonzero(sc.pl_valid):
    pts = sc.pt_xy[p, centre][sc.pt_valid[p, centre]].astype(np.float64)
    if len(pts) < 2:
      continue
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    length[p] = s[-1]
    if s[-1] < 1e-3:
      continue
    at = np.arange(0.0, s[-1], POINT_SPACING_M)
    seg = np.clip(np.searchsorted(s, at, side="right") - 1, 0, len(pts) - 2)
    d = pts[seg + 1] - pts[seg]
    xy.append(np.stack([np.interp(at, s, pts[:, 0]), np.interp(at, s, pts[:, 1])], -1))
    heading.append(np.arctan2(d[:, 1], d[:, 0]))
    polygon.append(np.full(len(at), p))
    along.append(at)
    ptype.append(np.full(len(at), sc.pl_type[p]))
  cat = lambda parts, shape: np.concatenate(parts) if parts else np.zeros(shape)  # noqa: E731
  return _MapPoints(cat(xy, (0, 2)), cat(heading, (0,)), cat(polygon, (0,)).astype(int), cat(along, (0,)),
                    cat(ptype, (0,)).astype(int), length)


def _paths(sc: datatypes.Scene, pts: _MapPoints, n: int, reach_m: float) -> list[np.ndarray]:
  """The lane paths from map point n, each the `[M]` map points along it for `reach_m` (successors
  followed, depth first) or to where the lanes end."""
  succ = datatypes.EDGE_TYPES.index("SUCC")
  out, stack = [], [(pts.polygon[n], pts.along[n], np.zeros(0, int))]
  while stack:
    p, start, path = stack.pop()
    on = np.flatnonzero((pts.polygon == p) & (pts.along >= start))
    path = np.concatenate([path, on[np.argsort(pts.along[on])]])[: int(reach_m / POINT_SPACING_M) + 1]
    nxt = np.flatnonzero(sc.pl_edge[p] == succ)
    if len(path) * POINT_SPACING_M >= reach_m or not len(nxt) or len(out) + len(stack) > 64:
      out.append(path)
    else:
      stack += [(q, 0.0, path) for q in nxt]
  return out


def _route(maneuver: str, pts: _MapPoints, n: int, paths: list[np.ndarray], rng: np.random.Generator
           ) -> np.ndarray | None:
  """The map points where a goal makes `maneuver` from map point n along one of `paths` (drawn among those
  that make it): for a turn, the points turned by its angle; straight, the points at least 5 m on along a
  path that keeps within 20 degrees; None when no path makes it."""
  for i in rng.permutation(len(paths)):
    path = paths[i]
    dh = _wrap_deg(pts.heading[path] - pts.heading[n])
    if maneuver == "straight":
      keep = (np.abs(dh) <= 20).all() and len(path) * POINT_SPACING_M >= STRAIGHT_MIN_M
      at = path[int(STRAIGHT_MIN_M / POINT_SPACING_M):] if keep else path[:0]
    else:
      at = path[{"left": (dh >= 45) & (dh <= 135), "right": (dh <= -45) & (dh >= -135),
                 "u_turn": np.abs(dh) >= 150}[maneuver]]
    if len(at):
      return at
  return None


def _relation_mask(kind: str, distance: tuple[float, float], xy: np.ndarray, heading: np.ndarray,
                   to_xy: np.ndarray, to_heading: float) -> np.ndarray:
  """`[N]` candidates (`xy` `[N, 2]`, `heading` `[N]`) whose initial state stands in relation `kind` to
  the agent at `to_xy`, `to_heading` (the initial-state part of `relation_holds`; cut_in's goal aside)."""
  c, s = math.cos(to_heading), math.sin(to_heading)
  d = xy - to_xy
  x, y = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
  dh = np.abs(_wrap_deg(heading - to_heading))
  lo, hi = distance
  inside = lambda v: (v >= lo) & (v <= hi)  # noqa: E731
  same = dh <= 30.0
  if kind == "ahead":
    return same & (np.abs(y) <= SAME_LANE_Y_M) & inside(x)
  if kind == "behind":
    return same & (np.abs(y) <= SAME_LANE_Y_M) & inside(-x)
  lane = lambda side: (side >= LANE_Y_M[0]) & (side <= LANE_Y_M[1])  # noqa: E731
  if kind == "left_lane":
    return same & lane(y) & inside(np.abs(x))
  if kind == "right_lane":
    return same & lane(-y) & inside(np.abs(x))
  if kind == "oncoming":
    return (dh >= 150.0) & inside(x)
  if kind == "crossing":
    return (dh >= 60.0) & (dh <= 120.0) & inside(np.hypot(d[:, 0], d[:, 1]))
  return same & lane(np.abs(y)) & inside(x)   # cut_in


ROUTE_POINTS = 64   # a placement's route: at most this many points


@dataclasses.dataclass(frozen=True)
class Placement:
  """Where a spec's k constrained agents start, and where their goals hold their maneuver."""

  initial: np.ndarray       # [k, 4] x, y (m, scene frame), speed (m/s), heading (rad)
  route: np.ndarray         # [k, ROUTE_POINTS, 2] m: points where the agent's goal holds its maneuver (or
                            # for cut_in, the lane ahead of the agent it cuts in front of)
  route_heading: np.ndarray  # [k, ROUTE_POINTS] rad, the lane's direction at each route point
  route_valid: np.ndarray   # [k, ROUTE_POINTS]


def relation_order(spec: Spec) -> list[int]:
  """The constrained agents' indices, each after the agent it relates to (`parse` refuses circles)."""
  order = []
  while len(order) < len(spec.agents):
    for k, a in enumerate(spec.agents):
      if k not in order and (a.relation is None or a.relation.to in order):
        order.append(k)
  return order


def propose(spec: Spec, scene: datatypes.Scene, rng: np.random.Generator, tries: int = 20) -> Placement | None:
  """A placement of the spec's k constrained agents on `scene`'s map (unbatched): initial states that hold
  every predicate of the initial states (region, initial speed, relations but cut_in's goal), each turning
  or straight agent where a lane path ahead makes its maneuver within the distance it drives in 6 s (that
  path's points where the goal holds it: its route, which the cost draws its goal to), the agents' boxes
  apart; None when `tries` attempts find none.

  Each agent stands on a centreline of its type's lanes (pedestrians on a crossing, walking across it
  either way), drawn among the points that hold its predicates, nearer ones to its relation's agent
  more likely; its speed drawn in its range (`DEFAULT_SPEED` without one, 0 when stationary)."""
  sc = jax.tree_util.tree_map(np.asarray, scene)
  pts = _map_points(sc)
  if not len(pts.xy):
    return None
  regions = region_distances(pts.xy, sc) if any(a.region != "any" for a in spec.agents) else {}
  order = relation_order(spec)
  size = np.array([datatypes.AGENT_BOX_SIZE_M[datatypes.AGENT_TYPES[a.type]] for a in spec.agents])
  k_all = len(spec.agents)
  for _ in range(tries):
    out = np.zeros((k_all, 4))
    point = np.zeros(k_all, int)
    route = np.zeros((k_all, ROUTE_POINTS, 2))
    route_heading = np.zeros((k_all, ROUTE_POINTS))
    route_valid = np.zeros((k_all, ROUTE_POINTS), bool)

    def set_route(k, at):
      at = at[np.linspace(0, len(at) - 1, min(len(at), ROUTE_POINTS)).round().astype(int)]
      route[k, :len(at)], route_heading[k, :len(at)], route_valid[k, :len(at)] = pts.xy[at], pts.heading[at], True

    for k in order:
      a = spec.agents[k]
      type_name = datatypes.AGENT_TYPES[a.type]
      ok = np.isin(pts.ptype, [datatypes.POLYGON_TYPES.index(t) for t in LANE_TYPES[type_name]])
      heading = pts.heading.copy()
      if type_name == "pedestrian":   # across the crossing, either way
        heading = np.where(rng.random(len(heading)) < 0.5, heading, heading + np.pi)
      if a.region != "any":
        ok &= regions[a.region] <= (INTERSECTION_M if a.region == "intersection" else CROSSWALK_M)
      weight = np.ones(len(ok))
      if a.relation is not None:
        j = a.relation.to
        ok &= _relation_mask(a.relation.kind, a.relation.distance, pts.xy, heading, out[j, :2], out[j, 3])
        weight = 1.0 / (1.0 + np.hypot(*(pts.xy - out[j, :2]).T))
      for j in (j for j in order[:order.index(k)]):   # boxes apart from those placed, taken as parallel
        c, s = math.cos(out[j, 3]), math.sin(out[j, 3])
        d = pts.xy - out[j, :2]
        ok &= ~((np.abs(c * d[:, 0] + s * d[:, 1]) < (size[k, 0] + size[j, 0]) / 2 + 1.0)
                & (np.abs(-s * d[:, 0] + c * d[:, 1]) < (size[k, 1] + size[j, 1]) / 2 + 0.3))
      speed_range = (0.0, 0.0) if a.maneuver == "stationary" else a.speed[0] or DEFAULT_SPEED[type_name]
      speed = rng.uniform(*speed_range)
      candidates = rng.choice(len(ok), size=min(64, int(ok.sum())), replace=False,
                              p=weight * ok / (weight * ok).sum()) if ok.any() else []
      for n in candidates:
        if a.maneuver in ("left", "right", "u_turn", "straight"):
          reach = max(15.0, speed * SECONDS + 10.0) if a.maneuver != "straight" else max(10.0, speed * SECONDS)
          at = _route(a.maneuver, pts, n, _paths(sc, pts, n, reach), rng)
          if at is None:
            continue
          set_route(k, at)
        out[k], point[k] = (*pts.xy[n], speed, heading[n]), n
        break
      else:
        break
    else:
      for k, a in enumerate(spec.agents):   # a cut-in's goal: the lane ahead of the agent it cuts in front of
        if a.relation is not None and a.relation.kind == "cut_in":
          j = a.relation.to
          if route_valid[j].any():
            route[k], route_heading[k], route_valid[k] = route[j], route_heading[j], route_valid[j]
          else:
            ahead = _paths(sc, pts, point[j], max(20.0, out[j, 2] * SECONDS + 20.0))[0]
            set_route(k, ahead[int(STRAIGHT_MIN_M / POINT_SPACING_M):] if len(ahead) > 10 else ahead)
      return Placement(out.astype(np.float32), route.astype(np.float32), route_heading.astype(np.float32),
                       route_valid)
  return None


def route_goals(spec: Spec, placement: Placement, state: np.ndarray, heading: np.ndarray,
                predicates: dict[str, bool]) -> tuple[np.ndarray, np.ndarray]:
  """Goals on the placement's routes for the constrained agents whose sampled goal misses the spec, for the
  sampler to hold: `(goal [k, 4], held [k])`, goal (x, y, speed, heading) where `held`.

  An agent whose maneuver (left, right, straight, u_turn) failed gets the route point nearest, along the
  road, to where its initial speed takes it in 6 s. A cut-in whose relation failed and the agent it cuts in
  on get a pair of goals, the cut-in's within its lane band ahead of the other's (on the other's route, or
  at its sampled goal without one), each as near as it goes to where its speed takes it. A goal speed is
  what covers its distance from the initial speed at a constant acceleration, within the agent's goal
  range. `state` `[A, 2, 3]`, `heading` `[A, 2]`, `predicates` of that sample (`check`)."""
  k_all = len(spec.agents)
  goal, held = np.zeros((k_all, 4), np.float32), np.zeros(k_all, bool)

  def candidates(k):   # [N, 2] route points, [N] their headings, [N] how far the agent drives to each
    valid = placement.route_valid[k]
    pts = placement.route[k][valid].astype(np.float64)
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    travelled += np.hypot(*(pts[0] - placement.initial[k, :2])) if len(pts) else 0.0
    return pts, placement.route_heading[k][valid].astype(np.float64), travelled

  def miss(k, travelled):   # [N] metres off where agent k's initial speed takes it in 6 s
    return np.abs(travelled - max(float(placement.initial[k, 2]) * SECONDS, STRAIGHT_MIN_M + 1.0))

  def hold(k, xy, direction, travelled):
    v0 = float(placement.initial[k, 2])
    speed = max(2.0 * travelled / SECONDS - v0, 0.0)
    if spec.agents[k].speed[1] is not None:
      speed = min(max(speed, spec.agents[k].speed[1][0]), spec.agents[k].speed[1][1])
    goal[k], held[k] = (*xy, speed, direction), True

  for k, a in enumerate(spec.agents):
    if a.maneuver in ("left", "right", "straight", "u_turn") and not predicates.get(f"{spec.label(k)}.maneuver", True):
      pts, dirs, travelled = candidates(k)
      if len(pts):
        n = int(np.argmin(miss(k, travelled)))
        hold(k, pts[n], dirs[n], travelled[n])
  for k, a in enumerate(spec.agents):
    if a.relation is None or a.relation.kind != "cut_in" or predicates.get(f"{spec.label(k)}.relation", True):
      continue
    j = a.relation.to
    pts, dirs, travelled = candidates(k)
    if placement.route_valid[j].any():
      to_pts, to_dirs, to_travelled = candidates(j)
    else:   # its sampled goal
      to_pts, to_dirs = state[j, 1:2, :2].astype(np.float64), heading[j, 1:2].astype(np.float64)
      to_travelled = np.hypot(*(to_pts[0] - placement.initial[j, :2]))[None]
    c, s = np.cos(to_dirs)[:, None], np.sin(to_dirs)[:, None]
    d = pts[None] - to_pts[:, None]                                       # [M, N, 2]
    x, y = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]
    gap = sum(datatypes.AGENT_BOX_SIZE_M[datatypes.AGENT_TYPES[spec.agents[i].type]][0] for i in (j, k)) / 2 + 1.0
    ok = (np.abs(y) <= CUT_IN_GOAL_Y_M - 0.5) & (x >= gap)
    if not ok.any():
      continue
    score = np.where(ok, miss(j, to_travelled)[:, None] + miss(k, travelled)[None], np.inf)
    m, n = np.unravel_index(np.argmin(score), score.shape)
    hold(j, to_pts[m], to_dirs[m], to_travelled[m])
    if not placement.route_valid[j].any():
      goal[j, 2] = state[j, 1, 2]   # its sampled goal as it is
    hold(k, pts[n], dirs[n], travelled[n])
  return goal, held


# ---- the differentiable cost ------------------------------------------------------------------


@struct.dataclass
class SpecArrays:
  """A spec per agent slot, `[B, A]` (traced): what `cost` reads. Unconstrained agents have maneuver 0
  (any), open speed ranges, region 0 (any) and relation -1."""

  constrained: jax.Array   # [B, A] bool
  maneuver: jax.Array      # [B, A] int32, MANEUVERS index
  speed_lo: jax.Array      # [B, A, 2] m/s, initial and goal
  speed_hi: jax.Array      # [B, A, 2]
  region: jax.Array        # [B, A] int32, REGIONS index
  relation_to: jax.Array   # [B, A] int32, the related agent's slot, -1 for none
  relation: jax.Array      # [B, A] int32, RELATIONS index
  distance: jax.Array      # [B, A, 2] metres, low and high
  route: jax.Array         # [B, A, R, 2] metres: where the agent's goal holds its maneuver (`Placement.route`)
  route_valid: jax.Array   # [B, A, R]


def held_tokens(spec: Spec, placement: Placement, num_agents: int) -> tuple[np.ndarray, np.ndarray]:
  """`(state [A, 2, 4], mask [A, 2])` the sampler holds (inpainting) for a placement (`propose`): every
  constrained agent's initial state, and a stationary agent's goal (where it started, at rest)."""
  state, mask = np.zeros((num_agents, 2, 4), np.float32), np.zeros((num_agents, 2), bool)
  k = len(spec.agents)
  initial = placement.initial
  state[:k, 0], mask[:k, 0] = initial, True
  for i, a in enumerate(spec.agents):
    if a.maneuver == "stationary":
      state[i, 1], mask[i, 1] = initial[i], True
  return state, mask


def arrays(spec: Spec, batch_size: int, num_agents: int, placements: list[Placement] | None = None) -> SpecArrays:
  """`spec`'s arrays for a batch of `batch_size` scenes of `num_agents` slots (constrained agents first), with
  each scene's `placements` routes (none without)."""
  a = np.zeros((num_agents,), bool)
  man, reg, to, rel = (np.zeros(num_agents, np.int32) for _ in range(4))
  to[:] = -1
  lo, hi = np.zeros((num_agents, 2), np.float32), np.full((num_agents, 2), NO_LIMIT, np.float32)
  dist = np.zeros((num_agents, 2), np.float32)
  for k, agent in enumerate(spec.agents[:num_agents]):
    a[k] = True
    man[k], reg[k] = MANEUVERS.index(agent.maneuver), REGIONS.index(agent.region)
    for t, r in enumerate(agent.speed):
      if r is not None:
        lo[k, t], hi[k, t] = r
    if agent.relation is not None:
      to[k], rel[k], dist[k] = agent.relation.to, RELATIONS.index(agent.relation.kind), agent.relation.distance
  tile = lambda x: jnp.asarray(np.broadcast_to(x, (batch_size,) + x.shape))  # noqa: E731
  route = np.zeros((batch_size, num_agents, ROUTE_POINTS, 2), np.float32)
  route_valid = np.zeros((batch_size, num_agents, ROUTE_POINTS), bool)
  k = min(len(spec.agents), num_agents)
  for b, p in enumerate(placements or []):
    route[b, :k], route_valid[b, :k] = p.route[:k], p.route_valid[:k]
  return SpecArrays(tile(a), tile(man), tile(lo), tile(hi), tile(reg), tile(to), tile(rel), tile(dist),
                    jnp.asarray(route), jnp.asarray(route_valid))


def _outside(x, lo, hi):
  """How far x is outside [lo, hi] (0 inside)."""
  return jax.nn.relu(lo - x) + jax.nn.relu(x - hi)


def _softmin_distance(xy, pts, valid, k: float = 1.0):
  """`[A]` soft-min distance of points `xy` `[A, 2]` to `pts` `[N, 2]` (or each its own `[A, N, 2]`) where
  `valid` (`[N]` or `[A, N]`; 1e4 where none)."""
  pts, valid = (pts, valid) if pts.ndim == 3 else (pts[None], valid[None])
  d = jnp.sqrt(jnp.sum((xy[:, None] - pts) ** 2, -1) + 1e-6)
  d = jnp.where(valid, d, NO_LIMIT)
  return -jax.nn.logsumexp(-k * d, axis=-1) / k


def cost(state: jax.Array, direction: jax.Array, scene: datatypes.Scene, spec: SpecArrays) -> jax.Array:
  """Mean over the constrained agents of how far one scene's sample is from its spec, in metres (and m/s;
  the heading terms in units of their cosines and sines, times 10): the differentiable form of `check`,
  a little inside each range so that guided samples land inside it.

  Args: state `[1, A, 2, 3]`, direction `[1, A, 2, 2]` unit heading vectors, scene (batch of one),
  spec `SpecArrays` of this scene (`[A]` fields).
  """
  p, v, u = state[0, :, :, :2], state[0, :, :, 2], direction[0]            # [A, 2, 2], [A, 2], [A, 2, 2]
  normal = jnp.stack([-u[..., 1], u[..., 0]], -1)                          # left of the heading
  turn_sin = u[:, 0, 0] * u[:, 1, 1] - u[:, 0, 1] * u[:, 1, 0]             # sin of the heading change
  turn_cos = jnp.sum(u[:, 0] * u[:, 1], -1)
  moved = p[:, 1] - p[:, 0]
  dist = jnp.sqrt(jnp.sum(moved ** 2, -1) + 1e-6)
  lateral = jnp.sum(moved * normal[:, 0], -1)                              # goal left of the initial heading
  w = 10.0   # heading terms: a cosine's 0.1 weighs as a metre
  man = spec.maneuver
  maneuver = jnp.select(
      [man == 1, man == 2, man == 3, man == 4, man == 5],
      [w * jax.nn.relu(TURN_SIN + 0.1 - turn_sin) + jax.nn.relu(4.0 - lateral),
       w * jax.nn.relu(TURN_SIN + 0.1 + turn_sin) + jax.nn.relu(4.0 + lateral),
       w * jax.nn.relu(STRAIGHT_COS + 0.02 - turn_cos) + jax.nn.relu(STRAIGHT_MIN_M + 1.0 - dist)
       + jax.nn.relu(jnp.abs(lateral) - 0.3 * dist),
       w * jax.nn.relu(turn_cos - U_TURN_COS + 0.05),
       jax.nn.relu(dist - 0.5 * STATIONARY_MAX_M) + jax.nn.relu(v[:, 0] - 0.3) + jax.nn.relu(v[:, 1] - 0.3)],
      jnp.zeros_like(turn_cos))
  margin = jnp.minimum(0.5, 0.1 * (spec.speed_hi - spec.speed_lo))
  speed = jnp.sum(_outside(v, spec.speed_lo + margin, spec.speed_hi - margin), -1)
  inter_xy, inter_valid, cross_xy, cross_valid = _region_points(jax.tree_util.tree_map(lambda x: x[0], scene))
  region = jnp.select([spec.region == 1, spec.region == 2],
                      [jax.nn.relu(_softmin_distance(p[:, 0], inter_xy, inter_valid) - (INTERSECTION_M - 5.0)),
                       jax.nn.relu(_softmin_distance(p[:, 0], cross_xy, cross_valid) - (CROSSWALK_M - 1.0))], 0.0)
  relation = _relation_cost(p, u, normal, spec, w)
  on_route = jnp.where(spec.route_valid.any(-1),   # the goal onto its route (the placement's lane path)
                       jax.nn.relu(_softmin_distance(p[:, 1], spec.route, spec.route_valid, k=4.0) - 0.5), 0.0)
  total = maneuver + speed + region + relation + on_route
  return jnp.sum(jnp.where(spec.constrained, total, 0.0)) / jnp.maximum(jnp.sum(spec.constrained), 1)


def _relation_cost(p, u, normal, spec: SpecArrays, w: float) -> jax.Array:
  """`[A]` each agent's distance from its relation (`relation_holds`), 0 without one."""
  j = jnp.maximum(spec.relation_to, 0)
  d = p[:, 0] - p[j, 0]                                                    # in j's initial frame
  x, y = jnp.sum(d * u[j, 0], -1), jnp.sum(d * normal[j, 0], -1)
  hcos = jnp.sum(u[:, 0] * u[j, 0], -1)
  lo, hi = spec.distance[:, 0], spec.distance[:, 1]
  shrink = jnp.minimum(1.0, 0.1 * (hi - lo))
  lo_in, hi_in = lo + shrink, hi - shrink
  same = w * jax.nn.relu(SAME_HEADING + 0.03 - hcos)
  lane_y = lambda side: _outside(side, LANE_Y_M[0] + 0.5, LANE_Y_M[1] - 0.5)  # noqa: E731
  d1 = p[:, 1] - p[j, 1]                                                   # cut_in: in j's goal frame
  x1, y1 = jnp.sum(d1 * u[j, 1], -1), jnp.sum(d1 * jnp.stack([-u[j, 1, 1], u[j, 1, 0]], -1), -1)
  kind = spec.relation
  out = jnp.select(
      [kind == 0, kind == 1, kind == 2, kind == 3, kind == 4, kind == 5, kind == 6],
      [same + jax.nn.relu(jnp.abs(y) - SAME_LANE_Y_M + 0.5) + _outside(x, lo_in, hi_in),
       same + jax.nn.relu(jnp.abs(y) - SAME_LANE_Y_M + 0.5) + _outside(-x, lo_in, hi_in),
       same + lane_y(y) + _outside(jnp.abs(x), lo_in, hi_in),
       same + lane_y(-y) + _outside(jnp.abs(x), lo_in, hi_in),
       w * jax.nn.relu(hcos + SAME_HEADING + 0.03) + _outside(x, lo_in, hi_in),
       w * jax.nn.relu(jnp.abs(hcos) - CROSSING_COS + 0.05) + _outside(jnp.sqrt(jnp.sum(d ** 2, -1) + 1e-6), lo_in, hi_in),
       same + lane_y(jnp.abs(y)) + _outside(x, lo_in, hi_in) + jax.nn.relu(jnp.abs(y1) - CUT_IN_GOAL_Y_M + 0.5)
       + jax.nn.relu(2.0 - x1)],
      0.0)
  return jnp.where(spec.relation_to >= 0, out, 0.0)
