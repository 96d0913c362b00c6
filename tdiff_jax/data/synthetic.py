"""Synthetic AV2 worlds: seeded procedural scenarios written in the real AV2 file format.

Each world is one of
* a four-way intersection (50 %), a T junction (30 %) or a straight road with a mid-block crossing (20 %);
* arms with 1 to 3 lanes each way (right-hand traffic), sometimes a left-turn pocket and a bike lane,
  split into 1 to 4 lane segments; connector lanes through the junction for straight, left and right
  turns, forming a consistent lane graph (predecessors, successors, same-direction neighbours);
* crosswalks across the arms, drivable-area polygons (the junction box and one per arm) and the
  lane-mark types a real map uses;
* 110 steps at 10 Hz of traffic: the AV and a focal vehicle present throughout, vehicles following
  routes through the lane graph with cruising, accelerating, stopping and queued speed profiles,
  parked cars at the kerb, a bus or motorcyclist now and then, cyclists, pedestrians on crosswalks
  and sidewalks, static objects, and track fragments that enter or leave mid-scenario.
Agents are placed one by one and rejected if they would come too close to an agent placed before, so
worlds are collision-free. The whole world is rotated and translated into a random "city" frame.

Scenarios go through av2's own serializer and the map JSON carries every field av2's loader needs
(centrelines included), so the code that reads real AV2 reads these.

Command:
  python -m tdiff_jax.data.synthetic --out DIR --num N --seed S [--val_fraction 0.1]
writes DIR/train/<id>/ and DIR/val/<id>/ folders. Reruns skip scenarios already written; each
scenario folder appears atomically.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import shutil
import uuid
from concurrent import futures
from pathlib import Path

import numpy as np
from absl import flags
from av2.datasets.motion_forecasting.data_schema import (
    ArgoverseScenario, ObjectState, ObjectType, Track, TrackCategory)

from tdiff_jax import cli, files
from tdiff_jax.data import av2_io

NUM_STEPS = 110
DT = 0.1
OBSERVED_STEPS = 50


# ------------------------------------------------------------------------------------------------
# Geometry helpers
# ------------------------------------------------------------------------------------------------

def _rot(a: float) -> np.ndarray:
  return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


def _arc_length(xy: np.ndarray) -> np.ndarray:
  return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=-1))])


def _resample(xy: np.ndarray, spacing: float) -> np.ndarray:
  """Resample to points at most `spacing` apart, ends kept."""
  cum = _arc_length(xy)
  n = max(2, int(math.ceil(cum[-1] / spacing)) + 1)
  s = np.linspace(0.0, cum[-1], n)
  return np.stack([np.interp(s, cum, xy[:, 0]), np.interp(s, cum, xy[:, 1])], -1)


def _bezier(p0, h0, p1, h1, n: int = 40) -> np.ndarray:
  """Cubic Bezier from p0 (unit tangent h0) to p1 (unit tangent h1)."""
  k = 0.4 * np.linalg.norm(p1 - p0)
  c0, c1 = p0 + k * h0, p1 - k * h1
  t = np.linspace(0.0, 1.0, n)[:, None]
  return (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * c0 + 3 * (1 - t) * t ** 2 * c1 + t ** 3 * p1


def _normals(xy: np.ndarray) -> np.ndarray:
  d = np.gradient(xy, axis=0)
  d /= np.linalg.norm(d, axis=-1, keepdims=True) + 1e-12
  return np.stack([-d[:, 1], d[:, 0]], -1)  # left normal


class Path2D:
  """A polyline parametrised by arc length: position and heading at any s."""

  def __init__(self, xy: np.ndarray):
    self.xy = _resample(xy, 0.5)
    self.s = _arc_length(self.xy)
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


# ------------------------------------------------------------------------------------------------
# Map
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
  role: str = ""  # "in", "out", "connector"

  @functools.cached_property
  def length(self) -> float:
    return float(_arc_length(self.center)[-1])

  def boundaries(self) -> tuple[np.ndarray, np.ndarray]:
    if self.straight:  # real AV2 boundaries of straight lanes have just their two ends
      c = self.center[[0, -1]]
    else:
      c = _resample(self.center, 3.0)
    n = _normals(c) if not self.straight else np.repeat(_normals(self.center)[:1], 2, axis=0)
    return c + n * self.width / 2, c - n * self.width / 2


@dataclasses.dataclass
class Arm:
  angle: float
  n_in: int
  n_out: int
  pocket: bool
  bike: bool
  length: float
  lane_width: float
  attach: float = 0.0  # distance from the junction centre to where the arm starts
  in_slots: list = dataclasses.field(default_factory=list)   # (offset, width, kind)
  out_slots: list = dataclasses.field(default_factory=list)
  in_lanes: dict = dataclasses.field(default_factory=dict)   # (segment, slot) -> Lane
  out_lanes: dict = dataclasses.field(default_factory=dict)
  cuts: list = dataclasses.field(default_factory=list)       # segment boundaries along u

  @property
  def u(self) -> np.ndarray:
    return np.array([math.cos(self.angle), math.sin(self.angle)])

  @property
  def v(self) -> np.ndarray:
    return np.array([-math.sin(self.angle), math.cos(self.angle)])

  @property
  def width_in(self) -> float:
    return sum(w for _, w, _ in self.in_slots)

  @property
  def width_out(self) -> float:
    return sum(w for _, w, _ in self.out_slots)

  def point(self, along: float, lateral: float) -> np.ndarray:
    return along * self.u + lateral * self.v


def _slots(widths_kinds):
  """Cumulative lateral centre offsets for (width, kind) slots going outward from the median."""
  out, acc = [], 0.0
  for w, kind in widths_kinds:
    out.append((acc + w / 2, w, kind))
    acc += w
  return out


@dataclasses.dataclass
class World:
  lanes: list[Lane]
  crosswalks: list[tuple[int, np.ndarray, np.ndarray]]  # (id, edge1 [2,2], edge2 [2,2])
  drivable_areas: list[tuple[int, np.ndarray]]          # (id, ring [N, 2])
  arms: list[Arm]
  box: tuple[float, float, float, float]
  kind: str
  sidewalks: list[np.ndarray]                           # paths pedestrians walk along
  parking: list[tuple[np.ndarray, float]]               # (kerb line [2, 2], heading)


def build_world(rng: np.random.Generator) -> World:
  kind = rng.choice(["cross", "tee", "road"], p=[0.5, 0.3, 0.2])
  lane_w = float(rng.uniform(3.1, 3.8))
  angles = {"cross": [0, 90, 180, 270], "tee": [0, 180, 270], "road": [0, 180]}[kind]
  if kind == "tee":
    turn = 90 * int(rng.integers(4))
    angles = [(a + turn) % 360 for a in angles]
  junction = kind != "road"
  arms = []
  main_in, main_out = int(rng.integers(1, 4)), int(rng.integers(1, 4))
  for i, deg in enumerate(angles):
    opposite_of_first = kind == "road" and i == 1
    arms.append(Arm(
        angle=math.radians(deg),
        n_in=main_out if opposite_of_first else int(rng.integers(1, 4)) if junction else main_in,
        n_out=main_in if opposite_of_first else int(rng.integers(1, 4)) if junction else main_out,
        pocket=junction and rng.random() < 0.4,
        bike=rng.random() < 0.25,
        length=float(rng.uniform(70.0, 150.0)),
        lane_width=lane_w))
  for arm in arms:
    in_kinds = ([(lane_w, "pocket")] if arm.pocket else []) + [(lane_w, "through")] * arm.n_in
    out_kinds = [(lane_w, "through")] * arm.n_out
    if arm.bike:
      in_kinds.append((1.5, "bike"))
      out_kinds.append((1.5, "bike"))
    arm.in_slots, arm.out_slots = _slots(in_kinds), _slots(out_kinds)

  # Junction box: axis-aligned, wide enough for every arm's cross-section, plus a margin.
  margin = float(rng.uniform(2.0, 5.0)) if junction else float(rng.uniform(2.5, 4.0))
  xs, ys = [0.0], [0.0]
  for arm in arms:
    lo, hi = -arm.width_out, arm.width_in
    ends = [arm.point(0.0, lo), arm.point(0.0, hi)]
    if abs(arm.u[0]) > 0.5:  # east/west arm: its width spans y
      ys += [e[1] for e in ends]
    else:
      xs += [e[0] for e in ends]
  if junction:
    box = (min(xs) - margin, max(xs) + margin, min(ys) - margin, max(ys) + margin)
  else:  # a road: the "box" is the mid-block crossing zone
    box = (-margin, margin, min(ys), max(ys))
  for arm in arms:
    arm.attach = {0: box[1], 90: box[3], 180: -box[0], 270: -box[2]}[round(math.degrees(arm.angle)) % 360]

  ids = iter(range(int(rng.integers(10_000_000, 400_000_000)), 10**10))
  lanes: list[Lane] = []
  for arm in arms:
    n_seg = int(rng.integers(1, 5))
    # Balanced segment lengths (real AV2 lanes: median ~20 m, rarely under 4 m).
    arm.cuts = [0.0] + [float(c) for c in np.cumsum(rng.dirichlet(np.full(n_seg, 4.0))) * arm.length]
    for seg in range(n_seg):
      a0, a1 = arm.attach + arm.cuts[seg], arm.attach + arm.cuts[seg + 1]
      for slot, (off, w, skind) in enumerate(arm.in_slots):
        if skind == "pocket" and seg != 0 and n_seg > 1:
          continue  # the pocket opens in the segment next to the junction
        c = np.stack([arm.point(a1, off), arm.point(a0, off)])  # inbound: towards the junction
        tapered = skind == "pocket" and n_seg > 1
        if tapered:  # the pocket peels off the inner through lane over a taper
          taper = min(15.0, 0.5 * (a1 - a0))
          parent = arm.in_slots[slot + 1][0]
          c = np.stack([arm.point(a1, parent), arm.point(a1 - taper, off), arm.point(a0, off)])
        arm.in_lanes[(seg, slot)] = Lane(next(ids), _resample(c, 2.0), w,
                                         "BIKE" if skind == "bike" else "VEHICLE", role="in",
                                         straight=not tapered)
      for slot, (off, w, skind) in enumerate(arm.out_slots):
        c = np.stack([arm.point(a0, -off), arm.point(a1, -off)])
        arm.out_lanes[(seg, slot)] = Lane(next(ids), _resample(c, 2.0), w,
                                          "BIKE" if skind == "bike" else "VEHICLE", role="out")
    # Marks, neighbours and the chain along the arm.
    for lanes_of, slots in ((arm.in_lanes, arm.in_slots), (arm.out_lanes, arm.out_slots)):
      for (seg, slot), lane in lanes_of.items():
        skind = slots[slot][2]
        lane.left_mark = "DOUBLE_SOLID_YELLOW" if slot == 0 or (slot == 1 and slots[0][2] == "pocket" and
                                                                (seg, 0) not in lanes_of) else "DASHED_WHITE"
        if skind == "pocket":
          lane.right_mark = "SOLID_WHITE"
        if slot + 1 < len(slots) and slots[slot + 1][2] == "bike":
          lane.right_mark = "SOLID_WHITE"
        if skind == "bike":
          lane.left_mark, lane.right_mark = "SOLID_WHITE", "NONE"
        elif slot == len(slots) - 1:
          lane.right_mark = "SOLID_WHITE"
        left, right = lanes_of.get((seg, slot - 1)), lanes_of.get((seg, slot + 1))
        lane.left_neighbor = left.id if left is not None else None
        lane.right_neighbor = right.id if right is not None else None
    for seg in range(n_seg - 1):
      for slot in range(len(arm.in_slots)):
        far, near = arm.in_lanes.get((seg + 1, slot)), arm.in_lanes.get((seg, slot))
        if near is None:
          continue
        if far is None and arm.in_slots[slot][2] == "pocket":  # a pocket branches off the inner lane
          far = arm.in_lanes.get((seg + 1, slot + 1))
        if far is not None:
          far.successors.append(near.id)
          near.predecessors.append(far.id)
      for slot in range(len(arm.out_slots)):
        a, b = arm.out_lanes[(seg, slot)], arm.out_lanes[(seg + 1, slot)]
        a.successors.append(b.id)
        b.predecessors.append(a.id)
    lanes += list(arm.in_lanes.values()) + list(arm.out_lanes.values())

  # Connectors through the junction.
  def in_end(arm, slot):
    return arm.in_lanes[(0, slot)]

  def out_start(arm, slot):
    return arm.out_lanes[(0, slot)]

  by_angle = {round(math.degrees(a.angle)) % 360: a for a in arms}
  for src in arms:
    deg = round(math.degrees(src.angle)) % 360
    through = [i for i, s in enumerate(src.in_slots) if s[2] == "through"]
    bikes = [i for i, s in enumerate(src.in_slots) if s[2] == "bike"]
    pocket = [i for i, s in enumerate(src.in_slots) if s[2] == "pocket"]
    pairs = []
    straight = by_angle.get((deg + 180) % 360)
    if straight is not None:
      s_through = [i for i, s in enumerate(straight.out_slots) if s[2] == "through"]
      for j, slot in enumerate(through):
        pairs.append((slot, straight, s_through[min(j, len(s_through) - 1)]))
      if bikes:
        s_bike = [i for i, s in enumerate(straight.out_slots) if s[2] == "bike"]
        if s_bike:
          pairs.append((bikes[0], straight, s_bike[0]))
    left = by_angle.get((deg - 90) % 360)
    if left is not None and junction:
      pairs.append(((pocket or through)[0], left, 0))
    right = by_angle.get((deg + 90) % 360)
    if right is not None and junction:
      r_through = [i for i, s in enumerate(right.out_slots) if s[2] == "through"]
      pairs.append((through[-1], right, r_through[-1]))
    for slot, dst, dslot in pairs:
      a, b = in_end(src, slot), out_start(dst, dslot)
      h0 = a.center[-1] - a.center[-2]
      h1 = b.center[1] - b.center[0]
      curve = _bezier(a.center[-1], h0 / np.linalg.norm(h0), b.center[0], h1 / np.linalg.norm(h1))
      conn = Lane(next(ids), _resample(curve, 2.0), min(a.width, b.width), a.lane_type,
                  is_intersection=junction, left_mark="NONE", right_mark="NONE",
                  predecessors=[a.id], successors=[b.id], straight=False, role="connector")
      a.successors.append(conn.id)
      b.predecessors.append(conn.id)
      lanes.append(conn)

  # Crosswalks across the arms just outside the box (or across the road, mid-block).
  cw_ids = iter(range(int(rng.integers(1_000_000, 40_000_000)), 10**9))
  crosswalks, sidewalks = [], []
  for arm in arms:
    if junction and rng.random() < 0.9:
      w = float(rng.uniform(3.0, 5.0))
      lo, hi = -arm.width_out - 0.5, arm.width_in + 0.5
      e1 = np.stack([arm.point(arm.attach + 1.0, lo), arm.point(arm.attach + 1.0, hi)])
      e2 = np.stack([arm.point(arm.attach + 1.0 + w, lo), arm.point(arm.attach + 1.0 + w, hi)])
      crosswalks.append((next(cw_ids), e1, e2))
    for lateral in (arm.width_in + 2.5, -arm.width_out - 2.5):
      sidewalks.append(np.stack([arm.point(arm.attach + 2.0, lateral), arm.point(arm.attach + arm.length, lateral)]))
  if not junction and rng.random() < 0.7:
    lo, hi = box[2] - 0.5, box[3] + 0.5
    e1 = np.array([[box[0] + 0.5, lo], [box[0] + 0.5, hi]])
    e2 = np.array([[box[1] - 0.5, lo], [box[1] - 0.5, hi]])
    crosswalks.append((next(cw_ids), e1, e2))

  # Drivable areas: the box and one rectangle per arm (with a parking strip on some arms).
  da_ids = iter(range(int(rng.integers(1_000_000, 9_000_000)), 10**9))
  das = [(next(da_ids), np.array([[box[0], box[2]], [box[1], box[2]], [box[1], box[3]], [box[0], box[3]]]))]
  parking = []
  for arm in arms:
    strip = 2.4 if rng.random() < 0.5 else 0.0
    lo, hi = -arm.width_out - 0.3 - strip, arm.width_in + 0.3
    a0, a1 = arm.attach, arm.attach + arm.length
    das.append((next(da_ids), np.stack([arm.point(a0, lo), arm.point(a1, lo), arm.point(a1, hi), arm.point(a0, hi)])))
    if strip:
      kerb = -arm.width_out - 0.3 - strip / 2
      parking.append((np.stack([arm.point(a0 + 8.0, kerb), arm.point(a1 - 2.0, kerb)]), arm.angle))
  return World(lanes, crosswalks, das, arms, box, kind, sidewalks, parking)


# ------------------------------------------------------------------------------------------------
# Traffic
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class Agent:
  object_type: str
  xy: np.ndarray       # [110, 2]
  heading: np.ndarray  # [110]
  speed: np.ndarray    # [110]
  present: np.ndarray  # [110] bool
  role: str = ""


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
  else:
    raise ValueError(kind)
  return np.clip(v, 0.0, None)


def _drive(path: Path2D, s0: float, v: np.ndarray, hold_at_end: bool):
  s = s0 + np.concatenate([[0.0], np.cumsum(v[:-1] * DT)])
  present = np.ones(NUM_STEPS, bool)
  if hold_at_end:
    beyond = s > path.length
    s = np.minimum(s, path.length)
    v = np.where(beyond, 0.0, v)
  else:
    present = s <= path.length  # the agent leaves the map at the end of its route
  xy, h = path.at(s)
  return xy, h, v, present


def _clearance(kind: str) -> float:
  return {"vehicle": 5.0, "bus": 8.0, "motorcyclist": 3.5, "cyclist": 2.5, "pedestrian": 1.2,
          "static": 2.0, "background": 2.0, "construction": 2.0}[kind]


def populate(world: World, rng: np.random.Generator) -> list[Agent]:
  lane_of = {lane.id: lane for lane in world.lanes}
  vehicle_lanes = [l for l in world.lanes if l.lane_type == "VEHICLE"]
  bike_lanes = [l for l in world.lanes if l.lane_type == "BIKE" and l.role != "connector"]
  outer_lanes = [l for l in vehicle_lanes if l.role in ("in", "out") and l.right_mark == "SOLID_WHITE"]
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

  def add(make, tries: int = 25) -> bool:
    for _ in range(tries):
      cand = make()
      if cand is not None and fits(cand):
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
      prof = profile or rng.choice(["cruise", "accelerate", "stop", "queued"], p=[0.5, 0.2, 0.18, 0.12])
      stop_at = lane.length if lane.role == "in" else None
      v = _speed_profile(rng, prof, v_max, stop_at, s0)
      xy, h, v, present = _drive(path, s0, v, hold_at_end=full)
      return Agent(kind, xy, h, v, present, role=str(prof))
    return make

  # The AV and the focal vehicle are present for all 110 steps.
  add(on_lane("vehicle", 14.0, lanes=[l for l in vehicle_lanes if l.role == "in"] or vehicle_lanes, full=True), 60)
  agents[-1].role = "AV"
  if add(on_lane("vehicle", 14.0, full=True), 60):
    agents[-1].role = "focal"
  inbound = [l for l in vehicle_lanes if l.role == "in"]
  for _ in range(int(rng.integers(6, 28))):
    # Most traffic enters from the arms, so it stays on the map longer (as tracked AV2 traffic does).
    pool = inbound if rng.random() < 0.6 and inbound else vehicle_lanes
    add(on_lane("vehicle", float(rng.uniform(9.0, 16.0)), lanes=pool))
  if rng.random() < 0.2:
    add(on_lane("bus", 11.0, profile="cruise"))
  if rng.random() < 0.15:
    add(on_lane("motorcyclist", 16.0))
  for _ in range(int(rng.integers(0, 3))):
    add(on_lane("cyclist", float(rng.uniform(3.0, 7.0)), profile="cruise", lanes=bike_lanes or outer_lanes))

  # Parked cars along parking strips: present throughout, speed 0.
  for kerb, angle in world.parking:
    for _ in range(int(rng.integers(0, 5))):
      def make_parked(kerb=kerb, angle=angle):
        p = kerb[0] + rng.uniform(0, 1) * (kerb[1] - kerb[0])
        xy = np.repeat(p[None], NUM_STEPS, 0) + rng.normal(0, 0.02, (NUM_STEPS, 2))
        h = np.full(NUM_STEPS, angle + (np.pi if rng.random() < 0.5 else 0.0) + rng.normal(0, 0.03))
        return Agent("vehicle", xy, np.arctan2(np.sin(h), np.cos(h)), np.zeros(NUM_STEPS),
                     np.ones(NUM_STEPS, bool), role="parked")
      add(make_parked, 10)

  # Pedestrians on crosswalks (walk across, then wait at the kerb) and sidewalks.
  for _, e1, e2 in world.crosswalks:
    for _ in range(int(rng.integers(0, 3)) if rng.random() < 0.5 else 0):
      def make_ped(e1=e1, e2=e2):
        mid = 0.5 * (e1 + e2)
        d = mid[1] - mid[0]
        d /= np.linalg.norm(d)
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
  for _ in range(int(rng.integers(0, 6))):
    def make_static():
      walk = world.sidewalks[int(rng.integers(len(world.sidewalks)))]
      p = walk[0] + rng.uniform(0, 1) * (walk[1] - walk[0])
      return Agent(str(rng.choice(["static", "background", "construction"])), np.repeat(p[None], NUM_STEPS, 0),
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


# ------------------------------------------------------------------------------------------------
# AV2 files
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class SyntheticScenario:
  """A generated world as av2 objects: the scenario and the map JSON dict."""

  scenario: ArgoverseScenario
  map_json: dict
  kind: str


def _pts(xy: np.ndarray, z: np.ndarray | float) -> list[dict]:
  z = np.broadcast_to(np.asarray(z, np.float64), (len(xy),))
  return [{"x": round(x, 2), "y": round(y, 2), "z": round(zz, 2)}
          for (x, y), zz in zip(np.asarray(xy, np.float64).tolist(), z.tolist())]


def scenario_id_for(seed: int, index: int) -> str:
  """The scenario id of (seed, index), known before generating it (so reruns can skip it)."""
  return str(uuid.UUID(bytes=np.random.default_rng([seed, index, 1]).bytes(16), version=4))


def generate_scenario(seed: int, index: int) -> SyntheticScenario:
  """Deterministic in (seed, index)."""
  rng = np.random.default_rng([seed, index])
  world = build_world(rng)
  agents = populate(world, rng)
  scenario_id = scenario_id_for(seed, index)

  # Place the local world in a random city frame.
  rot = _rot(float(rng.uniform(-np.pi, np.pi)))
  angle = math.atan2(rot[1, 0], rot[0, 0])
  shift = rng.uniform(-1500, 4500, 2).round(2)
  to_city = lambda xy: np.asarray(xy) @ rot.T + shift  # noqa: E731
  ground = float(rng.uniform(-20, 30))

  lanes = {}
  for lane in world.lanes:
    left, right = lane.boundaries()
    z_left = ground + 0.01 * np.arange(len(left))
    z_right = ground + 0.01 * np.arange(len(right))
    lanes[str(lane.id)] = {
        "centerline": _pts(to_city(lane.center), 0.0),
        "id": lane.id,
        "is_intersection": bool(lane.is_intersection),
        "lane_type": lane.lane_type,
        "left_lane_boundary": _pts(to_city(left), z_left),
        "left_lane_mark_type": lane.left_mark,
        "left_neighbor_id": lane.left_neighbor,
        "predecessors": list(lane.predecessors),
        "right_lane_boundary": _pts(to_city(right), z_right),
        "right_lane_mark_type": lane.right_mark,
        "right_neighbor_id": lane.right_neighbor,
        "successors": list(lane.successors),
    }
  crossings = {str(i): {"edge1": _pts(to_city(e1), ground), "edge2": _pts(to_city(e2), ground), "id": i}
               for i, e1, e2 in world.crosswalks}
  areas = {str(i): {"area_boundary": _pts(to_city(ring), ground), "id": i} for i, ring in world.drivable_areas}
  map_json = {"drivable_areas": areas, "lane_segments": lanes, "pedestrian_crossings": crossings}

  base = int(rng.integers(10_000, 900_000))
  tracks = []
  focal_id = None
  for k, agent in enumerate(agents):
    track_id = "AV" if agent.role == "AV" else str(base + k)
    if agent.role == "AV":
      category = TrackCategory.UNSCORED_TRACK
    elif agent.role == "focal":
      category, focal_id = TrackCategory.FOCAL_TRACK, track_id
    elif agent.present.all() and agent.role not in ("static", "parked"):
      category = TrackCategory.SCORED_TRACK if rng.random() < 0.3 else TrackCategory.UNSCORED_TRACK
    else:
      category = TrackCategory.TRACK_FRAGMENT
    xy = to_city(agent.xy)
    heading = np.arctan2(np.sin(agent.heading + angle), np.cos(agent.heading + angle))
    vel = agent.speed[:, None] * np.stack([np.cos(heading), np.sin(heading)], -1)
    steps = np.flatnonzero(agent.present)
    states = [ObjectState(observed=t < OBSERVED_STEPS, timestep=t, position=(x, y), heading=h, velocity=(vx, vy))
              for t, (x, y), h, (vx, vy) in zip(steps.tolist(), xy[steps].tolist(), heading[steps].tolist(),
                                                vel[steps].tolist())]
    tracks.append(Track(track_id, states, ObjectType(agent.object_type), category))
  if focal_id is None:  # no focal vehicle could be placed: promote a full-length track
    full = [t for t in tracks if t.track_id != "AV" and len(t.object_states) == NUM_STEPS]
    focal = (full or tracks)[0]
    focal.category = TrackCategory.FOCAL_TRACK
    focal_id = focal.track_id
  tracks.sort(key=lambda t: t.track_id)  # av2's loader groups tracks by string id
  start = float(int(rng.integers(315_000_000_000_000_000, 320_000_000_000_000_000)))
  timestamps = np.linspace(start, start + (NUM_STEPS - 1) * 1e8, NUM_STEPS)
  scenario = ArgoverseScenario(scenario_id=scenario_id, timestamps_ns=timestamps, tracks=tracks,
                               focal_track_id=focal_id, city_name="synthetic", map_id=None, slice_id=None)
  return SyntheticScenario(scenario, map_json, world.kind)


def write_scenario(sc: SyntheticScenario, split_dir: Path) -> Path:
  """Writes `<split_dir>/<id>/` atomically: a folder appears complete or not at all."""
  return av2_io.write_scenario_folder(sc.scenario, sc.map_json, split_dir)


def _generate_one(args) -> str:
  seed, index, split_dir = args
  if (Path(split_dir) / scenario_id_for(seed, index)).is_dir():
    return scenario_id_for(seed, index)  # written by an earlier run
  sc = generate_scenario(seed, index)
  write_scenario(sc, Path(split_dir))
  return sc.scenario.scenario_id


def split_of(index: int, num: int, val_fraction: float) -> str:
  num_val = int(math.ceil(num * val_fraction)) if val_fraction > 0 else 0
  return "val" if index >= num - num_val else "train"


def generate_dataset(out: Path | str, num: int, seed: int = 0, val_fraction: float = 0.1,
                     workers: int | None = None, progress: bool = True,
                     splits: tuple[str, ...] = ("train", "val")) -> dict[str, int]:
  """Writes `num` scenarios under out/train and out/val. Resumable: existing scenarios are kept.
  `splits=("val",)` writes the validation scenarios only (a later call with both splits adds the rest).

  `out/synthetic.json` records what the folder holds (written before the first scenario, with the
  counts once all are written). A folder made with other settings, or holding scenario folders this
  generator did not record, is refused: reusing it would mix two datasets and leak scenarios between
  the splits. Returns the number of scenarios per split.
  """
  from tqdm import tqdm

  out = Path(out)
  done_file = out / "synthetic.json"
  asked = {"num": num, "seed": seed, "val_fraction": val_fraction}
  if done_file.exists():
    meta = json.loads(done_file.read_text())
    made = {k: meta.get(k) for k in asked}
    if made != asked:
      raise ValueError(f"{out} holds synthetic scenarios made with {made}, not the {asked} asked for; "
                       "use another folder (or delete this one)")
    if meta.get("counts"):
      return meta["counts"]
  elif any(p.is_dir() and any(p.iterdir()) for p in (out / "train", out / "val")):
    raise ValueError(f"{out} already holds scenario folders that this generator did not record; "
                     "use another folder (or delete this one)")
  out.mkdir(parents=True, exist_ok=True)
  files.atomic_write_text(done_file, json.dumps(asked))   # what this folder is being filled with
  jobs, counts = [], {"train": 0, "val": 0}
  for i in range(num):
    split = split_of(i, num, val_fraction)
    counts[split] += 1
    if split in splits:
      (out / split).mkdir(parents=True, exist_ok=True)
      jobs.append((seed, i, str(out / split)))
  for split in counts:  # leftovers of a killed run
    for tmp in (out / split).glob(".tmp-*") if (out / split).exists() else []:
      shutil.rmtree(tmp, ignore_errors=True)
  workers = workers or os.cpu_count() or 1
  bar = tqdm(total=len(jobs), desc="synthetic scenarios", disable=not progress, unit="scn")
  if workers == 1:
    for job in jobs:
      _generate_one(job)
      bar.update()
  else:
    import multiprocessing
    with futures.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
      for _ in pool.map(_generate_one, jobs, chunksize=8):
        bar.update()
  bar.close()
  if set(splits) >= set(counts):
    files.atomic_write_text(done_file, json.dumps({**asked, "counts": counts}))
  return counts


def define_flags(values: flags.FlagValues) -> None:
  flags.DEFINE_string("out", None, "output directory (gets train/ and val/)", required=True, flag_values=values)
  flags.DEFINE_integer("num", 1000, "number of scenarios in all", lower_bound=1, flag_values=values)
  cli.define_seed_flag(values)
  flags.DEFINE_float("val_fraction", 0.1, "share of the scenarios in val/, in [0, 1)", lower_bound=0.0,
                     upper_bound=0.999999, flag_values=values)
  flags.DEFINE_integer("workers", 0, "processes (0: all cores)", lower_bound=0, flag_values=values)


def run(f: flags.FlagValues, args: list[str]) -> None:
  cli.no_arguments(args)
  try:
    counts = generate_dataset(files.user_path(f.out), f.num, f.seed, f.val_fraction, f.workers or None)
  except (OSError, ValueError) as e:
    raise SystemExit(f"synthetic: {e}") from None
  print(json.dumps({"out": str(f.out), **counts}))


main = cli.entry_point(define_flags, run)  # `python -m tdiff_jax.data.synthetic --out=DIR`, `main(["--out=DIR"])`


if __name__ == "__main__":
  main()
