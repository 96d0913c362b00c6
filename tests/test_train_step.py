"""The train step: one compile per shape, product kernels, validation, frozen parts and their caches, the
sharded step, the flat optimiser."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import chex
import jax
import numpy as np
import optax
import pytest
from flax import nnx

from configs import hl as hl_config
from tests.tiny import tiny_config
from tdiff_jax import diffusion, models
from tdiff_jax.data import batches
from tdiff_jax.train import optim, trainer

ROOT = Path(__file__).resolve().parent.parent


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
  polygon -> polygon attention and the denoiser."""
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


def test_frozen_map_inputs_and_relations_are_computed_once_per_scene_for_the_same_steps(tiny_cache, monkeypatch):
  """With the map encoder's input side and polygon -> polygon relation embedding frozen (the default's
  `train.freeze_map_inputs`), training computes them once for every polygon of
  the training split (`trainer.map_inputs_cache`): the encoder given a batch's rows gives the polygons it
  computes itself, two steps given them match two steps that compute them, and the relation embedding
  keeps its initial weights while the polygon -> polygon attention trains. The step is the trainer's, its
  products on XLA's own kernels. Not cached when the input side trains, when it would exceed
  `trainer.MAP_INPUT_CACHE_MB`, or when it is not a constant of each polygon (two map layers)."""
  config = tiny_config(tiny_cache, freeze_map_inputs=True)
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
  results = []
  for given in (None, inputs):
    step = trainer.jit_train_step(graphdef, tx, config, flat=flat).lower(state, batch, consts, None, given).compile()
    # XLA's default compile hands products to the YNNPACK library; the trainer's options take every one back.
    assert "__ynn_fusion" not in step.as_text()
    s = jax.tree_util.tree_map(np.array, state)   # the step donates its state
    for _ in range(2):   # the first step's learning rate is 0 (warmup)
      s, metrics = step(s, batch, consts, None, given)
    results.append((float(metrics["loss"]), flat.unravel(s.params)["map_encoder"]))
  (loss, trained), (loss_cached, trained_cached) = results
  np.testing.assert_allclose(loss_cached, loss, rtol=1e-5)
  for name in ("r_pl2pl", "edge_type"):
    chex.assert_trees_all_equal(trained_cached[name], params["map_encoder"][name])
  assert all(_changed(trained_cached["pl2pl"], params["map_encoder"]["pl2pl"]))
  assert trainer.map_inputs_cache(tiny_config(tiny_cache), graphdef, params, norm, source) is None
  two_layers = tiny_config(tiny_cache, freeze_map_inputs=True)
  two_layers.model.map_layers = 2
  graphdef2, params2 = models.split_model(models.create_model(two_layers))
  assert trainer.map_inputs_cache(two_layers, graphdef2, params2, norm, source) is None
  monkeypatch.setattr(trainer, "MAP_INPUT_CACHE_MB", 0.01)
  assert trainer.map_inputs_cache(config, graphdef, params, norm, source) is None


def test_sharded_packed_step_matches_the_single_device_step(tiny_cache):
  """One train step of an all-pairs map encoder on four CPU devices, each device's scenes packed apart,
  equals the dense step on one (`tests/sharded_step_check.py`)."""
  done = subprocess.run([sys.executable, str(ROOT / "tests" / "sharded_step_check.py"), str(tiny_cache)],
                        capture_output=True, text=True, timeout=600, cwd=ROOT)
  assert done.returncode == 0, done.stderr[-3000:]
  result = json.loads(done.stdout.strip().splitlines()[-1])
  assert result["devices"] == 4
  # An all-pairs map encoder's packed polygons, one list per device on four: the dense step's result.
  assert result["packed_shards"] == 4
  assert result["packed_max_abs_diff"] < 1e-5


def test_weight_decay_only_on_weight_matrices(tiny_cache):
  _, params = models.split_model(models.create_model(tiny_config(tiny_cache)))
  mask = optim.decay_mask(params)
  flat = {jax.tree_util.keystr(k): v for k, v in jax.tree_util.tree_leaves_with_path(mask)}
  assert flat["['state_in']['kernel']"] and flat["['map_encoder']['pt_input']['w1']"]
  assert not flat["['state_in']['bias']"] and not flat["['type_emb']['embedding']"]
  assert not flat["['map_encoder']['latents']"] and not flat["['token_norm']['scale']"]
  assert not any(v for k, v in flat.items() if "lambda_" in k or "freqs" in k or "subln" in k)


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
