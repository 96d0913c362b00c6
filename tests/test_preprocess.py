"""The preprocessing cache: bad inputs skipped with reasons, manifest, resume, atomic writes, caps."""

from __future__ import annotations

import json
import subprocess
import sys

import ml_collections
import numpy as np
import pytest

from tests.av2_samples import DATA, REAL_110
from tdiff_jax import datatypes, files
from tdiff_jax.data import batches, config as config_lib, normalize, preprocess


def test_bad_inputs_are_skipped_with_reasons_and_the_rest_lands(mixed_dataset, mixed_cache):
  _, expected_bad = mixed_dataset
  _, manifest = mixed_cache
  skipped = {s["scenario"]: s for s in manifest["skipped"]}
  assert set(skipped) == set(expected_bad)
  for name, reason in expected_bad.items():
    assert reason in skipped[name]["reason"], skipped[name]
    assert name in skipped[name]["file"]  # the record names the file
  train, val = manifest["splits"]["train"], manifest["splits"]["val"]
  assert train["scenario_folders"] == 2 + 1 + 4 + 5 and train["skipped"] == 6 and train["scenes"] == 6
  assert val["scenes"] == 3 and val["skipped"] == 0


def test_manifest_contents(mixed_cache):
  out, manifest = mixed_cache
  cfg = config_lib.default_data_config()
  assert manifest["config_hash"] == config_lib.config_hash(cfg)
  assert manifest["caps"]["agents"] == cfg.max_agents and manifest["caps"]["points_per_polygon"] == 30
  assert manifest["av2_version"] == "0.3.6"
  assert manifest["feature_layout"]["agent_state"] == list(datatypes.AGENT_FEATURES)
  assert json.loads((out / preprocess.MANIFEST).read_text()) == manifest
  # Normalisation statistics come from the training split.
  train = preprocess.load_arrays(out / "train")
  stats = normalize.normalization_stats(train["agent_state"], train["agent_valid"], train["frame_scale"])
  np.testing.assert_allclose(manifest["normalization"]["mean"], stats["mean"], rtol=1e-10)
  np.testing.assert_allclose(manifest["normalization"]["std"], stats["std"], rtol=1e-10)
  assert manifest["normalization"]["split"] == "train"


def test_shards_hold_valid_scenes(mixed_cache):
  out, manifest = mixed_cache
  ds = batches.load_split(out, "train")
  assert len(ds) == manifest["splits"]["train"]["scenes"]
  ds.scenes.validate()
  assert len(set(ds.scenario_ids.tolist())) == len(ds)


def _arrays(out):
  return {s: preprocess.load_arrays(out / s) for s in ("train", "val")}


def test_rerun_resumes_and_rebuilds_only_damaged_shards(mixed_dataset, tmp_path):
  root, _ = mixed_dataset
  out = tmp_path / "cache"
  preprocess.preprocess(root, out, workers=1, shard_size=4, progress=False)
  first = _arrays(out)
  shards = preprocess.shard_paths(out / "train")
  assert len(shards) == 3 and all(p.with_suffix(".json").exists() for p in shards)
  mtimes = {p: p.stat().st_mtime_ns for p in shards}
  preprocess.preprocess(root, out, workers=1, shard_size=4, progress=False)
  assert {p: p.stat().st_mtime_ns for p in shards} == mtimes  # nothing redone
  shards[0].unlink()                                           # lost
  shards[1].write_bytes(shards[1].read_bytes()[:100])          # damaged
  (out / "train" / ".tmp-shard_00002-123.array_record").write_bytes(b"half")  # left by a killed run
  preprocess.preprocess(root, out, workers=1, shard_size=4, progress=False)
  assert shards[2].stat().st_mtime_ns == mtimes[shards[2]]
  assert not list(out.glob("*/.tmp-*"))
  again = _arrays(out)
  for split in first:
    for name in first[split]:
      np.testing.assert_array_equal(again[split][name], first[split][name])


def test_all_cores_give_the_same_cache(mixed_dataset, mixed_cache, tmp_path):
  root, _ = mixed_dataset
  out = tmp_path / "par"
  preprocess.preprocess(root, out, workers=2, shard_size=3, progress=False)
  ref, got = _arrays(mixed_cache[0]), _arrays(out)
  for split in ref:
    for name in ref[split]:
      np.testing.assert_array_equal(got[split][name], ref[split][name])


