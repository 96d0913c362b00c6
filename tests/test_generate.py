"""`python sample.py` / `generate`: outputs, failed maps reported, agent plans, no-checkpoint message."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import chex
import jax
import numpy as np
import pytest

from configs import hl as hl_config
from tests.av2_samples import DATA, REAL_50, REAL_110
from tdiff_jax import checkpoint, generate, geometry, metrics, models, sampling
from tdiff_jax.data import synthetic
from tdiff_jax.train import trainer

ROOT = Path(__file__).resolve().parent.parent
FAST = sampling.SamplerOptions(method="ddim", stride=10)


def _refuse(token):
  raise ValueError(f"not strict JSON: {token}")


@pytest.fixture(scope="module")
def trained(tmp_path_factory, tiny_cache) -> Path:
  """A tiny HL model trained for 3 steps on the session's tiny synthetic worlds (`tiny_cache`), which the
  workdir holds as a run on the synthetic default does (`synthetic/`, `cache/`)."""
  workdir = tmp_path_factory.mktemp("hl_tiny")
  for name in ("synthetic", "cache"):
    (workdir / name).symlink_to(tiny_cache.parent / name, target_is_directory=True)
  config = hl_config.get_config("tiny")
  config.data.cache_dir = str(tiny_cache)
  config.train.num_steps = 3
  trainer.train_and_evaluate(config, workdir)
  return workdir


@pytest.fixture(scope="module")
def maps(trained, tmp_path_factory) -> Path:
  folder = tmp_path_factory.mktemp("maps")
  for sc in sorted((trained / "synthetic" / "val").iterdir())[:2]:
    shutil.copytree(sc, folder / sc.name)
  shutil.copytree(DATA / REAL_50, folder / REAL_50)   # a real test-split map: no goal step, still a map
  broken = synthetic.write_scenario(synthetic.generate_scenario(9, 0), folder)
  next(broken.glob("*.json")).write_text("{")
  # A good map beside a broken parquet: sampling needs only the map, so it is used, with a warning.
  tracks_broken = synthetic.write_scenario(synthetic.generate_scenario(9, 1), folder)
  parquet = next(tracks_broken.glob("*.parquet"))
  parquet.write_bytes(parquet.read_bytes()[:100])
  return folder


def test_generate_writes_samples_pictures_and_summary(trained, maps, tmp_path):
  summary = generate.generate(trained, maps, tmp_path, num_per_map=2, options=FAST, progress=False)
  assert summary["maps_sampled"] == 4 and summary["samples"] == 8
  assert len(summary["failed_maps"]) == 1 and "broken map JSON" in summary["failed_maps"][0]["reason"]
  [warned] = [w for w in summary["map_warnings"] if "only the map is used" in w["warning"]]
  assert "only the map is used: unreadable scenario parquet" in warned["warning"]
  [capped] = [w for w in summary["map_warnings"] if w is not warned]   # the real map's lanes beyond the tiny cap
  assert capped["map"] == REAL_50 and "lane(s) or crosswalk(s) beyond the cap of 128" in capped["warning"]
  z = np.load(tmp_path / "samples.npz")
  assert z["state"].shape[0] == 8 and z["state"].shape[2:] == (2, 3)
  assert warned["map"] in set(z["scenario_id"].tolist())
  assert (z["valid"].sum(-1) >= 1).all() and np.isfinite(z["state"]).all()
  assert len(list(tmp_path.glob("*.png"))) == 8
  summary = json.loads((tmp_path / "summary.json").read_text(), parse_constant=_refuse)   # strict JSON
  assert summary["samples"] == 8
  assert z["city_xy"].dtype == np.float64   # city coordinates of 1e6 m and more keep their centimetres
  # Speeds are magnitudes; the ones the model put below zero are marked, counted, and only on valid agents.
  assert (z["state"][..., 2] >= 0).all() and z["negative_speed"].shape == z["state"].shape[:3]
  assert not (z["negative_speed"] & ~z["valid"][..., None]).any()
  assert summary["negative_speeds_set_to_zero"] == int(z["negative_speed"].sum())
  # In the maps' order, each map's samples in turn; a sample depends on its place in that order only, not
  # on the batch it was sampled in.
  folders = [p.name for p in sorted(maps.iterdir()) if p.name != summary["failed_maps"][0]["map"]]
  assert z["map_folder"].tolist() == [f for f in folders for _ in range(2)]
  assert z["sample_index"].tolist() == [0, 1] * 4
  generate.generate(trained, maps, tmp_path / "one_by_one", num_per_map=2, options=FAST, progress=False,
                    pictures=False, batch_size=4)
  # Up to float rounding, which the sampler's steps grow to millimetres in a few agents.
  np.testing.assert_allclose(np.load(tmp_path / "one_by_one" / "samples.npz")["state"], z["state"], atol=1e-2)


def test_agent_count_choices(trained, maps, tmp_path):
  fixed = generate.generate(trained, maps, tmp_path / "a", num_agents=3, options=FAST, pictures=False, progress=False)
  z = np.load(tmp_path / "a" / "samples.npz")
  assert (z["valid"].sum(-1) == 3).all() and fixed["samples"] == 4
  gt = generate.generate(trained, maps, tmp_path / "b", num_agents=-1, options=FAST, pictures=False, progress=False)
  reasons = " ".join(f["reason"] for f in gt["failed_maps"])
  assert gt["samples"] == 2 and "no goal step" in reasons  # ground truth needs agents
  assert "unreadable scenario parquet" in reasons            # ... and so their parquet
  with pytest.raises(ValueError, match="num_agents=1000 is more than this model places: at most 32"):
    generate.generate(trained, maps, tmp_path / "d", num_agents=1000, options=FAST, pictures=False, progress=False)
  only_bad = tmp_path / "only_bad"
  shutil.copytree(maps / REAL_50, only_bad / REAL_50)
  with pytest.raises(ValueError, match=f"none of the 1 map.*{REAL_50}.*no goal step"):  # nothing generated
    generate.generate(trained, only_bad, tmp_path / "c", num_agents=-1, options=FAST, pictures=False, progress=False)
  assert not (tmp_path / "c" / "samples.npz").exists()


def test_missing_checkpoint_says_how_to_train(tmp_path):
  with pytest.raises(FileNotFoundError, match="train one first"):
    generate.generate(tmp_path / "nothing", tmp_path, tmp_path / "out")
  # `~` is expanded (the shell leaves it in `--flag=~/x`).
  env = {**os.environ, "HOME": str(tmp_path)}
  done = subprocess.run([sys.executable, "sample.py", "--hl_workdir=~/nothing"], capture_output=True,
                        text=True, timeout=300, cwd=ROOT, env=env)
  assert done.returncode != 0 and "python train.py --config=configs/hl.py" in done.stderr
  assert f"no checkpoint in {tmp_path / 'nothing'}" in done.stderr


def test_sample_without_training_uses_the_pretrained_models(tmp_path):
  """`python sample.py` where no workdir exists: the shipped HL model and infiller write complete scenarios
  (here on two real AV2 maps, in a few sampler steps)."""
  maps = tmp_path / "maps"
  for name in REAL_110[:2]:
    shutil.copytree(DATA / name, maps / name)
  done = subprocess.run([sys.executable, str(ROOT / "sample.py"), f"--maps={maps}", "--method=ddim", "--steps=5"],
                        capture_output=True, text=True, timeout=600, cwd=tmp_path,
                        env={**os.environ, "TDIFF_JAX_COMPILATION_CACHE": "0"})
  assert done.returncode == 0, done.stderr[-2000:]
  summary = json.loads(done.stdout.strip().splitlines()[-1])
  assert summary["checkpoint"] == str(checkpoint.pretrained_dir("hl"))
  assert summary["infiller_checkpoint"] == str(checkpoint.pretrained_dir("infill"))
  out = tmp_path / "workdirs" / "hl" / "samples"
  assert summary["samples"] == len(summary["scenarios"]) == 2 and len(list(out.glob("*.png"))) == 2
  for gen in summary["scenarios"]:
    assert (out / "scenarios" / gen["scenario_id"] / f"scenario_{gen['scenario_id']}.parquet").is_file()
  z = np.load(out / "samples.npz")
  valid = z["valid"]
  assert valid.sum() > 0 and np.isfinite(z["trajectory"][valid]).all()
  np.testing.assert_allclose(z["trajectory"][:, :, 0][valid], z["state"][:, :, 0, :2][valid], atol=1e-3)
  np.testing.assert_allclose(z["trajectory"][:, :, -1][valid], z["state"][:, :, 1, :2][valid], atol=1e-3)


def test_the_pretrained_models_are_those_of_record():
  """The shipped models are the default recipe's, and pretrained.json holds the README's Table I of them."""
  from configs import infill as infill_config
  info = json.loads((checkpoint.PRETRAINED / "pretrained.json").read_text())
  for task, config in (("hl", hl_config.get_config()), ("infill", infill_config.get_config())):
    loaded = checkpoint.load_checkpoint(checkpoint.pretrained_dir(task), task=task)
    assert loaded.record["step"] == info["models"][task]["step"] == config.train.num_steps
    assert models.model_spec(loaded.config) == models.model_spec(config)
    assert sum(f.stat().st_size for f in checkpoint.pretrained_dir(task).iterdir()) < 5_000_000
  record = json.loads((ROOT / "results" / "table1_synthetic_val.json").read_text())
  assert info["table_i"]["table_i"] == record["table_i"]


def test_an_exported_model_is_its_checkpoint(trained, tmp_path):
  """An exported model loads as its checkpoint: the same EMA parameters, statistics, schedule and lane pull
  (sampling from one: `test_sample_without_training_uses_the_pretrained_models`)."""
  exported = checkpoint.export_model(trained, tmp_path / "exported")
  assert checkpoint.has_checkpoint(exported) and checkpoint.is_exported(exported)
  a, b = checkpoint.load_checkpoint(trained), checkpoint.load_checkpoint(exported, task="hl")
  chex.assert_trees_all_equal(a.params, b.params)
  chex.assert_trees_all_equal((a.norm, a.sched), (b.norm, b.sched))
  assert (a.lane_pull, a.record["step"]) == (b.lane_pull, b.record["step"])
  assert models.model_spec(a.config) == models.model_spec(b.config)
  (exported / "params.npz").write_bytes(b"not a zip")
  with pytest.raises(ValueError, match=f"{exported / 'params.npz'}: does not load"):
    checkpoint.load_checkpoint(exported)
  with pytest.raises(ValueError, match="holds the 'hl' model"):
    checkpoint.load_checkpoint(checkpoint.export_model(trained, tmp_path / "again"), task="infill")


@pytest.fixture(scope="module")
def trained_infiller(trained, tmp_path_factory) -> Path:
  from configs import infill as infill_config
  workdir = tmp_path_factory.mktemp("infill_tiny")
  config = infill_config.get_config("tiny")
  config.data.cache_dir = str(trained / "cache")   # the HL run's tiny synthetic cache
  config.train.num_steps = 3
  trainer.train_and_evaluate(config, workdir)
  return workdir


@pytest.fixture(scope="module")
def stochastic_infiller(trained_infiller, tmp_path_factory) -> Path:
  """A generative infiller of the tiny config with fresh weights, exported (what is tested is how its
  draws are made and written, not its skill)."""
  import ml_collections

  from tdiff_jax import models
  record = json.loads(json.dumps(checkpoint.load_checkpoint(trained_infiller, task="infill").record))
  record["config"]["model"]["flow_noise_m"] = 3.0
  _, params = models.split_model(models.create_model(ml_collections.ConfigDict(record["config"])))
  return checkpoint.write_exported(tmp_path_factory.mktemp("infill_stochastic"), params, record)


def test_trajectory_draws_of_a_stochastic_infiller(trained, trained_infiller, stochastic_infiller, maps, tmp_path):
  summary = generate.generate(trained, maps, tmp_path / "gen", options=FAST, progress=False, max_maps=1,
                              pictures=False, infill_workdir=stochastic_infiller, trajectories_per_sample=2)
  z = np.load(tmp_path / "gen" / "samples.npz")
  traj, valid = z["trajectory"], z["valid"]                 # [N, K, A, H, 2]
  assert traj.shape[:2] == (1, 2) and z["trajectory_city"].shape == traj.shape
  for d in range(2):   # every draw runs exactly between the sampled states
    np.testing.assert_allclose(traj[:, d, :, 0][valid], z["state"][:, :, 0, :2][valid], atol=1e-3)
    np.testing.assert_allclose(traj[:, d, :, -1][valid], z["state"][:, :, 1, :2][valid], atol=1e-3)
  assert np.abs(traj[:, 0] - traj[:, 1]).max(-1)[valid].mean() > 1e-2     # and the draws differ
  assert [s["draw"] for s in summary["scenarios"]] == [0, 1]
  assert len(list((tmp_path / "gen" / "scenarios").iterdir())) == 2
  with pytest.raises(ValueError, match="needs a stochastic infiller"):
    generate.generate(trained, maps, tmp_path / "det", options=FAST, progress=False, max_maps=1,
                      infill_workdir=trained_infiller, trajectories_per_sample=2)


def test_repair_resamples_only_the_faulty_agents_and_never_adds_faults(trained, trained_infiller):
  """`repair.sample_complete`: round 0 is the sampler alone; a kept round changes only the agents at fault
  (the others held to their states), no scene ends with more faulty agents, and the trajectories are the
  final states' infilled."""
  from tdiff_jax import datatypes, repair
  from tdiff_jax.data import batches, scene_builder
  hl = checkpoint.load_checkpoint(trained, task="hl")
  inf = checkpoint.load_checkpoint(trained_infiller, task="infill")
  scenes = [scene_builder.load_scene(f, hl.config.data.scene)[0]
            for f in sorted((trained / "synthetic" / "val").iterdir())[:4]]
  batch = batches.crop_to_bucket(datatypes.stack_scenes(scenes), batches.sampler_agent_buckets(hl.config.data),
                                 hl.config.data.polygon_buckets)
  batch = jax.tree_util.tree_map(jax.numpy.asarray, batch)
  batch = batch.replace(agent_state=jax.numpy.zeros_like(batch.agent_state))
  run = lambda rounds: repair.sample_complete(hl, inf, batch, jax.random.key(3), FAST, mode=0,  # noqa: E731
                                              repair_rounds=rounds)
  plain, fixed = run(0), run(2)
  alone = sampling.sample(hl.graphdef, hl.params, batch, hl.norm, hl.sched, jax.random.key(3), FAST,
                          lane_pull=hl.lane_pull)
  # The same draws, compiled inside another program: float rounding, grown over the sampler's steps.
  chex.assert_trees_all_close(plain.hl.state, alone.state, atol=1e-2)
  count = lambda c: np.asarray(c.overlap | c.offroad).sum(-1)   # noqa: E731
  valid = np.asarray(batch.agent_valid)
  assert count(plain).sum() > 0 and (count(fixed) <= count(plain)).all()   # the tiny model's agents collide
  assert (np.asarray(fixed.resampled)[valid] > 0).any() and not np.asarray(fixed.resampled)[~valid].any()
  held = (np.asarray(fixed.resampled) == 0) & valid
  np.testing.assert_allclose(np.asarray(fixed.hl.state)[held], np.asarray(plain.hl.state)[held], atol=1e-3)
  moved = np.abs(np.asarray(fixed.hl.state) - np.asarray(plain.hl.state)).max((-1, -2)) > 1e-2
  assert (moved & valid & ~held).any()
  state, traj = np.asarray(fixed.hl.state), np.asarray(fixed.trajectory)
  np.testing.assert_allclose(traj[:, :, 0][valid], state[:, :, 0, :2][valid], atol=1e-3)
  np.testing.assert_allclose(traj[:, :, -1][valid], state[:, :, 1, :2][valid], atol=1e-3)
  overlap, offroad = repair.faults(fixed.trajectory, batch.agent_valid, fixed.hl.heading[..., 0], batch.agent_type,
                                   geometry.map_geometry(batch))
  assert (np.asarray(overlap) == np.asarray(fixed.overlap)).all() and (np.asarray(offroad) == np.asarray(fixed.offroad)).all()
  with pytest.raises(ValueError, match="repair_rounds"):
    run(-1)


