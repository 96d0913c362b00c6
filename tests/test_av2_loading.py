"""Real AV2 samples -> scene arrays: shapes, masks, city metres, topology, agent selection."""

from __future__ import annotations

import json
import shutil

import chex
import jax
import numpy as np
import pytest
from av2.datasets.motion_forecasting.scenario_serialization import load_argoverse_scenario_parquet
from av2.map.map_api import ArgoverseStaticMap

from tests.av2_samples import DATA, REAL_110, REAL_50
from tdiff_jax import datatypes
from tdiff_jax.data import av2_io, config as config_lib, map_features, scene_builder


@pytest.fixture(scope="module")
def loaded():
  return {sid: scene_builder.load_scene(DATA / sid) for sid in REAL_110}


def test_every_real_sample_loads_and_validates(loaded):
  cfg = config_lib.default_data_config()
  for sid, (scene, info) in loaded.items():
    scene.validate()
    assert info.scenario_id == sid
    chex.assert_shape(scene.agent_state, (cfg.max_agents, 2, 4))
    chex.assert_shape(scene.pt_xy, (cfg.max_polygons, 3 * cfg.points_per_polyline, 2))
    chex.assert_shape(scene.pl_edge, (cfg.max_polygons, cfg.max_polygons))
    chex.assert_type([scene.agent_state, scene.pt_xy], np.float32)
    chex.assert_type([scene.agent_type, scene.pl_type, scene.pt_type], np.int32)
    assert scene.pl_edge.dtype == np.int8 and scene.agent_valid.dtype == bool
    n = int(scene.agent_valid.sum())
    assert n == len(info.track_ids) >= 1
    # Padding is zero and masked.
    assert not scene.agent_state[n:].any() and not scene.pt_valid[~scene.pl_valid].any()
    assert scene.pt_valid[scene.pl_valid].all()


def test_track_columns_match_av2s_loader_on_every_real_sample():
  """The pyarrow column reader gives av2's tracks: the same ids, types and every row's state."""
  for sid in [*REAL_110, REAL_50]:
    table = av2_io.load_tracks(av2_io.find_scenario_files(DATA / sid))
    sc = load_argoverse_scenario_parquet(DATA / sid / f"scenario_{sid}.parquet")
    assert (table.scenario_id, table.city_name) == (sc.scenario_id, sc.city_name)
    assert table.num_tracks == len(sc.tracks)
    assert table.last_step == max(s.timestep for t in sc.tracks for s in t.object_states)
    rows = {(tid, int(step)): i for i, (tid, step) in enumerate(zip(table.track_id, table.timestep))}
    assert len(rows) == len(table.track_id) == sum(len(t.object_states) for t in sc.tracks)
    for t in sc.tracks:
      for s in t.object_states:
        i = rows[(t.track_id, s.timestep)]
        assert table.object_type[i] == t.object_type.value
        np.testing.assert_array_equal(table.position[i], s.position)
        np.testing.assert_array_equal(table.velocity[i], s.velocity)
        assert table.heading[i] == s.heading


def test_map_reader_matches_av2s_map_on_every_real_sample():
  """The map JSON read once (lane attributes and coordinate arrays) gives what av2's `ArgoverseStaticMap`
  reads: the same lanes, types, marks, topology and every vertex; the av2 map itself is built on demand."""
  for sid in [*REAL_110, REAL_50]:
    raw = av2_io.read_scenario_folder(DATA / sid, map_only=True)
    ref = ArgoverseStaticMap.from_json(raw.files.map_json)
    assert set(raw.lanes) == set(ref.vector_lane_segments) == set(raw.polylines.lane_left)
    for lane_id, lane in raw.lanes.items():
      r = ref.vector_lane_segments[lane_id]
      assert (lane.lane_type, lane.left_mark_type, lane.right_mark_type) == (
          r.lane_type.value, r.left_mark_type.value, r.right_mark_type.value)
      assert lane.is_intersection == r.is_intersection
      assert (list(lane.predecessors), list(lane.successors)) == (r.predecessors, r.successors)
      assert (lane.left_neighbor_id, lane.right_neighbor_id) == (r.left_neighbor_id, r.right_neighbor_id)
      np.testing.assert_array_equal(raw.polylines.lane_left[lane_id], r.left_lane_boundary.xyz[:, :2])
      np.testing.assert_array_equal(raw.polylines.lane_right[lane_id], r.right_lane_boundary.xyz[:, :2])
    assert set(raw.polylines.crosswalk_edges) == set(ref.vector_pedestrian_crossings)
    for pc_id, (e1, e2) in raw.polylines.crosswalk_edges.items():
      np.testing.assert_array_equal(e1, ref.vector_pedestrian_crossings[pc_id].edge1.xyz[:, :2])
      np.testing.assert_array_equal(e2, ref.vector_pedestrian_crossings[pc_id].edge2.xyz[:, :2])
    assert set(raw.polylines.drivable_areas) == set(ref.vector_drivable_areas)
    for da_id, ring in raw.polylines.drivable_areas.items():  # av2 closes the ring with the first vertex
      np.testing.assert_array_equal(ring, ref.vector_drivable_areas[da_id].xyz[:-1, :2])
    assert set(raw.static_map.vector_lane_segments) == set(raw.lanes)


