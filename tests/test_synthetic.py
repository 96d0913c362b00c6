"""Synthetic AV2 worlds: real format round trip, determinism, a consistent lane graph, plausible traffic, each
road part of the generator, and traffic on real AV2 maps."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from av2.datasets.motion_forecasting.scenario_serialization import load_argoverse_scenario_parquet
from av2.map.map_api import ArgoverseStaticMap

from tdiff_jax import audit
from tdiff_jax.data import road_network, scene_builder, synthetic

NUM = 12


@pytest.fixture(scope="module")
def written(tmp_path_factory):
  out = tmp_path_factory.mktemp("synthetic")
  counts = synthetic.generate_dataset(out, NUM, seed=7, val_fraction=0.25, workers=1, progress=False)
  return out, counts


def _folders(out):
  return sorted(p for split in ("train", "val") for p in (out / split).iterdir())


def test_splits_and_layout(written):
  out, counts = written
  assert counts == {"train": 9, "val": 3}
  for folder in _folders(out):
    sid = folder.name
    assert (folder / f"scenario_{sid}.parquet").is_file()
    assert (folder / f"log_map_archive_{sid}.json").is_file()
  assert not list(out.glob("*/.tmp-*"))


def test_round_trip_through_av2_is_identical(written):
  out, _ = written
  for index in range(3):
    generated = synthetic.generate_scenario(7, index)
    sid = generated.scenario.scenario_id
    folder = out / synthetic.split_of(index, NUM, 0.25) / sid
    loaded = load_argoverse_scenario_parquet(folder / f"scenario_{sid}.parquet")
    g = generated.scenario
    assert (loaded.scenario_id, loaded.focal_track_id, loaded.city_name) == (g.scenario_id, g.focal_track_id, g.city_name)
    np.testing.assert_array_equal(loaded.timestamps_ns, g.timestamps_ns)
    assert [t.track_id for t in loaded.tracks] == [t.track_id for t in g.tracks]
    for lt, gt in zip(loaded.tracks, g.tracks):
      assert (lt.object_type, lt.category) == (gt.object_type, gt.category)
      assert lt.object_states == gt.object_states  # exact floats
    # The map JSON reloads with av2 and equals what was generated.
    static_map = ArgoverseStaticMap.from_json(folder / f"log_map_archive_{sid}.json")
    assert json.loads((folder / f"log_map_archive_{sid}.json").read_text()) == generated.map_json
    assert set(static_map.vector_lane_segments) == {int(k) for k in generated.map_json["lane_segments"]}
    for lid, lane in static_map.vector_lane_segments.items():
      src = generated.map_json["lane_segments"][str(lid)]
      np.testing.assert_array_equal(lane.left_lane_boundary.xyz[:, 0], [p["x"] for p in src["left_lane_boundary"]])
      assert lane.successors == src["successors"] and lane.predecessors == src["predecessors"]
    assert len(static_map.vector_drivable_areas) >= 2


def test_same_seed_same_world_other_seed_other_world():
  a, b, c = synthetic.generate_scenario(3, 5), synthetic.generate_scenario(3, 5), synthetic.generate_scenario(4, 5)
  assert a.map_json == b.map_json and a.scenario.scenario_id == b.scenario.scenario_id
  assert [t.object_states for t in a.scenario.tracks] == [t.object_states for t in b.scenario.tracks]
  assert a.map_json != c.map_json and a.scenario.scenario_id != c.scenario.scenario_id


def _check_lane_graph(lanes: dict) -> None:
    for lid, lane in lanes.items():
      end = np.array([lane["centerline"][-1]["x"], lane["centerline"][-1]["y"]])
      for succ in lane["successors"]:
        assert int(lid) in lanes[str(succ)]["predecessors"]
        start = lanes[str(succ)]["centerline"][0]
        assert np.hypot(start["x"] - end[0], start["y"] - end[1]) < 0.05  # successors continue the lane
      for pred in lane["predecessors"]:
        assert int(lid) in lanes[str(pred)]["successors"]
      for side, back in (("left", "right"), ("right", "left")):
        n = lane[f"{side}_neighbor_id"]
        if n is not None:  # neighbours point back at each other, on the opposite side
          assert lanes[str(n)][f"{back}_neighbor_id"] == int(lid)
      spacing = np.linalg.norm(np.diff([[p["x"], p["y"]] for p in lane["centerline"]], axis=0), axis=-1)
      assert spacing.max() <= 2.01


def test_lane_graph_is_consistent():
  for index in range(8):
    _check_lane_graph(synthetic.generate_scenario(11, index).map_json["lane_segments"])


def _first_with(part: str, seed: int = 0) -> int:
  """The first index whose world holds the road part (worlds alone are cheap to build)."""
  return next(i for i in range(300) if part in road_network.build_world(np.random.default_rng([seed, i])).parts)


def _heading_change(lane: dict) -> float:
  xy = np.array([[p["x"], p["y"]] for p in lane["centerline"]])
  h = np.unwrap(np.arctan2(*np.diff(xy, axis=0).T[::-1]))
  return float(np.ptp(h))


def _part_is_there(part: str, lanes: dict) -> bool:
  """What the part looks like in the lane graph written, where it shows there."""
  road = {k: l for k, l in lanes.items() if not l["is_intersection"]}
  if part == "several_junctions":  # connector lanes in at least two groups not joined by connectors
    groups, seen = 0, set()
    for k in (k for k, l in lanes.items() if l["is_intersection"]):
      if k in seen:
        continue
      groups += 1
      todo = [k]
      while todo:
        c = todo.pop()
        if c in seen:
          continue
        seen.add(c)
        ends = {str(i) for i in lanes[c]["predecessors"] + lanes[c]["successors"]}
        todo += [n for e in ends for n in [e] + [str(i) for i in lanes[e]["predecessors"] + lanes[e]["successors"]]
                 if lanes[n]["is_intersection"]]
    return groups >= 2
  if part == "curve":
    return any(_heading_change(l) > np.radians(10) and l["left_lane_mark_type"] == "DOUBLE_SOLID_YELLOW"
               for l in road.values())
  if part == "merge":  # a road lane that two road lanes lead into
    return any(sum(str(p) in road for p in l["predecessors"]) >= 2 for l in road.values())
  if part in ("split", "pocket"):  # a road lane that leads into two road lanes
    return any(sum(str(n) in road for n in l["successors"]) >= 2 for l in road.values())
  if part == "bike_lane":
    return any(l["lane_type"] == "BIKE" for l in road.values())
  if part == "u_turn":
    return any(_heading_change(l) > np.radians(150) for k, l in lanes.items() if l["is_intersection"])
  return True  # the rest shows in the drivable areas, crosswalks or traffic (checked below for all parts)


@pytest.mark.parametrize("part", road_network.PARTS)
def test_each_road_part_loads_in_av2_with_a_consistent_graph_and_clean_traffic(part, tmp_path):
  index = _first_with(part)
  generated = synthetic.generate_scenario(0, index)
  folder = synthetic.write_scenario(generated, tmp_path)
  sid = generated.scenario.scenario_id
  static_map = ArgoverseStaticMap.from_json(folder / f"log_map_archive_{sid}.json")   # av2 reads both files
  assert len(static_map.vector_lane_segments) == len(generated.map_json["lane_segments"])
  assert len(load_argoverse_scenario_parquet(folder / f"scenario_{sid}.parquet").tracks) >= 2
  lanes = generated.map_json["lane_segments"]
  _check_lane_graph(lanes)
  assert _part_is_there(part, lanes)
  # The traffic, read back: no two agents' boxes overlap at any step of 50-109, road users stay on the road.
  counts = audit.check_scenario(folder)
  assert counts["overlap"] == 0 and counts["offroad"] == 0
  assert counts["road_users"] >= 2


def test_traffic_on_real_av2_maps(tmp_path):
  """--maps: scenarios on the test AV2 maps, with each map's JSON unchanged; a map av2 refuses is skipped
  and counted."""
  maps = tmp_path / "maps"
  maps.mkdir()
  data = Path(__file__).parent / "data"
  real = [d for d in sorted(data.iterdir()) if d.is_dir()]
  for d in real:
    (maps / d.name).mkdir()
    for f in d.glob("log_map_archive_*.json"):
      (maps / d.name / f.name).write_bytes(f.read_bytes())      # the maps alone, no logs
  broken = maps / "broken"
  broken.mkdir()
  (broken / "log_map_archive_broken.json").write_text("{")
  out = tmp_path / "out"
  counts = synthetic.generate_dataset(out, 2 * (len(real) + 1), seed=3, val_fraction=0.0, workers=1, progress=False,
                                      maps=maps)
  assert counts == {"train": 2 * len(real), "val": 0, "skipped": 2}
  sources = [json.loads(f.read_text()) for d in real for f in d.glob("log_map_archive_*.json")]
  for folder in sorted((out / "train").iterdir()):
    sid = folder.name
    assert json.loads((folder / f"log_map_archive_{sid}.json").read_text()) in sources
    scenario = load_argoverse_scenario_parquet(folder / f"scenario_{sid}.parquet")
    assert any(t.track_id == "AV" and len(t.object_states) == 110 for t in scenario.tracks)
    counts = audit.check_scenario(folder)
    assert counts["overlap"] == 0 and counts["offroad"] == 0 and counts["road_users"] >= 2
    scene, _ = scene_builder.load_scene(folder)
    assert int(scene.agent_valid.sum()) >= 2


def test_traffic_is_plausible(written):
  out, _ = written
  kinds = set()
  for folder in _folders(out):
    scene, info = scene_builder.load_scene(folder)
    scene.validate()
    sc = load_argoverse_scenario_parquet(next(folder.glob("scenario_*.parquet")))
    full = [t for t in sc.tracks if len(t.object_states) == 110]
    assert any(t.track_id == "AV" for t in full)
    assert any(t.track_id == sc.focal_track_id for t in full)
    n = int(scene.agent_valid.sum())
    assert 2 <= n <= 40
    assert scene.agent_state[:n, :, 2].max() < 25.0  # m/s
    kinds.update(scene.agent_type[:n].tolist())
    # Velocity agrees with the motion between steps for moving vehicles (10 Hz).
    for t in sc.tracks:
      if t.object_type.value == "vehicle" and len(t.object_states) > 2:
        xy = np.array([s.position for s in t.object_states])
        v = np.array([s.velocity for s in t.object_states])
        step = np.diff(xy, axis=0) / 0.1
        moving = np.linalg.norm(v[:-1], axis=-1) > 2.0
        if moving.any():
          cos = (step[moving] * v[:-1][moving]).sum(-1) / (
              np.linalg.norm(step[moving], axis=-1) * np.linalg.norm(v[:-1][moving], axis=-1) + 1e-9)
          assert np.median(cos) > 0.95
    # No two kept agents overlap at the initial state.
    xy = scene.agent_state[:n, 0, :2]
    d = np.linalg.norm(xy[:, None] - xy[None], axis=-1) + np.eye(n) * 1e3
    assert d.min() > 0.5
  assert 0 in kinds and len(kinds) >= 2  # vehicles and at least one other type across the split


def test_rerun_skips_finished_and_cleans_partial(written, tmp_path):
  out = tmp_path / "syn"
  synthetic.generate_dataset(out, 3, seed=1, val_fraction=0.0, workers=1, progress=False)
  first = sorted((out / "train").iterdir())
  mtimes = [p.stat().st_mtime_ns for p in first]
  (out / "synthetic.json").write_text(json.dumps({"num": 3, "seed": 1, "val_fraction": 0.0,  # killed mid-way
                                                  "generator": synthetic.GENERATOR_VERSION}))
  (out / "train" / ".tmp-dead-1").mkdir()    # a half-written scenario of the killed run
  synthetic.generate_dataset(out, 3, seed=1, val_fraction=0.0, workers=1, progress=False)
  assert [p.stat().st_mtime_ns for p in sorted((out / "train").iterdir())] == mtimes
  assert not (out / "train" / ".tmp-dead-1").exists()


def test_a_folder_made_with_other_settings_is_refused(tmp_path):
  out = tmp_path / "syn"
  assert synthetic.generate_dataset(out, 4, seed=1, val_fraction=0.25, workers=1, progress=False) == {
      "train": 3, "val": 1}
  before = _folders(out)
  with pytest.raises(ValueError, match=r"made with \{'num': 4, 'seed': 1, 'val_fraction': 0.25, 'generator': 2\}, not the "
                                       r"\{'num': 2, 'seed': 1"):
    synthetic.generate_dataset(out, 2, seed=1, val_fraction=0.5, workers=1, progress=False)
  assert _folders(out) == before                       # nothing written, no train/val leak
  (out / "synthetic.json").unlink()                    # folders this generator did not record
  with pytest.raises(ValueError, match="did not record"):
    synthetic.generate_dataset(out, 4, seed=1, val_fraction=0.25, workers=1, progress=False)


def test_command_line(tmp_path, capsys):
  synthetic.main(["--out", str(tmp_path / "cli"), "--num", "2", "--seed", "3", "--workers", "1"])
  assert json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == {
      "out": str(tmp_path / "cli"), "train": 1, "val": 1}