def test_end_to_end_writes_av2_scenarios_that_av2_reads_back(trained, trained_infiller, maps, tmp_path):
  from av2.datasets.motion_forecasting.scenario_serialization import load_argoverse_scenario_parquet
  from av2.map.map_api import ArgoverseStaticMap
  from tdiff_jax import datatypes
  from tdiff_jax.data import config as config_lib, scene_builder

  summary = generate.generate(trained, maps, tmp_path, num_per_map=1, options=FAST, progress=False,
                              infill_workdir=trained_infiller, infill_mode="both")
  assert summary["infill_mode"] == "both" and len(summary["scenarios"]) == summary["samples"] == 4
  z = np.load(tmp_path / "samples.npz")
  traj, valid = z["trajectory"], z["valid"]
  assert traj.shape[2:] == (datatypes.HORIZON, 2) and np.isfinite(traj).all()
  # Mode "both": every trajectory runs exactly from the sampled initial to the sampled goal position.
  np.testing.assert_allclose(traj[:, :, 0][valid], z["state"][:, :, 0, :2][valid], atol=1e-3)
  np.testing.assert_allclose(traj[:, :, -1][valid], z["state"][:, :, 1, :2][valid], atol=1e-3)
  assert len(list(tmp_path.glob("*.png"))) == 4
  for i, gen in enumerate(summary["scenarios"]):
    folder = tmp_path / "scenarios" / gen["scenario_id"]
    scenario = load_argoverse_scenario_parquet(folder / f"scenario_{gen['scenario_id']}.parquet")
    ArgoverseStaticMap.from_json(folder / f"log_map_archive_{gen['scenario_id']}.json")
    rows = np.flatnonzero(valid[i])
    assert len(scenario.tracks) == len(rows) and scenario.focal_track_id == "0"
    for track in scenario.tracks:
      row = rows[int(track.track_id)]
      steps = [s.timestep for s in track.object_states]
      assert steps == list(range(datatypes.INITIAL_STEP, datatypes.GOAL_STEP + 1))
      xy = np.array([s.position for s in track.object_states])
      np.testing.assert_allclose(xy, z["trajectory_city"][i, row], atol=1e-6)
      assert track.object_type.value == datatypes.AGENT_TYPES[z["agent_type"][i, row]]
    # Our own loader reads the generated folder too: the ground truth is the generated scenario.
    cfg = config_lib.default_data_config()
    cfg.near_lane_types = ""   # keep every agent, on a lane or not
    scene, info = scene_builder.load_scene(folder, cfg)
    assert scene.agent_valid.sum() == len(rows) and scene.agent_future_valid[:len(rows)].all()
  # The audit of what was written: every generated agent read back; the logged scenarios of the maps that
  # have one (the map-only ones have no tracks to read: skipped and listed).
  audited = summary["complete_scenarios"]
  assert audited["generated"]["scenarios"] == 4 and audited["generated"]["agents"] == int(valid.sum())
  assert 0 <= audited["generated"]["overlap"] <= audited["generated"]["agents"]
  assert audited["logged"]["scenarios"] + len(audited["logged"]["skipped"]) == 4
  assert audited["logged"]["overlap_pct"] == 0.0   # logged traffic never overlaps


