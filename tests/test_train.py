"""Training runs: checkpoints, exact resume, NaN stop, several processes, the CLI (the step itself: test_train_step.py)."""

from __future__ import annotations

import json
import os
import shutil
import re
import subprocess
import sys
from pathlib import Path

import chex
import jax
import numpy as np
import pytest

from array_record.python import array_record_module

from configs import hl as hl_config
from tests.av2_samples import DATA
from tests.tiny import tiny_config
from tdiff_jax import checkpoint, files, models
from tdiff_jax.data import batches, preprocess, records
from tdiff_jax.train import distributed, optim, trainer

ROOT = Path(__file__).resolve().parent.parent


def _final_params(workdir: Path):
  ckpt = checkpoint.Checkpointer(workdir / "checkpoints")
  config = tiny_config(Path("."))
  graphdef, params = models.split_model(models.create_model(config))
  template = trainer.init_state(config, params, optim.make_optimizer(config.train))
  state, record = ckpt.restore(template)
  ckpt.close()
  return state, record


def test_checkpoint_round_trip(tmp_path, tiny_cache):
  config = tiny_config(tiny_cache)
  graphdef, params = models.split_model(models.create_model(config))
  tx = optim.make_optimizer(config.train)
  init = trainer.init_state(config, params, tx)
  noisy = jax.tree_util.tree_map(lambda x: x + 0.5, init.params)
  state = trainer.TrainState(init.step + 7, noisy, tx.init(noisy), init.ema, jax.random.key_data(jax.random.key(3)))
  ckpt = checkpoint.Checkpointer(tmp_path / "ck")
  record = {"step": 7, "data_position": {"epoch": 1, "position": 2, "seed": 0}, "config": config.to_dict()}
  ckpt.save(7, state, record)
  restored, rec = ckpt.restore(init)  # the template only gives structure, dtypes and shardings
  chex.assert_trees_all_equal(jax.device_get(restored), jax.device_get(state))
  assert rec == json.loads(json.dumps(record))
  ckpt.close()


@pytest.fixture(scope="module")
def six_steps(tiny_cache, tmp_path_factory) -> Path:
  """A workdir trained straight for 6 steps (checkpoints at steps 3 and 6)."""
  workdir = tmp_path_factory.mktemp("straight")
  trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=6), workdir)
  return workdir


def test_a_damaged_latest_checkpoint_falls_back_and_training_resumes_exactly(tmp_path, tiny_cache, six_steps):
  config = tiny_config(tiny_cache, num_steps=6)
  shutil.copytree(six_steps, tmp_path, dirs_exist_ok=True)
  # The newest step's array data lost (every data file: which arrays a file holds is orbax's choice, and
  # losing only the largest left the EMA parameters readable on some runs).
  state = tmp_path / "checkpoints" / "6" / "state"
  data_files = [p for p in state.rglob("*") if p.is_file() and p.parent.name == "d"]
  assert data_files
  for p in data_files:
    p.unlink()
  ckpt = checkpoint.Checkpointer(tmp_path / "checkpoints")
  assert ckpt.latest_step() == 6
  template = trainer.init_state(config, models.split_model(models.create_model(config))[1],
                                optim.make_optimizer(config.train))
  state, record = ckpt.restore(template)
  assert int(state.step) == 3 and record["step"] == 3 and ckpt.skipped == [6]
  ckpt.close()
  assert checkpoint.load_checkpoint(tmp_path, task="hl").record["step"] == 3
  # A kill in the middle of saving a step leaves orbax's temporary folder; it is ignored. Rows logged after
  # the checkpoint, then killed, are dropped.
  partial = tmp_path / "checkpoints" / "5.orbax-checkpoint-tmp-1234567"
  (partial / "state").mkdir(parents=True)
  (partial / "state" / "half_written").write_bytes(b"\0" * 100)
  with open(tmp_path / "metrics.jsonl", "a") as f:
    f.write(json.dumps({"step": 4, "loss": -1.0}) + "\n" + '{"step": 5, "lo')
  trainer.train_and_evaluate(config, tmp_path)                   # resumes from 3 and saves 6 again
  assert (tmp_path / "checkpoints" / "6.damaged").is_dir()
  again = checkpoint.Checkpointer(tmp_path / "checkpoints")
  resumed, record = again.restore(template)
  assert int(resumed.step) == 6 and again.skipped == []
  again.close()
  # The same parameters, EMA and data position as the run trained straight to step 6.
  straight, straight_record = _final_params(six_steps)
  assert record["data_position"] == straight_record["data_position"]
  chex.assert_trees_all_close(jax.device_get(resumed.params), jax.device_get(straight.params), atol=1e-6)
  chex.assert_trees_all_close(jax.device_get(resumed.ema), jax.device_get(straight.ema), atol=1e-6)
  rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
  steps = [r["step"] for r in rows if "loss" in r]
  assert steps == sorted(set(steps)) and steps[-1] == 6 and all(r.get("loss") != -1.0 for r in rows)
  # Changed training settings are named when a run resumes (a changed recipe never continues silently).
  assert trainer.changed_fields(record["config"], tiny_config(tiny_cache, num_steps=8)) == ["train.num_steps: 6 -> 8"]


