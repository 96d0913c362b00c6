"""Traffic on a lane graph: the agents of the synthetic AV2 worlds (`tdiff_jax.data.synthetic`).

`populate(world, rng)` fills a `road_network.World` (a generated one, or an AV2 map read by
`world_from_map`) with 110 steps at 10 Hz of traffic: the AV and a focal vehicle present throughout,
vehicles following routes through the lane graph with cruising, accelerating, stopping and queued speed
profiles under the world's speed limit, queues standing at the stop lines of red approaches, parked cars
along kerbs and in parking lots, a bus or
motorcyclist now and then, cyclists, pedestrians on crosswalks and sidewalks, static objects, and track
fragments that enter or leave mid-scenario. How busy and how fast a world is varies from world to world.
Agents are placed one by one and rejected if they would come too close to an agent placed before (at any
step), so the traffic is collision-free.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from tdiff_jax.data import av2_io
from tdiff_jax.data.road_network import Lane, Path2D, World, inside_rings, resample

NUM_STEPS = 110
DT = 0.1
# At most this many agents in a scenario (real AV2 scenarios keep at most about 33 near the lanes).
MAX_AGENTS = 32


@dataclasses.dataclass
class Agent:
  object_type: str
  xy: np.ndarray       # [110, 2]
  heading: np.ndarray  # [110]
  speed: np.ndarray    # [110]
  present: np.ndarray  # [110] bool
  role: str = ""


def world_from_map(raw: av2_io.RawScenario) -> World:
  """A `World` of an AV2 map as read by `av2_io.read_scenario_folder` (its lanes, crosswalks and drivable
  areas; lanes beside the kerb give the parking kerbs), for traffic on maps without logs. Lane ids, and so
  the map JSON written with the traffic, are the map's own."""
  lines = raw.polylines
  lanes = []
  for lane_id, attr in raw.lanes.items():
    left, right = lines.lane_left[lane_id], lines.lane_right[lane_id]
    center = lines.lane_center.get(lane_id)
    if center is None:  # the boundaries' mean, point by point after resampling both to one count
      n = max(len(left), len(right), 2)
      center = 0.5 * (_resample_n(left, n) + _resample_n(right, n))
    center = resample(center, 2.0)
    width = float(np.median(np.linalg.norm(_resample_n(left, 10) - _resample_n(right, 10), axis=-1)))
    lanes.append(Lane(lane_id, center, width, attr.lane_type, attr.is_intersection, attr.left_mark_type,
                      attr.right_mark_type, [i for i in attr.predecessors if i in raw.lanes],
                      [i for i in attr.successors if i in raw.lanes], attr.left_neighbor_id,
                      attr.right_neighbor_id, straight=False, left=left, right=right))
  lane_of = {l.id: l for l in lanes}
  for lane in lanes:
    into_junction = any(lane_of[s].is_intersection for s in lane.successors)
    lane.role = "connector" if lane.is_intersection else "in" if into_junction else "out"
  kerbs = [l for l in lanes if l.lane_type == "VEHICLE" and not l.is_intersection and l.right_neighbor is None
           and l.length > 20.0]
  # Parked cars keep to the kerb half of the outer lane (a real map's drivable area may end at its edge).
  parking = [path.offset(path.s, -max(0.5 * l.width - 1.0, 0.0)) for l in kerbs for path in [Path2D(l.center)]]
  crosswalks = [(i, e1, e2) for i, (e1, e2) in lines.crosswalk_edges.items()]
  areas = list(lines.drivable_areas.items())
  return World(lanes, crosswalks, areas, "map", sidewalks=[], parking=parking)


def _resample_n(xy: np.ndarray, n: int) -> np.ndarray:
  cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=-1))])
  s = np.linspace(0.0, cum[-1], n)
  return np.stack([np.interp(s, cum, xy[:, 0]), np.interp(s, cum, xy[:, 1])], -1)


def _route(start: Lane, rng, lane_of: dict, min_len: float, paths: dict | None = None) -> Path2D:
  """A path of at least `min_len` m from `start` along random successors; `paths` keeps the paths built
  (by their lanes' ids) for reuse."""
  lanes, lane = [start], start
  total = start.length
  while total < min_len and lane.successors:
    lane = lane_of[lane.successors[int(rng.integers(len(lane.successors)))]]
    lanes.append(lane)
    total += lane.length
  paths = {} if paths is None else paths
  key = tuple(l.id for l in lanes)
  if key not in paths:
    paths[key] = Path2D(np.concatenate([lanes[0].center] + [l.center[1:] for l in lanes[1:]]))
  return paths[key]