def test_an_old_cache_format_is_refused_with_the_command_that_rebuilds_it(mixed_cache, tmp_path):
  import shutil
  old = tmp_path / "old"
  shutil.copytree(mixed_cache[0], old)
  manifest = json.loads((old / preprocess.MANIFEST).read_text())
  manifest["format_version"] = 3
  (old / preprocess.MANIFEST).write_text(json.dumps(manifest))
  with pytest.raises(ValueError, match=r"cache format 3, this code reads 5; rebuild the cache with: "
                                       r"python -m tdiff_jax.data.preprocess --data_dir .* --force"):
    batches.open_split(old, "train")


def test_streaming_split_matches_the_in_memory_one(mixed_cache):
  out, manifest = mixed_cache
  memory, stream = batches.load_split(out, "train"), batches.open_split(out, "train")
  assert len(stream) == len(memory) and stream.scenario_ids.tolist() == memory.scenario_ids.tolist()
  np.testing.assert_array_equal(stream.num_agents, memory.num_agents)
  np.testing.assert_array_equal(stream.num_polygons, memory.num_polygons)
  for i in range(len(stream)):
    scene = stream[i]
    assert str(scene["scenario_id"]) == memory.scenario_ids[i]
    for name in datatypes.SCENE_FIELDS:
      np.testing.assert_array_equal(scene[name], getattr(memory.scenes, name)[i])
  # Statistics merged from per-shard moments equal the ones of the whole split at once.
  offsets = normalize.offset_stats(memory.scenes.agent_state, memory.scenes.agent_valid, memory.scenes.frame_scale)
  np.testing.assert_allclose(manifest["goal_offset_normalization"]["mean"], offsets["mean"], rtol=1e-10)
  np.testing.assert_allclose(manifest["goal_offset_normalization"]["std"], offsets["std"], rtol=1e-10)
  counts = np.bincount(memory.scenes.agent_type[memory.scenes.agent_valid], minlength=len(datatypes.AGENT_TYPES))
  assert manifest["splits"]["train"]["agent_type_counts"] == counts.tolist()


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
  target = tmp_path / "shard.npz"

  def dies_midway(f):
    f.write(b"partial")
    raise KeyboardInterrupt

  with pytest.raises(KeyboardInterrupt):
    files.atomic_write(target, dies_midway)
  assert list(tmp_path.iterdir()) == []


def test_a_full_disk_or_read_only_folder_names_the_file(tmp_path):
  import errno

  def disk_full(f):
    f.write(b"partial")
    raise OSError(errno.ENOSPC, "No space left on device")

  with pytest.raises(OSError, match=f"cannot write {tmp_path / 'shard.npz'}: No space left on device"):
    files.atomic_write(tmp_path / "shard.npz", disk_full)
  assert list(tmp_path.iterdir()) == []

  def read_only(f):
    raise PermissionError(errno.EACCES, "Permission denied")

  with pytest.raises(PermissionError, match=f"cannot write {tmp_path / 'manifest.json'}: Permission denied"):
    files.atomic_write(tmp_path / "manifest.json", read_only)
  assert list(tmp_path.iterdir()) == []


def test_caps_truncate_and_count(mixed_dataset, tmp_path):
  root, _ = mixed_dataset
  cfg = config_lib.default_data_config()
  cfg.max_agents, cfg.max_polygons = 3, 40
  manifest = preprocess.preprocess(root, tmp_path / "small", cfg, workers=1, progress=False)
  totals, affected = manifest["truncation"]["totals"], manifest["truncation"]["scenes_affected"]
  assert totals["agents_dropped"] > 0 and totals["polygons_dropped"] > 0
  assert 0 < affected["agents_dropped"] <= 9
  assert manifest["splits"]["train"]["max_agents_seen"] > 3  # the real maximum is still reported
  ds = batches.load_split(tmp_path / "small", "train", cfg)
  assert ds.scenes.agent_valid.shape[1:] == (3,) and ds.scenes.pl_edge.shape[1:] == (40, 40)
  # A cache is only read with the config it was made with.
  with pytest.raises(ValueError, match="max_agents: cache 3 vs config 64"):
    batches.load_split(tmp_path / "small", "train")