def _real_sample_with_lane_edited(tmp_path, edit):
  """A copy of a real sample whose first lane segment's JSON entry `edit(lane)` changed in place:
  the folder, the map path and the lane's id."""
  sid = REAL_110[0]
  folder = tmp_path / sid
  shutil.copytree(DATA / sid, folder)
  path = folder / f"log_map_archive_{sid}.json"
  data = json.loads(path.read_text())
  lane_id, lane = next(iter(data["lane_segments"].items()))
  edit(lane)
  path.write_text(json.dumps(data))
  return folder, path, int(lane_id)


def test_a_lane_type_av2_does_not_know_names_the_map(tmp_path):
  folder, path, _ = _real_sample_with_lane_edited(tmp_path, lambda lane: lane.update(lane_type="HOVERCRAFT"))
  with pytest.raises(av2_io.BadScenarioError, match=f"{path.name}.*lane_type 'HOVERCRAFT'"):
    scene_builder.load_scene(folder)


def test_a_lane_without_a_json_centreline_gets_av2s_inferred_one(tmp_path):
  folder, path, lane_id = _real_sample_with_lane_edited(tmp_path, lambda lane: lane.pop("centerline"))
  raw = av2_io.read_scenario_folder(folder)
  center = {p.lane_id: p.center for p in map_features.lane_polygons(raw)}[lane_id]
  expected = ArgoverseStaticMap.from_json(path).get_lane_segment_centerline(lane_id)[:, :2]
  np.testing.assert_array_equal(center, expected)
  scene_builder.build_scene(raw, config_lib.default_data_config())[0].validate()


def test_track_writer_writes_av2s_serializer_file_byte_for_byte(tmp_path):
  """`write_tracks_parquet` (what the synthetic worlds and `sample.py`'s exports are written with) gives
  the file av2's serializer writes, on every real sample read back by av2 and on synthetic scenarios
  (one with a map and a slice id set, so every optional column is covered)."""
  from av2.datasets.motion_forecasting.scenario_serialization import serialize_argoverse_scenario_parquet

  from tdiff_jax.data import synthetic

  scenarios = [load_argoverse_scenario_parquet(DATA / sid / f"scenario_{sid}.parquet") for sid in [*REAL_110, REAL_50]]
  scenarios += [synthetic.generate_scenario(3, i).scenario for i in range(3)]
  scenarios[-1].map_id, scenarios[-1].slice_id = 7, "slice-a"
  for i, scenario in enumerate(scenarios):
    serialize_argoverse_scenario_parquet(tmp_path / f"av2_{i}.parquet", scenario)
    av2_io.write_tracks_parquet(tmp_path / f"ours_{i}.parquet", scenario)
    assert (tmp_path / f"ours_{i}.parquet").read_bytes() == (tmp_path / f"av2_{i}.parquet").read_bytes(), i
  scenarios[0].tracks = []
  with pytest.raises(ValueError, match="no tracks"):
    av2_io.write_tracks_parquet(tmp_path / "empty.parquet", scenarios[0])


