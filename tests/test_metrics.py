"""Realism metrics on hand-built scenes with known answers, and ground truth against itself."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.av2_samples import DATA, REAL_110
from tdiff_jax import datatypes, metrics
from tdiff_jax.data import scene_builder

A = 4
VEHICLE, PEDESTRIAN = datatypes.AGENT_TYPES.index("vehicle"), datatypes.AGENT_TYPES.index("pedestrian")


def straight_road(agent_xy, agent_type=None, heading=None) -> datatypes.Scene:
  """One lane along the x axis from -50 to 50 m (centreline y = 0, boundaries y = +-2), drivable area
  the rectangle [-50, 30] x [-5, 5]; agents at `agent_xy` `[n, 2]` (initial = goal)."""
  n = len(agent_xy)
  k = 10
  x = np.linspace(-50, 50, k)
  pt_xy = np.zeros((2, 3 * k, 2), np.float32)
  for side, y in enumerate((2.0, -2.0, 0.0)):
    pt_xy[0, side * k:(side + 1) * k] = np.stack([x, np.full(k, y)], -1)
  pt_side = np.repeat(np.arange(3), k)[None].repeat(2, 0).astype(np.int32)
  state = np.zeros((A, 2, 4), np.float32)
  state[:n, :, :2] = np.asarray(agent_xy, np.float32)[:, None]
  state[:n, :, 2] = 5.0
  if heading is not None:
    state[:n, :, 3] = np.asarray(heading)[:, None]
  types_ = np.zeros(A, np.int32)
  if agent_type is not None:
    types_[:n] = agent_type
  da = np.zeros((1, 4, 2), np.float32)
  da[0] = [[-50, -5], [30, -5], [30, 5], [-50, 5]]
  scene = datatypes.Scene(
      agent_state=state, agent_type=types_, agent_valid=np.arange(A) < n,
      agent_future=np.zeros((A, datatypes.HORIZON, 2), np.float32),
      agent_future_valid=np.zeros((A, datatypes.HORIZON), bool),
      pl_xy=np.array([[-50, 0], [0, 0]], np.float32), pl_heading=np.zeros(2, np.float32),
      pl_type=np.zeros(2, np.int32), pl_intersection=np.zeros(2, np.int32), pl_valid=np.array([True, False]),
      pt_xy=pt_xy, pt_heading=np.zeros((2, 3 * k), np.float32), pt_type=np.full((2, 3 * k), 16, np.int32),
      pt_side=pt_side, pt_valid=np.array([True, False])[:, None].repeat(3 * k, 1),
      pl_edge=np.zeros((2, 2), np.int8), da_xy=da, da_valid=np.ones((1, 4), bool),
      frame_origin=np.zeros(2), frame_scale=np.float32(125.0))
  scene.validate()
  return scene


def accumulate(scene: datatypes.Scene, token: int = 0) -> dict:
  batch = jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], scene)
  s = batch.agent_state[:, :, token]
  return jax.device_get(metrics.state_accumulators(s[..., :2], s[..., 2], s[..., 3], batch))


def test_official_collision_is_centre_distance_below_2m():
  acc = accumulate(straight_road([[0, 0], [1.5, 0], [20, 0]]))
  assert acc["official/collision_sum"] == 2 and acc["official/collision_count"] == 3
  # Two pedestrians 1.5 m apart do not collide under the official rule (1 m for pedestrian pairs).
  acc = accumulate(straight_road([[0, 0], [1.5, 0]], agent_type=[PEDESTRIAN, PEDESTRIAN]))
  assert acc["official/collision_sum"] == 0


def test_box_overlap_that_centre_distance_misses():
  # Two 4 m x 2 m cars nose to tail, centres 3.5 m apart: boxes overlap by 0.5 m, centres are > 2 m apart.
  acc = accumulate(straight_road([[0, 0], [3.5, 0]]))
  assert acc["official/collision_sum"] == 0 and acc["strict/collision_sum"] == 2
  # Side by side 2.5 m apart: neither rule fires. Rotated by 90 degrees: the boxes (now 4 m across) overlap.
  assert accumulate(straight_road([[0, 0], [0, 2.5]]))["strict/collision_sum"] == 0
  acc = accumulate(straight_road([[0, 0], [0, 2.5]], heading=[np.pi / 2, np.pi / 2]))
  assert acc["strict/collision_sum"] == 2


def test_offroad_both_conventions_and_agents_outside_the_map():
  # Centreline vertices are 11.1 m apart; the official convention measures to points every 2.8 m.
  # (0, 4.5): 4.5 m from the nearest such point (official: off-road), inside the drivable area (strict: on).
  # (40, 0): 1.1 m from a point (official: on), beyond the drivable area's end (strict: off).
  # (80, 0): outside the map crop: off under the official rule; strict excludes and counts it.
  acc = accumulate(straight_road([[0, 4.5], [40, 0], [80, 0], [-50 + 400 / 9, 0]]))  # the last on a vertex
  assert acc["official/offroad_sum"] == 2 and acc["official/offroad_count"] == 4
  assert acc["strict/offroad_sum"] == 1 and acc["strict/offroad_count"] == 3 and acc["strict/outside_map"] == 1
  # Near edge: official = distance to centreline vertices (11.1 m spacing), strict = to the segments.
  np.testing.assert_allclose(acc["strict/near_edge_sum"] / acc["strict/near_edge_count"], (4.5 + 0 + 30 + 0) / 4,
                             rtol=1e-4)


def test_js_divergence_known_values():
  p = np.array([1.0, 0.0])
  q = np.array([0.0, 1.0])
  assert metrics.js_divergence(p, p) == 0.0
  np.testing.assert_allclose(metrics.js_divergence(p, q), np.log(2), rtol=1e-12)
  np.testing.assert_allclose(metrics.js_distance(p, q), np.sqrt(np.log(2)), rtol=1e-12)
  h1, h2 = np.array([3.0, 1.0]), np.array([1.0, 1.0])       # [0.75, 0.25] vs [0.5, 0.5]
  m = np.array([0.625, 0.375])
  want = 0.5 * (0.75 * np.log(0.75 / m[0]) + 0.25 * np.log(0.25 / m[1])) + 0.5 * (0.5 * np.log(0.5 / m[0]) + 0.5 * np.log(0.5 / m[1]))
  np.testing.assert_allclose(metrics.js_divergence(h1, h2), want, rtol=1e-12)
  assert np.isnan(metrics.js_divergence(np.zeros(3), np.ones(3)))   # an empty histogram


def test_histogram_bins_drop_or_clip():
  acc = accumulate(straight_road([[0, 0], [3.0, 0.5]]))
  # Speeds 5 m/s -> bin 5 of [0, 50]; nearest distances ~3.04 m -> bin 3 (both conventions).
  assert acc["official/hist_speed"][5] == 2 and acc["official/hist_speed"].sum() == 2
  assert acc["official/hist_nearest_distance"][3] == 2
  far = accumulate(straight_road([[-40, 0], [40, 4.0]]))
  # Lateral deviation 4 m is beyond the [0, 3] m bins: dropped (official), clipped into the last bin (strict).
  assert far["official/hist_lateral_deviation"].sum() == 1
  assert far["strict/hist_lateral_deviation"][-1] == 1


def test_edge_cases_one_agent_and_none():
  one = accumulate(straight_road([[0, 0]]))
  assert one["official/collision_sum"] == 0 and one["strict/collision_sum"] == 0
  assert one["official/hist_nearest_distance"][0] == 1          # official: an agent alone counts as 0 m
  assert one["strict/hist_nearest_distance"].sum() == 0         # strict: excluded
  assert one["official/hist_local_density"].sum() == 0
  none = accumulate(straight_road(np.zeros((0, 2))))
  assert all(float(np.sum(v)) == 0 for v in none.values())
  row = metrics.summarize(metrics.add(None, none), metrics.add(None, none), "official")
  assert np.isnan(row["collision_rate_pct"]) and np.isnan(row["jsd_speed"])


def test_ground_truth_against_itself():
  scenes = [scene_builder.load_scene(DATA / sid)[0] for sid in REAL_110]
  batch = jax.tree_util.tree_map(jnp.asarray, datatypes.stack_scenes(scenes))
  total = None
  for tok in range(2):
    s = batch.agent_state[:, :, tok]
    total = metrics.add(total, metrics.state_accumulators(s[..., :2], s[..., 2], s[..., 3], batch))
  for conv in metrics.CONVENTIONS:
    row = metrics.summarize(total, total, conv)
    assert row["agents"] == 2 * int(batch.agent_valid.sum())
    for name in metrics.HISTOGRAMS:
      assert row[f"jsd_{name}"] == pytest.approx(0.0, abs=1e-12)
    assert 0.0 <= row["offroad_rate_pct"] <= 100.0 and 0.0 < row["near_edge_m"] < 10.0
  # Real AV2 ground truth: vehicles kept near lanes, so the official off-road rate is low.
  assert metrics.summarize(total, None, "official")["offroad_rate_pct"] < 10.0


def lane_network(initial, goal, speed, agent_type=None, lane_2_y=20.0) -> datatypes.Scene:
  """Lane 0 from (-50, 0) to (0, 0), its successor lane 1 from (0, 0) to (50, 0), and lane 2 from
  (50, `lane_2_y`) to (-50, `lane_2_y`), connected to neither (3.5: the opposite lane of a two-way road);
  one agent per row of `initial`, `goal` `[n, 2]`."""
  n, k, p = len(initial), 10, 3
  pt_xy = np.zeros((p, 3 * k, 2), np.float32)
  for lane, (x0, x1, y) in enumerate(((-50, 0, 0), (0, 50, 0), (50, -50, lane_2_y))):
    x = np.linspace(x0, x1, k)
    for side, dy in enumerate((2.0, -2.0, 0.0)):
      pt_xy[lane, side * k:(side + 1) * k] = np.stack([x, np.full(k, y + dy)], -1)
  state = np.zeros((A, 2, 4), np.float32)
  state[:n, 0, :2], state[:n, 1, :2] = initial, goal
  state[:n, :, 2] = np.asarray(speed, np.float32)[:, None]
  types_ = np.zeros(A, np.int32)
  if agent_type is not None:
    types_[:n] = agent_type
  edge = np.zeros((p, p), np.int8)
  edge[0, 1] = datatypes.EDGE_TYPES.index("SUCC")
  edge[1, 0] = datatypes.EDGE_TYPES.index("PRED")
  scene = datatypes.Scene(
      agent_state=state, agent_type=types_, agent_valid=np.arange(A) < n,
      agent_future=np.zeros((A, datatypes.HORIZON, 2), np.float32),
      agent_future_valid=np.zeros((A, datatypes.HORIZON), bool),
      pl_xy=pt_xy[:, 2 * k], pl_heading=np.array([0, 0, np.pi], np.float32),
      pl_type=np.zeros(p, np.int32), pl_intersection=np.zeros(p, np.int32), pl_valid=np.ones(p, bool),
      pt_xy=pt_xy, pt_heading=np.zeros((p, 3 * k), np.float32), pt_type=np.full((p, 3 * k), 16, np.int32),
      pt_side=np.repeat(np.arange(3), k)[None].repeat(p, 0).astype(np.int32), pt_valid=np.ones((p, 3 * k), bool),
      pl_edge=edge, da_xy=np.zeros((1, 4, 2), np.float32), da_valid=np.zeros((1, 4), bool),
      frame_origin=np.zeros(2), frame_scale=np.float32(125.0))
  scene.validate()
  return scene


@pytest.mark.parametrize("initial, goal, speed, lane_2_y, reason", [
    ((-30, 0), (5, 0), 5.0, 20.0, "reachable"),      # 35 m ahead through the successor, 6 s x 5 m/s + 10 m = 40 m allowed
    ((-30, 0), (45, 0), 5.0, 20.0, "too_far"),       # 75 m: too far for 5 m/s
    ((-30, 0), (45, 0), 15.0, 20.0, "reachable"),    # ... but not for 15 m/s
    ((-10, 0), (-30, 0), 5.0, 20.0, "behind"),       # behind the start on a directed lane
    ((-10, 0), (-11, 0), 0.0, 20.0, "reachable"),    # a stopped agent a metre back: within the slack
    ((-30, 0), (0, 20), 5.0, 20.0, "no_route"),      # on a lane not connected to the start
    ((-30, 0), (5, 10), 5.0, 20.0, "off_lane"),      # the goal 10 m from every lane
    ((-30, 0), (5, 2.2), 5.0, 3.5, "lane_width_off"),  # the goal nearer the opposite lane than its own
    ((-30, 0), (5, 1.5), 5.0, 3.5, "reachable"),     # ... and nearer its own
])
def test_goal_reachability_follows_the_directed_lane_graph(initial, goal, speed, lane_2_y, reason):
  scene = lane_network([initial], [goal], [speed], lane_2_y=lane_2_y)
  counts = metrics.goal_reachability(scene.agent_state, scene)
  assert set(counts) == set(metrics.REACHABILITY_COUNTS)
  assert counts["road_users"] == 1 and counts["pedestrians"] == 0
  assert {k: counts[k] for k in ("reachable", *metrics.REACHABILITY_FAILURES)} == {
      k: int(k == reason) for k in ("reachable", *metrics.REACHABILITY_FAILURES)}


def test_goal_reachability_excludes_and_counts_pedestrians():
  scene = lane_network([(-30, 0), (-30, 0)], [(5, 0), (5, 0)], [5.0, 5.0], [VEHICLE, PEDESTRIAN])
  counts = metrics.goal_reachability(scene.agent_state, scene)
  assert counts == {**dict.fromkeys(metrics.REACHABILITY_FAILURES, 0), "reachable": 1, "road_users": 1, "pedestrians": 1}
  assert metrics.reachability_pct(counts) == 100.0


def test_ground_truth_goals_are_reachable_on_real_maps():
  counts = {"reachable": 0, "road_users": 0}
  shuffled = {"reachable": 0, "road_users": 0}
  for sid in REAL_110:
    s, _ = scene_builder.load_scene(DATA / sid)
    for k, v in metrics.goal_reachability(s.agent_state, s).items():
      counts[k] = counts.get(k, 0) + v
    st = np.array(s.agent_state)
    n = int(s.agent_valid.sum())
    st[:n, 1] = st[np.roll(np.arange(n), 1), 1]  # every agent gets another agent's goal
    for k, v in metrics.goal_reachability(st, s).items():
      shuffled[k] = shuffled.get(k, 0) + v
  assert metrics.reachability_pct(counts) >= 80.0, counts
  assert metrics.reachability_pct(shuffled) < metrics.reachability_pct(counts) - 30.0, (counts, shuffled)
