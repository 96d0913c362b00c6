"""Procedural road networks: the map half of the synthetic AV2 worlds (`tdiff_jax.data.synthetic`).

A network is a few roads joined at junctions, in the manner of MetaDrive's block-assembled maps:
* layouts: one junction of 3 to 5 arms at irregular angles (45 %), a corridor of 2 or 3 junctions along a
  main road that may bend (40 %), or a junction-free road, straight or S-curved, with a mid-block
  crossing (15 %);
* roads: a median reference line (straight, or straight then an arc of 35 to 160 m radius) with 1 to 3
  lanes each way (a side road is one-way now and then), lane widths 2.9 to 4.2 m, 1 to 4 lane segments
  along it, a left-turn pocket at a junction, a lane that ends in a merge (or, seen the other way, a
  lane added by a split), a bike lane, a parking strip at the kerb and now and then a parking lot beside;
* junctions: connector lanes for straight, left and right movements between every inbound and outbound
  road end (turn angles read from the geometry), a drivable area around the road ends, crosswalks;
* drivable areas along every road and around every junction; sidewalks beyond the kerbs.
The lane graph is consistent (successors continue their predecessors, neighbours point at each other)
and every lane carries the AV2 fields av2's loader needs. Deterministic in the generator passed in.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

# ------------------------------------------------------------------------------------------------
# Geometry helpers
# ------------------------------------------------------------------------------------------------


def arc_length(xy: np.ndarray) -> np.ndarray:
  return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=-1))])


def resample(xy: np.ndarray, spacing: float) -> np.ndarray:
  """Resample to points at most `spacing` apart, ends kept."""
  cum = arc_length(xy)
  n = max(2, int(math.ceil(cum[-1] / spacing)) + 1)
  s = np.linspace(0.0, cum[-1], n)
  return np.stack([np.interp(s, cum, xy[:, 0]), np.interp(s, cum, xy[:, 1])], -1)


def bezier(p0, h0, p1, h1, n: int = 40, reach: float = 0.0) -> np.ndarray:
  """Cubic Bezier from p0 (unit tangent h0) to p1 (unit tangent h1); its control points at least `reach`
  m from the ends."""
  k = max(0.4 * np.linalg.norm(p1 - p0), reach)
  c0, c1 = p0 + k * h0, p1 - k * h1
  t = np.linspace(0.0, 1.0, n)[:, None]
  return (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * c0 + 3 * (1 - t) * t ** 2 * c1 + t ** 3 * p1


def left_normals(xy: np.ndarray) -> np.ndarray:
  d = np.gradient(xy, axis=0)
  d /= np.linalg.norm(d, axis=-1, keepdims=True) + 1e-12
  return np.stack([-d[:, 1], d[:, 0]], -1)


def convex_hull(points: np.ndarray) -> np.ndarray:
  """[H, 2] the convex hull of [N, 2] points, counter-clockwise (Andrew's monotone chain)."""
  pts = sorted(set(map(tuple, np.round(points, 6).tolist())))
  if len(pts) < 3:
    return np.array(pts)

  def half(seq):
    out = []
    for p in seq:
      while len(out) >= 2 and ((out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                               - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])) <= 0:
        out.pop()
      out.append(p)
    return out[:-1]

  return np.array(half(pts) + half(pts[::-1]))


def inside_rings(xy: np.ndarray, rings: list[np.ndarray]) -> np.ndarray:
  """[N] whether each of the [N, 2] points lies inside one of the rings (even-odd rule)."""
  inside = np.zeros(len(xy), bool)
  for ring in rings:
    a, b = ring, np.roll(ring, -1, axis=0)                       # edges a -> b, [E, 2]
    x, y = xy[:, None, 0], xy[:, None, 1]
    crosses = (a[None, :, 1] > y) != (b[None, :, 1] > y)
    t = (y - a[None, :, 1]) / np.where(crosses, b[None, :, 1] - a[None, :, 1], 1.0)
    hit = crosses & (x < a[None, :, 0] + t * (b[None, :, 0] - a[None, :, 0]))
    inside |= hit.sum(-1) % 2 == 1
  return inside