def test_sample_cli_runs_and_its_second_run_reads_the_compilation_cache(trained, maps, tmp_path):
  """`python sample.py` end to end (a subprocess, the HL model alone): results written, the compiled
  programs kept in the cache folder, and a second run (--overwrite) from that cache samples the same."""
  env = {**os.environ, "TDIFF_JAX_COMPILATION_CACHE": "1", "TDIFF_JAX_CACHE_DIR": str(tmp_path / "cache")}
  cmd = [sys.executable, "sample.py", f"--hl_workdir={trained}", f"--maps={maps}", f"--out={tmp_path / 'out'}",
         "--infill_workdir=", "--method=ddim", "--steps=5"]
  first = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=ROOT, env=env)
  assert first.returncode == 0, first.stderr[-2000:]
  samples = np.load(tmp_path / "out" / "samples.npz")["state"]
  cached = sorted(p.name for p in (tmp_path / "cache").iterdir())
  assert cached and json.loads(first.stdout.strip().splitlines()[-1])["samples"] == len(samples)
  second = subprocess.run(cmd + ["--overwrite"], capture_output=True, text=True, timeout=600, cwd=ROOT, env=env)
  assert second.returncode == 0, second.stderr[-2000:]
  np.testing.assert_array_equal(np.load(tmp_path / "out" / "samples.npz")["state"], samples)
  assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == cached   # nothing compiled again


