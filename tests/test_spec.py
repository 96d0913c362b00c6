"""Scenario specs: the file's checks, the exact predicates, the cost that guides towards them, placements on
real maps, and `sample.py --spec` end to end with the shipped models."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.av2_samples import DATA, REAL_110
from tdiff_jax import checkpoint, datatypes, generate, sampling
from tdiff_jax import spec as spec_lib
from tdiff_jax.data import scene_builder

ROOT = Path(__file__).resolve().parent.parent
LIBRARY = sorted((ROOT / "specs").glob("*.yaml"))
VEHICLE = datatypes.AGENT_TYPES.index("vehicle")


def test_the_library_holds_the_eight_situations_and_every_spec_parses():
  names = {spec_lib.load(path, max_agents=64).name for path in LIBRARY}
  assert {"unprotected_left_turn", "cut_in", "pedestrian_crossing_ahead", "queue_at_junction",
          "right_turn_with_cyclist", "oncoming_straight_road", "stopped_vehicle_ahead", "u_turn"} <= names
  spec = spec_lib.load(ROOT / "specs" / "unprotected_left_turn.yaml")
  assert [spec.label(k) for k in range(3)] == ["ego", "oncoming#1", "oncoming#2"]
  assert spec.agents[1].relation == spec_lib.Relation(0, "oncoming", (10.0, 50.0)) and spec.others is None


GOOD = {"name": "x", "agents": [{"name": "ego", "type": "vehicle"},
                                {"name": "b", "type": "cyclist", "relation": {"to": "ego", "kind": "ahead",
                                                                            "distance": [1, 5]}}]}


def _with(path: str, value):
  raw = json.loads(json.dumps(GOOD))
  *parents, last = path.split(".")
  node = raw
  for p in parents:
    node = node[int(p)] if p.isdigit() else node[p]
  node[int(last) if last.isdigit() else last] = value
  return raw


@pytest.mark.parametrize("raw, key", [
    (_with("colour", 1), "colour: unknown key"),
    (_with("agents.0.type", "car"), "agents[0].type: unknown value 'car'"),
    (_with("agents.1.relation.kind", "beside"), "agents[1].relation.kind: unknown value 'beside'"),
    (_with("agents.1.relation.to", "nobody"), "agents[1].relation.to: 'nobody' names no agent"),
    (_with("agents.1.relation.distance", [5, 1]), "agents[1].relation.distance: empty or negative range"),
    (_with("agents.0.speed", {"initial": [3]}), "agents[0].speed.initial: expected [low, high]"),
    (_with("agents.1.count", 70), "agents: 71 constrained"),
    (_with("others", 64), "others: 2 constrained + 64 other agents"),
    (_with("agents.0.maneuver", "jump"), "agents[0].maneuver: unknown value 'jump'"),
    (_with("agents.0.relation", {"to": "b", "kind": "behind", "distance": [1, 5]}), "agents[0].relation.to: the relations go round in a circle"),
    (_with("agents", []), "agents: expected a non-empty list"),
])
def test_a_bad_spec_is_one_error_naming_the_key(raw, key):
  with pytest.raises(spec_lib.SpecError, match="^" + re.escape("bad.yaml: " + key)):
    spec_lib.parse(raw, "bad.yaml", max_agents=64)


def test_a_bad_spec_file_stops_sample_py_before_any_model_is_loaded(tmp_path):
  bad = tmp_path / "bad.yaml"
  bad.write_text("agents:\n  - type: vehicle\n    maneuver: left\n    region: junction\n")
  run = subprocess.run([sys.executable, str(ROOT / "sample.py"), f"--spec={bad}", f"--hl_workdir={tmp_path / 'none'}",
                        f"--out={tmp_path / 'out'}"], capture_output=True, text=True, cwd=ROOT, timeout=120)
  assert run.returncode != 0
  assert f"{bad}: agents[0].region: unknown value 'junction'" in run.stderr and "checkpoint" not in run.stderr
  assert not (tmp_path / "out").exists()
  broken = tmp_path / "broken.json"
  broken.write_text("{")
  with pytest.raises(spec_lib.SpecError, match="broken.json: not valid JSON"):
    spec_lib.load(broken)


def _pose(x, y, heading_deg, speed=5.0):
  return [x, y, speed], math.radians(heading_deg)


def _states(*agents):
  """`(state [A, 2, 3], heading [A, 2])` from per agent ((x, y, heading) initial, (x, y, heading) goal)."""
  state = np.array([[[a[0][0], a[0][1], 5.0], [a[1][0], a[1][1], 5.0]] for a in agents])
  heading = np.radians([[a[0][2], a[1][2]] for a in agents])
  return state, heading


@pytest.mark.parametrize("maneuver, goal, holds", [
    ("left", (15, 15, 90), True), ("left", (15, -15, -90), False), ("right", (15, -15, -90), True),
    ("straight", (30, 1, 5), True), ("straight", (3, 0, 0), False), ("straight", (20, 10, 40), False),
    ("u_turn", (0, 8, 175), True), ("u_turn", (15, 15, 90), False), ("stationary", (0.5, 0, 0), True),
    ("stationary", (5, 0, 0), False)])
def test_maneuvers_from_the_initial_to_the_goal_heading(maneuver, goal, holds):
  state, heading = _states(((0, 0, 0), goal))
  assert spec_lib.maneuver_holds(maneuver, state[0], heading[0]) == holds


@pytest.mark.parametrize("kind, other, holds", [
    ("ahead", ((10, 1, 10), (40, 1, 0)), True), ("ahead", ((-10, 0, 0), (20, 0, 0)), False),
    ("behind", ((-10, 1, 0), (20, 0, 0)), True), ("left_lane", ((5, 3.5, 0), (30, 3.5, 0)), True),
    ("left_lane", ((5, -3.5, 0), (30, -3.5, 0)), False), ("right_lane", ((5, -3.5, 0), (30, -3.5, 0)), True),
    ("oncoming", ((15, 3.5, 180), (0, 3.5, 180)), True), ("oncoming", ((30, 3.5, 0), (60, 3.5, 0)), False),
    ("crossing", ((12, 5, 90), (12, 12, 90)), True), ("crossing", ((12, 5, 180), (0, 5, 180)), False),
    ("cut_in", ((8, 3.5, 0), (45, 0.5, 0)), True), ("cut_in", ((8, 3.5, 0), (45, 3.5, 0)), False),
])
def test_relations_in_the_frame_of_the_related_agent(kind, other, holds):
  """Agent 0 starts at the origin heading +x and ends 30 m ahead; agent 1 stands in relation `kind` to it
  (distance 2 to 20 m) or not."""
  state, heading = _states(((0, 0, 0), (30, 0, 0)), other)
  assert spec_lib.relation_holds(kind, (2.0, 20.0), state, heading, 1, 0) == holds


def _empty_scene(num_agents=4):
  return jax.tree_util.tree_map(jnp.asarray, datatypes.Scene.zeros(num_agents, 2, 30, batch_shape=(1,)))


@pytest.mark.parametrize("kind", ["ahead", "left_lane", "oncoming", "cut_in"])
def test_descending_the_cost_reaches_states_that_hold_the_relation(kind):
  """From a state that misses a relation (the related agent's states held), gradient steps on the cost of
  the free agent's positions and heading reach one the exact predicate accepts; there the cost is ~0."""
  spec = spec_lib.parse({"agents": [{"name": "a", "type": "vehicle", "maneuver": "straight"},
                                    {"name": "b", "type": "vehicle",
                                     "relation": {"to": "a", "kind": kind, "distance": [5, 20]}}]})
  arrays = jax.tree_util.tree_map(lambda x: x[0], spec_lib.arrays(spec, 1, 2))
  scene = _empty_scene(2)
  held = jnp.array([[[0.0, 0.0], [40.0, 0.0]]])                             # agent a: straight along +x
  free = jnp.array([[[-30.0, 20.0], [-10.0, 25.0]]])                        # agent b, far off
  angle = jnp.array([[0.0, 0.0], [2.5, 2.5]])

  def cost(free, b_angle):
    xy = jnp.concatenate([held, free])[None]
    state = jnp.concatenate([xy, jnp.full((1, 2, 2, 1), 8.0)], -1)
    a = jnp.concatenate([angle[:1], b_angle[None]])
    return spec_lib.cost(state, jnp.stack([jnp.cos(a), jnp.sin(a)], -1)[None], scene, arrays)

  @jax.jit
  def descend(free, b_angle):
    def step(carry, _):
      free, b_angle = carry
      g_xy, g_angle = jax.grad(cost, argnums=(0, 1))(free, b_angle)
      return (free - 0.5 * g_xy, b_angle - 0.02 * g_angle), None
    return jax.lax.scan(step, (free, b_angle), None, length=400)[0]

  free, b_angle = descend(free, angle[1])
  xy = np.concatenate([np.asarray(held), np.asarray(free)])
  state = np.concatenate([xy, np.full((2, 2, 1), 8.0)], -1)
  heading = np.stack([np.zeros(2), np.asarray(b_angle)])
  assert spec_lib.check(spec, state, heading, jax.tree_util.tree_map(lambda x: x[0], scene))["b.relation"]
  assert float(cost(free, b_angle)) < 0.5


@pytest.fixture(scope="module")
def real_scenes():
  return [scene_builder.load_scene(DATA / name)[0] for name in REAL_110]


def test_placements_on_real_maps_hold_the_initial_predicates(real_scenes):
  """On every test map where a library spec can hold, its placement holds what the initial states decide:
  regions, initial speeds, relations (all but cut_in's goal), agents' boxes apart."""
  placed = 0
  for path in LIBRARY:
    spec = spec_lib.load(path)
    for scene in real_scenes:
      if spec_lib.feasibility(spec, scene):
        continue
      placement = spec_lib.propose(spec, scene, np.random.default_rng(0))
      if placement is None:
        continue
      placed += 1
      initial = placement.initial
      state = np.stack([initial[:, :3], initial[:, :3]], 1)               # goal = initial: initial predicates
      heading = np.stack([initial[:, 3], initial[:, 3]], 1)
      got = spec_lib.check(spec, state, heading, scene)
      for k, a in enumerate(spec.agents):
        label = spec.label(k)
        assert got.get(f"{label}.region", True), (spec.name, label)
        if a.speed[0] is not None:
          assert a.speed[0][0] <= initial[k, 2] <= a.speed[0][1]
        if a.relation is not None and a.relation.kind != "cut_in":
          assert got[f"{label}.relation"], (spec.name, label)
        if a.maneuver == "stationary":
          assert initial[k, 2] == 0.0
        if a.maneuver in ("left", "right", "u_turn", "straight"):   # a route for its goal: where it makes it
          assert placement.route_valid[k].any(), (spec.name, label)
      d = np.hypot(*(initial[:, None, :2] - initial[None, :, :2]).transpose(2, 0, 1))
      assert (d[~np.eye(len(initial), dtype=bool)] > 0.5).all()
  assert placed >= 6


def test_route_goals_make_the_missed_maneuvers_and_cut_ins_hold(real_scenes):
  """Goals that stay where the agents started miss every maneuver and the cut-in; the route goals that
  replace them make the spec's goal predicates hold, and nothing is held for a sample that holds them."""
  checked = 0
  for name in ("u_turn", "unprotected_left_turn", "right_turn_with_cyclist", "cut_in", "oncoming_straight_road"):
    spec = spec_lib.load(ROOT / "specs" / f"{name}.yaml")
    for scene in real_scenes:
      placement = None if spec_lib.feasibility(spec, scene) else spec_lib.propose(spec, scene,
                                                                                  np.random.default_rng(1))
      if placement is None:
        continue
      initial = placement.initial
      state = np.stack([initial[:, :3], initial[:, :3]], 1)
      heading = np.stack([initial[:, 3], initial[:, 3]], 1)
      missed = spec_lib.check(spec, state, heading, scene)
      goal, held = spec_lib.route_goals(spec, placement, state, heading, missed)
      state[held, 1], heading[held, 1] = goal[held, :3], goal[held, 3]
      got = spec_lib.check(spec, state, heading, scene)
      for k, a in enumerate(spec.agents):
        label = spec.label(k)
        if a.maneuver in ("left", "right", "straight", "u_turn"):
          assert held[k] and got[f"{label}.maneuver"], (name, label)
        if a.relation is not None and a.relation.kind == "cut_in":
          assert held[k] and got[f"{label}.relation"], (name, label)
      assert not spec_lib.route_goals(spec, placement, state, heading, got)[1].any()
      checked += 1
  assert checked >= 5


def test_the_agentless_scenes_padding_a_batch_are_never_judged_off_the_spec(real_scenes):
  """A batch is padded with agentless copies of a scene; judging them off the spec would run every redraw
  round and placement for nothing."""
  spec = spec_lib.load(ROOT / "specs" / "u_turn.yaml")
  stats = {"type_frequency": np.eye(len(datatypes.AGENT_TYPES))[VEHICLE]}
  scene = generate.plan_agents(real_scenes[0], 4, stats, np.random.default_rng(0), spec=spec)
  pad = scene.replace(agent_valid=np.zeros_like(scene.agent_valid))
  batch = datatypes.stack_scenes([scene, pad])
  a = scene.agent_valid.shape[0]
  still = type("Sample", (), {"state": np.zeros((2, a, 2, 3), np.float32), "heading": np.zeros((2, a, 2), np.float32)})
  judged = generate._spec_violations(spec, batch, still)   # nobody moves: the u-turn is missed
  assert judged[0, 0] and not judged[1].any()


def test_a_map_without_junctions_or_crossings_cannot_hold_specs_that_need_them(real_scenes):
  scene = real_scenes[0]
  assert not spec_lib.feasibility(spec_lib.load(ROOT / "specs" / "stopped_vehicle_ahead.yaml"), scene)
  bare = scene.replace(pl_intersection=np.where(scene.pl_intersection == 1, 0, scene.pl_intersection),
                       pl_valid=scene.pl_valid & (scene.pl_type != datatypes.CROSSWALK))
  queue = spec_lib.feasibility(spec_lib.load(ROOT / "specs" / "queue_at_junction.yaml"), bare)
  crossing = spec_lib.feasibility(spec_lib.load(ROOT / "specs" / "pedestrian_crossing_ahead.yaml"), bare)
  assert queue == ["region intersection: the map has no lane in an intersection"]
  assert crossing == ["region crosswalk: the map has no pedestrian crossing"]


def test_sample_with_a_spec_writes_what_was_asked_and_checks_it(real_scenes, tmp_path):
  """The shipped models on two real test maps, a spec with a relation and a stationary agent: the constrained
  agents come first (the focal track is the spec's first agent), `spec_satisfied` is the exact check of the
  written states, and the summary has the rates per predicate."""
  maps = tmp_path / "maps"
  maps.mkdir()
  for name in REAL_110[:2]:
    (maps / name).symlink_to(DATA / name, target_is_directory=True)
  spec = spec_lib.load(ROOT / "specs" / "stopped_vehicle_ahead.yaml")
  summary = generate.generate(checkpoint.pretrained_dir("hl"), maps, tmp_path / "out", num_per_map=1, seed=0,
                              options=sampling.SamplerOptions("ddim", stride=50, costs=("paths",)), progress=False,
                              pictures=False, infill_workdir=checkpoint.pretrained_dir("infill"),
                              repair_rounds=1, spec=spec)
  z = np.load(tmp_path / "out" / "samples.npz")
  s = summary["spec"]
  assert s["name"] == "stopped_vehicle_ahead" and s["samples"] == len(z["state"]) == 2 - len(s["infeasible_maps"])
  assert set(s["predicates_pct"]) == set(spec.predicates())
  assert s["predicates_pct"]["ego.speed"] == s["predicates_pct"]["stopped.relation"] == 100.0   # held as placed
  assert (z["spec_agent"][:, :3] == [0, 1, -1]).all() and (z["spec_agent"][:, 3:] == -1).all()
  assert (z["agent_type"][:, :2] == VEHICLE).all()
  for i, name in enumerate(z["map_folder"]):
    scene = real_scenes[REAL_110.index(str(name))]
    got = spec_lib.check(spec, z["state"][i], z["heading"][i], scene)
    assert bool(z["spec_satisfied"][i]) == all(got.values())
    np.testing.assert_allclose(z["state"][i, 1, 1, :2], z["state"][i, 1, 0, :2], atol=1e-3)   # stationary
  assert s["satisfied"] == int(z["spec_satisfied"].sum())
  from av2.datasets.motion_forecasting.scenario_serialization import load_argoverse_scenario_parquet
  gen = summary["scenarios"][0]["scenario_id"]
  scenario = load_argoverse_scenario_parquet(tmp_path / "out" / "scenarios" / gen / f"scenario_{gen}.parquet")
  focal = next(t for t in scenario.tracks if t.track_id == scenario.focal_track_id)
  np.testing.assert_allclose(focal.object_states[0].position, z["city_xy"][0, 0, 0], atol=1e-3)