def test_scene_agents_match_a_build_from_av2s_tracks(loaded):
  """Candidates, their order and their states as built row by row from av2's `ArgoverseScenario`."""
  for sid, (scene, info) in loaded.items():
    sc = load_argoverse_scenario_parquet(DATA / sid / f"scenario_{sid}.parquet")
    cand = [t for t in sorted(sc.tracks, key=lambda t: t.track_id)
            if t.object_type.value in datatypes.AGENT_TYPES
            and {datatypes.INITIAL_STEP, datatypes.GOAL_STEP} <= {s.timestep for s in t.object_states}]
    table = av2_io.load_tracks(av2_io.find_scenario_files(DATA / sid))
    ids, types, states, future, future_valid = scene_builder._track_arrays(table, set(datatypes.AGENT_TYPES))
    assert ids == [t.track_id for t in cand]
    for k, t in enumerate(cand):
      at = {s.timestep: s for s in t.object_states}
      assert types[k] == datatypes.AGENT_TYPES.index(t.object_type.value)
      for tok, step in enumerate((datatypes.INITIAL_STEP, datatypes.GOAL_STEP)):
        s = at[step]
        np.testing.assert_array_equal(states[k, tok], [*s.position, np.hypot(*s.velocity), s.heading])
      for h in range(datatypes.HORIZON):
        assert future_valid[k, h] == (datatypes.INITIAL_STEP + h in at)
        if future_valid[k, h]:
          np.testing.assert_array_equal(future[k, h], at[datatypes.INITIAL_STEP + h].position)
    assert set(info.track_ids) <= set(ids) and info.num_candidates <= len(ids)


def test_test_split_sample_is_rejected_with_reason():
  with pytest.raises(av2_io.BadScenarioError, match="only 50 steps, no goal step 109"):
    scene_builder.load_scene(DATA / REAL_50)


def test_a_parquet_without_rows_says_so(tmp_path):
  import shutil

  import pandas as pd
  folder = shutil.copytree(DATA / REAL_110[0], tmp_path / REAL_110[0])
  parquet = next(folder.glob("*.parquet"))
  pd.read_parquet(parquet).iloc[:0].to_parquet(parquet)
  with pytest.raises(av2_io.BadScenarioError, match="scenario parquet has no rows") as e:
    scene_builder.load_scene(folder)
  assert e.value.path == str(parquet)
  # Only the map is needed to sample on it: the map is used and the ignored tracks are said.
  scene, info = scene_builder.load_scene(folder, require_agents=False)
  assert scene.pl_valid.any() and not scene.agent_valid.any()
  assert info.scenario_id == REAL_110[0] and "no rows" in info.warnings[0]


def test_positions_back_in_city_metres_match_av2(loaded):
  for sid, (scene, info) in loaded.items():
    sc = load_argoverse_scenario_parquet(DATA / sid / f"scenario_{sid}.parquet")
    tracks = {t.track_id: t for t in sc.tracks}
    city = datatypes.to_city(scene, scene.agent_xy.astype(np.float64))
    for row, tid in enumerate(info.track_ids):
      states = {s.timestep: s for s in tracks[tid].object_states}
      for tok, step in enumerate((datatypes.INITIAL_STEP, datatypes.GOAL_STEP)):
        s = states[step]
        np.testing.assert_allclose(city[row, tok], s.position, atol=5e-3)  # float32 offsets
        np.testing.assert_allclose(scene.agent_state[row, tok, 2], np.hypot(*s.velocity), rtol=1e-5)
        np.testing.assert_allclose(scene.agent_state[row, tok, 3], s.heading, atol=1e-6)


def test_agent_selection_rules(loaded):
  """Kept: present at 50 and 109, a modelled type, road users near a lane; ordered by distance."""
  for sid, (scene, info) in loaded.items():
    sc = load_argoverse_scenario_parquet(DATA / sid / f"scenario_{sid}.parquet")
    expected_candidates = {
        t.track_id for t in sc.tracks
        if t.object_type.value in datatypes.AGENT_TYPES
        and {datatypes.INITIAL_STEP, datatypes.GOAL_STEP} <= {s.timestep for s in t.object_states}}
    assert set(info.track_ids) <= expected_candidates
    n = len(info.track_ids)
    d = np.linalg.norm(scene.agent_state[:n, 0, :2], axis=-1)
    assert np.all(np.diff(d) >= 0)
  # The Pittsburgh sample has a pedestrian and two cyclists among its kept agents.
  scene, _ = loaded["0a0a2bb7-c4f4-44cd-958a-9ee15cb34aca"]
  kept_types = scene.agent_type[scene.agent_valid]
  assert (kept_types == datatypes.AGENT_TYPES.index("pedestrian")).sum() == 1
  assert (kept_types == datatypes.AGENT_TYPES.index("cyclist")).sum() == 2