def _speed_profile(rng, kind: str, v_max: float, stop_at: float | None, s0: float) -> np.ndarray:
  """[110] speeds (m/s) for a motion profile."""
  t = np.arange(NUM_STEPS) * DT
  if kind == "cruise":
    v0 = rng.uniform(0.5, 1.0) * v_max
    v = v0 * (1 + 0.08 * np.sin(2 * np.pi * t / rng.uniform(6, 15) + rng.uniform(0, 6)))
  elif kind == "accelerate":
    v0, v1, acc = rng.uniform(0, 3), rng.uniform(0.6, 1.0) * v_max, rng.uniform(1.0, 2.5)
    t0 = rng.uniform(0, 6)
    v = np.clip(v0 + acc * np.clip(t - t0, 0, None), 0, v1)
  elif kind == "queued":
    t_go = rng.uniform(2, 14)  # may stay still the whole scenario
    v = np.clip(rng.uniform(1.2, 2.2) * np.clip(t - t_go, 0, None), 0, rng.uniform(0.5, 1.0) * v_max)
  elif kind == "stop":
    v0 = rng.uniform(0.5, 0.9) * v_max
    dist = (stop_at - s0) if stop_at is not None and stop_at > s0 + 5 else rng.uniform(15, 60)
    dec = float(np.clip(v0 ** 2 / (2 * dist), 0.8, 4.0))
    t_brake = max(0.0, (dist - v0 ** 2 / (2 * dec)) / v0)
    v = np.clip(v0 - dec * np.clip(t - t_brake, 0, None), 0, None)
  elif kind == "creep":  # stop-and-go at walking pace, as in a dense queue
    v = rng.uniform(0.8, 3.0) * (0.5 + 0.5 * np.sin(2 * np.pi * t / rng.uniform(5, 12) + rng.uniform(0, 6)))
  else:
    raise ValueError(kind)
  return np.clip(v, 0.0, None)


def _drive(path: Path2D, s0: float, v: np.ndarray, hold_at_end: bool):
  s = s0 + np.concatenate([[0.0], np.cumsum(v[:-1] * DT)])
  present = np.ones(NUM_STEPS, bool)
  if hold_at_end:  # waits 3 m before the route's end (at the map's edge its centre would lie on it)
    end = max(path.length - 3.0, min(s0, path.length))
    beyond = s > end
    s = np.minimum(s, end)
    v = np.where(beyond, 0.0, v)
  else:
    present = s <= path.length  # the agent leaves the map at the end of its route
  xy, h = path.at(s)
  return xy, h, v, present


def _clearance(kind: str) -> float:
  return {"vehicle": 5.0, "bus": 12.0, "motorcyclist": 3.5, "cyclist": 2.5, "pedestrian": 1.2,
          "static": 2.0, "background": 2.0, "construction": 2.0}[kind]


def _parked(p: np.ndarray, heading: float) -> Agent:
  xy = np.repeat(p[None], NUM_STEPS, 0)
  h = np.full(NUM_STEPS, np.arctan2(np.sin(heading), np.cos(heading)))
  return Agent("vehicle", xy, h, np.zeros(NUM_STEPS), np.ones(NUM_STEPS, bool), role="parked")


