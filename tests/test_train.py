"""The trainer: checkpoints, exact resume, NaN stop, one compile per shape, data parallelism, the CLI."""

from __future__ import annotations

import json
import os
import shutil
import re
import subprocess
import sys
from pathlib import Path
from unittest import mock

import chex
import jax
import numpy as np
import optax
import pytest
from flax import nnx

from array_record.python import array_record_module

from configs import hl as hl_config
from tests.av2_samples import DATA
from tdiff_jax import checkpoint, diffusion, files, models
from tdiff_jax.data import batches, preprocess, records, synthetic
from tdiff_jax.train import distributed, optim, trainer

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def tiny_cache(tmp_path_factory) -> Path:
  config = hl_config.get_config("tiny")
  root = tmp_path_factory.mktemp("tiny")
  synthetic.generate_dataset(root / "synthetic", config.data.synthetic_num, seed=0,
                             val_fraction=config.data.synthetic_val_fraction, workers=1, progress=False)
  preprocess.preprocess(root / "synthetic", root / "cache", config.data.scene, workers=1, progress=False)
  return root / "cache"


def tiny_config(cache: Path, **train):
  config = hl_config.get_config("tiny")
  config.data.cache_dir = str(cache)
  config.train.update(train)
  return config


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


def test_a_damaged_latest_checkpoint_falls_back_to_the_previous_step(tmp_path, tiny_cache, six_steps):
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
  trainer.train_and_evaluate(config, tmp_path)                   # resumes from 3 and saves 6 again
  assert (tmp_path / "checkpoints" / "6.damaged").is_dir()
  again = checkpoint.Checkpointer(tmp_path / "checkpoints")
  assert int(again.restore(template)[0].step) == 6 and again.skipped == []
  again.close()


def test_resume_continues_at_the_right_step_with_the_same_data(tmp_path, tiny_cache, six_steps):
  straight = six_steps
  resumed = tmp_path / "resumed"
  trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=3), resumed)
  # A kill in the middle of saving step 6 leaves orbax's temporary folder; it must be ignored.
  partial = resumed / "checkpoints" / "6.orbax-checkpoint-tmp-1234567"
  (partial / "state").mkdir(parents=True)
  (partial / "state" / "half_written").write_bytes(b"\0" * 100)
  assert checkpoint.Checkpointer(resumed / "checkpoints").latest_step() == 3
  with open(resumed / "metrics.jsonl", "a") as f:   # logged after the checkpoint, then killed
    f.write(json.dumps({"step": 4, "loss": -1.0}) + "\n" + '{"step": 5, "lo')
  with mock.patch.object(trainer.logging, "warning", wraps=trainer.logging.warning) as warning:
    trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=6), resumed)
  # The longer run is allowed, and said aloud (a changed recipe never continues a run silently).
  said = [call.args[0] % call.args[1:] for call in warning.call_args_list]
  assert any("changed since" in line and "train.num_steps: 3 -> 6" in line for line in said), said
  a, rec_a = _final_params(straight)
  b, rec_b = _final_params(resumed)
  assert int(a.step) == int(b.step) == 6
  assert rec_a["data_position"] == rec_b["data_position"]
  chex.assert_trees_all_close(jax.device_get(a.params), jax.device_get(b.params), atol=1e-6)
  chex.assert_trees_all_close(jax.device_get(a.ema), jax.device_get(b.ema), atol=1e-6)
  lines = [json.loads(l) for l in (resumed / "metrics.jsonl").read_text().splitlines()]
  train_steps = [l["step"] for l in lines if "loss" in l]
  assert train_steps == sorted(train_steps) and train_steps[-1] == 6 and 3 in train_steps
  assert len(train_steps) == len(set(train_steps)) and all(l.get("loss") != -1.0 for l in lines)   # no repeats
  assert (resumed / "config.json").exists()