def test_agent_types_config_field():
  cfg = config_lib.default_data_config()
  cfg.agent_types = "vehicle"
  scene, _ = scene_builder.load_scene(DATA / "0a0a2bb7-c4f4-44cd-958a-9ee15cb34aca", cfg)
  assert (scene.agent_type[scene.agent_valid] == 0).all()
  cfg.agent_types = "vehicle,hovercraft"
  with pytest.raises(ValueError, match="hovercraft"):
    scene_builder.load_scene(DATA / "0a0a2bb7-c4f4-44cd-958a-9ee15cb34aca", cfg)


def test_polygons_lanes_and_crosswalks_both_ways(loaded):
  for sid, (scene, _) in loaded.items():
    raw = json.loads((DATA / sid / f"log_map_archive_{sid}.json").read_text())
    n_lanes, n_cw = len(raw["lane_segments"]), len(raw["pedestrian_crossings"])
    assert scene.pl_valid.sum() == n_lanes + 2 * n_cw
    cw = scene.pl_type == datatypes.POLYGON_TYPES.index("PEDESTRIAN")
    assert cw.sum() == 2 * n_cw
    # The two directions of a crosswalk: same centreline, reversed.
    k3 = scene.num_points // 3
    centres = scene.pt_xy[cw][:, 2 * k3:]
    for c in centres:
      match = np.abs(centres - c[::-1]).max(axis=(1, 2)) < 1e-3
      assert match.sum() == 1


def test_topology_edges_match_json(loaded):
  for sid, (scene, info) in loaded.items():
    raw = json.loads((DATA / sid / f"log_map_archive_{sid}.json").read_text())
    lanes = {int(k): v for k, v in raw["lane_segments"].items()}
    cw = scene.pl_type == datatypes.POLYGON_TYPES.index("PEDESTRIAN")
    row = {pid: r for r, pid in enumerate(info.polygon_ids) if not cw[r]}
    assert sorted(row) == sorted(lanes)
    # Each lane's row starts at its JSON centreline.
    for lid, r in row.items():
      p = lanes[lid]["centerline"][0]
      np.testing.assert_allclose(scene.pl_xy[r] + scene.frame_origin, [p["x"], p["y"]], atol=5e-3)
    expected = np.zeros_like(scene.pl_edge)
    for lid, l in lanes.items():
      rel = [(j, 1) for j in l["predecessors"]] + [(j, 2) for j in l["successors"]]
      rel += [(l["left_neighbor_id"], 3), (l["right_neighbor_id"], 4)]
      for j, kind in rel:
        if j in row:  # references outside the crop are dropped
          expected[row[lid], row[j]] = kind
    np.testing.assert_array_equal(scene.pl_edge, expected)
    assert (scene.pl_edge > 0).sum() > len(lanes) // 2  # the graph is not empty


def test_drivable_areas_kept(loaded):
  for sid, (scene, _) in loaded.items():
    raw = json.loads((DATA / sid / f"log_map_archive_{sid}.json").read_text())
    counts = sorted(len(d["area_boundary"]) for d in raw["drivable_areas"].values())
    assert sorted(scene.da_valid.sum(1)[scene.da_valid.any(1)]) == counts


def test_a_drivable_area_needs_three_vertices_distinct_at_the_micrometre():
  def degenerate(ring):
    polylines = av2_io.MapPolylines({}, {}, {}, {}, {7: np.asarray(ring, np.float64)})
    return map_features.encode_drivable_areas(polylines, np.zeros(2), 4, 16)[3]

  assert degenerate([[0, 0], [0, 0], [0, 0]]) == 1
  assert degenerate([[0, 0], [1, 0], [1, 1e-7], [0, 0]]) == 1   # the third vertex within a micrometre
  assert degenerate([[0, 0], [1, 0], [1, 1e-5]]) == 0
  assert degenerate([[5, 5], [5, 5], [1, 0], [1, 0], [0, 2]]) == 0
  assert degenerate([[5, 5], [1, 0], [5, 5], [1, 0]]) == 1


