"""The realism score on hand-made trajectories with known speeds, accelerations, turn rates, gaps and
times to collision, and the score's ordering: the logged scenario itself beats shuffled ones."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tdiff_jax import datatypes, geometry, realism
from tests.test_metrics import straight_road

T = 60
VEHICLE = datatypes.AGENT_TYPES.index("vehicle")
t = np.arange(T) * realism.DT


def features(xy, heading0=None, agent_type=None, valid=None, scene=None):
  """`trajectory_features` of one scenario `xy` `[A, T, 2]` on `scene` (default: the straight road)."""
  xy = jnp.asarray(xy, jnp.float32)[None]
  a = xy.shape[1]
  valid = jnp.ones((1, a, T), bool) if valid is None else jnp.asarray(valid)[None]
  heading0 = jnp.zeros((1, a)) if heading0 is None else jnp.asarray(heading0, jnp.float32)[None]
  types = jnp.full((1, a), VEHICLE) if agent_type is None else jnp.asarray(agent_type)[None]
  scene = straight_road([[0, 0]]) if scene is None else scene
  geom = geometry.map_geometry(jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], scene))
  return jax.device_get(realism.trajectory_features(xy, valid, heading0, types, geom))


def line(x0, y0, speed, accel=0.0, heading=0.0):
  s = x0 + speed * t + 0.5 * accel * t ** 2
  return np.stack([s * np.cos(heading), y0 + s * np.sin(heading)], -1)


def test_kinematics_of_straight_accelerating_and_turning_motion():
  circle_r, rate = 20.0, 0.3   # 6 m/s on a 20 m circle: 0.3 rad/s
  circle = np.stack([circle_r * np.sin(rate * t), circle_r * (1 - np.cos(rate * t))], -1)
  f = features(np.stack([line(-40, 0, 10.0), line(-40, 3, 2.0, accel=1.5), circle]))
  inner = slice(2, T - 2)
  speed, speed_ok = f["linear_speed"]
  assert not speed_ok[0, :, 0].any() and speed_ok[0, :, 1:-1].all()
  np.testing.assert_allclose(speed[0, 0, inner], 10.0, atol=1e-3)
  np.testing.assert_allclose(speed[0, 1, inner], 2.0 + 1.5 * t[inner], atol=1e-3)
  np.testing.assert_allclose(speed[0, 2, inner], circle_r * rate, rtol=1e-3)
  np.testing.assert_allclose(f["linear_acceleration"][0][0, :2, inner], [[0.0] * (T - 4), [1.5] * (T - 4)], atol=1e-2)
  np.testing.assert_allclose(f["angular_speed"][0][0, 0, inner], 0.0, atol=1e-4)
  np.testing.assert_allclose(f["angular_speed"][0][0, 2, inner], rate, rtol=1e-2)
  np.testing.assert_allclose(f["angular_acceleration"][0][0, 2, 3:T - 3], 0.0, atol=1e-2)


def test_a_stopped_object_keeps_its_initial_heading():
  xy = np.stack([np.full((T, 2), 5.0), line(-40, 0, 8.0, heading=0.5)])
  heading = realism.motion_headings(jnp.asarray(xy), jnp.ones((2, T), bool), jnp.asarray([1.2, 0.0]))
  np.testing.assert_allclose(heading[0], 1.2, atol=1e-6)
  np.testing.assert_allclose(heading[1], 0.5, atol=1e-5)


@pytest.mark.parametrize("offset, expected", [((0.0, 5.0), 3.0), ((7.0, 0.0), 3.0), ((0.0, 1.0), -1.0)])
def test_distance_between_boxes(offset, expected):
  # Two 4 m x 2 m cars, heading 0: side by side 5 m apart (gap 3 m), nose to tail 7 m apart (gap 3 m),
  # or overlapping by 1 m sideways (rounded corners keep the straight sides' distances).
  xy = np.stack([np.zeros((T, 2)), np.broadcast_to(offset, (T, 2))])
  f = features(xy)
  np.testing.assert_allclose(f["distance_to_nearest_object"][0][0, :, 10], expected, atol=1e-4)
  assert f["collision"][0][0].tolist() == [expected < 0] * 2


def test_box_signed_distance_at_a_corner_is_the_corner_gap():
  unit = geometry.box_corners(jnp.zeros(2), 0.0, jnp.array([2.0, 2.0]))
  other = geometry.box_corners(jnp.array([4.0, 4.0]), 0.0, jnp.array([2.0, 2.0]))
  np.testing.assert_allclose(realism.box_signed_distance(unit, other), np.sqrt(8.0), rtol=1e-5)  # (1, 1) to (3, 3)


def test_time_to_collision_of_a_follower():
  # A follower at 10 m/s 20 m behind a leader at 5 m/s (both 4 m long): a 16 m gap closing at 5 m/s.
  xy = np.stack([line(-40, 0, 10.0), line(-20, 0, 5.0), line(-40, 20, 1.0)])
  ttc, _ = features(xy)["time_to_collision"]
  np.testing.assert_allclose(ttc[0, 0, 5], (16.0 - 5 * 5 * realism.DT) / 5.0, rtol=1e-3)
  assert ttc[0, 1, 5] == realism.MAX_TTC_S and ttc[0, 2, 5] == realism.MAX_TTC_S   # followed, and alone


def test_road_edge_distance_and_offroad():
  # The straight road's drivable area is [-50, 30] x [-5, 5]: a car on its centre line is 4 m inside
  # (its side 1 m from the centre); one driving out past x = 30 leaves it.
  xy = np.stack([np.broadcast_to([0.0, 0.0], (T, 2)), line(20, 0, 5.0)])
  edge, road = features(xy, agent_type=[VEHICLE, VEHICLE])["distance_to_road_edge"]
  np.testing.assert_allclose(edge[0, 0], -4.0, atol=1e-3)
  assert edge[0, 1, 0] < 0 and edge[0, 1, -1] > 0 and road.all()
  f = features(xy)
  assert f["offroad"][0][0].tolist() == [False, True]
  pedestrian = datatypes.AGENT_TYPES.index("pedestrian")
  assert not features(xy, agent_type=[pedestrian, pedestrian])["distance_to_road_edge"][1].any()


def scenario_scores(logged, generated):
  """Scores of logged features (one scenario) under generated features' pooled histograms."""
  counts = {k: v.sum(0, keepdims=True) for k, v in realism.histograms(generated).items()}
  return realism.scores(jax.device_get(realism.log_likelihoods(counts, logged)))