class Path2D:
  """A polyline parametrised by arc length: position, heading and left normal at any s."""

  def __init__(self, xy: np.ndarray):
    self.xy = resample(np.asarray(xy, np.float64), 0.5)
    self.s = arc_length(self.xy)
    d = np.gradient(self.xy, axis=0)
    self.heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))

  @property
  def length(self) -> float:
    return float(self.s[-1])

  def at(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.interp(s, self.s, self.xy[:, 0])
    y = np.interp(s, self.s, self.xy[:, 1])
    h = np.interp(s, self.s, self.heading)
    return np.stack([x, y], -1), np.arctan2(np.sin(h), np.cos(h))

  def offset(self, s: np.ndarray, lateral: np.ndarray | float) -> np.ndarray:
    """[N, 2] points `lateral` m left of the path at arc lengths s (negative: right)."""
    xy, h = self.at(s)
    return xy + np.asarray(lateral)[..., None] * np.stack([-np.sin(h), np.cos(h)], -1)


# ------------------------------------------------------------------------------------------------
# Map elements
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class Lane:
  id: int
  center: np.ndarray  # [N, 2] local frame, direction of travel
  width: float
  lane_type: str = "VEHICLE"
  is_intersection: bool = False
  left_mark: str = "DASHED_WHITE"
  right_mark: str = "DASHED_WHITE"
  predecessors: list[int] = dataclasses.field(default_factory=list)
  successors: list[int] = dataclasses.field(default_factory=list)
  left_neighbor: int | None = None
  right_neighbor: int | None = None
  straight: bool = True
  role: str = ""  # "in" (towards a junction), "out" (away from one), "connector"
  node: int | None = None  # a connector's junction
  left: np.ndarray | None = None   # [M, 2] boundaries when known (lanes read from a map)
  right: np.ndarray | None = None

  @functools.cached_property
  def length(self) -> float:
    return float(arc_length(self.center)[-1])

  def boundaries(self) -> tuple[np.ndarray, np.ndarray]:
    if self.left is not None and self.right is not None:
      return self.left, self.right
    if self.straight:  # real AV2 boundaries of straight lanes have just their two ends
      c = self.center[[0, -1]]
      n = np.repeat(left_normals(self.center)[:1], 2, axis=0)
    else:
      c = resample(self.center, 3.0)
      n = left_normals(c)
    return c + n * self.width / 2, c - n * self.width / 2


@dataclasses.dataclass
class World:
  lanes: list[Lane]
  crosswalks: list[tuple[int, np.ndarray, np.ndarray]]  # (id, edge1 [2, 2], edge2 [2, 2])
  drivable_areas: list[tuple[int, np.ndarray]]          # (id, ring [N, 2])
  kind: str
  sidewalks: list[np.ndarray]                           # [N, 2] paths pedestrians walk along
  parking: list[np.ndarray]                             # [N, 2] kerb lines cars park along (facing either way)
  lots: list[tuple[np.ndarray, float]] = dataclasses.field(default_factory=list)  # (bay centres [M, 2], heading)
  parts: frozenset[str] = frozenset()  # the road parts it holds (`PARTS`)


# The road parts a generated world may hold (`World.parts`).
PARTS = ("junction", "angled_junction", "several_junctions", "curve", "pocket", "merge", "split", "one_way",
         "bike_lane", "parking_strip", "parking_lot", "u_turn", "mid_block_crossing")


# ------------------------------------------------------------------------------------------------
# Roads
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class Side:
  """One direction of a road: its slots (lanes side by side) going outward from the median."""

  slots: list[tuple[float, float, str]]  # (lateral centre offset from the median, width, kind)
  forward: bool                          # travels with the road's reference line
  lanes: dict = dataclasses.field(default_factory=dict)  # (segment, slot) -> Lane

  @property
  def width(self) -> float:
    return sum(w for _, w, _ in self.slots)


@dataclasses.dataclass
class Road:
  path: Path2D                 # the median, from the start end to the far end
  fwd: Side                    # lanes right of the median, travelling start -> end
  bwd: Side                    # lanes left of the median, travelling end -> start
  nodes: tuple[int | None, int | None]  # the junction at each end (None: the map's edge)
  cuts: list[float] = dataclasses.field(default_factory=list)
  strip: tuple[float, float] = (0.0, 0.0)  # parking strip beyond the kerb (right of fwd, right of bwd)
  merge_seg: int = 0           # merge lanes run in the segments before this one


def _slots(widths_kinds) -> list[tuple[float, float, str]]:
  out, acc = [], 0.0
  for w, kind in widths_kinds:
    out.append((acc + w / 2, w, kind))
    acc += w
  return out


def _side_kinds(n: int, lane_w: float, pocket: bool, merge: bool, bike: bool):
  kinds = ([(lane_w, "pocket")] if pocket else []) + [(lane_w, "through")] * n
  if merge:
    kinds.append((lane_w, "merge"))
  if bike:
    kinds.append((1.5, "bike"))
  return kinds


def _exists(side: Side, road: Road, seg: int, slot: int) -> bool:
  """Whether a side's slot has a lane in a segment (pockets: the segment at the junction; merge lanes:
  the segments before `road.merge_seg` along the reference line)."""
  kind = side.slots[slot][2]
  n_seg = len(road.cuts) - 1
  if kind == "pocket":
    return n_seg == 1 or seg == (n_seg - 1 if side.forward else 0)
  if kind == "merge":
    return seg < road.merge_seg
  return True


def _nearest(slots, slot: int) -> int:
  """The slot of `slots` nearest to `slot` (where a lane that ends continues, or one that begins branches off)."""
  return min(slots, key=lambda j: abs(j - slot))


def _build_road_lanes(road: Road, ids) -> list[Lane]:
  lanes = []
  n_seg = len(road.cuts) - 1
  for side in (road.fwd, road.bwd):
    sign = -1.0 if side.forward else 1.0
    for seg in range(n_seg):
      s0, s1 = road.cuts[seg], road.cuts[seg + 1]
      for slot, (off, w, kind) in enumerate(side.slots):
        if not _exists(side, road, seg, slot):
          continue
        # A lane missing from the next segment along the reference line (or the previous one) tapers
        # into its nearest neighbour there: pockets peel off, merge lanes merge, split lanes peel off.
        lat0, lat1 = off, off
        for other, at_end in ((seg + 1, True), (seg - 1, False)):
          if 0 <= other < n_seg and not _exists(side, road, other, slot):
            partner = _nearest([j for j in range(len(side.slots)) if _exists(side, road, other, j)], slot)
            if at_end:
              lat1 = side.slots[partner][0]
            else:
              lat0 = side.slots[partner][0]
        n = max(2, int(math.ceil((s1 - s0) / 1.0)) + 1)
        s = np.linspace(s0, s1, n)
        taper = min(15.0, 0.5 * (s1 - s0))
        lat = np.full(n, off)
        lat = np.where(s < s0 + taper, lat0 + (off - lat0) * np.clip((s - s0) / taper, 0, 1), lat)
        lat = np.where(s > s1 - taper, off + (lat1 - off) * np.clip((s - (s1 - taper)) / taper, 0, 1), lat)
        center = road.path.offset(s, sign * lat)
        if not side.forward:
          center = center[::-1]
        curved = lat0 != off or lat1 != off or float(np.ptp(road.path.at(s)[1])) > 0.01
        lane = Lane(next(ids), resample(center, 2.0), w, "BIKE" if kind == "bike" else "VEHICLE",
                    straight=not curved)
        side.lanes[(seg, slot)] = lane
        lanes.append(lane)
    # Marks and neighbours within each segment; the chain along the road.
    for seg in range(n_seg):
      present = [j for j in range(len(side.slots)) if (seg, j) in side.lanes]
      vehicle = [j for j in present if side.slots[j][2] != "bike"]
      for j in present:
        lane, kind = side.lanes[(seg, j)], side.slots[j][2]
        lane.left_mark = "DOUBLE_SOLID_YELLOW" if j == present[0] else "DASHED_WHITE"
        lane.right_mark = "SOLID_WHITE" if j == vehicle[-1] or kind == "pocket" else "DASHED_WHITE"
        if kind == "bike":
          lane.left_mark, lane.right_mark = "SOLID_WHITE", "NONE"
        k = present.index(j)
        lane.left_neighbor = side.lanes[(seg, present[k - 1])].id if k > 0 else None
        lane.right_neighbor = side.lanes[(seg, present[k + 1])].id if k + 1 < len(present) else None
    lane_of = side.lanes
    for seg in range(n_seg - 1):
      a_seg, b_seg = (seg, seg + 1) if side.forward else (seg + 1, seg)  # a before b in travel order
      for slot in range(len(side.slots)):
        a, b = lane_of.get((a_seg, slot)), lane_of.get((b_seg, slot))
        if a is not None and b is None:  # ends: continues in its nearest neighbour
          b = lane_of[(b_seg, _nearest([j for j in range(len(side.slots)) if (b_seg, j) in lane_of], slot))]
        elif a is None and b is not None:  # begins: branches off its nearest neighbour
          a = lane_of[(a_seg, _nearest([j for j in range(len(side.slots)) if (a_seg, j) in lane_of], slot))]
        if a is not None and b is not None and b.id not in a.successors:
          a.successors.append(b.id)
          b.predecessors.append(a.id)
  return lanes


# ------------------------------------------------------------------------------------------------
# Layouts
# ------------------------------------------------------------------------------------------------

def _arm_path(rng, start: np.ndarray, angle: float, length: float, curved: bool) -> np.ndarray:
  """A stub road's reference line from a junction outward: straight, or straight then an arc."""
  u = np.array([math.cos(angle), math.sin(angle)])
  if not curved:
    return np.stack([start, start + length * u])
  straight = float(rng.uniform(15.0, 30.0))
  radius = float(rng.uniform(35.0, 160.0))
  turn = float(rng.choice([-1.0, 1.0])) * min(float(rng.uniform(0.3, 1.1)), (length - straight) / radius)
  t = np.linspace(0.0, 1.0, 40)
  head = angle + turn * t
  # The arc: integrate the heading over its length.
  step = (length - straight) / (len(t) - 1)
  pts = [start + straight * u]
  for h in head[1:]:
    pts.append(pts[-1] + step * np.array([math.cos(h), math.sin(h)]))
  return np.concatenate([start[None], np.array(pts)])


def _angles(rng, n: int, taken: list[float], min_gap: float) -> list[float]:
  """Up to n arm directions (radians) at least min_gap from each other and from `taken`."""
  out: list[float] = []
  for _ in range(200):
    if len(out) == n:
      break
    a = float(rng.uniform(-math.pi, math.pi))
    if all(abs(math.remainder(a - b, 2 * math.pi)) >= min_gap for b in taken + out):
      out.append(a)
  return out


def _clear_length(pts: np.ndarray, others: list[np.ndarray], need: float, skip: float) -> float:
  """How far along the polyline `pts` it stays at least `need` m from every polyline in `others` (its
  first `skip` m, by its own junction, are not checked)."""
  path = resample(pts, 2.0)
  s = arc_length(path)
  if not others:
    return float(s[-1])
  other = np.concatenate(others)
  d = np.linalg.norm(path[:, None] - other[None], axis=-1).min(-1)
  bad = np.flatnonzero((d < need) & (s > skip))
  return float(s[-1]) if not len(bad) else float(s[bad[0]])


def _layout(rng, kind: str) -> tuple[list[np.ndarray], list[tuple[int | None, int | None, float, bool]]]:
  """Junction centres and the links (start node, end node or None for the map's edge, direction at the
  start, is a side road)."""
  nodes: list[np.ndarray] = []
  links: list[tuple[int | None, int | None, float, bool]] = []
  if kind == "junction":
    nodes.append(np.zeros(2))
    n_arms = int(rng.choice([3, 4, 5], p=[0.35, 0.55, 0.10]))
    for a in _angles(rng, n_arms, [], math.radians(50 if n_arms == 5 else 60)):
      links.append((0, None, a, False))
  elif kind == "corridor":
    n_nodes = int(rng.choice([2, 3], p=[0.6, 0.4]))
    heading = 0.0
    nodes.append(np.zeros(2))
    for _ in range(1, n_nodes):
      heading += float(rng.uniform(-0.45, 0.45))
      nodes.append(nodes[-1] + float(rng.uniform(55.0, 100.0)) * np.array([math.cos(heading), math.sin(heading)]))
    for i in range(n_nodes):
      prev = nodes[i - 1] - nodes[i] if i > 0 else nodes[i] - nodes[i + 1]
      nxt = nodes[i + 1] - nodes[i] if i + 1 < n_nodes else nodes[i] - nodes[i - 1]
      main = [math.atan2(prev[1], prev[0]), math.atan2(nxt[1], nxt[0])]
      if i == 0:
        main[0] += float(rng.uniform(-0.4, 0.4))
        links.append((0, None, main[0], False))
      if i + 1 < n_nodes:
        links.append((i, i + 1, main[1], False))
      else:
        main[1] += float(rng.uniform(-0.4, 0.4))
        links.append((i, None, main[1], False))
      for a in _angles(rng, int(rng.choice([1, 2], p=[0.35, 0.65])), main, math.radians(55)):
        links.append((i, None, a, True))
  else:
    links.append((None, None, 0.0, False))
  return nodes, links


# At most this many map polygons in a world, a lane one and a crosswalk two (the scene has one each way); real
# AV2 map archives have 36 to 150, 64 at the median. A larger draw is made again, which keeps the training
# batches' size buckets few.
MAX_POLYGONS = 128


def build_world(rng: np.random.Generator) -> World:
  """A random road network of at most `MAX_POLYGONS` polygons."""
  while True:
    world = _build_world(rng)
    if len(world.lanes) + 2 * len(world.crosswalks) <= MAX_POLYGONS:
      return world


def _build_world(rng: np.random.Generator) -> World:
  kind = str(rng.choice(["junction", "corridor", "road"], p=[0.45, 0.4, 0.15]))
  lane_w = float(rng.uniform(2.9, 4.2))
  nodes, links = _layout(rng, kind)

  # Lane counts per link: the main road keeps its counts; side roads are narrower, now and then one-way.
  main_counts = (int(rng.integers(1, 4)), int(rng.integers(1, 4)))
  specs = []
  for a, b, angle, side_road in links:
    n_f, n_b = main_counts
    if kind == "junction" and rng.random() < 0.7:
      n_f, n_b = int(rng.integers(1, 4)), int(rng.integers(1, 4))
    if side_road:
      n_f, n_b = int(rng.integers(1, 3)), int(rng.integers(1, 3))
      if rng.random() < 0.12:  # one-way
        n_f, n_b = (0, n_b) if rng.random() < 0.5 else (n_f, 0)
    specs.append((a, b, angle, n_f, n_b))
  # How far each road starts from its junction's centre: enough for the widest arm at the narrowest angle.
  half = lambda n_f, n_b: (max(n_f, n_b) + 1.5) * lane_w + 1.5  # noqa: E731
  attach = {}
  for i in range(len(nodes)):
    here = [(angle, half(nf, nb)) for a, b, angle, nf, nb in specs if a == i] + [
        (math.atan2(*(nodes[a] - nodes[i])[::-1]), half(nf, nb)) for a, b, angle, nf, nb in specs if b == i]
    gaps = [abs(math.remainder(x - y, 2 * math.pi)) for k, (x, _) in enumerate(here) for y, _ in here[k + 1:]]
    widest = max(w for _, w in here)
    attach[i] = max(8.0, widest / math.tan(max(min(gaps, default=math.pi), 0.6) / 2) + float(rng.uniform(1.0, 4.0)))

  for i in range(1, len(nodes)):  # junctions far enough apart for a road between them
    d = nodes[i] - nodes[i - 1]
    need = attach[i - 1] + attach[i] + 20.0
    if np.linalg.norm(d) < need:
      for j in range(i, len(nodes)):
        nodes[j] = nodes[j] + (need - np.linalg.norm(d)) * d / np.linalg.norm(d)

  # Reference lines: roads between junctions first, then the stubs out to the map's edge, each kept clear
  # of the roads laid before it (a curve that would run into one is straightened, then shortened).
  order = sorted(range(len(specs)), key=lambda k: specs[k][1] is None)
  lines: dict[int, np.ndarray] = {}
  for k in order:
    a, b, angle, n_f, n_b = specs[k]
    if a is None:  # a junction-free road, maybe S-curved
      length = float(rng.uniform(140.0, 230.0))
      x = np.linspace(-length / 2, length / 2, 60)
      amp = float(rng.uniform(8.0, 30.0)) * float(rng.choice([-1.0, 1.0])) if rng.random() < 0.5 else 0.0
      lines[k] = np.stack([x, amp * np.tanh(x / float(rng.uniform(25.0, 60.0)))], -1)
    elif b is not None:
      d = nodes[b] - nodes[a]
      u = d / np.linalg.norm(d)
      lines[k] = np.stack([nodes[a] + attach[a] * u, nodes[b] - attach[b] * u])
    else:
      u = np.array([math.cos(angle), math.sin(angle)])
      length = float(rng.uniform(45.0, 90.0) if kind == "corridor" else rng.uniform(60.0, 130.0))
      others = [lines[j] for j in lines]
      need = half(n_f, n_b) + 2 * lane_w + 3.0
      for curved in ((True, False) if rng.random() < 0.35 else (False,)):
        pts = _arm_path(rng, nodes[a] + attach[a] * u, angle, length, curved)
        clear = _clear_length(pts, others, need, skip=need)
        if clear >= length - 1.0:
          break
      if clear < length - 1.0:
        pts = np.stack([pts[0], pts[0] + max(clear - 5.0, 20.0) * u])
      lines[k] = pts

  roads: list[Road] = []
  ends: dict[int, list[tuple[Road, bool]]] = {i: [] for i in range(len(nodes))}  # node -> (road, at its start)
  for k, (a, b, angle, n_f, n_b) in enumerate(specs):
    pocket_f = b is not None and n_f > 0 and rng.random() < 0.4      # inbound at the far end
    pocket_b = a is not None and n_b > 0 and rng.random() < 0.4      # inbound at the start
    merge = b is None and rng.random() < 0.15
    bike = rng.random() < 0.2
    # The merge lane's side: along the reference line it ends (a merge); against it, it begins (a split).
    merge_fwd = n_f > 0 and (n_b == 0 or rng.random() < 0.5)
    road = Road(Path2D(lines[k]),
                Side(_slots(_side_kinds(n_f, lane_w, pocket_f, merge and merge_fwd, bike and n_f > 0)), True),
                Side(_slots(_side_kinds(n_b, lane_w, pocket_b, merge and not merge_fwd, bike and n_b > 0)), False),
                (a, b), strip=tuple(2.4 if rng.random() < 0.45 else 0.0 for _ in range(2)))
    n_seg = int(rng.integers(1, 5)) if road.path.length > 40 else 1
    if merge:
      n_seg = max(n_seg, 2)
    road.cuts = [0.0] + [float(c) for c in np.cumsum(rng.dirichlet(np.full(n_seg, 4.0))) * road.path.length]
    road.merge_seg = int(rng.integers(1, n_seg)) if n_seg > 1 else n_seg
    roads.append(road)
    if a is not None:
      ends[a].append((road, True))
    if b is not None:
      ends[b].append((road, False))

  ids = iter(range(int(rng.integers(10_000_000, 400_000_000)), 10**10))
  lanes: list[Lane] = []
  for road in roads:
    lanes += _build_road_lanes(road, ids)
    for side, inbound_at_end in ((road.fwd, True), (road.bwd, False)):
      for lane in side.lanes.values():
        node = road.nodes[1] if inbound_at_end else road.nodes[0]
        lane.role = "in" if node is not None else "out"

  # Connectors through each junction, from every inbound end to every other road end's outbound lanes.
  for i, node_ends in ends.items():
    for road, at_start in node_ends:
      src = road.bwd if at_start else road.fwd
      if not src.slots:
        continue
      n_seg = len(road.cuts) - 1
      seg = 0 if at_start else n_seg - 1
      src_lanes = {j: l for (s, j), l in src.lanes.items() if s == seg}
      in_dir = src_lanes[min(src_lanes)].center[-1] - src_lanes[min(src_lanes)].center[-2]
      in_angle = math.atan2(in_dir[1], in_dir[0])
      through = [j for j in sorted(src_lanes) if src.slots[j][2] in ("through", "merge")]
      pocket = [j for j in sorted(src_lanes) if src.slots[j][2] == "pocket"]
      bikes = [j for j in sorted(src_lanes) if src.slots[j][2] == "bike"]
      double_left, u_turn = rng.random() < 0.3, rng.random() < 0.2
      for other, other_at_start in node_ends:
        if other is road and not u_turn:
          continue
        dst = other.fwd if other_at_start else other.bwd
        if not dst.slots:
          continue
        o_seg = 0 if other_at_start else len(other.cuts) - 1
        dst_lanes = {j: l for (s, j), l in dst.lanes.items() if s == o_seg}
        d_through = [j for j in sorted(dst_lanes) if dst.slots[j][2] in ("through", "merge")]
        d_bike = [j for j in sorted(dst_lanes) if dst.slots[j][2] == "bike"]
        if not d_through or not through:
          continue
        out_dir = dst_lanes[d_through[0]].center[1] - dst_lanes[d_through[0]].center[0]
        turn = math.remainder(math.atan2(out_dir[1], out_dir[0]) - in_angle, 2 * math.pi)
        if other is road:  # a U-turn from the innermost lane
          pairs = [((pocket or through)[0], d_through[0])]
        elif abs(turn) < math.radians(35):
          pairs = [(j, d_through[min(k, len(d_through) - 1)]) for k, j in enumerate(through)]
          if bikes and d_bike:
            pairs.append((bikes[0], d_bike[0]))
        elif turn > 0:
          if turn > math.radians(160):
            continue
          left_lanes = (pocket or through)[:2 if double_left and not pocket else 1]
          pairs = [(j, d_through[min(k, len(d_through) - 1)]) for k, j in enumerate(left_lanes)]
        else:
          if turn < -math.radians(160):
            continue
          pairs = [(through[-1], d_through[-1])]
        for j, dj in pairs:
          a, b = src_lanes[j], dst_lanes[dj]
          h0 = a.center[-1] - a.center[-2]
          h1 = b.center[1] - b.center[0]
          curve = bezier(a.center[-1], h0 / np.linalg.norm(h0), b.center[0], h1 / np.linalg.norm(h1),
                         reach=6.0 if other is road else 0.0)
          conn = Lane(next(ids), resample(curve, 2.0), min(a.width, b.width), a.lane_type,
                      is_intersection=True, left_mark="NONE", right_mark="NONE",
                      predecessors=[a.id], successors=[b.id], straight=False, role="connector", node=i)
          a.successors.append(conn.id)
          b.predecessors.append(conn.id)
          lanes.append(conn)

  # Crosswalks, drivable areas, sidewalks, parking.
  cw_ids = iter(range(int(rng.integers(1_000_000, 40_000_000)), 10**9))
  da_ids = iter(range(int(rng.integers(1_000_000, 9_000_000)), 10**9))
  crosswalks, sidewalks, parking, lots, areas = [], [], [], [], []

  def across(road: Road, s: float, extra: float = 0.5) -> np.ndarray:
    return np.stack([road.path.offset(np.array([s]), -(road.fwd.width + extra))[0],
                     road.path.offset(np.array([s]), road.bwd.width + extra)[0]])

  for i, node_ends in ends.items():
    corners = [np.concatenate(l.boundaries()) for l in lanes if l.role == "connector" and l.node == i]
    for road, at_start in node_ends:
      s = 0.0 if at_start else road.path.length
      corners += list(across(road, s, 0.3))
      if rng.random() < 0.85:
        w = float(rng.uniform(3.0, 5.0))
        s1 = s + 1.0 if at_start else s - 1.0
        s2 = s1 + w if at_start else s1 - w
        crosswalks.append((next(cw_ids), across(road, s1), across(road, s2)))
    hull = convex_hull(np.concatenate([np.reshape(c, (-1, 2)) for c in corners]))
    centre = hull.mean(0)
    areas.append((next(da_ids), centre + (hull - centre) * 1.04))
  if kind == "road" and rng.random() < 0.8:
    road = roads[0]
    s = road.path.length * float(rng.uniform(0.35, 0.65))
    crosswalks.append((next(cw_ids), across(road, s), across(road, s + float(rng.uniform(3.0, 5.0)))))

  for road in roads:
    s = np.linspace(0.0, road.path.length, max(2, int(road.path.length / 4.0) + 1))
    right_edge = -(road.fwd.width + 0.3 + road.strip[0])
    left_edge = road.bwd.width + 0.3 + road.strip[1]
    ring = np.concatenate([road.path.offset(s, right_edge), road.path.offset(s, left_edge)[::-1]])
    areas.append((next(da_ids), ring))
    s_walk = s[(s > (2.0 if road.nodes[0] is not None else 0.0))
               & (s < road.path.length - (2.0 if road.nodes[1] is not None else 0.0))]
    if len(s_walk) >= 2:
      sidewalks += [road.path.offset(s_walk, right_edge - 2.2), road.path.offset(s_walk, left_edge + 2.2)]
    for k, (strip, side_sign) in enumerate(zip(road.strip, (-1.0, 1.0))):
      width = road.fwd.width if k == 0 else road.bwd.width
      s_park = s[(s > 8.0) & (s < road.path.length - 8.0)]
      if strip and len(s_park) >= 2:
        parking.append(road.path.offset(s_park, side_sign * (width + 0.3 + strip / 2)))
    if road.nodes[1] is None and road.path.length > 60 and rng.random() < 0.15:
      # A parking lot beside the road: a drivable area with a row of bays.
      s0 = float(rng.uniform(15.0, road.path.length - 40.0))
      side_sign = float(rng.choice([-1.0, 1.0]))
      edge = (road.fwd.width if side_sign < 0 else road.bwd.width) + 0.3
      s_lot = np.linspace(s0, s0 + 25.0, 8)
      inner = road.path.offset(s_lot, side_sign * edge)
      outer = road.path.offset(s_lot, side_sign * (edge + 14.0))
      areas.append((next(da_ids), np.concatenate([inner, outer[::-1]])))
      bays = road.path.offset(np.linspace(s0 + 1.5, s0 + 23.5, 9), side_sign * (edge + 10.5))
      heading = float(road.path.at(np.array([s0]))[1][0]) + side_sign * math.pi / 2
      lots.append((bays, heading))
  parts = {"junction"} if nodes else set()
  if len(nodes) > 1:
    parts.add("several_junctions")
  for i in range(len(nodes)):
    dirs = [math.atan2(*(r.path.xy[1] - r.path.xy[0])[::-1]) if at_start else
            math.atan2(*(r.path.xy[-2] - r.path.xy[-1])[::-1]) for r, at_start in ends[i]]
    if any(abs(math.remainder(x - y, math.pi / 2)) > math.radians(10) for x in dirs for y in dirs):
      parts.add("angled_junction")
  for road in roads:
    if float(np.ptp(road.path.heading)) > math.radians(15):
      parts.add("curve")
    for side in (road.fwd, road.bwd):
      kinds = {k for _, _, k in side.slots}
      parts |= {"pocket"} & kinds
      if "bike" in kinds:
        parts.add("bike_lane")
      if "merge" in kinds and len(road.cuts) > 2:
        parts.add("merge" if side.forward else "split")
    if not road.fwd.slots or not road.bwd.slots:
      parts.add("one_way")
    if any(road.strip):
      parts.add("parking_strip")
  if lots:
    parts.add("parking_lot")
  if any(l.role == "connector" and np.dot(*[d / np.linalg.norm(d) for d in (
      l.center[1] - l.center[0], l.center[-1] - l.center[-2])]) < -0.95 for l in lanes):
    parts.add("u_turn")
  if kind == "road" and crosswalks:
    parts.add("mid_block_crossing")
  return World(lanes, crosswalks, areas, kind, sidewalks, parking, lots, frozenset(parts))