def test_a_checkpoint_of_the_first_train_state_format_resumes(tmp_path, tiny_cache, six_steps):
  """A checkpoint written before the optimiser state gained the `apply_if_finite` wrapper (format 1)
  resumes, and trains on exactly as the same checkpoint in the current format does."""
  state, record = _final_params(six_steps)
  old = tmp_path / "old"
  ckpt = checkpoint.Checkpointer(old / "checkpoints")
  ckpt.save(6, state.replace(opt_state=state.opt_state.inner_state),
            {k: v for k, v in record.items() if k != "train_state_format"})
  ckpt.close()
  shutil.copytree(six_steps / "checkpoints", tmp_path / "new" / "checkpoints")
  for workdir in (old, tmp_path / "new"):
    trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=8), workdir)
  a, rec_a = _final_params(old)
  b, rec_b = _final_params(tmp_path / "new")
  assert int(a.step) == int(b.step) == 8 and rec_a["train_state_format"] == trainer.TRAIN_STATE_FORMAT
  chex.assert_trees_all_close(jax.device_get(a.params), jax.device_get(b.params), atol=1e-6)
  chex.assert_trees_all_close(jax.device_get(a.opt_state), jax.device_get(b.opt_state), atol=1e-6)


def test_resume_accepts_a_model_field_added_later_and_refuses_a_changed_model(tmp_path, tiny_cache, six_steps):
  """A checkpoint whose model config lacks a field added since (at its default), or holds one since
  removed at the value that left it off, resumes; one trained with another width, or with a removed
  option on, is refused, naming it."""
  state, record = _final_params(six_steps)
  for name, change in (("older", lambda m: m.pop("lane_pull_route_m")), ("wider", lambda m: m.update(dim=64)),
                       ("removed_off", lambda m: m.update(social_geometry=False)),   # a field since removed, off
                       ("removed_on", lambda m: m.update(social_geometry=True))):
    rec = json.loads(json.dumps(record))
    change(rec["config"]["model"])
    ckpt = checkpoint.Checkpointer(tmp_path / name / "checkpoints")
    ckpt.save(6, state, rec)
    ckpt.close()
  assert trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=6), tmp_path / "older")["already_done"]
  with pytest.raises(ValueError, match=r"trained with another model \(dim: 64 -> 32"):
    trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=6), tmp_path / "wider")
  assert trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=6), tmp_path / "removed_off")["already_done"]
  with pytest.raises(ValueError, match=r"model.social_geometry=True is an option this version no longer has"):
    trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=6), tmp_path / "removed_on")
  rec = json.loads(json.dumps(record))
  rec["config"]["train"]["max_t"] = 30   # an option since removed, on
  ckpt = checkpoint.Checkpointer(tmp_path / "removed" / "checkpoints")
  ckpt.save(6, state, rec)
  ckpt.close()
  with pytest.raises(ValueError, match=r"trained with train.max_t=30, an option this version no longer has"):
    trainer.train_and_evaluate(tiny_config(tiny_cache, num_steps=6), tmp_path / "removed")


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
  config = tiny_config(bad_cache, num_steps=8, log_every=2, checkpoint_every=3)
  ds = batches.load_split(bad_cache, "train", config.data.scene)
  it = batches.BatchIterator(ds, config.train.batch_size, seed=config.seed, group_by_size=config.data.group_by_size)
  first_step = {}
  for step in range(1, 9):
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


def test_one_compile_per_bucket(tiny_cache):
  """The trainer's own jitted step: new data and values in a bucket reuse its compile; a second
  bucket compiles once more."""
  config = tiny_config(tiny_cache)
  ds = batches.load_split(tiny_cache, "train", config.data.scene)
  consts = trainer.Constants(trainer.norm_stats(config, ds.manifest),
                             diffusion.schedule_from_config(config.diffusion))
  graphdef, params = models.split_model(models.create_model(config))
  tx = optim.make_optimizer(config.train)
  step = trainer.jit_train_step(graphdef, tx, config)
  state = trainer.init_state(config, params, tx)
  it = batches.BatchIterator(ds, 4, seed=0)
  tight = ((int(ds.num_agents.max()),), (int(ds.num_polygons.max()),))   # every batch fits, smaller than the cap
  assert tight != (config.data.agent_buckets, config.data.polygon_buckets)
  for buckets in ((config.data.agent_buckets, config.data.polygon_buckets), tight):
    for _ in range(2):
      state, metrics = step(state, batches.crop_to_bucket(next(it), *buckets), consts)
  assert step._cache_size() == 2
  assert int(state.step) == 4 and np.isfinite(float(metrics["loss"]))