def test_sample_cli_names_a_missing_infiller_and_a_flag_out_of_range(trained, tmp_path):
  done = subprocess.run([sys.executable, "sample.py", f"--hl_workdir={trained}", f"--infill_workdir={tmp_path / 'none'}"],
                        capture_output=True, text=True, timeout=300, cwd=ROOT)
  assert done.returncode != 0 and "python train.py --config=configs/infill.py" in done.stderr
  done = subprocess.run([sys.executable, "sample.py", f"--hl_workdir={trained}", "--num_per_map=0"],
                        capture_output=True, text=True, timeout=300, cwd=ROOT)
  assert done.returncode != 0 and "flag --num_per_map=0" in done.stderr and "Traceback" not in done.stderr


def test_evaluate_prints_tables_i_and_ii(trained, trained_infiller, stochastic_infiller, tmp_path, capsys):
  from tdiff_jax import evaluate
  data = tmp_path / "data"
  for sc in sorted((trained / "synthetic" / "val").iterdir())[:3]:
    shutil.copytree(sc, data / sc.name)
  shutil.copytree(DATA / REAL_110[0], data / REAL_110[0])     # real AV2 with 110 steps
  shutil.copytree(DATA / REAL_50, data / REAL_50)             # no goal step: skipped and counted
  evaluate.main([f"--hl_workdir={trained}", f"--infill_workdir={trained_infiller}", f"--data={data}",
                 f"--out={tmp_path / 'eval'}", "--batch_size=2", "--guided_row=lane", "--realism_rollouts=1",
                 f"--stochastic_infill_workdir={stochastic_infiller}", "--repair_rounds=2"])
  md = capsys.readouterr().out
  assert "**official convention** (JS distance" in md and "**strict convention** (JS divergence" in md
  result = json.loads((tmp_path / "eval" / "table.json").read_text(), parse_constant=_refuse)   # strict JSON
  assert (tmp_path / "eval" / "table.md").read_text() == md
  assert result["scenes"] == 4 and len(result["skipped"]) == 1
  sampler = result["hl_checkpoint"]["sampler"]   # the default guidance, repaired with the infiller
  assert sampler["guidance"] == ["paths", "path_offroad"] and sampler["repair_rounds"] == 2
  # Each scene's complete sample written as an AV2 folder and audited as read back, beside the logged scenes.
  audited = result["complete_scenarios"]
  assert audited["generated"]["scenarios"] == audited["logged"]["scenarios"] == 4
  assert audited["generated"]["agents"] == audited["logged"]["agents"] == result["agents"]
  assert len(list((tmp_path / "eval" / "scenarios").iterdir())) == 4 and "Complete scenarios as written" in md
  assert f"- skipped `{REAL_50}`: " in md and "no goal step" in md            # why, not only how many
  with pytest.raises(SystemExit, match=f"evaluate: {tmp_path / 'eval'} holds an earlier run's results: pass --overwrite"):
    evaluate.main([f"--hl_workdir={trained}", f"--data={data}", f"--out={tmp_path / 'eval'}"])
  for conv in ("official", "strict"):
    for endpoint in ("initial", "goal"):
      gt, model = result["table_i"][conv][endpoint]["GT"], result["table_i"][conv][endpoint]["model"]
      assert gt["agents"] == model["agents"] == result["agents"]   # the ground truth's agent count
      assert gt["jsd_speed"] is None and 0.0 <= model["jsd_speed"] <= 1.0
      assert 0.0 <= gt["collision_rate_pct"] <= 100.0
      assert 0.0 <= model["goal_reachable_pct"] <= 100.0 and gt["goal_reachable_pct"] >= 50.0
  reach = result["goal_reachability"]
  assert reach["gt"]["road_users"] + reach["gt"]["pedestrians"] == result["agents"]
  for who in ("gt", "model"):   # every road user is reachable or has one reason not to be
    assert reach[who]["reachable"] + sum(reach[who][k] for k in metrics.REACHABILITY_FAILURES) == reach[who]["road_users"]
  assert "not reachable, by reason" in md
  control = result["shuffled_map_control"]["initial"]
  assert control["gt"]["own_map_offroad_pct"] <= control["gt"]["other_map_offroad_pct"]
  assert "Shuffled-map control" in md and "Goal reachable (%)" in md
  assert (tmp_path / "eval" / "grid.png").stat().st_size > 10_000     # ground truth next to samples
  table_ii = result["table_ii"]
  assert set(table_ii) == {"both", "initial", "goal", "none"}
  for mode in ("both", "goal"):   # the goal is pinned: no final error, no miss
    assert table_ii[mode]["fde_m"] < 1e-3 and table_ii[mode]["miss_rate_pct"] == 0.0
  assert all(r["ade_m"] > 0 for r in table_ii.values())
  # The realism of complete scenarios: every row scored on every map with logged trajectories (the
  # 50-step scenario was skipped), each score in (0, 1], none above the logged trajectories' own.
  realism = result["realism"]
  assert realism["rollouts_per_map"] == 1 and set(realism["rows"]) == set(evaluate.REALISM_ROWS)
  for row in realism["rows"].values():
    assert row["maps"] == 4 and 0.0 < row["meta"] <= 1.0
    assert row["meta"] <= realism["rows"]["logged"]["meta"] + 1e-9
  assert "Realism of complete scenarios" in md and "| HL samples, then the infiller | **" in md
  # The stochastic infiller: its own Table II (pinned ends exact for its draws), realism rows, diversity.
  assert result["table_ii_stochastic"]["both"]["fde_m"] < 1e-3 and "stochastic infiller, one draw" in md
  diversity = realism["diversity"]
  assert diversity["pairwise_ade_m"] > 0 and diversity["pinned_goal_error_max_m"] < 1e-3
  assert diversity["agents"] == result["agents"] and "| HL samples, then the stochastic infiller | **" in md
  assert (tmp_path / "eval" / "realism.png").stat().st_size > 10_000
  _check_pictures_and_report(trained, data, result, md, tmp_path / "eval")