def test_a_checkpoint_of_the_first_train_state_format_resumes(tmp_path, tiny_cache, six_steps):
  """A checkpoint written before the optimiser state gained the `apply_if_finite` wrapper (format 1)
  restores to the state the same checkpoint restores to in the current format (training resumes from
  that state; every save writes the current format)."""
  state, record = _final_params(six_steps)
  old = tmp_path / "old"
  ckpt = checkpoint.Checkpointer(old / "checkpoints")
  ckpt.save(6, state.replace(opt_state=state.opt_state.inner_state),
            {k: v for k, v in record.items() if k != "train_state_format"})
  config = tiny_config(tiny_cache, num_steps=6)
  template = trainer.init_state(config, models.split_model(models.create_model(config))[1],
                                optim.make_optimizer(config.train))
  restored, _ = trainer._restore_train_state(ckpt, template, trainer.resume_record(config, old))
  ckpt.close()
  chex.assert_trees_all_equal(jax.device_get(restored), jax.device_get(state))


def test_resume_accepts_a_model_field_added_later_and_refuses_a_changed_model(tmp_path, tiny_cache, six_steps):
  """A checkpoint whose model config lacks a field added since (at its default) resumes; one trained with
  another width is refused, naming it; one whose config names an option of an earlier version (a model
  field since removed, the lane pull's old place, a training option since removed) is refused, naming the
  option and the version that reads it."""
  state, record = _final_params(six_steps)
  for name, change in (("older", lambda c: c["model"].pop("fourier_tables")),
                       ("wider", lambda c: c["model"].update(dim=64)),
                       ("removed", lambda c: c["model"].update(social_geometry=False)),   # even at its off value
                       ("moved", lambda c: c["model"].update(lane_pull_m=0.0)),             # the lane pull's old place
                       ("removed_train", lambda c: c["train"].update(max_t=30))):
    rec = json.loads(json.dumps(record))
    change(rec["config"])
    ckpt = checkpoint.Checkpointer(tmp_path / name / "checkpoints")
    ckpt.save(6, state, rec)
    ckpt.close()
  assert trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=6), tmp_path / "older")["already_done"]
  with pytest.raises(ValueError, match=r"trained with another model \(dim: 64 -> 32"):
    trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=6), tmp_path / "wider")
  for name, option in (("removed", "model.social_geometry"), ("moved", "model.lane_pull_m"),
                       ("removed_train", "train.max_t")):
    with pytest.raises(ValueError, match=rf"{option}: option\(s\) of tdiff_jax 0.2.0 and earlier.*"
                                         r"pip install tdiff_jax==0.2.0"):
      trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=6), tmp_path / name)
  with pytest.raises(ValueError, match=r"model.social_geometry: option\(s\) of tdiff_jax 0.2.0"):
    checkpoint.load_checkpoint(tmp_path / "removed")


def _snapshot(folder: Path) -> dict:
  return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*"))}


