"""Hostile inputs that need no model: output folders the tool does not own, names read from files, non-finite
numbers, map content that shrinks, unbounded reads and folders that must be counted (README, Reliability)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from tests.av2_samples import DATA, REAL_110
from tdiff_jax import files
from tdiff_jax.data import av2_io, config as config_lib, scene_builder


def _strict(text: str):
  """JSON as RFC 8259 reads it: NaN and Infinity are not numbers there."""
  def refuse(token):
    raise ValueError(f"not strict JSON: {token}")
  return json.loads(text, parse_constant=refuse)


def _run(path, overwrite=False, inputs=(), write=("a.txt",)):
  with files.output_folder(path, overwrite, "test", inputs) as staging:
    for name in write:
      (staging / name).parent.mkdir(parents=True, exist_ok=True)
      (staging / name).write_text("new")


# ---- 1. output folders ----------------------------------------------------------------------------------


def test_a_folder_of_user_files_is_never_replaced_whatever_its_file_names(tmp_path):
  mine = tmp_path / "mine"
  mine.mkdir()
  (mine / "summary.json").write_text("{}")   # the name an earlier version took as its own
  (mine / "table.json").write_text("{}")
  (mine / "notes.txt").write_text("keep")
  for overwrite in (False, True):
    with pytest.raises(FileExistsError, match="not an output folder of tdiff_jax") as e:
      _run(mine, overwrite)
    assert "--overwrite" not in str(e.value)
  assert sorted(p.name for p in mine.iterdir()) == ["notes.txt", "summary.json", "table.json"]


def test_overwrite_replaces_only_what_the_tool_wrote(tmp_path):
  out = tmp_path / "out"
  _run(out, write=("a.txt", "scenarios/x/b.txt"))
  marker = json.loads((out / files.OUTPUT_MARKER).read_text())
  assert marker["files"] == ["a.txt", "scenarios/x/b.txt"] and marker["command"] == "test"
  with pytest.raises(FileExistsError, match="--overwrite"):
    _run(out)
  (out / "scenarios" / "my_notes.txt").write_text("keep")   # a user's file among the results
  with pytest.raises(FileExistsError, match="did not write .*scenarios/my_notes.txt"):
    _run(out, overwrite=True)
  assert (out / "scenarios" / "my_notes.txt").read_text() == "keep" and (out / "a.txt").exists()
  (out / "scenarios" / "my_notes.txt").unlink()
  _run(out, overwrite=True, write=("c.txt",))
  assert sorted(p.name for p in out.iterdir()) == [files.OUTPUT_MARKER, "c.txt"]


def test_an_output_folder_that_is_or_holds_an_input_is_refused(tmp_path):
  maps = tmp_path / "project" / "maps"
  shutil.copytree(DATA / REAL_110[0], maps / REAL_110[0])
  before = sorted(str(p) for p in maps.rglob("*"))
  for out in (tmp_path / "project", maps):
    with pytest.raises(ValueError, match="would delete that input"):
      _run(out, overwrite=True, inputs=(maps,))
  link = tmp_path / "link"
  link.symlink_to(tmp_path / "project")
  with pytest.raises(ValueError, match="would delete that input"):
    _run(link, overwrite=True, inputs=(maps,))
  assert sorted(str(p) for p in maps.rglob("*")) == before


def test_a_linked_output_folder_is_written_where_it_points(tmp_path):
  target = tmp_path / "target"
  _run(target, write=("old.txt",))
  link = tmp_path / "link"
  link.symlink_to(target)
  _run(link, overwrite=True, write=("new.txt",))
  assert link.is_symlink() and (target / "new.txt").exists() and not (target / "old.txt").exists()


def test_staging_folders_of_killed_runs_are_removed_and_others_kept(tmp_path):
  out = tmp_path / "out"
  dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                        text=True).stdout.strip()   # a process that has ended
  staged = tmp_path / f".tmp-out-{dead}"
  staged.mkdir()
  (staged / files.OUTPUT_MARKER).write_text(json.dumps({"written_by": "tdiff_jax", "staging": True, "files": []}))
  (staged / "half.txt").write_text("x")
  foreign = tmp_path / f".tmp-out-{dead}0"
  foreign.mkdir()   # the same pattern, not ours: kept
  _run(out)
  assert not staged.exists() and foreign.exists()


# ---- 2. names read from files ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["../../x", "a/b", "line\nbreak", "x" * 300, "", ".hidden", "é"])
def test_names_from_file_contents_are_one_harmless_path_component(name):
  safe = files.safe_name(name)
  assert safe and len(safe) <= files.NAME_LIMIT and not safe.startswith(".")
  assert set(safe) <= set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-")
  assert files.safe_name("0a1e6f0a-1817-4a98-b02e-db8c9327d151") == "0a1e6f0a-1817-4a98-b02e-db8c9327d151"
  assert files.safe_name("a/b") != files.safe_name("a_b")   # distinct names stay distinct


# ---- 3. non-finite numbers ------------------------------------------------------------------------------


def test_json_written_is_strict_with_non_finite_values_as_null_and_listed():
  text = files.json_text({"a": float("nan"), "b": [1.0, np.float32("inf")], "c": np.int64(3)})
  assert _strict(text) == {"a": None, "b": [1.0, None], "c": 3, files.NON_FINITE_NOTE: ["a", "b[1]"]}


def _map_edited(tmp_path, edit):
  sid = REAL_110[0]
  folder = shutil.copytree(DATA / sid, tmp_path / sid)
  path = folder / f"log_map_archive_{sid}.json"
  data = json.loads(path.read_text())
  edit(data)
  path.write_text(json.dumps(data))
  return folder, path


def test_a_map_vertex_out_of_range_is_refused_naming_the_element(tmp_path):
  def far(data):
    next(iter(data["lane_segments"].values()))["left_lane_boundary"][0]["x"] = 1e300
  folder, path = _map_edited(tmp_path, far)
  for require_agents in (True, False):   # training data and a map to sample on alike
    with pytest.raises(av2_io.BadScenarioError, match=r"lane \d+ left boundary: vertex .* not a finite coordinate") as e:
      scene_builder.load_scene(folder, require_agents=require_agents)
    assert e.value.path == str(path)


def test_a_heading_that_is_no_angle_leaves_the_agent_out_and_says_so(tmp_path):
  import pandas as pd
  folder = shutil.copytree(DATA / REAL_110[0], tmp_path / REAL_110[0])
  parquet = next(folder.glob("*.parquet"))
  frame = pd.read_parquet(parquet)
  tid = frame[(frame.timestep == 50) & (frame.object_type == "vehicle") & (frame.track_id != "AV")].track_id.iloc[0]
  frame.loc[(frame.track_id == tid) & (frame.timestep == 50), "heading"] = 1e300
  frame.to_parquet(parquet)
  scene, info = scene_builder.load_scene(folder)
  assert info.agents_implausible == 1 and "heading 1e+300 rad is not an angle" in info.warnings[0]
  assert np.isfinite(scene.agent_state).all() and np.abs(scene.agent_state[..., 3]).max() <= np.pi + 1e-6


# ---- 5. map content that shrinks ------------------------------------------------------------------------


def test_agents_beyond_the_cap_are_said():
  cfg = config_lib.default_data_config()
  cfg.max_agents = 2
  _, info = scene_builder.load_scene(DATA / REAL_110[0], cfg)
  assert info.agents_dropped > 0
  assert f"{info.agents_dropped} agent(s) beyond the cap of 2 (the farthest from the map centre) left out" in info.warnings


def test_degenerate_lanes_and_drivable_areas_are_said(tmp_path):
  def shrink(data):
    for lane in list(data["lane_segments"].values())[:3]:
      lane["left_lane_boundary"] = lane["left_lane_boundary"][:1]
    for area in data["drivable_areas"].values():
      area["area_boundary"] = area["area_boundary"][:2]
  folder, _ = _map_edited(tmp_path, shrink)
  _, info = scene_builder.load_scene(folder, require_agents=False)
  said = " | ".join(info.warnings)
  assert "3 lane(s) or crosswalk(s) without length" in said
  assert "drivable area(s) with fewer than three distinct vertices dropped" in said
  assert "no drivable area: off-road is not judged" in said


# ---- 6. bounded reads -----------------------------------------------------------------------------------


def test_a_pipe_or_a_device_in_place_of_a_scenario_file_is_refused_without_reading(tmp_path):
  folder = shutil.copytree(DATA / REAL_110[0], tmp_path / "piped" / REAL_110[0])
  parquet = next(folder.glob("*.parquet"))
  parquet.unlink()
  os.mkfifo(parquet)   # reading it would block forever
  with pytest.raises(av2_io.BadScenarioError, match="not a regular file") as e:
    scene_builder.load_scene(folder)
  assert e.value.path == str(parquet)
  folder2 = shutil.copytree(DATA / REAL_110[0], tmp_path / "endless" / REAL_110[0])
  map_json = next(folder2.glob("*.json"))
  map_json.unlink()
  map_json.symlink_to("/dev/zero")   # endless
  with pytest.raises(av2_io.BadScenarioError, match="not a regular file"):
    scene_builder.load_scene(folder2, require_agents=False)


def test_a_file_beyond_the_size_cap_is_refused(tmp_path, monkeypatch):
  monkeypatch.setattr(av2_io, "MAX_FILE_BYTES", 1000)
  with pytest.raises(av2_io.BadScenarioError, match="more than the .* MiB a scenario file may hold"):
    scene_builder.load_scene(DATA / REAL_110[0])


# ---- 7. folders that must be counted --------------------------------------------------------------------


def test_an_unreadable_or_dangling_scenario_folder_is_counted_with_its_reason(tmp_path):
  from tdiff_jax.data import preprocess
  root = tmp_path / "data"
  shutil.copytree(DATA / REAL_110[0], root / "train" / REAL_110[0])
  (root / "train" / "gone").symlink_to(tmp_path / "nowhere")
  assert [p.name for p in av2_io.list_scenario_folders(root / "train")] == [REAL_110[0], "gone"]
  with pytest.raises(av2_io.BadScenarioError, match="a link to nothing"):
    av2_io.find_scenario_files(root / "train" / "gone")
  manifest = preprocess.preprocess(root, tmp_path / "cache", workers=1, progress=False)
  assert [s["scenario"] for s in manifest["skipped"]] == ["gone"]


@pytest.mark.skipif(os.geteuid() == 0, reason="permissions do not bind root")
def test_a_folder_without_read_permission_is_counted(tmp_path):
  folder = shutil.copytree(DATA / REAL_110[0], tmp_path / "data" / REAL_110[0])
  folder.chmod(0)
  try:
    assert av2_io.list_scenario_folders(tmp_path / "data") == [folder]
    with pytest.raises(av2_io.BadScenarioError, match="unreadable folder"):
      av2_io.find_scenario_files(folder)
  finally:
    folder.chmod(0o755)


def test_an_av2_root_without_val_is_refused_unless_the_split_is_named(tmp_path):
  root = tmp_path / "root"
  shutil.copytree(DATA / REAL_110[0], root / "train" / REAL_110[0])
  with pytest.raises(FileNotFoundError, match=r"holds train/: pass the folder of the split to use"):
    av2_io.map_folders(root)
  assert av2_io.map_folders(root / "train") == [root / "train" / REAL_110[0]]


# ---- the audit of complete scenarios as written (tdiff_jax.audit) ----------------------------------------


def test_boxes_overlap_by_separating_axes():
  from tdiff_jax import audit
  car = audit._SIZES[[0, 0]]
  one = np.ones((2, 1), bool)
  side = lambda gap: audit.overlapping_agents(np.array([[[0, 0]], [[0, gap]]], float), np.zeros((2, 1)), car, one)
  assert side(1.9).all() and not side(2.1).any()                        # 2 m wide cars side by side
  turned = np.array([[0.0], [np.pi / 4]])
  corner = lambda x, y: audit.overlapping_agents(np.array([[[0, 0]], [[x, y]]], float), turned, car, one)
  assert corner(3.9, 1.9).all() and not corner(4.4, 2.4).any()          # a corner just inside, just apart
  not_both = np.array([[True], [False]])                                  # never at one step together
  assert not audit.overlapping_agents(np.zeros((2, 1, 2)), np.zeros((2, 1)), car, not_both).any()
  square = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
  assert audit.outside_areas(np.array([[5, 5], [11, 5], [-1, -1]], float), [square]).tolist() == [False, True, True]


def test_the_audit_reads_written_scenarios_as_av2_does(tmp_path):
  """The logged agents of a real scenario written as a generated scenario: no overlap, as logged; one
  driving through another, and one moved off the map, are counted."""
  from tdiff_jax import audit, datatypes
  from tdiff_jax.data import av2_export
  folder = DATA / REAL_110[0]
  scene, info = scene_builder.load_scene(folder)
  logged = audit.audit_folders([folder], logged=True)
  n = int(scene.agent_valid.sum())
  assert logged["agents"] == n and logged["overlap"] == 0 and logged["scenarios"] == 1
  xy = datatypes.to_city(scene, scene.agent_future.astype(np.float64))[:n]
  xy[1] = xy[0] + np.array([0.5, 0.0])        # agent 1 drives through agent 0
  xy[2] += 500.0                              # agent 2 far off the road
  types = np.array(scene.agent_type[:n])
  types[2] = datatypes.AGENT_TYPES.index("vehicle")
  map_json = next(folder.glob("log_map_archive_*.json"))
  written = av2_export.write_generated_scenario(tmp_path, "gen", "city", map_json, xy, scene.agent_state[:n, 0, 3],
                                                types, np.ones(n, bool))
  got = audit.audit_folders([written])
  assert got["agents"] == n and got["overlap"] >= 2 and got["offroad"] >= 1
  assert got["overlap_pct"] == 100.0 * got["overlap"] / n


def test_the_audit_command_reads_any_folder_of_scenarios(tmp_path, capsys):
  from tdiff_jax import audit
  audit.main([str(DATA), f"--out={tmp_path / 'audit.json'}"])
  printed = _strict(capsys.readouterr().out)
  assert printed == _strict((tmp_path / "audit.json").read_text())
  assert printed["scenarios"]["scenarios"] == 4 and printed["scenarios"]["agents"] > 0
  with pytest.raises(SystemExit, match="audit: give"):
    audit.main([])