def test_caps_keep_closest_and_count_dropped():
  cfg = config_lib.default_data_config()
  cfg.max_agents, cfg.max_polygons, cfg.max_drivable_areas, cfg.max_drivable_area_vertices = 3, 20, 1, 50
  scene, info = scene_builder.load_scene(DATA / "0a1e6f0a-1817-4a98-b02e-db8c9327d151", cfg)
  scene.validate()
  full, full_info = scene_builder.load_scene(DATA / "0a1e6f0a-1817-4a98-b02e-db8c9327d151")
  assert info.agents_dropped == full_info.num_candidates - 3
  np.testing.assert_array_equal(scene.agent_state, full.agent_state[:3])  # closest three
  assert info.polygons_dropped == full.pl_valid.sum() - 20
  assert info.drivable_areas_dropped == full.da_valid.any(1).sum() - 1
  assert info.drivable_areas_resampled == 1 and scene.da_valid.sum() == 50


def test_scene_is_a_pytree_and_validate_catches_breaks(loaded):
  scene, _ = loaded[REAL_110[0]]
  leaves = jax.tree_util.tree_leaves(scene)
  assert len(leaves) == len(scene.to_dict())
  doubled = jax.jit(lambda s: s.replace(agent_state=s.agent_state * 2))(scene)
  np.testing.assert_allclose(doubled.agent_state, scene.agent_state * 2)
  with pytest.raises(ValueError, match="agent_state"):
    scene.replace(agent_state=scene.agent_state[:, :1]).validate()
  bad = scene.agent_valid.copy()
  bad[0], bad[-1] = False, True
  with pytest.raises(ValueError, match="packed"):
    scene.replace(agent_valid=bad).validate()
  nan = scene.pt_xy.copy()
  nan[0, 0, 0] = np.nan
  with pytest.raises(ValueError, match="NaN"):
    scene.replace(pt_xy=nan).validate()
  swapped = scene.pt_side.copy()
  swapped[0] = swapped[0, ::-1]  # centre polyline first: code that slices the centre third would miss it
  with pytest.raises(ValueError, match="pt_side"):
    scene.replace(pt_side=swapped).validate()


def test_ground_truth_trajectories_match_av2(loaded):
  """agent_future holds every kept track's positions at AV2 steps 50..109, in the scene frame."""
  for sid in REAL_110:
    scene, info = loaded[sid]
    sc = load_argoverse_scenario_parquet(DATA / sid / f"scenario_{sid}.parquet")
    tracks = {t.track_id: t for t in sc.tracks}
    for row, tid in enumerate(info.track_ids):
      at = {s.timestep: s.position for s in tracks[tid].object_states}
      for h in range(datatypes.HORIZON):
        step = datatypes.INITIAL_STEP + h
        assert scene.agent_future_valid[row, h] == (step in at)
        if step in at:
          np.testing.assert_allclose(scene.agent_future[row, h], np.asarray(at[step]) - scene.frame_origin, atol=1e-3)
    n = scene.agent_valid.sum()
    assert not scene.agent_future_valid[n:].any() and not scene.agent_future[n:].any()