def _check_pictures_and_report(trained, data, result, md, out):
  import base64
  import html.parser

  import jax.numpy as jnp
  import matplotlib.pyplot as plt

  from tdiff_jax import datatypes, evaluate, metrics, viz
  from tdiff_jax.data import av2_io, scene_builder
  # The guided row (--guided_row): sampled with lane guidance, scored like the others.
  for e in evaluate.ENDPOINTS:
    guided = result["table_i"]["official"][e]["guided"]
    assert guided["agents"] == result["agents"] and 0.0 <= guided["jsd_speed"] <= 1.0
  assert 'Rows "guided": ddim stride 10' in md and "| initial | guided |" in md
  # One distribution plot per metric and endpoint, and the plotted data are the accumulators' counts:
  # the ground truth's recomputed here from the scenes themselves.
  config = checkpoint.load_checkpoint(trained, task="hl").config
  scenes = []
  for folder in sorted(data.iterdir()):
    try:
      scenes.append(scene_builder.load_scene(folder, config.data.scene)[0])
    except av2_io.BadScenarioError:
      pass
  batch = datatypes.stack_scenes(scenes)
  for tok, e in enumerate(evaluate.ENDPOINTS):
    state = jnp.asarray(batch.agent_state[:, :, tok])
    acc = metrics.state_accumulators(state[..., :2], state[..., 2], state[..., 3], batch)
    for name in metrics.HISTOGRAMS:
      assert (out / f"dist_{name}_{e}.png").stat().st_size > 5_000
      hist = result["histograms"]["official"][e]
      fig, ax = plt.subplots()
      drawn = viz.draw_distribution(ax, name, hist["GT"][name], hist["model"][name])
      plt.close(fig)
      counts = np.asarray(acc[f"official/hist_{name}"])
      np.testing.assert_allclose(drawn["gt"] * counts.sum(), counts, atol=1e-6)
      model = np.asarray(hist["model"][name])
      np.testing.assert_allclose(drawn["model"] * model.sum(), model, atol=1e-6)
      assert len(drawn["edges"]) == metrics.HISTOGRAMS[name][0] + 1
    # Every model agent's speed lands in some bin of the official speed histogram (0 to 50 m/s).
    assert sum(result["histograms"]["official"][e]["model"]["speed"]) == result["agents"]
  assert (out / "rates.png").stat().st_size > 5_000
  # report.html: self-contained, every picture embedded and non-empty, the run described.
  images = []

  class Images(html.parser.HTMLParser):
    def handle_starttag(self, tag, attrs):
      if tag == "img":
        images.append(dict(attrs)["src"])

  page = (out / "report.html").read_text()
  Images().feed(page)
  assert len(images) == 1 + 2 * len(metrics.HISTOGRAMS) + 2     # rates, distributions, realism, grid
  for src in images:
    assert src.startswith("data:image/png;base64,")
    png = base64.b64decode(src.split(",", 1)[1])
    assert png.startswith(b"\x89PNG") and len(png) > 5_000
  assert "http" not in page.replace("http-equiv", "")             # nothing fetched from a network
  assert f"step {result['hl_checkpoint']['step']}" in page and "denoiser" in page   # checkpoint and config
  assert f"{result['scenes']} scenes used, 1 skipped" in page and "no goal step" in page


def test_animations_of_generated_and_ground_truth_scenarios(trained, trained_infiller, maps, tmp_path):
  from PIL import Image

  from tests.av2_samples import REAL_110
  from tdiff_jax import animate
  summary = generate.generate(trained, maps, tmp_path / "gen", num_per_map=1, options=FAST, progress=False,
                              max_maps=1, infill_workdir=trained_infiller, animate=True)
  [gif] = sorted((tmp_path / "gen").glob("*.gif"))
  assert gif.name == f"{summary['scenarios'][0]['map']}_0.gif"
  gt = animate.animate_folder(DATA / REAL_110[0], tmp_path)
  assert gt.name == f"{REAL_110[0]}.gif"
  for path in (gif, gt):
    with Image.open(path) as im:
      assert im.n_frames == 30 and im.info["duration"] == 200   # 6 s of 0.1 s steps, every 2nd, real time
      frames = []
      for k in (0, 29):
        im.seek(k)
        frames.append(np.asarray(im.convert("RGB"), np.int16))
    assert np.abs(frames[0] - frames[1]).sum() > 0                 # the agents moved
  assert not list(tmp_path.glob(".tmp-*"))
  with pytest.raises(ValueError, match="animate needs infilled trajectories"):
    generate.generate(trained, maps, tmp_path / "no", options=FAST, progress=False, animate=True)


