"""The trajectory infiller: modes pin the right ends, vmap == per-agent loop, padding is inert,
`infill` composes with jit/vmap, ADE/FDE/MR on known answers, and the loss can be driven down."""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import nnx

from configs import infill as infill_config
from tests.av2_samples import DATA, REAL_110
from tdiff_jax import datatypes, infilling, metrics
from tdiff_jax.data import config as config_lib, scene_builder
from tdiff_jax.models import infiller, map_encoder
from tdiff_jax.models.infiller import AgentInputs, InfillModelConfig, Infiller
from tdiff_jax.train import optim

TINY = InfillModelConfig(dim=32, heads=2, num_layers=1, temporal_layers=1, temporal_ff=32, num_freq_bands=4,
                         dropout=0.0)


@pytest.fixture(scope="module")
def batch() -> datatypes.Scene:
  cfg = config_lib.default_data_config()
  cfg.max_agents, cfg.max_polygons = 16, 128
  scenes = [scene_builder.load_scene(DATA / sid, cfg)[0] for sid in REAL_110]
  return jax.tree_util.tree_map(jnp.asarray, datatypes.stack_scenes(scenes))


@pytest.fixture(scope="module")
def model():
  m = Infiller(TINY, rngs=nnx.Rngs(0))
  graphdef, state = nnx.split(m)
  return m, graphdef, nnx.to_pure_dict(state)


def test_mode_weights_match_their_meaning():
  h = np.linspace(0, 1, datatypes.HORIZON)
  g = np.asarray(infiller.mode_weights(jnp.arange(4), datatypes.HORIZON))
  np.testing.assert_allclose(g[infilling.MODES.index("both")], h * (1 - h), atol=1e-7)
  np.testing.assert_allclose(g[infilling.MODES.index("initial")], h, atol=1e-7)
  np.testing.assert_allclose(g[infilling.MODES.index("goal")], 1 - h, atol=1e-7)
  np.testing.assert_allclose(g[infilling.MODES.index("none")], 1.0)
  b = infiller.bridge(jnp.array([1.0, 2.0]), jnp.array([7.0, -4.0]))
  np.testing.assert_allclose(b[0], [1, 2])
  np.testing.assert_allclose(b[-1], [7, -4], atol=1e-6)
  with pytest.raises(ValueError, match="unknown infill mode"):
    infilling.mode_id("start")


def test_hard_constraints_pin_the_given_states(model, batch, compiles):
  _, graphdef, params = model
  valid = np.asarray(batch.agent_valid)
  start, goal = np.asarray(batch.agent_state[..., 0, :2]), np.asarray(batch.agent_state[..., 1, :2])
  heading = batch.agent_state[..., 0, 3]
  before = compiles["jit(infill)"]
  for name in infilling.MODES:   # four modes, one compile
    out = np.asarray(infilling.infill(graphdef, params, batch, heading, infilling.mode_id(name)))
    d0 = np.abs(out[:, :, 0] - start)[valid].max()
    d1 = np.abs(out[:, :, -1] - goal)[valid].max()
    pins_start, pins_goal = name in ("both", "initial"), name in ("both", "goal")
    assert (d0 < 1e-4) == pins_start, (name, d0)   # float precision at city-scale metres
    assert (d1 < 1e-4) == pins_goal, (name, d1)
    assert not out[~valid].any()
  tight = batch.crop(num_polygons=int(np.asarray(batch.pl_valid).sum(-1).max()))   # another size bucket
  assert tight.num_polygons < batch.num_polygons
  infilling.infill(graphdef, params, tight, heading, 0)
  assert compiles["jit(infill)"] - before == 2