def test_exported_scenarios_carry_the_trajectories_headings_and_velocities(tmp_path):
  """An agent drives east at 10 m/s for 2 s, stops for 1 s, then drives north at 5 m/s; another never
  moves. Read back with av2's loader: velocities are the trajectory's finite differences, headings the
  direction of motion, held while stopped, and the initial heading before the first move."""
  from tdiff_jax.data import av2_export

  h = datatypes.HORIZON
  xy = np.zeros((2, h, 2))
  t = np.arange(h) * av2_export.DT_S
  east, stop = 20, 30                       # steps 0..20 driving east, 20..30 stopped, then north
  xy[0, :, 0] = 10.0 * np.minimum(t, t[east])
  xy[0, stop:, 1] = 5.0 * (t[stop:] - t[stop])
  xy[1] = [3.0, -4.0]
  origin = np.array([1000.0, 2000.0])
  sid = av2_export.generated_scenario_id(REAL_110[0], 0, 0)
  folder = av2_export.write_generated_scenario(
      tmp_path, sid, "PIT", DATA / REAL_110[0] / f"log_map_archive_{REAL_110[0]}.json", xy + origin,
      np.array([0.3, -1.2]), np.array([0, 2]), np.array([True, True]))
  scenario = load_argoverse_scenario_parquet(folder / f"scenario_{sid}.parquet")
  tracks = {tr.track_id: tr for tr in scenario.tracks}
  car, walker = tracks["0"].object_states, tracks["1"].object_states
  pos = np.array([s.position for s in car])
  vel = np.array([s.velocity for s in car])
  heading = np.array([s.heading for s in car])
  np.testing.assert_allclose(pos, xy[0] + origin, atol=1e-6)
  np.testing.assert_allclose(vel[1:-1], (pos[2:] - pos[:-2]) / (2 * av2_export.DT_S), atol=1e-6)
  np.testing.assert_allclose(vel[5], [10.0, 0.0], atol=1e-6)
  np.testing.assert_allclose(vel[45], [0.0, 5.0], atol=1e-6)
  assert heading[0] == pytest.approx(0.3)                       # not yet moving: the initial heading
  np.testing.assert_allclose(heading[1:east + 1], 0.0, atol=1e-9)    # east
  np.testing.assert_allclose(heading[east + 1:stop + 1], 0.0, atol=1e-9)   # stopped: held
  np.testing.assert_allclose(heading[stop + 1:], np.pi / 2, atol=1e-9)     # north
  assert all(s.heading == pytest.approx(-1.2) and s.velocity == (0.0, 0.0) for s in walker)
  assert tracks["1"].object_type.value == "pedestrian" and scenario.focal_track_id == "0"


def test_dataset_statistics_of_real_scenes():
  """`python -m tdiff_jax.data.stats` on the real AV2 samples: every scene read, agents kept, goals spread."""
  from tdiff_jax.data import stats
  out = stats.folder_stats([DATA / sid for sid in REAL_110])
  assert out["scenes"] == len(REAL_110) and not out["skipped"]
  assert out["kept_agents_per_scene"]["min"] > 0 and min(out["goal_offset_m"]["std_xy"]) > 1.0, out


def _real_sample_with_map_edited(tmp_path, edit, text_edit=None):
  """A copy of a real sample whose parsed map JSON `edit(data)` changed (and its text `text_edit(text)`)."""
  sid = REAL_110[0]
  folder = shutil.copytree(DATA / sid, tmp_path / sid)
  path = folder / f"log_map_archive_{sid}.json"
  data = json.loads(path.read_text())
  edit(data)
  text = json.dumps(data)
  path.write_text(text_edit(text) if text_edit else text)
  return folder, path


def _first_lane(data):
  return next(iter(data["lane_segments"].values()))


def _lane_ids_as_strings(data):
  lanes = data["lane_segments"]
  for lane in lanes.values():
    lane["id"] = str(lane["id"])
    lane["predecessors"] = [str(i) for i in lane["predecessors"]]
    lane["successors"] = [str(i) for i in lane["successors"]]


def _duplicate_lane_id(data):
  lanes = data["lane_segments"]
  first, second = list(lanes)[:2]
  lanes[second]["id"] = int(first)   # two lanes claim one id


@pytest.mark.parametrize("edit, text_edit, rule", [
    (_lane_ids_as_strings, None, r"id '\d+' is not an integer id"),
    (lambda d: _first_lane(d).update(is_intersection="false"), None, "is_intersection 'false' is not a boolean"),
    (_duplicate_lane_id, None, r"holds id \d+ \(each entry is keyed by its own id"),
    (lambda d: _first_lane(d).update(successors=[2**64 + 5]), None, "successors .* is not a list of integer ids"),
    (lambda d: _first_lane(d).update(left_neighbor_id="12"), None, "left_neighbor_id '12' is neither"),
    (lambda d: _first_lane(d)["centerline"][0].update(x="12.5"), None, "coordinates must be numbers"),
    # A key written twice in the text: a JSON parser keeps the last entry only.
    (lambda d: None, lambda t: t.replace('"lane_segments": {', '"lane_segments": {"1": ' + json.dumps(
        {**_first_lane(json.loads(t)), "id": 1}) + ', "1": ' + json.dumps({**_first_lane(json.loads(t)), "id": 1}) + ", "),
     "lane_segments: .* entries in the file but .* distinct keys"),
    # An id above 2^64: JSON parsers read it as a float, and ids would collide.
    (lambda d: None, lambda t: t.replace(f'"id": {next(iter(json.loads(t)["lane_segments"].values()))["id"]}',
                                         '"id": 18446744073709551621', 1), "is not an integer id"),
])
def test_a_map_json_of_wrong_types_or_repeated_ids_is_refused_naming_the_rule(tmp_path, edit, text_edit, rule):
  folder, path = _real_sample_with_map_edited(tmp_path, edit, text_edit)
  with pytest.raises(av2_io.BadScenarioError, match=rule) as e:
    scene_builder.load_scene(folder)
  assert e.value.path == str(path)