def test_errors_name_the_problem(tmp_path):
  with pytest.raises(FileNotFoundError, match="does not exist"):
    preprocess.preprocess(tmp_path / "nowhere", tmp_path / "out", progress=False)
  (tmp_path / "empty").mkdir()
  with pytest.raises(FileNotFoundError, match="no AV2 scenario folders"):
    preprocess.preprocess(tmp_path / "empty", tmp_path / "out", progress=False)
  with pytest.raises(FileNotFoundError, match="no manifest"):
    batches.load_split(tmp_path / "empty", "train")


def test_command_line_and_config_typo(mixed_dataset, tmp_path):
  root, _ = mixed_dataset
  cmd = [sys.executable, "-m", "tdiff_jax.data.preprocess", f"--data_dir={root / 'val'}",
         f"--out={tmp_path / 'cli'}", "--workers=1", "--config.max_agents=32"]
  done = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
  assert done.returncode == 0, done.stderr
  summary = json.loads(done.stdout.strip().splitlines()[-1])
  assert summary["splits"]["train"]["scenes"] == 3  # scenario folders directly: one split
  assert json.loads((tmp_path / "cli" / "manifest.json").read_text())["caps"]["agents"] == 32
  typo = subprocess.run(cmd[:-1] + ["--config.max_agentz=32"], capture_output=True, text=True, timeout=300)
  assert typo.returncode != 0 and "max_agentz" in typo.stderr


def _small_dataset(root):
  from tdiff_jax.data import synthetic
  train = root / "train"
  train.mkdir(parents=True)
  for i in range(4):
    synthetic.write_scenario(synthetic.generate_scenario(5, 20 + i), train)
  return sorted(train.iterdir())