def test_the_step_on_xla_own_product_kernels_trains_as_the_default_one(tiny_cache):
  """`train.cpu_products="xla"` compiles the train step without the YNNPACK library's fusions (XLA's own
  kernels); three steps give the default kernels' losses and parameters up to float rounding."""
  base = tiny_config(tiny_cache)
  ds = batches.load_split(tiny_cache, "train", base.data.scene)
  consts = trainer.Constants(trainer.norm_stats(base, ds.manifest), diffusion.schedule_from_config(base.diffusion))
  graphdef, params = models.split_model(models.create_model(base))
  it = batches.BatchIterator(ds, 4, seed=0)
  data = [batches.crop_to_bucket(next(it), base.data.agent_buckets, base.data.polygon_buckets) for _ in range(3)]
  runs = {}
  for kernels in ("ynnpack", "xla"):
    config = tiny_config(tiny_cache, cpu_products=kernels)
    flat, tx, state = trainer.init_flat_state(config, params)
    step = trainer.jit_train_step(graphdef, tx, config, flat=flat).lower(state, data[0], consts).compile()
    # The default compile hands products to the library; the option takes every one back.
    assert ("__ynn_fusion" in step.as_text()) == (kernels == "ynnpack")
    losses = []
    for batch in data:
      state, metrics = step(state, batch, consts)
      losses.append(float(metrics["loss"]))
    runs[kernels] = (losses, np.asarray(state.params))
  np.testing.assert_allclose(runs["xla"][0], runs["ynnpack"][0], rtol=1e-4)
  assert np.any(runs["xla"][1] != np.asarray(flat.ravel(params)))
  np.testing.assert_allclose(runs["xla"][1], runs["ynnpack"][1], atol=0.1 * 3e-3)