def test_training_curves(trained, tmp_path):
  from tdiff_jax import plot_metrics
  path = plot_metrics.plot_workdir(trained, tmp_path / "curves.png")
  assert path.stat().st_size > 10_000
  rows = plot_metrics.read_metrics(trained)
  assert [r["step"] for r in rows if "loss" in r] == [2, 3] and any("val_loss" in r for r in rows)
  with pytest.raises(FileNotFoundError, match="no metrics"):
    plot_metrics.plot_workdir(tmp_path)


def test_an_unwritable_output_is_one_line_naming_it(trained, tmp_path):
  from tdiff_jax import evaluate
  blocker = tmp_path / "a_file"
  blocker.write_text("")
  with pytest.raises(SystemExit, match=f"evaluate: .*{blocker / 'eval'}"):
    evaluate.main([f"--hl_workdir={trained}", f"--out={blocker / 'eval'}", "--infill_workdir="])


def test_guidance_weights_flag(trained, tmp_path):
  """--guidance_weights sets the named costs' weights and keeps the others'; a misspelt cost, a weight
  that is not a number or a negative one is a one-line error naming it."""
  from absl import flags

  from tdiff_jax import evaluate, sampler_flags, sampling
  values = flags.FlagValues()
  sampler_flags.define_sampler_flags(values)
  values(["prog", "--guidance_weights=offroad=2,boxes=0.5"])
  params = sampler_flags.guidance_params(values)
  defaults = sampling.GuidanceParams().weights
  assert params.scale == 1.0 and params.weights == {**defaults, "offroad": 2.0, "boxes": 0.5}
  args = [f"--hl_workdir={trained}", f"--out={tmp_path / 'eval'}", "--infill_workdir="]
  for bad, message in (("offroda=2", "unknown cost 'offroda'"), ("lane=x", "'lane=x' is not cost=weight"),
                       ("lane=-1", "must be >= 0")):
    with pytest.raises(SystemExit, match=f"evaluate: --guidance_weights: .*{message}"):
      evaluate.main(args + [f"--guidance_weights={bad}"])


def test_lane_pull_flag_samples_the_same_weights_with_the_pull(trained, maps, tmp_path):
  """--lane_pull_m (and `generate(lane_pull_m=...)`) sample the checkpoint's own weights and graph with the
  denoiser's lane pull, and the summary says so; 0 turns it off with its other settings; a route on a model
  without lane routes, a setting without a pull, or a negative distance is an error naming it."""
  from absl import app
  from tdiff_jax import checkpoint, evaluate, models
  from tdiff_jax.lane_pull import LanePull
  from tdiff_jax.models.paper_denoiser import PaperConfig
  loaded = checkpoint.load_checkpoint(trained, task="hl")
  assert loaded.lane_pull is None   # the tiny config trains without one
  pulled = checkpoint.with_lane_pull(loaded, 3.5)
  assert pulled.params is loaded.params and pulled.graphdef is loaded.graphdef
  assert pulled.lane_pull == LanePull(across_m=3.5)
  spaced = dataclasses.replace(pulled, lane_pull=LanePull(across_m=3.5, clearance_m=2.0, end_m=10.0))
  assert checkpoint.with_lane_pull(spaced, 0).lane_pull is None
  assert checkpoint.with_lane_pull(spaced, 5).lane_pull == LanePull(5.0, 2.0, 10.0)
  LanePull.check(models.model_spec(loaded.config))   # the tiny config's grounded denoiser
  with pytest.raises(ValueError, match=r"the lane pull needs model.denoiser='grounded'"):
    LanePull.check(PaperConfig())
  with pytest.raises(ValueError, match=r"lane_pull.end_m needs lane_pull.across_m > 0"):
    LanePull(end_m=10.0)
  kwargs = dict(num_per_map=1, options=FAST, pictures=False, progress=False, max_maps=2)
  plain = generate.generate(trained, maps, tmp_path / "plain", **kwargs)
  summary = generate.generate(trained, maps, tmp_path / "pull", lane_pull_m=3.5, **kwargs)
  assert plain["lane_pull"] is None
  assert summary["lane_pull"] == {"across_m": 3.5, "clearance_m": 0.0, "end_m": 0.0, "route_m": 0.0, "still_m": 0.0}
  a, b = (np.load(tmp_path / d / "samples.npz") for d in ("plain", "pull"))
  np.testing.assert_array_equal(a["valid"], b["valid"])
  assert not np.allclose(a["state"][..., :2], b["state"][..., :2])   # the pull moved some agents
  args = [f"--hl_workdir={trained}", f"--out={tmp_path / 'eval'}", "--infill_workdir="]
  with pytest.raises(app.UsageError, match="flag --lane_pull_m=-1"):   # refused at parse time
    evaluate.main(args + ["--lane_pull_m=-1"])