def test_the_logged_scenario_scores_above_shuffled_ones():
  rng = np.random.default_rng(0)
  speeds = rng.uniform(0, 15, 6)
  xy = np.stack([line(-45 + 8 * i, rng.uniform(-3, 3), s, accel=rng.uniform(-1, 1)) for i, s in enumerate(speeds)])
  logged = features(xy)
  assert scenario_scores(logged, logged)["meta"][0] > 0.5
  # Shuffled: each object's steps in random order (speeds, turns and gaps scrambled).
  shuffled = features(np.stack([x[rng.permutation(T)] for x in xy]))
  s_same, s_shuffled = scenario_scores(logged, logged), scenario_scores(logged, shuffled)
  assert s_same["meta"][0] > s_shuffled["meta"][0]
  for name in ("linear_speed", "linear_acceleration", "angular_speed"):
    assert s_same[name][0] > s_shuffled[name][0], name
  assert set(s_same) == set(realism.FEATURES) | {"meta"}


def test_weights_are_the_challenge_configuration_without_traffic_lights():
  assert sum(f.weight for f in realism.FEATURES.values()) + realism.TRAFFIC_LIGHT_WEIGHT == pytest.approx(1.0)
  # A feature without logged values (NaN) leaves the meta-metric the weighted mean of the others.
  per_map = realism.scores({"collision": (np.array([0.0]), np.array([2.0])),
                            "offroad": (np.array([0.0]), np.array([0.0]))})
  assert per_map["collision"][0] == 1.0 and np.isnan(per_map["offroad"][0]) and per_map["meta"][0] == 1.0