def test_vmapped_equals_per_agent_loop(model, batch):
  m, _, _ = model
  mode = jnp.asarray(np.random.default_rng(0).integers(0, 4, batch.agent_valid.shape), jnp.int32)
  heading = batch.agent_state[..., 0, 3]
  batched = np.asarray(jax.jit(lambda s, h, md: m(s, h, md))(batch, heading, mode))
  polygons = jax.jit(lambda s: m.encode_map(s).polygons)(batch)
  one = jax.jit(lambda pl, s, ag: m.infill_agent(pl, s, ag))
  for b in range(batch.agent_valid.shape[0]):
    scene_b = jax.tree_util.tree_map(lambda x, b=b: x[b], batch)
    for a in np.flatnonzero(np.asarray(batch.agent_valid[b])):
      agent = AgentInputs(index=jnp.int32(a), xy=scene_b.agent_state[a, 0, :2], heading=heading[b, a],
                          goal=scene_b.agent_state[a, 1, :2], speed=scene_b.agent_state[a, :, 2],
                          type=scene_b.agent_type[a], mode=mode[b, a])
      np.testing.assert_allclose(np.asarray(one(polygons[b], scene_b, agent)), batched[b, a], atol=1e-4)


def test_padded_agents_produce_nothing_and_affect_nothing(model, batch):
  _, graphdef, params = model
  heading = batch.agent_state[..., 0, 3]
  ref = np.asarray(infilling.infill(graphdef, params, batch, heading, 0))
  valid = np.asarray(batch.agent_valid)
  rng = np.random.default_rng(1)
  junk_state = np.where(valid[..., None, None], batch.agent_state, rng.normal(0, 50, batch.agent_state.shape))
  junk = batch.replace(agent_state=jnp.asarray(junk_state, jnp.float32),
                       agent_type=jnp.where(batch.agent_valid, batch.agent_type, 3))
  out = np.asarray(infilling.infill(graphdef, params, junk, jnp.where(batch.agent_valid, heading, 2.0), 0))
  np.testing.assert_allclose(out[valid], ref[valid], atol=1e-5)
  assert not out[~valid].any()


def test_infill_works_inside_jit_and_vmap(model, batch):
  _, graphdef, params = model
  heading = batch.agent_state[..., 0, 3]
  two = jax.tree_util.tree_map(lambda x: jnp.stack([x[:2], x[1:]]), batch)       # [2, 2, ...]
  mapped = jax.jit(jax.vmap(lambda s, h: infilling.infill(graphdef, params, s, h, 0)))(
      two, jnp.stack([heading[:2], heading[1:]]))
  direct = infilling.infill(graphdef, params, batch, heading, 0)
  np.testing.assert_allclose(mapped[0], direct[:2], atol=1e-5)
  np.testing.assert_allclose(mapped[1], direct[1:], atol=1e-5)


def test_maps_encoded_per_scene_give_the_same_trajectories(model, batch):
  _, graphdef, params = model
  heading = batch.agent_state[..., 0, 3]
  # Real maps of 65 to 83 polygons padded to 128: each is encoded alone at 96.
  ctx = infilling.encode_maps(graphdef, params, batch, (64, 96, 128))
  chex.assert_shape(ctx.polygons, (3, 128, TINY.dim))
  got = infilling.infill(graphdef, params, batch, heading, 0, map_context=ctx)
  np.testing.assert_allclose(got, infilling.infill(graphdef, params, batch, heading, 0), atol=1e-3)
  errors = infilling.infill_errors(graphdef, params, batch, ctx)
  reference = infilling.infill_errors(graphdef, params, batch)
  np.testing.assert_allclose(errors["ade"], reference["ade"], atol=1e-3)