def test_the_default_maps_are_the_val_split_of_the_training_data(tmp_path):
  def workdir(name: str, data: dict | None) -> Path:
    w = tmp_path / name
    w.mkdir()
    if data is not None:
      (w / "config.json").write_text(json.dumps({"data": data}))
    return w

  own = workdir("own", {"dir": "", "cache_dir": ""})
  (own / "synthetic" / "val").mkdir(parents=True)
  assert checkpoint.validation_maps(own) == own / "synthetic" / "val"

  root = tmp_path / "worlds"
  (root / "val").mkdir(parents=True)
  cache = tmp_path / "cache"
  cache.mkdir()
  (cache / "manifest.json").write_text(json.dumps({"source": str(root)}))
  assert checkpoint.validation_maps(workdir("cached", {"dir": "", "cache_dir": str(cache)})) == root / "val"
  assert checkpoint.validation_maps(workdir("av2", {"dir": str(root), "cache_dir": ""})) == root / "val"

  (tmp_path / "train_only" / "train").mkdir(parents=True)   # never falls back to the training split
  for w in (workdir("no_val", {"dir": str(tmp_path / "train_only")}), workdir("no_config", None)):
    with pytest.raises(ValueError, match=f"no validation split of .*{w.name}.*pass the maps"):
      checkpoint.validation_maps(w)

  # A model trained on synthetic worlds whose folder is gone: its validation worlds are made again, the
  # same scenarios as the full dataset's val split, and a later full generation adds the training ones.
  model = workdir("synthetic_model", {"dir": "", "cache_dir": "", "synthetic_num": 10})
  out = tmp_path / "elsewhere"
  val = checkpoint.validation_maps(out, model)
  assert val == out / "synthetic" / "val" and not (out / "synthetic" / "train").exists()
  full = tmp_path / "full"
  assert synthetic.generate_dataset(full, 10, workers=1, progress=False) == {"train": 9, "val": 1}
  assert sorted(p.name for p in val.iterdir()) == sorted(p.name for p in (full / "val").iterdir())
  assert synthetic.generate_dataset(out / "synthetic", 10, workers=1, progress=False) == {"train": 9, "val": 1}
  assert len(list((out / "synthetic" / "train").iterdir())) == 9


def test_a_workdir_holds_one_task(trained):
  from configs import infill as infill_config
  config = infill_config.get_config("tiny")
  config.data.cache_dir = str(trained / "cache")
  with pytest.raises(ValueError, match="is a 'hl' model"):
    trainer.train_and_evaluate(config, trained)
  with pytest.raises(ValueError, match="the 'infill' model is needed"):
    checkpoint.load_checkpoint(trained, task="infill")


def test_maps_sharing_a_scenario_id_keep_their_own_outputs(trained, trained_infiller, tmp_path):
  folder = tmp_path / "maps"
  source = sorted((trained / "synthetic" / "val").iterdir())[0]
  shutil.copytree(source, folder / "a")
  shutil.copytree(source, folder / "b")   # another folder, the same scenario id
  summary = generate.generate(trained, folder, tmp_path / "out", options=FAST, progress=False,
                              infill_workdir=trained_infiller)
  ids = [s["scenario_id"] for s in summary["scenarios"]]
  assert summary["samples"] == 2 and len(set(ids)) == 2
  assert sorted(p.name for p in (tmp_path / "out").glob("*.png")) == [f"{source.name}-2_0.png", f"{source.name}_0.png"]
  assert sorted(p.name for p in (tmp_path / "out" / "scenarios").iterdir()) == sorted(ids)
  assert any("repeats" in w["warning"] for w in summary["map_warnings"])
  assert np.load(tmp_path / "out" / "samples.npz")["map_folder"].tolist() == ["a", "b"]


def test_an_output_folder_of_another_run_is_refused_or_replaced_whole(trained, maps, tmp_path):
  out = tmp_path / "out"
  generate.generate(trained, maps, out, num_per_map=2, options=FAST, progress=False)
  before = sorted(p.name for p in out.iterdir())
  with pytest.raises(FileExistsError, match=f"{out} holds an earlier run's results: pass --overwrite"):
    generate.generate(trained, maps, out, options=FAST, progress=False)
  assert sorted(p.name for p in out.iterdir()) == before
  generate.generate(trained, maps, out, num_per_map=1, options=FAST, progress=False, max_maps=1, overwrite=True)
  summary = json.loads((out / "summary.json").read_text())
  assert summary["samples"] == 1 and len(list(out.glob("*.png"))) == 1   # nothing of the first run left
  stranger = tmp_path / "not_ours"
  stranger.mkdir()
  (stranger / "notes.txt").write_text("mine")
  with pytest.raises(FileExistsError, match="not an output folder of tdiff_jax"):
    generate.generate(trained, maps, stranger, options=FAST, progress=False, overwrite=True)
  assert (stranger / "notes.txt").read_text() == "mine"


def test_two_runs_into_one_folder_never_mix(tmp_path):
  from tdiff_jax import files
  out = tmp_path / "out"
  with pytest.raises(FileExistsError, match="received another run's results while this one ran"):
    with files.output_folder(out, overwrite=False, command="test") as mine:
      (mine / "summary.json").write_text("mine")
      out.mkdir()
      (out / "summary.json").write_text("theirs")   # the other run finished first
  assert (out / "summary.json").read_text() == "theirs"
  [kept] = [p for p in tmp_path.iterdir() if p.name.startswith("out.")]
  assert (kept / "summary.json").read_text() == "mine"
  assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]   # no temporary left behind


@pytest.mark.parametrize("flag, named", [
    ("--max_scenes=-1", "--max_scenes=-1"), ("--batch_size=0", "--batch_size=0"), ("--seed=-5", "--seed=-5"),
    (f"--seed={2**64 + 1}", "--seed="), (f"--seed={2**32}", "--seed="), ("--steps=-1", "--steps=-1"),
    ("--lane_pull_m=-1", "--lane_pull_m=-1"), ("--realism_rollouts=100000", "--realism_rollouts=100000"),
])
def test_flag_values_out_of_range_are_refused_at_parse_time_naming_the_flag(flag, named):
  from absl import app
  from tdiff_jax import evaluate
  with pytest.raises(app.UsageError, match=f"flag {named}"):
    evaluate.main([flag, "--hl_workdir=/nonexistent"])


def test_an_empty_val_split_is_never_replaced_by_train(trained, tmp_path):
  from tdiff_jax import evaluate
  root = tmp_path / "root"
  shutil.copytree(trained / "synthetic" / "train", root / "train")
  (root / "val").mkdir()
  with pytest.raises(SystemExit, match=f"evaluate: {root / 'val'}: no AV2 scenario folders"):
    evaluate.main([f"--hl_workdir={trained}", f"--data={root}", "--infill_workdir=", f"--out={tmp_path / 'e'}"])