def _tracks_edited(tmp_path, edit):
  import pandas as pd
  folder = shutil.copytree(DATA / REAL_110[0], tmp_path / REAL_110[0])
  parquet = next(folder.glob("*.parquet"))
  frame = pd.read_parquet(parquet)
  edit(frame).to_parquet(parquet)
  return folder, parquet


def _two_objects_one_id(frame):
  import pandas as pd
  a, b = [i for i in frame.track_id.unique() if i != "AV"][:2]
  other = frame[frame.track_id == b].assign(track_id=a)   # object b's rows under a's id
  return pd.concat([frame[frame.track_id != b], other])


@pytest.mark.parametrize("edit, rule", [
    (lambda f: f.iloc[list(range(len(f))) + [int((f.timestep == 50).values.argmax())]],   # a row given twice
     r"has 2 rows at timestep 50: one row per track and timestep"),
    (_two_objects_one_id, r"(has \d+ rows at timestep|has rows of object types)"),
    (lambda f: f.assign(heading=f.heading.astype(str)), "column 'heading' is of type .*string, expected numbers"),
    (lambda f: f.assign(object_type=f.object_type.where(f.object_type != "vehicle", "spaceship")),
     r"object types \['spaceship'\] are not av2's"),
])
def test_a_track_table_of_repeated_rows_or_wrong_types_is_refused_naming_the_rule(tmp_path, edit, rule):
  folder, parquet = _tracks_edited(tmp_path, edit)
  with pytest.raises(av2_io.BadScenarioError, match=rule) as e:
    scene_builder.load_scene(folder)
  assert e.value.path == str(parquet)


def test_two_objects_with_one_id_at_different_steps_are_refused(tmp_path):
  """Two objects that never share a step: only their types tell them apart."""
  def edit(frame):
    import pandas as pd
    ids = [i for i in frame.track_id.unique() if i != "AV"]
    a = ids[0]
    kind = frame[frame.track_id == a].object_type.iloc[0]
    other = frame[frame.track_id == a].copy()
    other["object_type"] = "cyclist" if kind != "cyclist" else "vehicle"
    other["timestep"] = other["timestep"] + 200
    other["track_id"] = a
    return pd.concat([frame, other])
  folder, _ = _tracks_edited(tmp_path, edit)
  with pytest.raises(av2_io.BadScenarioError, match="has rows of object types"):
    scene_builder.load_scene(folder)


def test_agents_outside_physical_ranges_are_left_out_and_said(tmp_path):
  def fast(frame):
    frame = frame.copy()
    tid = frame[(frame.timestep == 50) & (frame.object_type == "vehicle") & (frame.track_id != "AV")].track_id.iloc[0]
    frame.loc[(frame.track_id == tid) & (frame.timestep == 50), "velocity_x"] = 1000.0
    return frame
  folder, _ = _tracks_edited(tmp_path, fast)
  scene, info = scene_builder.load_scene(folder)
  plain, plain_info = scene_builder.load_scene(DATA / REAL_110[0])
  assert info.agents_implausible == 1 and int(scene.agent_valid.sum()) == int(plain.agent_valid.sum()) - 1
  assert "speed 1000.0 m/s above 70" in info.warnings[0]
  assert float(scene.agent_state[..., 2].max()) < 70.0
  # Map and tracks in different city frames: every agent is far outside the map; the scene is refused.
  folder2, _ = _tracks_edited(tmp_path / "shifted", lambda f: f.assign(position_x=f.position_x + 5000.0))
  with pytest.raises(av2_io.BadScenarioError, match="outside the map .*different city frames"):
    scene_builder.load_scene(folder2)