def populate(world: World, rng: np.random.Generator) -> list[Agent]:
  lane_of = {lane.id: lane for lane in world.lanes}
  vehicle_lanes = [l for l in world.lanes if l.lane_type in ("VEHICLE", "BUS") and l.length > 1.0]
  bike_lanes = [l for l in world.lanes if l.lane_type == "BIKE" and l.role != "connector" and l.length > 1.0]
  outer_lanes = [l for l in vehicle_lanes if l.role in ("in", "out") and l.right_mark == "SOLID_WHITE"]
  if not vehicle_lanes:
    return []
  # The world's character: its speed limit (m/s) and how busy it is.
  speed_limit = float(rng.uniform(7.0, 15.0))
  busy = float(rng.uniform(0.3, 1.2))
  agents: list[Agent] = []
  # The placed agents' tracks stacked, [N, 110, 2], [N, 110] and [N] (tracks do not change while placing).
  placed = {"xy": np.zeros((0, NUM_STEPS, 2)), "present": np.zeros((0, NUM_STEPS), bool), "clearance": np.zeros(0)}
  paths: dict[tuple[int, ...], Path2D] = {}  # routes met again

  def fits(cand: Agent) -> bool:
    """No placed agent present at the same step nearer than their mean clearance."""
    both = cand.present & placed["present"]
    near = both.any(-1)
    if not near.any():
      return True
    both = both[near]
    gap = 0.5 * (_clearance(cand.object_type) + placed["clearance"][near])
    dist = np.where(both, np.linalg.norm(cand.xy - placed["xy"][near], axis=-1), np.inf)
    return not (dist.min(-1) < gap).any()

  rings = [ring for _, ring in world.drivable_areas]

  def on_road(cand: Agent) -> bool:
    """Road users stay inside the drivable areas (where the map has any) at every step they exist."""
    return cand.object_type == "pedestrian" or not rings or bool(inside_rings(cand.xy[cand.present], rings).all())

  def add(make, tries: int = 25) -> bool:
    if len(agents) >= MAX_AGENTS:
      return False
    for _ in range(tries):
      cand = make()
      if cand is not None and fits(cand) and on_road(cand):
        agents.append(cand)
        placed["xy"] = np.concatenate([placed["xy"], cand.xy[None]])
        placed["present"] = np.concatenate([placed["present"], cand.present[None]])
        placed["clearance"] = np.append(placed["clearance"], _clearance(cand.object_type))
        return True
    return False

  def on_lane(kind: str, v_max: float, profile: str | None = None, lanes=None, full: bool = False):
    pool = lanes or vehicle_lanes
    weights = np.array([l.length for l in pool])
    weights = weights / weights.sum()

    def make():
      lane = pool[int(rng.choice(len(pool), p=weights))]
      path = _route(lane, rng, lane_of, 260.0, paths)
      s0 = float(rng.uniform(0, lane.length))
      prof = profile or str(rng.choice(["cruise", "accelerate", "stop", "queued", "creep"],
                                       p=[0.4, 0.18, 0.18, 0.14, 0.10]))
      stop_at = lane.length if lane.role == "in" else None
      v = _speed_profile(rng, prof, v_max, stop_at, s0)
      xy, h, v, present = _drive(path, s0, v, hold_at_end=full)
      return Agent(kind, xy, h, v, present, role=prof)
    return make

  # The AV and the focal vehicle are present for all 110 steps.
  inbound = [l for l in vehicle_lanes if l.role == "in"]
  add(on_lane("vehicle", speed_limit, lanes=inbound or vehicle_lanes, full=True), 60)
  if agents:
    agents[-1].role = "AV"
  if add(on_lane("vehicle", speed_limit, full=True), 60):
    agents[-1].role = "focal"
  # Queues at the stop lines: on a red approach, cars stand one behind the other until the light turns
  # green (possibly after the scenario's 11 s), then pull away a moment apart.
  red = float(rng.uniform(0.1, 0.6))
  at_stop_line = [l for l in inbound if any(lane_of[n].is_intersection for n in l.successors)]
  for lane in at_stop_line:
    if rng.random() >= red:
      continue
    t_go, gap = float(rng.uniform(1.0, 25.0)), float(rng.uniform(6.5, 8.5))
    for k in range(int(rng.integers(1, 4))):
      s0 = lane.length - 2.0 - k * gap
      if s0 < 0:
        break

      def make_queued(lane=lane, s0=s0, t_go=t_go + 1.2 * k):
        t = np.arange(NUM_STEPS) * DT
        v = np.clip(float(rng.uniform(1.2, 2.2)) * (t - t_go), 0.0, speed_limit * float(rng.uniform(0.6, 1.0)))
        xy, h, v, present = _drive(_route(lane, rng, lane_of, 260.0, paths), s0, v, hold_at_end=False)
        return Agent("vehicle", xy, h, v, present, role="queued")
      if not add(make_queued, 3):
        break
  lane_km = sum(l.length for l in vehicle_lanes if l.role != "connector") / 1000.0
  for _ in range(int(rng.integers(1, 5) + busy * min(lane_km, 2.5) * 4)):
    # Most traffic enters from the arms, so it stays on the map longer (as tracked AV2 traffic does).
    pool = inbound if rng.random() < 0.6 and inbound else vehicle_lanes
    add(on_lane("vehicle", speed_limit * float(rng.uniform(0.7, 1.1)), lanes=pool))
  if rng.random() < 0.2:
    add(on_lane("bus", 0.8 * speed_limit, profile="cruise"))
  if rng.random() < 0.15:
    add(on_lane("motorcyclist", 1.1 * speed_limit))
  for _ in range(int(rng.integers(0, 3))):
    if bike_lanes or outer_lanes:
      add(on_lane("cyclist", float(rng.uniform(3.0, 7.0)), profile="cruise", lanes=bike_lanes or outer_lanes))

  # Parked cars along kerbs and in parking lots: present throughout, speed 0.
  for kerb in world.parking:
    kerb_path = Path2D(kerb)
    for _ in range(int(rng.integers(1, 4)) if rng.random() < 0.45 else 0):
      def make_parked(kerb_path=kerb_path):
        p, h = kerb_path.at(np.array([rng.uniform(0, kerb_path.length)]))
        return _parked(p[0] + rng.normal(0, 0.05, 2), float(h[0]) + (np.pi if rng.random() < 0.15 else 0.0))
      add(make_parked, 10)
  for bays, heading in world.lots:
    for k in np.flatnonzero(rng.random(len(bays)) < rng.uniform(0.2, 0.8)):
      add(lambda k=k: _parked(bays[k], heading + (np.pi if rng.random() < 0.5 else 0.0) + rng.normal(0, 0.05)), 1)

  # Pedestrians on crosswalks (walk across, then wait at the kerb) and sidewalks.
  for _, e1, e2 in world.crosswalks:
    for _ in range(int(rng.integers(0, 3)) if rng.random() < 0.35 else 0):
      def make_ped(e1=e1, e2=e2):
        mid = 0.5 * (e1 + e2)
        d = mid[1] - mid[0]
        d /= np.linalg.norm(d) + 1e-9
        line = np.stack([mid[0] - 3 * d, mid[1] + 3 * d])
        if rng.random() < 0.5:
          line = line[::-1]
        path = Path2D(line)
        v = np.full(NUM_STEPS, rng.uniform(0.8, 1.7))
        xy, h, v, present = _drive(path, float(rng.uniform(0, path.length)), v, hold_at_end=True)
        return Agent("pedestrian", xy, h, v, present, role="crossing")
      add(make_ped)
  for walk in world.sidewalks:
    if rng.random() < 0.1:
      def make_walker(walk=walk):
        path = Path2D(walk if rng.random() < 0.5 else walk[::-1])
        v = np.full(NUM_STEPS, rng.uniform(0.9, 1.6))
        xy, h, v, present = _drive(path, float(rng.uniform(0, path.length)), v, hold_at_end=True)
        return Agent("pedestrian", xy, h, v, present, role="sidewalk")
      add(make_walker)

  # Static objects by the kerb (never modelled; AV2 files have them).
  for _ in range(int(rng.integers(0, 6)) if world.sidewalks else 0):
    def make_static():
      walk = Path2D(world.sidewalks[int(rng.integers(len(world.sidewalks)))])
      p, _ = walk.at(np.array([rng.uniform(0, walk.length)]))
      return Agent(str(rng.choice(["static", "background", "construction"])), np.repeat(p, NUM_STEPS, 0),
                   np.full(NUM_STEPS, rng.uniform(-np.pi, np.pi)), np.zeros(NUM_STEPS),
                   np.ones(NUM_STEPS, bool), role="static")
    add(make_static)

  # Track fragments: some agents are tracked only for part of the scenario.
  for agent in agents[2:]:
    if agent.role not in ("parked", "static") and rng.random() < 0.25:
      t0 = int(rng.integers(0, 90))
      t1 = int(rng.integers(t0 + 10, NUM_STEPS + 1))
      window = np.zeros(NUM_STEPS, bool)
      window[t0:t1] = True
      agent.present = agent.present & window
  return [a for a in agents if a.present.any()]