def test_validation_pads_its_batches_to_one_shape(tiny_cache):
  """Validation batches of different size buckets are all padded to the largest of them (one compile of
  the eval step, not one per bucket), and averaged over the same scenes."""
  config = tiny_config(tiny_cache)
  config.data.agent_buckets, config.data.polygon_buckets = (4, 8, 16, 32), (32, 48, 64, 96, 128)
  val = batches.load_split(tiny_cache, "val", config.data.scene)
  own = [batches.batch_bucket(val, np.arange(i * 2, i * 2 + 2), (config.data.agent_buckets, config.data.polygon_buckets))
         for i in range(len(val) // 2)]
  assert len(set(own)) > 1                                  # the batches' own buckets differ
  seen = []

  def eval_fn(params, batch, key, consts, packed):          # padding-invariant: what is valid
    seen.append((batch.num_agents, batch.num_polygons))
    return {"agents": batch.agent_valid.sum(), "x": (batch.agent_state[..., 0] * batch.agent_valid[..., None]).sum()}

  sharding = jax.sharding.NamedSharding(trainer.data_mesh(), jax.sharding.PartitionSpec("data"))
  totals = trainer.validate(eval_fn, None, None, val, 2, 10, config, sharding)
  assert seen == [(max(a for a, _ in own), max(p for _, p in own))] * len(own)
  scenes = [val[i] for i in range(2 * len(own))]
  assert totals["agents"] == pytest.approx(sum(s["agent_valid"].sum() for s in scenes) / len(own))
  assert totals["x"] == pytest.approx(sum((s["agent_state"][..., 0] * s["agent_valid"][:, None]).sum()
                                          for s in scenes) / len(own), rel=1e-5)


def test_the_training_loss_applies_dropout_and_the_validation_loss_does_not(tiny_cache):
  """With dropout on (interaction dropout off), the training loss of the same key, batch and steps
  depends on the dropout key: it differs from the validation loss, which has none."""
  config = tiny_config(tiny_cache, self_only_prob=0.0)
  config.model.dropout = 0.2
  ds = batches.load_split(tiny_cache, "train", config.data.scene)
  consts = trainer.Constants(trainer.norm_stats(config, ds.manifest),
                             diffusion.schedule_from_config(config.diffusion))
  graphdef, params = models.split_model(models.create_model(config))
  batch = batches.crop_to_bucket(next(batches.BatchIterator(ds, 4, seed=0)), config.data.agent_buckets,
                                 config.data.polygon_buckets)
  train_loss, val_loss = trainer.task_loss(config, train=True), trainer.task_loss(config, train=False)

  @jax.jit
  def losses(key):
    model = nnx.merge(graphdef, params)
    return train_loss(model, batch, consts, key)[0], val_loss(model, batch, consts, key)[0]
  (t1, v1), (t1_again, _) = losses(jax.random.key(1)), losses(jax.random.key(1))
  assert float(t1) == float(t1_again) and np.isfinite(float(v1))
  assert abs(float(t1) - float(v1)) > 1e-6


def _changed(new, old) -> list[bool]:
  return jax.tree_util.tree_leaves(jax.tree_util.tree_map(lambda a, b: bool(np.any(np.asarray(a) != np.asarray(b))),
                                                          new, old))


def test_frozen_map_encoder_parts_keep_their_weights_while_the_rest_trains(tiny_cache):
  """`train.freeze_map_inputs`: the flat step (what training runs) leaves every parameter of the map
  encoder's input side and its EMA at its initial value, weight decay included, and trains the encoder's
  polygon -> polygon layer and the denoiser; so does the pytree step."""
  config = tiny_config(tiny_cache, weight_decay=0.5, freeze_map_inputs=True)
  ds = batches.load_split(tiny_cache, "train", config.data.scene)
  consts = trainer.Constants(trainer.norm_stats(config, ds.manifest),
                             diffusion.schedule_from_config(config.diffusion))
  graphdef, params = models.split_model(models.create_model(config))
  it = batches.BatchIterator(ds, 4, seed=0)
  batch = batches.crop_to_bucket(next(it), config.data.agent_buckets, config.data.polygon_buckets)
  flat, tx, state = trainer.init_flat_state(config, params)
  step = trainer.jit_train_step(graphdef, tx, config, flat=flat)
  state, metrics = step(state, batch, consts)
  state, _ = step(state, batch, consts)
  assert np.isfinite(float(metrics["loss"])) and float(metrics["grad_norm"]) > 0
  trained, ema = flat.unravel(state.params), flat.unravel(state.ema)
  encoder = params["map_encoder"]
  inputs = [m.split("/")[1] for m in optim.MAP_INPUT_MODULES if m.split("/")[1] in encoder]
  assert "pt2pl" in inputs and "r_pt2pl" in inputs
  for name in inputs:
    chex.assert_trees_all_equal(trained["map_encoder"][name], encoder[name])
    chex.assert_trees_all_equal(ema["map_encoder"][name], encoder[name])
  # The polygon -> polygon layer's weights train (its norms' and biases' too: every leaf moves).
  assert all(_changed(trained["map_encoder"]["pl2pl"], encoder["pl2pl"]))
  for name in ("state_in", "layers"):
    assert all(_changed(trained[name], params[name])), name
  # The pytree path (`make_train_step` without `flat`).
  tree_tx = optim.make_optimizer(config.train)
  copied = jax.tree_util.tree_map(np.array, params)   # the step donates its state
  tree_step = trainer.jit_train_step(graphdef, tree_tx, config)
  tree_state, _ = tree_step(trainer.init_state(config, copied, tree_tx), batch, consts)
  tree_state, _ = tree_step(tree_state, batch, consts)   # the first step's learning rate is 0 (warmup)
  for name in inputs:
    chex.assert_trees_all_equal(tree_state.params["map_encoder"][name], encoder[name])
    chex.assert_trees_all_equal(tree_state.ema["map_encoder"][name], encoder[name])
  assert all(_changed(tree_state.params["layers"], params["layers"]))


def test_a_frozen_input_side_is_computed_once_per_scene_for_the_same_steps(tiny_cache):
  """With the map encoder's input side frozen, training computes it once for every polygon of the
  training split (`trainer.map_inputs_cache`): a batch's rows are the encoder's own input side of that
  batch, and two steps given them match two steps that compute it (loss and parameters). Not cached when
  the input side trains, when it would exceed `train.map_input_cache_mb`, or when it is not a constant of
  each polygon (two map layers)."""
  config = tiny_config(tiny_cache, freeze_map_inputs=True)
  source = batches.open_split(tiny_cache, "train", config.data.scene)   # the streamed split training reads
  norm = trainer.norm_stats(config, batches.read_manifest(tiny_cache))
  consts = trainer.Constants(norm, diffusion.schedule_from_config(config.diffusion))
  graphdef, params = models.split_model(models.create_model(config))
  cache = trainer.map_inputs_cache(config, graphdef, params, norm, source)
  assert cache is not None and cache.rows.shape == (int(source.num_polygons.sum()), 2, config.model.dim)
  it = trainer.batch_iterator(source, 4, config, train=True)
  indices, batch = it.next_with_indices()
  assert len(indices) == 4 and batch.pl_valid.sum() == source.num_polygons[indices].sum()
  inputs = cache.take(indices, batch.num_polygons)
  ref = nnx.merge(graphdef, params).map_encoder.input_side(batch, norm.mean[:2], norm.std[:2])
  np.testing.assert_allclose(inputs.embedding, ref.embedding, atol=1e-5)
  np.testing.assert_allclose(inputs.attended, ref.attended, atol=1e-5)
  flat, tx, state = trainer.init_flat_state(config, params)
  step = jax.jit(trainer.make_train_step(graphdef, tx, config, flat))
  results = []
  for given in (None, inputs):
    s = state
    for _ in range(2):   # the first step's learning rate is 0 (warmup)
      s, metrics = step(s, batch, consts, None, given)
    results.append((float(metrics["loss"]), float(metrics["grad_norm"]), np.asarray(s.params)))
  (loss, grad_norm, trained), (loss_cached, grad_norm_cached, trained_cached) = results
  np.testing.assert_allclose(loss_cached, loss, rtol=1e-5)
  np.testing.assert_allclose(grad_norm_cached, grad_norm, rtol=1e-4)
  assert np.any(trained != np.asarray(state.params))
  # Within a tenth of the step's learning rate (Adam's update size): rounding in a near-zero gradient moves
  # its normalised update by more than its own size.
  np.testing.assert_allclose(trained_cached, trained, atol=0.1 * 1.5e-3)
  assert trainer.map_inputs_cache(tiny_config(tiny_cache), graphdef, params, norm, source) is None
  assert trainer.map_inputs_cache(tiny_config(tiny_cache, freeze_map_inputs=True, map_input_cache_mb=0.01),
                                  graphdef, params, norm, source) is None
  two_layers = tiny_config(tiny_cache, freeze_map_inputs=True)
  two_layers.model.map_layers = 2
  graphdef2, params2 = models.split_model(models.create_model(two_layers))
  assert trainer.map_inputs_cache(two_layers, graphdef2, params2, norm, source) is None


def test_frozen_relations_are_cached_with_the_input_side_for_the_same_steps(tiny_cache):
  """With the polygon -> polygon relation embedding frozen too (`train.freeze_map_relations`), the cache
  also holds every polygon's k nearest pairs and their embedded relations: the encoder given a batch's
  rows gives the polygons it computes itself, two steps given them match two steps that compute them,
  and the relation embedding keeps its initial weights while the polygon -> polygon attention trains."""
  config = tiny_config(tiny_cache, freeze_map_inputs=True, freeze_map_relations=True)
  source = batches.open_split(tiny_cache, "train", config.data.scene)
  norm = trainer.norm_stats(config, batches.read_manifest(tiny_cache))
  consts = trainer.Constants(norm, diffusion.schedule_from_config(config.diffusion))
  graphdef, params = models.split_model(models.create_model(config))
  cache = trainer.map_inputs_cache(config, graphdef, params, norm, source)
  k, n = config.model.pl2pl_neighbors, int(source.num_polygons.sum())
  assert cache.pl2pl_index.shape == cache.pl2pl_valid.shape == (n, k)
  assert cache.pl2pl_relation.shape == (n, k, config.model.dim) and cache.pl2pl_valid.any()
  indices, batch = trainer.batch_iterator(source, 4, config, train=True).next_with_indices()
  inputs = cache.take(indices, batch.num_polygons)
  assert inputs.pl2pl_relation.shape == batch.pl_valid.shape + (k, config.model.dim)
  encoder = nnx.merge(graphdef, params).map_encoder
  stats = (norm.mean[:2], norm.std[:2])
  np.testing.assert_allclose(encoder(batch, *stats, inputs=inputs).polygons, encoder(batch, *stats).polygons,
                             atol=1e-4)
  flat, tx, state = trainer.init_flat_state(config, params)
  step = jax.jit(trainer.make_train_step(graphdef, tx, config, flat))
  results = []
  for given in (inputs.replace(pl2pl_index=None, pl2pl_valid=None, pl2pl_relation=None), inputs):
    s = state
    for _ in range(2):   # the first step's learning rate is 0 (warmup)
      s, metrics = step(s, batch, consts, None, given)
    results.append((float(metrics["loss"]), flat.unravel(s.params)["map_encoder"]))
  (loss, trained), (loss_cached, trained_cached) = results
  np.testing.assert_allclose(loss_cached, loss, rtol=1e-5)
  for name in ("r_pl2pl", "edge_type"):
    chex.assert_trees_all_equal(trained_cached[name], params["map_encoder"][name])
  assert all(_changed(trained_cached["pl2pl"], params["map_encoder"]["pl2pl"]))


def test_sharded_step_matches_the_single_device_step(tiny_cache):
  """One train step on four CPU devices equals the step on one; with an all-pairs map encoder too, each
  device's scenes packed apart (`tests/sharded_step_check.py`)."""
  done = subprocess.run([sys.executable, str(ROOT / "tests" / "sharded_step_check.py"), str(tiny_cache)],
                        capture_output=True, text=True, timeout=600, cwd=ROOT)
  assert done.returncode == 0, done.stderr[-3000:]
  result = json.loads(done.stdout.strip().splitlines()[-1])
  assert result["devices"] == 4
  assert result["max_abs_diff"] < 1e-5
  # An all-pairs map encoder's packed polygons, one list per device on four: the dense step's result.
  assert result["packed_shards"] == 4
  assert result["packed_max_abs_diff"] < 1e-5


def _free_port() -> int:
  import socket
  with socket.socket() as sock:
    sock.bind(("localhost", 0))
    return sock.getsockname()[1]


def _train_processes(cache: Path, workdir: Path, num_steps: int, processes: int) -> None:
  """`train.py` on the tiny config as `processes` processes connected through jax.distributed."""
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


def _logged(workdir: Path) -> dict[int, dict]:
  rows = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
  out: dict[int, dict] = {}
  for r in rows:
    assert not set(r) - {"step"} & set(out.get(r["step"], {})), f"step {r['step']} logged twice"
    out.setdefault(r["step"], {}).update(r)
  return out


def test_two_processes_train_like_one_and_resume(tmp_path, tiny_cache, six_steps):
  # Two processes (one CPU device each, connected on localhost), each reading 2 of the 4 scenes of
  # every global batch: stopped after the step-3 checkpoint, resumed to step 6; the same losses and
  # validation losses as one process trained straight (`six_steps`).
  _train_processes(tiny_cache, tmp_path, 3, processes=2)
  assert checkpoint.Checkpointer(tmp_path / "checkpoints").latest_step() == 3
  _train_processes(tiny_cache, tmp_path, 6, processes=2)
  one, two = _logged(six_steps), _logged(tmp_path)  # process 0 alone writes metrics, once per step
  assert sorted(one) == sorted(two) == [2, 3, 4, 6]
  # The processes' gradients are summed in another order than one process sums them: float rounding, within
  # 5e-7 relative to step 4 (after the resume). On a Zen 4 AMD EPYC (AVX-512) a near-tie flips between steps
  # 4 and 6 (the losses at step 6 then differ by up to 1.3e-3 relative), so step 6 gets a looser tolerance.
  for step in one:
    for key in ("loss", "val_loss", "val_ema_loss"):
      if key in one[step]:
        np.testing.assert_allclose(two[step][key], one[step][key], rtol=1e-4 if step <= 4 else 5e-3,
                                   err_msg=f"{key} at step {step}")
  assert (checkpoint.Checkpointer(tmp_path / "checkpoints").restore_record()["data_position"]
          == checkpoint.Checkpointer(six_steps / "checkpoints").restore_record()["data_position"])


def test_train_command_on_the_synthetic_default_and_a_config_typo(tmp_path):
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
  typo = subprocess.run(cmd + ["--config.train.batch_sise=3"], capture_output=True, text=True, timeout=600,
                        cwd=ROOT, env=env)
  assert typo.returncode != 0 and "batch_sise" in typo.stderr
  ascent = subprocess.run(cmd[:2] + ["--config=configs/hl.py:tiny", f"--workdir={tmp_path / 'wd2'}",
                                     "--config.train.lr=-0.001"], capture_output=True, text=True, timeout=600,
                          cwd=ROOT, env=env)
  assert ascent.returncode != 0 and "train.py: config error: config.train.lr=-0.001: must be > 0.0" in ascent.stderr
  assert "Traceback" not in ascent.stderr and not (tmp_path / "wd2" / "synthetic").exists()   # no work done


@pytest.mark.parametrize("field, value, message", [
    ("train.lr", -1e-3, "config.train.lr=-0.001: must be > 0.0"),
    ("train.ema_decay", 1.5, "config.train.ema_decay=1.5: must be >= 0.0 and <= 1.0"),
    ("model.dim", 33, "config.model.dim=33: must be a multiple of config.model.heads=2"),
    ("data.scene.agent_types", "vehicle,tram", "unknown agent types ['tram']"),
    ("model.prediction", "score", "model.prediction='score'"),
    ("model.lane_pull_noise_m", 3.0, "model.lane_pull_noise_m needs model.lane_pull_m > 0"),
    ("model.lane_pull_clearance_m", 2.0, "model.lane_pull_clearance_m needs model.lane_pull_m > 0"),
    ("model.lane_pull_end_m", 10.0, "model.lane_pull_end_m needs model.lane_pull_m > 0"),
    ("model.lane_pull_route_m", 5.0, "model.lane_pull_route_m needs model.lane_pull_m > 0"),
    ("train.adam_b2", 0.0, "config.train.adam_b2=0.0: must be > 0.0 and <= 1.0"),
    ("model.fourier_tables", 1, "model.fourier_tables must be 0 (exact) or an integer >= 2, got 1"),
    ("train.cpu_products", "mkl", "config.train.cpu_products='mkl': choose one of ('ynnpack', 'xla')"),
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


def test_weight_decay_only_on_weight_matrices(tiny_cache):
  _, params = models.split_model(models.create_model(tiny_config(tiny_cache)))
  mask = optim.decay_mask(params)
  flat = {jax.tree_util.keystr(k): v for k, v in jax.tree_util.tree_leaves_with_path(mask)}
  assert flat["['state_in']['kernel']"] and flat["['map_encoder']['pt_input']['w1']"]
  assert not flat["['state_in']['bias']"] and not flat["['type_emb']['embedding']"]
  assert not flat["['map_encoder']['latents']"] and not flat["['token_norm']['scale']"]
  assert not any(v for k, v in flat.items() if "lambda_" in k or "freqs" in k or "subln" in k)


def test_adam_b2_is_adams_second_moment_decay():
  # `train.adam_b2` reaches Adam: the optimiser's update is optax's AdamW with that b2 (clipping off here).
  params = {"w": np.ones((3, 2), np.float32)}
  config = hl_config.get_config("tiny").train
  config.update(dict(adam_b2=0.5, grad_clip=1e6, weight_decay=0.0))
  ours, ref = optim.make_optimizer(config, skip_nonfinite=False), optax.adam(optim.learning_rate_schedule(config), b2=0.5)
  default_config = config.copy_and_resolve_references()
  default_config.adam_b2 = 0.999
  default = optim.make_optimizer(default_config, skip_nonfinite=False)
  s, s_ref, s_def = ours.init(params), ref.init(params), default.init(params)
  for i in range(3):
    g = {"w": np.full((3, 2), [1.0, -2.0, 0.5][i], np.float32)}
    u, s = ours.update(g, s, params)
    u_ref, s_ref = ref.update(g, s_ref, params)
    u_def, s_def = default.update(g, s_def, params)
  np.testing.assert_allclose(u["w"], u_ref["w"], rtol=1e-6)
  assert not np.allclose(u["w"], u_def["w"], rtol=1e-3)


def test_flat_optimizer_is_adamw_on_the_parameter_pytree(tiny_cache):
  # Training updates the parameters as one vector; the same AdamW (clipping, decay mask, schedule,
  # skipped non-finite steps) as optax's on the pytree, and the checkpoint's pytree state round-trips.
  config = tiny_config(tiny_cache, grad_clip=0.05, weight_decay=0.5)
  _, params = models.split_model(models.create_model(config))
  flat = optim.FlatParams.of(params)
  tx, flat_tx = optim.make_optimizer(config.train), optim.make_optimizer(config.train, flat=flat)
  tree_p, tree_s = params, tx.init(params)
  flat_p, flat_s = flat.ravel(params), optim.flatten_state(tx.init(params), flat)
  chex.assert_trees_all_equal_structs(flat_s, flat_tx.init(flat_p))
  update, flat_update = jax.jit(tx.update), jax.jit(flat_tx.update)
  for i in range(4):
    grads = jax.tree_util.tree_map(lambda x: np.cos(np.arange(x.size, dtype=np.float32) + i).reshape(x.shape), params)
    if i == 2:  # a non-finite gradient changes nothing
      grads = jax.tree_util.tree_map(lambda g: g * np.nan, grads)
    u, tree_s = update(grads, tree_s, tree_p)
    tree_p = optax.apply_updates(tree_p, u)
    u, flat_s = flat_update(flat.ravel(grads), flat_s, flat_p)
    flat_p = flat_p + u
  assert int(tree_s.total_notfinite) == int(flat_s.total_notfinite) == 1
  chex.assert_trees_all_close(flat.unravel(flat_p), tree_p, atol=1e-6)
  chex.assert_trees_all_close(optim.unflatten_state(flat_s, tree_s, flat), tree_s, atol=1e-6)
  # Decay reaches exactly the leaves of `decay_mask`.
  decayed = jax.tree_util.tree_map(lambda m, x: np.full(x.shape, m, np.float32), optim.decay_mask(params), params)
  np.testing.assert_array_equal(flat.decay_multiplier(), flat.ravel(decayed))


def test_public_api_resolves():
  import tdiff_jax
  import inspect
  for name in tdiff_jax.__all__:   # every export resolves to a module, a class or a function
    obj = getattr(tdiff_jax, name)
    assert inspect.ismodule(obj) or callable(obj) or isinstance(obj, tuple), name
  with pytest.raises(AttributeError):
    tdiff_jax.no_such_thing  # noqa: B018