def test_a_refused_resume_changes_nothing_in_the_workdir(tmp_path, tiny_cache, six_steps):
  """Another model or other training data: refused, naming both, before the workdir's config, cache or
  checkpoints are touched (the same workdir still evaluates on its own data)."""
  workdir = shutil.copytree(six_steps, tmp_path / "w")
  (workdir / "config.json").write_text(tiny_config(tiny_cache).to_json(indent=1))
  before = _snapshot(workdir)
  wider = tiny_config(tiny_cache, num_steps=9)
  wider.model.dim = 64
  other_root = tiny_config(tiny_cache, num_steps=9)
  other_root.data.cache_dir = ""
  other_root.data.dir = str(DATA)
  other_seed = tiny_config(tiny_cache, num_steps=9)
  other_seed.data.cache_dir = ""   # the workdir's own synthetic worlds, of another seed
  for config, message in ((wider, r"trained with another model \(dim: 32 -> 64"), (other_root, r"trained on other data \(data.dir: ''"),
                          (other_seed, r"trained on other data \(data.cache_dir")):
    with pytest.raises(ValueError, match=message):
      trainer.train_and_evaluate(config, workdir)
    assert _snapshot(workdir) == before
  missing = tiny_config(tiny_cache)
  missing.data.dir = str(tmp_path / "nowhere")
  with pytest.raises(FileNotFoundError, match="nowhere: no such directory"):
    trainer.train_and_evaluate(missing, tmp_path / "fresh")
  assert not (tmp_path / "fresh").exists()


def test_a_step_with_only_its_metadata_is_skipped_by_sampling_and_resuming(tmp_path, tiny_cache, six_steps):
  workdir = shutil.copytree(six_steps, tmp_path / "w")
  for item in ("state", "record"):   # an interrupted save: the step's metadata alone
    shutil.rmtree(workdir / "checkpoints" / "6" / item)
  assert checkpoint.load_checkpoint(workdir, task="hl").record["step"] == 3
  assert trainer.resume_record(tiny_config(tiny_cache, num_steps=6), workdir)["step"] == 3
  with pytest.raises(ValueError, match="checkpoint step 6 does not restore"):
    checkpoint.load_checkpoint(workdir, task="hl", step=6)