def test_the_readme_jax_snippet_runs(trained, trained_infiller, capsys):
  """The README's "Using the sampler from JAX" snippet, on the tiny models: samples and trajectories."""
  section = (ROOT / "README.md").read_text().split("## Using the sampler from JAX", 1)[1]
  code = section.split("```python\n", 1)[1].split("```", 1)[0]
  for old, new in (('"tests/data"', repr(str(trained / "synthetic" / "val"))),   # the tiny models, to compile less
                   ('td.pretrained_dir("hl")', repr(str(trained))),
                   ('td.pretrained_dir("infill")', repr(str(trained_infiller)))):
    assert old in code
    code = code.replace(old, new)
  exec(compile(code, "README.md", "exec"), {})
  states, trajectories = capsys.readouterr().out.splitlines()[-2:]   # one batch of both scenes (one size)
  assert states.startswith("[1 0] (2, ") and states.endswith(", 2, 3)")   # their positions, then [B, A, 2, 3]
  assert trajectories.startswith("(2, ") and trajectories.endswith(", 60, 2)")


# ---- hostile inputs with a model (issue classes: outputs, names, non-finite numbers, models and workdirs) ----


def test_sample_refuses_an_out_that_holds_its_maps(trained, tmp_path):
  project = tmp_path / "project"
  shutil.copytree(sorted((trained / "synthetic" / "val").iterdir())[0], project / "maps" / "m")
  before = sorted(str(p) for p in project.rglob("*"))
  with pytest.raises(ValueError, match="would delete that input"):
    generate.generate(trained, project / "maps", project, options=FAST, progress=False, overwrite=True)
  with pytest.raises(ValueError, match="would delete that input"):
    generate.generate(trained, project / "maps", trained, options=FAST, progress=False, overwrite=True)
  assert sorted(str(p) for p in project.rglob("*")) == before
  with pytest.raises(ValueError, match="trajectories_per_sample must be between 1 and 64"):
    generate.generate(trained, project / "maps", tmp_path / "o", trajectories_per_sample=100000)


def test_a_scenario_id_that_is_a_path_names_no_file_outside_out(trained, tmp_path):
  import pandas as pd
  maps = tmp_path / "deep" / "er" / "maps"
  folder = shutil.copytree(sorted((trained / "synthetic" / "val").iterdir())[0], maps / "m")
  parquet = next(folder.glob("*.parquet"))
  pd.read_parquet(parquet).assign(scenario_id="../../x").to_parquet(parquet)
  out = tmp_path / "deep" / "er" / "out"
  summary = generate.generate(trained, maps, out, options=FAST, progress=False)
  [png] = out.glob("*.png")
  assert png.name.startswith("_.._x-") and not (tmp_path / "deep" / "x_0.png").exists()
  assert "is not a safe file name" in summary["map_warnings"][-1]["warning"]
  assert {p.name for p in tmp_path.rglob("*.png")} == {png.name}


def test_broken_models_are_refused_at_load_naming_the_file_and_field(trained, tmp_path):
  good = checkpoint.load_checkpoint(trained)
  broken = jax.tree_util.tree_map(lambda x: x, good.params)
  leaves, treedef = jax.tree_util.tree_flatten(broken)
  leaves[0] = leaves[0].at[0].set(np.nan)
  checkpoint.write_exported(tmp_path / "nan_params", jax.tree_util.tree_unflatten(treedef, leaves), good.record)
  with pytest.raises(ValueError, match=f"{tmp_path / 'nan_params' / 'params.npz'}: parameter .* holds NaN or inf"):
    checkpoint.load_checkpoint(tmp_path / "nan_params")
  exported = checkpoint.export_model(trained, tmp_path / "nan_stats")
  record = json.loads((exported / "record.json").read_text())
  record["normalization"]["std"][0] = float("inf")
  (exported / "record.json").write_text(json.dumps(record))   # as another program may write it: Infinity
  with pytest.raises(ValueError, match="normalisation statistic std is .*not finite"):
    checkpoint.load_checkpoint(exported)
  del record["normalization"]
  (exported / "record.json").write_text(json.dumps(record))
  with pytest.raises(ValueError, match=r"record.json: not an exported model's record \(fields \['normalization'\] missing"):
    checkpoint.load_checkpoint(exported)
  with pytest.raises(ValueError, match="NaN or inf states for 1 agent"):
    generate._check_finite(np.array([[[[np.nan, 0, 0]] * 2]]), np.zeros((1, 1, 2)), np.ones((1, 1), bool), "w")


def test_checkpoints_win_over_an_exported_model_and_config_edits_change_no_sampler(trained, tmp_path):
  from tdiff_jax import sampler_flags
  workdir = tmp_path / "both"
  shutil.copytree(trained, workdir, symlinks=True)
  checkpoint.export_model(trained, tmp_path / "exported")
  shutil.copy(tmp_path / "exported" / "params.npz", workdir / "params.npz")
  assert not checkpoint.is_exported(workdir)
  assert "data_position" in checkpoint.load_checkpoint(workdir).record   # the training checkpoint's record
  steps = sampler_flags.diffusion_steps(workdir)
  config = json.loads((workdir / "config.json").read_text())
  config["diffusion"]["num_steps"] = 7   # an edited config.json beside the checkpoints
  (workdir / "config.json").write_text(json.dumps(config))
  assert sampler_flags.diffusion_steps(workdir) == steps == checkpoint.load_checkpoint(workdir).config.diffusion.num_steps


def test_export_never_replaces_a_folder_it_did_not_write(trained, tmp_path):
  mine = tmp_path / "mine"
  mine.mkdir()
  (mine / "config.json").write_text("my own")
  with pytest.raises(FileExistsError, match="not an output folder of tdiff_jax"):
    checkpoint.export_model(trained, mine, overwrite=True)
  assert (mine / "config.json").read_text() == "my own"
  checkpoint.export_model(trained, tmp_path / "exp")
  with pytest.raises(FileExistsError, match="--overwrite"):
    checkpoint.export_model(trained, tmp_path / "exp")
  checkpoint.export_model(trained, tmp_path / "exp", overwrite=True)
  assert checkpoint.is_exported(tmp_path / "exp")


def test_a_workdir_trains_one_run_at_a_time(tmp_path, tiny_cache):
  from tdiff_jax import files
  config = hl_config.get_config("tiny")
  config.data.cache_dir = str(tiny_cache)
  with files.exclusive_lock(tmp_path / "wd", "training run"):   # another run holds it
    with pytest.raises(ValueError, match=f"{tmp_path / 'wd'} is in use by another training run"):
      trainer.train_and_evaluate(config, tmp_path / "wd")
  assert sorted(p.name for p in (tmp_path / "wd").iterdir()) == [files.LOCK_FILE]