def test_resume_rebuilds_shards_whose_sources_changed_and_force_rebuilds_all(tmp_path, capsys):
  root, out = tmp_path / "data", tmp_path / "cache"
  folders = _small_dataset(root)
  preprocess.preprocess(root, out, workers=1, shard_size=2, progress=False)
  shards = preprocess.shard_paths(out / "train")
  mtimes = {p: p.stat().st_mtime_ns for p in shards}
  # A source file corrupted after the cache was built: its shard is rebuilt and the scenario skipped.
  parquet = next(folders[3].glob("*.parquet"))
  good = parquet.read_bytes()
  parquet.write_bytes(good[: len(good) // 2])
  manifest = preprocess.preprocess(root, out, workers=1, shard_size=2, progress=True)
  assert "sources changed since the last run: train/" + folders[3].name in capsys.readouterr().err
  assert shards[0].stat().st_mtime_ns == mtimes[shards[0]]  # untouched shard reused
  assert shards[1].stat().st_mtime_ns != mtimes[shards[1]]
  assert [s["scenario"] for s in manifest["skipped"]] == [folders[3].name]
  # Fixed again: it lands again.
  parquet.write_bytes(good)
  manifest = preprocess.preprocess(root, out, workers=1, shard_size=2, progress=False)
  assert manifest["skipped"] == [] and manifest["splits"]["train"]["scenes"] == 4
  # --force rebuilds everything, from the command line too.
  before = {p: p.stat().st_mtime_ns for p in shards}
  subprocess.run([sys.executable, "-m", "tdiff_jax.data.preprocess", f"--data_dir={root}", f"--out={out}",
                  "--workers=1", "--shard_size=2", "--force"], check=True, capture_output=True)
  assert all(p.stat().st_mtime_ns != before[p] for p in shards)


def test_degenerate_map_elements_are_dropped_and_counted(tmp_path):
  root = tmp_path / "data"
  folders = _small_dataset(root)
  map_json = next(folders[0].glob("*.json"))
  raw = json.loads(map_json.read_text())
  lane = next(iter(raw["lane_segments"].values()))
  lane["left_lane_boundary"] = lane["left_lane_boundary"][:1]  # a single-point boundary
  area = next(iter(raw["drivable_areas"].values()))
  area["area_boundary"] = area["area_boundary"][:2]  # a two-vertex "area"
  map_json.write_text(json.dumps(raw))
  manifest = preprocess.preprocess(root, tmp_path / "cache", workers=1, progress=False)
  degenerate = manifest["degenerate_map_elements"]
  assert degenerate["totals"] == {"polygons_degenerate": 1, "drivable_areas_degenerate": 1}
  assert degenerate["scenes_affected"] == {"polygons_degenerate": 1, "drivable_areas_degenerate": 1}
  arrays = preprocess.load_arrays(tmp_path / "cache" / "train", ["pt_xy", "pt_valid", "scenario_id"])
  # No kept polygon has a zero-length polyline.
  pts = arrays["pt_xy"].reshape(*arrays["pt_xy"].shape[:2], 3, -1, 2)
  length = np.linalg.norm(np.diff(pts, axis=-2), axis=-1).sum(-1)  # [S, P, 3]
  valid = arrays["pt_valid"].reshape(*length.shape, -1).all(-1)
  assert (length[valid] > 0).all()


def test_duplicates_leaks_ignored_and_hidden_folders(tmp_path, caplog):
  import shutil
  root = tmp_path / "data"
  folders = _small_dataset(root)
  (root / "val").mkdir()
  shutil.copytree(folders[0], root / "val" / folders[0].name)            # the same scenario in two splits
  shutil.copytree(folders[1], root / "train" / (folders[1].name + "-copy"))  # twice in one split
  shutil.copytree(folders[2], root / folders[2].name)                     # beside the split folders
  shutil.copytree(folders[3], root / "train" / f".tmp-{folders[3].name}-123")  # an interrupted write
  with caplog.at_level("WARNING"):
    manifest = preprocess.preprocess(root, tmp_path / "cache", workers=1, progress=False)
  warnings = manifest["warnings"]
  assert len(warnings) == 3 and all(w in caplog.text for w in warnings)
  warnings = [w.split(": ", 1)[1] for w in warnings]  # without the data folder
  assert f"scenario {folders[0].name} appears in two splits: train/{folders[0].name}, val/{folders[0].name}" in warnings
  assert any(f"scenario {folders[1].name} appears in several folders" in w for w in warnings)
  assert any("1 scenario folder(s) beside the split folders are ignored" in w and folders[2].name in w for w in warnings)
  # The hidden folder is neither a scene nor a skip.
  assert manifest["splits"]["train"]["scenario_folders"] == 5 and manifest["skipped"] == []


def test_a_record_round_trips_every_array_exactly():
  from tdiff_jax.data import records
  arrays = {"scalar": np.float32(125.0), "transposed": np.arange(12, dtype=np.int64).reshape(3, 4).T,
            "flags": np.array([True, False]), "id": np.array("0a1e6f0a"), "empty": np.zeros((0, 3), np.float32)}
  back = records.decode(records.encode(arrays))
  assert set(back) == set(arrays)
  for name, value in arrays.items():
    value = np.asarray(value)
    assert back[name].shape == value.shape and back[name].dtype == value.dtype, name
    np.testing.assert_array_equal(back[name], value)


def test_training_data_from_a_real_av2_root(tmp_path):
  """`data.dir` (training's real-data branch): an AV2 root is preprocessed into the cache once, which
  later runs reuse; a missing root is named."""
  import shutil

  from tdiff_jax.train import data_setup

  root = tmp_path / "av2"
  for split, sids in (("train", REAL_110[:2]), ("val", REAL_110[2:])):
    for sid in sids:
      shutil.copytree(DATA / sid, root / split / sid)
  c = config_lib.default_data_config()
  data = ml_collections.ConfigDict({"dir": str(root), "cache_dir": "", "scene": c, "workers": 1})
  cache = data_setup.prepare_cache(data, tmp_path / "work")
  assert cache == tmp_path / "work" / "cache"
  manifest = batches.read_manifest(cache)
  assert manifest["splits"]["train"]["scenes"] == 2 and manifest["splits"]["val"]["scenes"] == 1
  train = batches.open_split(cache, "train", c)
  assert sorted(train.scenario_ids) == sorted(REAL_110[:2])
  shard = preprocess.shard_paths(cache / "train")[0]
  before = shard.stat().st_mtime_ns
  assert data_setup.prepare_cache(data, tmp_path / "work") == cache and shard.stat().st_mtime_ns == before
  data.dir = str(tmp_path / "nowhere")
  with pytest.raises(FileNotFoundError, match="data.dir=.*nowhere: no such directory"):
    data_setup.prepare_cache(data, tmp_path / "work")


def _damage_edited_counts(train):
  meta_path = preprocess.shard_paths(train)[0].with_suffix(".json")
  meta = json.loads(meta_path.read_text())
  meta["num_agents"] = [1 for _ in meta["num_agents"]]   # batching would crop every scene to one agent
  meta_path.write_text(json.dumps(meta))
  return meta_path


def _damage_swapped_records(train):
  first, second = preprocess.shard_paths(train)[:2]
  first.write_bytes(second.read_bytes())                  # another shard's scenes under this one's metadata
  return first


def _damage_flipped_bytes(train):
  path = preprocess.shard_paths(train)[1]
  data = bytearray(path.read_bytes())
  for i in range(len(data) // 2, len(data) // 2 + 16):
    data[i] ^= 0xFF
  path.write_bytes(bytes(data))
  return path


def _damage_edited_manifest(train):
  path = train.parent / preprocess.MANIFEST
  manifest = json.loads(path.read_text())
  manifest["normalization"]["std"] = [1.0, 1.0, 1.0]
  path.write_text(json.dumps(manifest))
  return path


@pytest.mark.parametrize("damage", [_damage_edited_counts, _damage_swapped_records, _damage_flipped_bytes,
                                    _damage_edited_manifest])
def test_a_damaged_shard_is_named_when_opened_and_rebuilt_by_preprocessing(mixed_dataset, tmp_path, capsys, damage):
  root, _ = mixed_dataset
  out = tmp_path / "cache"
  preprocess.preprocess(root, out, workers=1, shard_size=3, progress=False)
  first = _arrays(out)
  named = damage(out / "train")
  with pytest.raises(ValueError, match=f"{named.name}: .*(checksum).*rebuild it with: python -m "
                                       f"tdiff_jax.data.preprocess --data_dir {root} --out {out}"):
    batches.open_split(out, "train")
  preprocess.preprocess(root, out, workers=1, shard_size=3, progress=True)   # the rerun rebuilds it
  assert damage is _damage_edited_manifest or "rebuilding a shard" in capsys.readouterr().err
  assert len(batches.open_split(out, "train")) == len(first["train"]["scenario_id"])
  again = _arrays(out)
  for name in first["train"]:
    np.testing.assert_array_equal(again["train"][name], first["train"][name])


def test_a_record_that_does_not_read_names_its_shard(mixed_cache, tmp_path):
  import shutil
  cache = shutil.copytree(mixed_cache[0], tmp_path / "cache")
  source = batches.open_split(cache, "train")
  _damage_flipped_bytes(cache / "train")   # after the split was opened and checked
  with pytest.raises(ValueError, match=r"shard_00001\.array_record: .*does not read .*rebuild it with"):
    for i in range(len(source)):
      source[i]


def test_one_absurd_agent_does_not_move_the_statistics_and_is_said(tmp_path, capsys):
  import pandas as pd
  folders = _small_dataset(tmp_path / "clean")
  clean = preprocess.preprocess(tmp_path / "clean", tmp_path / "clean_cache", workers=1, progress=False)
  parquet = next(folders[1].glob("*.parquet"))
  frame = pd.read_parquet(parquet)
  tid = frame[(frame.timestep == 50) & (frame.object_type == "vehicle")].track_id.iloc[0]
  frame.loc[(frame.track_id == tid) & (frame.timestep == 50), "velocity_x"] = 1000.0
  frame.to_parquet(parquet)
  bad = preprocess.preprocess(tmp_path / "clean", tmp_path / "bad_cache", workers=1, progress=False)
  np.testing.assert_allclose(bad["normalization"]["std"], clean["normalization"]["std"], rtol=0.2)
  assert bad["implausible_agents"] == {"totals": 1, "scenes_affected": 1}
  assert any("speed 1000.0 m/s above 70" in w for w in bad["warnings"])
  assert "speed 1000.0 m/s above 70" in capsys.readouterr().err