def test_nan_loss_stops_and_keeps_the_last_good_checkpoint(tmp_path, tiny_cache):
  # Copy the cache and put NaN into a scene that the trainer first meets after the step-3 checkpoint.
  bad_cache = tmp_path / "cache"
  shutil.copytree(tiny_cache, bad_cache)
  config = tiny_config(bad_cache, num_steps=6, log_every=2)   # six_steps' config: its compiled steps reused
  ds = batches.load_split(bad_cache, "train", config.data.scene)
  it = batches.BatchIterator(ds, config.train.batch_size, seed=config.seed, group_by_size=True)
  first_step = {}
  for step in range(1, 7):
    for i in it.next_indices().tolist():
      first_step.setdefault(i, step)
  target = next(i for i, step in sorted(first_step.items()) if 4 <= step <= 6)
  shards = preprocess.shard_paths(bad_cache / "train")
  sizes = [len(json.loads(p.with_suffix(".json").read_text())["scenario_ids"]) for p in shards]
  k = int(np.searchsorted(np.cumsum(sizes), target, side="right"))
  reader = array_record_module.ArrayRecordReader(str(shards[k]))
  scenes = [dict(records.decode(r)) for r in reader.read_all()]
  reader.close()
  row = target - sum(sizes[:k])
  scenes[row]["agent_state"] = scenes[row]["agent_state"].copy()
  scenes[row]["agent_state"][0, 0, 0] = np.nan
  records.write(shards[k], [records.encode(s) for s in scenes])
  meta_path = shards[k].with_suffix(".json")   # sealed again: a NaN scene in a shard that passes its checks
  meta = json.loads(meta_path.read_text())
  meta["records_sha256"] = files.sha256(shards[k])
  meta["meta_sha256"] = preprocess._meta_checksum(meta)
  meta_path.write_text(json.dumps(meta))
  with pytest.raises(FloatingPointError, match="last good checkpoint is step 3"):
    trainer.train_and_evaluate(config, tmp_path / "run")
  state, record = _final_params(tmp_path / "run")
  assert record["step"] == 3
  assert all(np.isfinite(x).all() for x in jax.tree_util.tree_leaves(jax.device_get(state.params)))
  lines = [json.loads(l) for l in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
  assert any("error" in l for l in lines)


def _free_port() -> int:
  import socket
  with socket.socket() as sock:
    sock.bind(("localhost", 0))
    return sock.getsockname()[1]


def _train_processes(cache: Path, workdir: Path, num_steps: int, processes: int) -> str:
  """`train.py` on the tiny config as `processes` processes connected through jax.distributed; returns
  process 0's log."""
  # One CPU device per process: a device count in XLA_FLAGS (a caller's) is dropped, other flags are kept.
  flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split() if "device_count" not in f)
  env = os.environ | {"XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
  cmd = [sys.executable, "train.py", "--config=configs/hl.py:tiny", f"--workdir={workdir}",
         f"--config.data.cache_dir={cache}", f"--config.train.num_steps={num_steps}",
         f"--coordinator_address=localhost:{_free_port()}", f"--num_processes={processes}"]
  procs = [subprocess.Popen(cmd + [f"--process_id={i}"], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True) for i in range(processes)]
  outs = [p.communicate(timeout=600) for p in procs]
  for p, (_, err) in zip(procs, outs):
    assert p.returncode == 0, err[-3000:]
  return outs[0][1]


def _logged(workdir: Path) -> dict[int, dict]:
  rows = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
  out: dict[int, dict] = {}
  for r in rows:
    assert not set(r) - {"step"} & set(out.get(r["step"], {})), f"step {r['step']} logged twice"
    out.setdefault(r["step"], {}).update(r)
  return out


def test_two_processes_train_like_one(tmp_path, tiny_cache, six_steps):
  # Two processes (one CPU device each, connected on localhost), each reading 2 of the 4 scenes of
  # every global batch, saving checkpoints together: the same losses, validation losses and data position
  # as one process (`six_steps`) over their first 3 steps (the learning rate is the same up to there; steps
  # 4 to 6 run the same code). (Resuming reads the same data position and checkpoint: the damaged-
  # checkpoint test resumes one process exactly.)
  _train_processes(tiny_cache, tmp_path, 3, processes=2)
  one, two = _logged(six_steps), _logged(tmp_path)  # process 0 alone writes metrics, once per step
  assert sorted(two) == [2, 3] and (tmp_path / "config.json").exists()
  # The processes' gradients are summed in another order than one process sums them: float rounding.
  for step in two:
    for key in ("loss", "val_loss", "val_ema_loss"):
      if key in one[step]:
        np.testing.assert_allclose(two[step][key], one[step][key], rtol=1e-4, err_msg=f"{key} at step {step}")
  assert (checkpoint.Checkpointer(tmp_path / "checkpoints").restore_record()["data_position"]
          == checkpoint.Checkpointer(six_steps / "checkpoints").restore_record(3)["data_position"])


def test_train_command_on_the_synthetic_default_and_a_config_typo(tmp_path, six_steps):
  cmd = [sys.executable, "train.py", "--config=configs/hl.py:tiny", f"--workdir={tmp_path / 'wd'}"]
  env = {**os.environ, "JAX_PLATFORMS": "cpu"}
  # The CPU split into two devices (`train.cpu_devices`), each running half of every batch.
  done = subprocess.run(cmd + ["--config.train.cpu_devices=2"], capture_output=True, text=True, timeout=600,
                        cwd=ROOT, env=env)
  assert done.returncode == 0, done.stderr[-3000:]
  assert "devices [CpuDevice(id=0), CpuDevice(id=1)]" in done.stderr
  assert (tmp_path / "wd" / "synthetic" / "train").is_dir()          # generated once into the workdir
  assert (tmp_path / "wd" / "cache" / "manifest.json").is_file()
  assert (tmp_path / "wd" / "checkpoints" / "6").is_dir()
  assert "step 2/6: loss" in done.stderr and "step 6/6: loss" in done.stderr   # progress without a terminal
  # The same synthetic worlds as the tiny cache, each batch sharded over the devices: the losses of one
  # device's run (`six_steps`) to float rounding: the devices' gradients are summed in another order, within
  # 5e-7 relative up to step 4. On a Zen 4 AMD EPYC (AVX-512) a near-tie flips between steps 4 and 6 (the
  # losses at step 6 then differ by up to 1.3e-3 relative), so step 6 gets a looser tolerance.
  one, split = _logged(six_steps), _logged(tmp_path / "wd")
  assert sorted(one) == sorted(split) == [2, 3, 4, 6]
  for step in one:
    for key in ("loss", "val_loss", "val_ema_loss"):
      if key in one[step]:
        np.testing.assert_allclose(split[step][key], one[step][key], rtol=1e-4 if step <= 4 else 5e-3,
                                   err_msg=f"{key} at step {step}")
  typo = subprocess.run(cmd + ["--config.train.batch_sise=3"], capture_output=True, text=True, timeout=600,
                        cwd=ROOT, env=env)
  assert typo.returncode != 0 and "batch_sise" in typo.stderr and "Traceback" not in typo.stderr


@pytest.mark.parametrize("field, value, message", [
    ("train.lr", -1e-3, "config.train.lr=-0.001: must be > 0.0"),
    ("train.ema_decay", 1.5, "config.train.ema_decay=1.5: must be >= 0.0 and <= 1.0"),
    ("model.dim", 33, "config.model.dim=33: must be a multiple of config.model.heads=2"),
    ("data.scene.agent_types", "vehicle,tram", "unknown agent types ['tram']"),
    ("model.denoiser", "score", "config.model.denoiser='score'"),
    ("model.prediction", "x0", "model.prediction: option(s) of tdiff_jax 0.2.0"),
    ("lane_pull.clearance_m", 2.0, "lane_pull.clearance_m needs lane_pull.across_m > 0"),
    ("lane_pull.end_m", 10.0, "lane_pull.end_m needs lane_pull.across_m > 0"),
    ("lane_pull.across_m", -1.0, "lane_pull.across_m must be >= 0"),
    ("model.fourier_tables", 1, "model.fourier_tables must be 0 (exact) or an integer >= 2, got 1"),
    ("train.cpu_devices", -1, "config.train.cpu_devices must be >= 0 (0: one per core), got -1"),
])
def test_config_errors_name_the_field_before_any_work(tmp_path, field, value, message):
  config = hl_config.get_config("tiny")
  node, name = config, field.split(".")
  for part in name[:-1]:
    node = node[part]
  node[name[-1]] = value
  with pytest.raises(ValueError, match=re.escape(message)):
    trainer.train_and_evaluate(config, tmp_path / "wd")
  assert not (tmp_path / "wd" / "synthetic").exists() and not (tmp_path / "wd" / "cache").exists()


def test_one_cpu_device_per_core_divides_the_batch():
  assert distributed.cpu_device_count(0, 8, cores=2) == 2    # one per core
  assert distributed.cpu_device_count(0, 8, cores=3) == 2    # as many as divide the batch
  assert distributed.cpu_device_count(0, 6, cores=16) == 6   # at most one scene per device
  assert distributed.cpu_device_count(0, 7, cores=1) == 1
  assert distributed.cpu_device_count(3, 8, cores=2) == 3    # as asked (check_config then names the batch)
  with pytest.raises(ValueError, match="cpu_devices must be >= 0"):
    distributed.cpu_device_count(-1, 8)


def test_public_api_resolves():
  import tdiff_jax
  import inspect
  for name in tdiff_jax.__all__:   # every export resolves to a module, a class or a function
    obj = getattr(tdiff_jax, name)
    assert inspect.ismodule(obj) or callable(obj) or isinstance(obj, tuple), name
  with pytest.raises(AttributeError):
    tdiff_jax.no_such_thing  # noqa: B018