@pytest.mark.parametrize("nearest", [False, True], ids=["all_pairs", "nearest_polygons"])
def test_packed_agents_give_the_padded_batch_trajectories(model, batch, nearest):
  """Scenes of 4, 9 and 16 agents in one batch: the valid agents and their (agent, polygon) and
  (agent, agent) pairs listed (`pack_agents`) give the trajectories of one call on the padded batch,
  with every polygon within the radius or only each agent's k nearest, and agents paired only within
  a short radius."""
  _, graphdef, params = model   # the module's model (its map encodings compiled already), or:
  cfg = dataclasses.replace(TINY, pl2a_neighbors=8, a2a_radius_m=20.0) if nearest else TINY
  if nearest:
    graphdef, state = nnx.split(Infiller(cfg, rngs=nnx.Rngs(0)))
    params = nnx.to_pure_dict(state)
  keep = np.arange(batch.num_agents)[None] < np.array([[4], [9], [16]])   # different sizes per scene
  varied = batch.replace(agent_valid=batch.agent_valid & jnp.asarray(keep))
  valid = np.asarray(varied.agent_valid)
  heading = varied.agent_state[..., 0, 3]
  mode = jnp.asarray(np.arange(varied.num_agents * 3).reshape(3, -1) % len(infilling.MODES))

  packed = infilling.pack_agents(graphdef, params, varied)
  assert int(packed.agent_valid.sum()) == valid.sum() and packed.shape[0] < valid.size
  dst = np.asarray(packed.pl_dst)
  assert (np.diff(dst) >= 0).all() and (np.diff(np.asarray(packed.a_dst)) >= 0).all()   # sorted by query
  per_agent = np.bincount(dst[np.asarray(packed.pl_valid)], minlength=packed.shape[0])[:valid.sum()]
  assert per_agent.min() > 0 and (cfg.pl2a_neighbors == 0 or per_agent.max() == cfg.pl2a_neighbors)
  assert 0 < int(packed.a_valid.sum()) < sum(n * (n - 1) for n in valid.sum(-1)) or cfg.a2a_radius_m > 100

  got = infilling.infill_packed(graphdef, params, varied, heading, mode, polygon_buckets=(64, 96, 128))
  want = infilling.infill(graphdef, params, varied, heading, mode)
  chex.assert_shape(got, want.shape)
  np.testing.assert_allclose(got, want, atol=1e-3)
  assert float(jnp.abs(got[~varied.agent_valid]).max()) == 0.0 and float(jnp.abs(got[varied.agent_valid]).max()) > 1.0


def test_fourier_tables_give_the_exact_trajectories_to_interpolation_error(model, batch):
  """`fourier_tables`: the relation embeddings (map encoder and per agent) interpolated from tables give
  the exact model's trajectories on real AV2 scenes, packed as `sample.py` infills, to a few millimetres."""
  _, graphdef, params = model
  graphdef_tables, _ = nnx.split(Infiller(dataclasses.replace(TINY, fourier_tables=128), rngs=nnx.Rngs(0)))
  heading = batch.agent_state[..., 0, 3]
  got, want = (infilling.infill_packed(g, params, batch, heading, 0, polygon_buckets=(64, 96, 128))
               for g in (graphdef_tables, graphdef))
  gap = np.abs(np.asarray(got - want))[np.asarray(batch.agent_valid)]
  assert 1e-7 < gap.max() < 5e-3, gap.max()
  with pytest.raises(ValueError, match="fourier_tables must be 0"):
    InfillModelConfig(fourier_tables=1)


def test_displacement_errors_known_answers():
  target = jnp.zeros((2, 5, 2))
  pred = target + jnp.array([3.0, 4.0])
  valid = jnp.array([[True] * 5, [True, True, True, False, False]])
  pred = pred.at[1, 2].set(jnp.array([0.0, 1.0]))
  ade, fde, has = metrics.displacement_errors(pred, target, valid)
  np.testing.assert_allclose(ade, [5.0, (5 + 5 + 1) / 3], rtol=1e-5)
  np.testing.assert_allclose(fde, [5.0, 1.0], rtol=1e-5)          # the last valid step
  assert has.all()
  table = metrics.summarize_displacement_errors(np.stack([ade] * 4), np.stack([fde] * 4), np.array([True, True]),
                                              infilling.MODES)
  assert table["both"]["miss_rate_pct"] == 50.0 and table["none"]["agents"] == 2


def test_loss_can_be_driven_down(model, batch):
  m, graphdef, params = model
  tx = optax.adam(3e-3)
  opt = tx.init(params)
  mode = jnp.zeros(batch.agent_valid.shape, jnp.int32)
  packed = map_encoder.pack_polygons(batch, TINY.pl2pl_radius_m)   # as training passes an all-pairs encoder

  @jax.jit
  def step(params, opt, batch, packed, mode):   # data as arguments: closed-over arrays get constant-folded
    def loss_fn(p):
      return infilling.infill_loss(nnx.merge(graphdef, p), batch, jax.random.key(0), 0.5, mode=mode, packed=packed)[0]
    loss, grads = jax.value_and_grad(loss_fn)(params)
    updates, opt = tx.update(grads, opt, params)
    return optax.apply_updates(params, updates), opt, loss

  losses = []
  for _ in range(40):
    params, opt, loss = step(params, opt, batch, packed, mode)
    losses.append(float(loss))
  assert np.isfinite(losses).all() and losses[-1] < 0.6 * losses[0], losses[::8]


def test_packed_polygons_give_the_same_loss(model, batch):
  """The all-pairs map encoder over the batch's packed polygons and pairs (what training passes): the same loss."""
  _, graphdef, params = model
  packed = map_encoder.pack_polygons(batch, TINY.pl2pl_radius_m)
  mode = jnp.zeros(batch.agent_valid.shape, jnp.int32)
  loss = jax.jit(lambda p, batch, packed: infilling.infill_loss(nnx.merge(graphdef, p), batch, jax.random.key(0), 0.5,
                                                               train=False, mode=mode, packed=packed)[0])
  np.testing.assert_allclose(loss(params, batch, packed), loss(params, batch, None), rtol=1e-5)


def test_generative_infiller_draws_differ_and_meet_the_hard_constraints_exactly(batch):
  """The flow-matching infiller: its loss trains, each key draws other trajectories, every draw pins the
  mode's ends exactly, packed and padded calls draw the same, and a draw is a pure function of its key."""
  m = Infiller(dataclasses.replace(TINY, flow_noise_m=3.0), rngs=nnx.Rngs(0))
  graphdef, state = nnx.split(m)
  params = nnx.to_pure_dict(state)
  loss, logged = jax.jit(lambda p, b: infilling.infill_loss(nnx.merge(graphdef, p), b, jax.random.key(1), 0.5))(
      params, batch)
  assert np.isfinite(loss) and logged["ade"] > 0
  valid = np.asarray(batch.agent_valid)
  start, goal = np.asarray(batch.agent_state[..., 0, :2]), np.asarray(batch.agent_state[..., 1, :2])
  heading = batch.agent_state[..., 0, 3]
  for name in ("both", "none"):
    mode = infilling.mode_id(name)
    draws = [np.asarray(infilling.infill(graphdef, params, batch, heading, mode, jax.random.key(k))) for k in (0, 1)]
    assert np.abs(draws[0] - draws[1])[valid].mean() > 1e-3                 # diversity
    np.testing.assert_array_equal(draws[0], infilling.infill(graphdef, params, batch, heading, mode, jax.random.key(0)))
    if name == "both":
      for d in draws:
        assert np.abs(d[:, :, 0] - start)[valid].max() < 1e-4 and np.abs(d[:, :, -1] - goal)[valid].max() < 1e-4
  packed = infilling.infill_packed(graphdef, params, batch, heading, 0, jax.random.key(0), polygon_buckets=(64, 128))
  np.testing.assert_allclose(packed, infilling.infill(graphdef, params, batch, heading, 0, jax.random.key(0)),
                             atol=2e-3)
  with pytest.raises(ValueError, match="generative infiller"):
    m(batch, heading, jnp.zeros(valid.shape, jnp.int32))


@pytest.mark.parametrize("variant", ["default", "av2", "stochastic", "tiny"])
def test_infiller_configs_train_every_weight(variant):
  """No infiller config keeps a module at its initial weights (the HL default freezes some of its map
  encoder; the infiller's configs, built on the HL ones, must not inherit that)."""
  assert optim.frozen_modules(infill_config.get_config(variant).train) == ()
