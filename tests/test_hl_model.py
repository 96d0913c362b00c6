"""The HL denoisers (paper and grounded) and the lane pull: shapes, padding and permutation invariance, masked rows, the
entropy term, the grounding geometry, overfitting."""

from __future__ import annotations

import dataclasses
import functools
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from flax import nnx

from tests.av2_samples import DATA, REAL_110
from tdiff_jax import datatypes, diffusion, hl_objective, metrics
from tdiff_jax.data import batches, config as data_config, normalize, scene_builder
from tdiff_jax.models import grounding, layers, map_encoder
from tdiff_jax.lane_pull import LanePull
from tdiff_jax.models.grounded_denoiser import GroundedConfig, GroundedDenoiser
from tdiff_jax.models.paper_denoiser import PaperConfig, PaperDenoiser

CFG = PaperConfig(dim=32, heads=2, num_layers=2, num_freq_bands=4, num_latents=4, dropout=0.0,
                  pl2pl_neighbors=0, max_agents=64)
# The grounded denoiser, attending to each token's 8 nearest polygons (the gathered code path).
GROUNDED = GroundedConfig(**dataclasses.asdict(CFG), grounded_neighbors=8)
CONFIGS = {"paper": CFG, "grounded": GROUNDED}
# The lane-pull tests' random network: a seed whose untrained speed estimates leave enough moving tokens for
# the clearance check, and whose goal estimates leave several goals on lanes the initial lane does not lead
# to (so the checks have teeth; seeds 1, 2, 7 and 8 leave fewer).
PULL_SEED = 5
NORM = normalize.NormStats(jnp.array([0.0, 0.0, -0.7]), jnp.array([0.4, 0.4, 0.3]))


def _model(cfg: PaperConfig, seed: int = 0) -> PaperDenoiser:
  return (GroundedDenoiser if isinstance(cfg, GroundedConfig) else PaperDenoiser)(cfg, rngs=nnx.Rngs(seed))


def _norm(cfg: PaperConfig) -> normalize.NormStats:
  norm = NORM.with_heading(cfg.heading_state)
  if cfg.goal_offset:
    offsets = {"mean": [0.0, 0.0], "std": [0.2, 0.2]}
    norm = norm.with_offsets(offsets)
  return norm


def _batch(sids, a=16, p=128, config=None) -> datatypes.Scene:
  scenes = [scene_builder.load_scene(DATA / sid, config)[0] for sid in sids]
  stacked = datatypes.stack_scenes(scenes)
  return batches.crop_to_bucket(stacked, (a,), (p,))


def _to_jax(scene: datatypes.Scene) -> datatypes.Scene:
  return jax.tree_util.tree_map(jnp.asarray, scene)


def _pad(scene: datatypes.Scene, a: int, p: int) -> datatypes.Scene:
  """Adds padding rows (zeros, masked) up to a agents and p polygons."""
  d = scene.to_dict()
  da, dp = a - scene.num_agents, p - scene.num_polygons
  def pad(x, axes_amounts):
    widths = [(0, 0)] * x.ndim
    for ax, n in axes_amounts:
      widths[ax] = (0, n)
    return np.pad(x, widths)
  for k in datatypes.AGENT_FIELDS:
    d[k] = pad(d[k], [(1, da)])
  for k in datatypes.POLYGON_FIELDS:
    d[k] = pad(d[k], [(1, dp)])
  d["pl_edge"] = pad(d["pl_edge"], [(1, dp), (2, dp)])
  return datatypes.Scene.from_dict(d)


@pytest.fixture(scope="module", params=sorted(CONFIGS))
def model_fn(request):
  """The model as `(scene, x_t [B, A, 2, 3], beta, agent_id) -> (eps [B, A, 2, F], maps)`; with headings in
  the state, x_t gets two heading features made from its own (so padding and permutations carry over)."""
  cfg = CONFIGS[request.param]
  graphdef, params = nnx.split(_model(cfg))

  @jax.jit
  def apply(params, scene, x_t, beta, agent_id):
    alpha_bar = jnp.full(beta.shape, 0.5)
    if cfg.heading_state:
      x_t = jnp.concatenate([x_t, jnp.sin(3.0 * x_t[..., :2])], -1)
    return nnx.merge(graphdef, params)(scene, x_t, beta, alpha_bar, _norm(cfg), agent_id=agent_id)

  def fn(scene, x_t, beta, agent_id=None):
    return apply(params, _to_jax(scene), x_t, beta, agent_id)
  fn.state_dim = cfg.state_dim
  return fn


@pytest.fixture(scope="module")
def batch():
  return _batch(REAL_110[:2])


def _inputs(scene: datatypes.Scene, seed=0):
  b, a = scene.agent_valid.shape
  x_t = jax.random.normal(jax.random.key(seed), (b, a, 2, 3))
  return jnp.where(jnp.asarray(scene.agent_valid)[..., None, None], x_t, 0.0), jnp.full((b,), 0.02)


def test_shapes_and_padded_agents_get_zero(model_fn, batch):
  x_t, beta = _inputs(batch)
  eps, maps = model_fn(batch, x_t, beta)
  assert eps.shape == (2, 16, 2, model_fn.state_dim) and len(maps) == CFG.num_layers
  assert maps[0].shape == (2, CFG.heads, 32, 128)
  assert bool(jnp.isfinite(eps).all())
  assert float(jnp.abs(eps[~batch.agent_valid]).max()) == 0.0


def test_dropout_acts_in_training_only(batch):
  """With dropout on (the CPU default config's 0.1, here 0.3), a training call (a key) is random and
  reproducible per key; without a key the model is deterministic and differs from a training call."""
  model = _model(dataclasses.replace(GROUNDED, dropout=0.3))
  scene = _to_jax(batch)
  x_t, beta = _inputs(batch)
  x_t = jnp.concatenate([x_t, x_t[..., :2]], -1)
  call = jax.jit(lambda k: model(scene, x_t, beta, jnp.full(beta.shape, 0.5), _norm(GROUNDED), key=k)[0])
  plain = jax.jit(lambda: model(scene, x_t, beta, jnp.full(beta.shape, 0.5), _norm(GROUNDED))[0])
  k1, k2 = jax.random.split(jax.random.key(0))
  valid = np.asarray(batch.agent_valid)
  np.testing.assert_array_equal(call(k1), call(k1))
  np.testing.assert_array_equal(plain(), plain())
  assert np.abs(np.asarray(call(k1) - call(k2))[valid]).mean() > 1e-3
  assert np.abs(np.asarray(call(k1) - plain())[valid]).mean() > 1e-3


def test_padding_does_not_matter(model_fn, batch):
  x_t, beta = _inputs(batch)
  eps, _ = model_fn(batch, x_t, beta)
  bigger = _pad(batch, 24, 160)
  eps_big, _ = model_fn(bigger, jnp.pad(x_t, ((0, 0), (0, 8), (0, 0), (0, 0))), beta)
  valid = batch.agent_valid
  np.testing.assert_allclose(eps_big[:, :16][valid], eps[valid], atol=2e-5)


def test_permuting_agents_with_identities_and_polygons_does_not_matter(model_fn, batch):
  one = jax.tree_util.tree_map(lambda x: x[:1], batch)
  x_t, beta = _inputs(one)
  n, m = int(one.agent_valid.sum()), int(one.pl_valid.sum())
  rng = np.random.default_rng(0)
  pa = np.concatenate([rng.permutation(n), np.arange(n, one.num_agents)])
  pp = np.concatenate([rng.permutation(m), np.arange(m, one.num_polygons)])
  d = one.to_dict()
  for k in ("agent_state", "agent_type", "agent_valid"):
    d[k] = d[k][:, pa]
  for k in ("pl_xy", "pl_heading", "pl_type", "pl_intersection", "pl_valid", "pt_xy", "pt_heading", "pt_type",
            "pt_side", "pt_valid"):
    d[k] = d[k][:, pp]
  d["pl_edge"] = d["pl_edge"][:, pp][:, :, pp]
  permuted = datatypes.Scene.from_dict(d)
  ids = jnp.arange(one.num_agents)[None]
  eps, _ = model_fn(one, x_t, beta, ids)
  eps_p, _ = model_fn(permuted, x_t[:, pa], beta, ids[:, pa])
  np.testing.assert_allclose(eps_p, eps[:, pa], atol=2e-5)


def test_noise_scaled_speed_step(batch):
  """The grounded denoiser's speed moves from sqrt(alpha_bar) x_t by sqrt(1 - alpha_bar) times the head's
  output: with the head's last layer a constant c, x0's speed is sqrt(alpha_bar) x_t + sqrt(1 - alpha_bar) c
  at every noise level (a stopped agent stays stopped at low noise)."""
  scene = _to_jax(batch)
  x_t, _ = _inputs(batch)
  x_t = jnp.concatenate([x_t, x_t[..., :2]], -1)
  b = x_t.shape[0]
  model = _model(GROUNDED)
  model.speed_head[1].kernel[...] = jnp.zeros_like(model.speed_head[1].kernel[...])
  model.speed_head[1].bias[...] = jnp.full_like(model.speed_head[1].bias[...], 0.7)
  graphdef, params = nnx.split(model)
  valid = np.asarray(batch.agent_valid)
  for alpha_bar in (1.0 - 1e-4, 0.5, 0.01):
    ab = jnp.full((b,), alpha_bar)
    eps = jax.jit(lambda p, scene, x_t, ab: nnx.merge(graphdef, p)(scene, x_t, 1.0 - ab, ab, _norm(GROUNDED))[0])(
        params, scene, x_t, ab)
    sqrt_ab, sqrt_1m = np.sqrt(alpha_bar), np.sqrt(1.0 - alpha_bar)
    x0 = (x_t - sqrt_1m * eps) / sqrt_ab
    np.testing.assert_allclose(np.asarray(x0[..., 2])[valid], np.asarray(sqrt_ab * x_t[..., 2] + sqrt_1m * 0.7)[valid],
                               rtol=1e-3, atol=1e-4)


def _estimates_at_x_t(cfg: GroundedConfig) -> tuple:
  """(graphdef, params) of an untrained grounded denoiser whose position and heading heads' last layers are
  zeroed: its position and heading estimates are where x_t puts them, its speed estimates the network's."""
  model = _model(cfg, PULL_SEED)
  for layer in (model.pos_head[1], model.heading_head[1], model.frame_head):
    layer.kernel[...] = jnp.zeros_like(layer.kernel[...])
    layer.bias[...] = jnp.zeros_like(layer.bias[...])
  return nnx.split(model)


def test_lane_pull_puts_moving_tokens_across_onto_a_lane_their_heading_agrees_with(batch):
  """With `LanePull(across_m=d)` a moving road user's position estimate (speed estimate at least 1 m/s) is
  moved across a lane centreline segment its heading estimate agrees with (within 60 degrees) onto that
  segment's line, by at most d; stopped tokens, pedestrians, speeds and headings are untouched; with
  `clearance_m=c` each token either pulled or left, and no two tokens of one kind nearer than min(c, their
  distance without the pull); with `end_m=e` also back onto the centreline from at most e past its end.
  The same parameters and graph with and without it: the pull is the call's."""
  cfg = GROUNDED
  norm = _norm(cfg)
  scene = _to_jax(batch)
  b = batch.agent_valid.shape[0]
  x_t = normalize.normalized_state(scene, norm)          # the truth, on its lanes, as at the lowest noise
  # The position and heading heads' last layers zeroed: the untrained network's estimates are then where
  # x_t puts them (the truth, on its lanes), its speed estimates random (some tokens stopped).
  graphdef, params = _estimates_at_x_t(cfg)

  def variant(**fields):
    return LanePull(across_m=2.5, **fields)
  pull = variant()

  @functools.partial(jax.jit, static_argnums=2)   # compiled: eager, the network's operations run one by one
  def eps_of(params, x_t, lane_pull, ab):
    return nnx.merge(graphdef, params)(scene, x_t, jnp.full((b,), 1e-2), ab, norm, position_step=lane_pull)[0]

  def x0_of(lane_pull, alpha_bar, x_t=x_t):
    ab = jnp.full((b,), alpha_bar)
    eps = eps_of(params, x_t, lane_pull, ab)
    return (x_t - jnp.sqrt(1.0 - ab)[:, None, None, None] * eps) / jnp.sqrt(ab)[:, None, None, None]

  def metres(x0):
    return np.asarray(normalize.positions_to_metres(x0[..., :2], scene.frame_scale, norm))

  net, pulled = x0_of(None, 1.0 - 1e-4), x0_of(pull, 1.0 - 1e-4)
  valid = np.asarray(batch.agent_valid)
  np.testing.assert_allclose(np.asarray(pulled[..., 2:])[valid], np.asarray(net[..., 2:])[valid], atol=1e-5)
  move = metres(pulled) - metres(net)                                                   # [B, A, 2, 2] m
  dist = np.linalg.norm(move, axis=-1)
  mps = np.asarray(normalize.denormalize_state(net, scene.frame_scale, norm))[..., 2]
  heading = np.asarray(normalize.denormalize_heading(net))
  pedestrian = (np.asarray(batch.agent_type) == datatypes.PEDESTRIAN)[..., None]
  assert np.all(dist[valid[..., None] & ((mps < 1.0) | pedestrian)] < 1e-4) and np.all(dist <= 2.5 + 1e-3)
  lines = grounding.centerlines(scene)
  start, end = (np.asarray(x, np.float64) for x in (lines.start, lines.end))
  seg_ok = np.asarray(lines.valid, bool) & np.asarray(batch.lane_polygons)[..., None]   # lanes, not crosswalks
  moved = np.argwhere(dist > 1e-3)
  assert len(moved) >= 3                                                                # it has teeth
  for i, a, k in moved:
    u = end[i] - start[i]
    u = u / np.maximum(np.linalg.norm(u, axis=-1, keepdims=True), 1e-9)                # [P, S, 2]
    h = np.array([np.cos(heading[i, a, k]), np.sin(heading[i, a, k])])
    rel = metres(pulled)[i, a, k] - start[i]
    off_line = np.abs(u[..., 0] * rel[..., 1] - u[..., 1] * rel[..., 0])              # from each segment's line
    across = np.abs(np.sum(u * move[i, a, k], -1))                                      # the move along it
    ok = seg_ok[i] & (np.sum(u * h, -1) > 0.5) & (off_line < 2e-3) & (across < 2e-3)
    assert ok.any(), (i, a, k, move[i, a, k])

  # Clearance: a distance the pull brings about half the pairs it brings closer under.
  pair = (valid[:, :, None] & valid[:, None, :] & ~np.eye(valid.shape[1], dtype=bool))[..., None]   # [B, A, A, 1]
  gap = lambda xy: np.linalg.norm(xy[:, :, None] - xy[:, None], axis=-1)              # noqa: E731  [B, A, A, 2]
  closer = pair & (gap(metres(pulled)) < gap(metres(net)) - 1e-3)
  clearance = float(np.median(gap(metres(pulled))[closer]))
  kept = metres(x0_of(variant(clearance_m=clearance), 1.0 - 1e-4))
  left, pulled_too = (np.linalg.norm(kept - m, axis=-1) < 1e-3 for m in (metres(net), metres(pulled)))
  assert np.all((left | pulled_too)[valid]) and 0 < np.sum(pulled_too & ~left) < np.sum(dist > 1e-3)
  assert np.all(gap(kept)[pair[..., 0]] >= np.minimum(clearance, gap(metres(net))[pair[..., 0]]) - 1e-3)

  # Ends: with `end_m=e` a token past the end (or before the start) of the centreline it is pulled
  # to, by at most e along it, lands on the centreline itself (a segment, not only its line); no other moves.
  # The truth driven 40 m on along its headings puts tokens past the ends of these small maps' lanes.
  truth_m = np.asarray(scene.agent_state[..., :2])
  ahead = truth_m + 40.0 * np.stack([np.cos(scene.agent_state[..., 3]), np.sin(scene.agent_state[..., 3])], -1)
  x_ahead = x_t.at[..., :2].set(normalize.positions_from_metres(jnp.asarray(ahead), scene.frame_scale, norm))
  x_ahead = jnp.where(scene.agent_valid[..., None, None], x_ahead, 0.0)
  net, across_only, ended = (x0_of(lp, 1.0 - 1e-4, x_ahead) for lp in (None, pull, variant(end_m=50.0)))
  np.testing.assert_allclose(np.asarray(ended[..., 2:])[valid], np.asarray(net[..., 2:])[valid], atol=1e-5)
  mps = np.asarray(normalize.denormalize_state(net, scene.frame_scale, norm))[..., 2]
  heading = np.asarray(normalize.denormalize_heading(net))
  end_move = metres(ended) - metres(net)
  back = np.linalg.norm(end_move - (metres(across_only) - metres(net)), axis=-1) > 1e-3   # not across alone
  assert 2 <= back.sum() and not np.any(back & ((mps < 1.0) | pedestrian | ~valid[..., None]))
  assert np.all(np.linalg.norm(end_move, axis=-1) <= np.hypot(2.5, 50.0) + 1e-3)
  for i, a, k in np.argwhere(back):
    u = end[i] - start[i]
    frac = np.clip(np.sum((metres(ended)[i, a, k] - start[i]) * u, -1) / np.maximum(np.sum(u * u, -1), 1e-12), 0, 1)
    off_segment = np.linalg.norm(start[i] + frac[..., None] * u - metres(ended)[i, a, k], axis=-1)   # [P, S]
    h = np.array([np.cos(heading[i, a, k]), np.sin(heading[i, a, k])])
    agrees = np.sum(u * h, -1) > 0.5 * np.linalg.norm(u, axis=-1)
    assert (seg_ok[i] & agrees & (off_segment < 2e-3)).any(), (i, a, k, end_move[i, a, k])


def test_fully_masked_rows_give_zeros_not_nan(model_fn, batch):
  probs = layers.masked_softmax(jnp.array([[1.0, 2.0], [3.0, 4.0]]), jnp.array([[True, False], [False, False]]))
  np.testing.assert_array_equal(probs, [[1.0, 0.0], [0.0, 0.0]])
  no_map = batch.replace(pl_valid=np.zeros_like(batch.pl_valid), pt_valid=np.zeros_like(batch.pt_valid),
                         pl_edge=np.zeros_like(batch.pl_edge))
  x_t, beta = _inputs(batch)
  eps, maps = model_fn(no_map, x_t, beta)
  assert bool(jnp.isfinite(eps).all()) and float(jnp.abs(maps[0]).max()) == 0.0
  no_agents = batch.replace(agent_valid=np.zeros_like(batch.agent_valid))
  eps, _ = model_fn(no_agents, x_t, beta)
  assert float(jnp.abs(eps).max()) == 0.0


def test_attention_entropy_on_a_hand_made_map():
  agent_valid = jnp.array([[True, False]])           # 2 agents -> 4 tokens; tokens 2, 3 are padding
  pl_valid = jnp.array([[True, True, True, True, False, False]])
  peaked = jnp.zeros((1, 1, 4, 6)).at[:, :, :, 0].set(1.0)
  uniform = jnp.zeros((1, 1, 4, 6)).at[:, :, :, :4].set(0.25)
  # Padded polygons and padded agents' tokens must not count.
  uniform = uniform.at[:, :, :, 4:].set(9.0).at[:, :, 2:, :].set(5.0)
  assert float(hl_objective.attention_entropy([peaked], agent_valid, pl_valid)) == pytest.approx(0.0, abs=1e-5)
  # |w| / ||w||_2 = 0.5 for 4 equal weights: -4 * 0.5 log 0.5 / 4 polygons = 0.5 log 2.
  expected = 0.5 * np.log(2.0)
  assert float(hl_objective.attention_entropy([uniform], agent_valid, pl_valid)) == pytest.approx(expected, rel=1e-4)
  assert float(hl_objective.attention_entropy([uniform, peaked], agent_valid, pl_valid)) == pytest.approx(expected, rel=1e-4)
  negative = uniform.at[:, :, :2, 1].set(-0.25)       # differential weights can be negative
  assert float(hl_objective.attention_entropy([negative], agent_valid, pl_valid)) == pytest.approx(expected, rel=1e-4)


@pytest.mark.parametrize("goal_offset,heading", [(False, False), (True, False), (True, True)])
def test_state_normalisation_round_trip(batch, goal_offset, heading):
  scenes = _to_jax(batch)
  stats = normalize.offset_stats(batch.agent_state, batch.agent_valid, batch.frame_scale)
  norm = NORM.with_offsets(stats) if goal_offset else NORM
  norm = norm.with_heading(heading)
  again = normalize.NormStats.from_json(norm.to_json())
  assert (again.heading, again.goal_offset) == (heading, goal_offset)
  x = normalize.normalized_state(scenes, norm)
  assert x.shape[-1] == norm.state_dim == (5 if heading else 3)
  back = normalize.denormalize_state(x, batch.frame_scale, norm)
  valid = batch.agent_valid
  np.testing.assert_allclose(back[valid], batch.agent_state[valid][..., :3], atol=1e-3)
  if heading:  # unit vectors whose angle is the heading
    np.testing.assert_allclose(np.linalg.norm(np.asarray(x[..., 3:5])[valid], axis=-1), 1.0, atol=1e-5)
    turn = np.asarray(normalize.denormalize_heading(x))[valid] - batch.agent_state[valid][..., 3]
    np.testing.assert_allclose(np.angle(np.exp(1j * turn)), 0.0, atol=1e-5)
  if goal_offset:  # the goal token holds the z-normalised offset from the initial position
    offset = batch.agent_state[..., 1, :2] - batch.agent_state[..., 0, :2]
    offset = offset / batch.frame_scale[:, None, None]
    np.testing.assert_allclose(np.asarray(x[..., 1, :2])[valid],
                               ((offset - norm.offset_mean) / norm.offset_std)[valid], atol=1e-4)
    np.testing.assert_allclose(np.asarray(x[..., 1, :2])[valid].std(0), 1.0, atol=1e-3)   # unit variance


def test_relation_features_on_a_straight_lane():
  """A lane along +x at y = 0 seen from (5, 3): 3 m to the right of the token, along 0, across -3."""
  k = 30
  pt_xy = np.zeros((1, 2, k, 2), np.float32)
  pt_xy[0, 0, 20:] = np.stack([np.linspace(-10, 10, 10), np.zeros(10)], -1)    # polygon 0's centreline
  pt_side = np.repeat(np.arange(3), 10)[None, None].repeat(2, 1)
  scene = datatypes.Scene.zeros(1, 2, k, batch_shape=(1,)).replace(
      pt_xy=pt_xy, pt_side=pt_side, pt_valid=np.array([[True], [False]])[None].repeat(k, -1),
      pl_valid=np.array([[True, False]]))
  feats, dist, arc = grounding.relation_features(jnp.array([[[5.0, 3.0], [30.0, 0.0]]]), grounding.centerlines(scene))
  np.testing.assert_allclose(dist[0, :, 0], [3.0, 20.0], atol=1e-4)             # past the end: to the last point
  np.testing.assert_allclose(feats[0, 0, 0], [0.0, -0.3, 0.0, -0.3, 0.3, np.log1p(3.0), 1.0, 0.0], atol=1e-5)
  np.testing.assert_allclose(arc[0, :, 0], [15.0, 20.0], atol=1e-4)              # along the centreline from its start
  assert float(feats[0, 0, 1].max()) == 0.0 and float(dist[0, 0, 1]) > 1e3           # the padded polygon


def _lane_row() -> datatypes.Scene:
  """Lanes 0 -> 1 -> 2 along +x (20 m each, at y = 0), lane 3 beside lane 1 (y = 3.5, lane changes both
  ways), polygon 4 a crosswalk at x = 0."""
  k, p = 30, 5
  pt_xy = np.zeros((1, p, k, 2), np.float32)
  for i, x0 in enumerate((0.0, 20.0, 40.0)):
    pt_xy[0, i, 20:] = np.stack([np.linspace(x0, x0 + 20, 10), np.zeros(10)], -1)
  pt_xy[0, 3, 20:] = np.stack([np.linspace(20, 40, 10), np.full(10, 3.5)], -1)
  pt_xy[0, 4, 20:] = np.stack([np.zeros(10), np.linspace(-5, 5, 10)], -1)
  succ, left, right = (datatypes.EDGE_TYPES.index(n) for n in ("SUCC", "LEFT", "RIGHT"))
  edge = np.zeros((1, p, p), np.int8)
  edge[0, 0, 1] = edge[0, 1, 2] = succ
  edge[0, 1, 3], edge[0, 3, 1] = left, right
  pl_type = np.zeros((1, p), np.int32)
  pl_type[0, 4] = datatypes.POLYGON_TYPES.index("PEDESTRIAN")
  return datatypes.Scene.zeros(1, p, k, batch_shape=(1,)).replace(
      pt_xy=pt_xy, pt_side=np.repeat(np.arange(3), 10)[None, None].repeat(p, 1).astype(np.int32),
      pt_valid=np.ones((1, p, k), bool), pl_valid=np.ones((1, p), bool), pl_edge=edge, pl_type=pl_type)


def test_lane_routes_follow_successors_and_lane_changes_only():
  routes = np.asarray(grounding.lane_routes(_lane_row(), grounding.centerlines(_lane_row())))[0]
  inf = np.inf
  np.testing.assert_allclose(routes, [[0, 20, 40, 20, inf],      # 0 -> 3 through 1 and a lane change
                                      [inf, 0, 20, 0, inf],       # no way back to 0
                                      [inf, inf, 0, inf, inf],
                                      [inf, 0, 20, 0, inf],
                                      [inf, inf, inf, inf, 0]], atol=1e-4)   # the crosswalk: no lane graph


def test_route_features_say_how_far_along_the_lanes_the_goal_lies():
  """Agent 0 starts at x = 5 on lane 0 with its goal at x = 45 on lane 2, 40 m ahead: its goal token's
  pair with lane 2 and its initial token's pair with lane 0 both see a 40 m route. Agent 1 goes the
  other way, which the lane graph does not allow: no route. The crosswalk has none either."""
  row = _lane_row()
  scene = row
  model = _model(dataclasses.replace(GROUNDED, grounded_neighbors=0))
  lines = grounding.centerlines(scene)
  ctx = SimpleNamespace(routes=grounding.lane_routes(scene, lines))
  position = jnp.array([[[5.0, 0.0], [45.0, 0.0], [45.0, 0.0], [5.0, 0.0]]])          # [B, 2A, 2] m
  _, dist, arc = grounding.relation_features(position, lines)
  route = np.asarray(model._route_features(ctx, -dist, dist, arc))[0].reshape(2, 2, 5, 3)  # [A, 2, P, 3]
  np.testing.assert_allclose(route[0, 1, 2], [1.0, 4.0, np.log1p(40.0)], atol=1e-4)   # goal token, lane 2
  np.testing.assert_allclose(route[0, 0, 0], [1.0, 4.0, np.log1p(40.0)], atol=1e-4)   # initial token, lane 0
  np.testing.assert_allclose(route[1, 1, 0], [0.0, 0.0, 0.0])                          # backwards: no route
  np.testing.assert_allclose(route[1, 0, 2], [0.0, 0.0, 0.0])
  np.testing.assert_allclose(route[0, :, 4], 0.0)                                      # the crosswalk


@pytest.mark.parametrize("cfg, lane_pull", [(GROUNDED, None), (GROUNDED, LanePull(across_m=3.5))],
                         ids=["grounded", "lane_pull"])
def test_noise_draws_are_the_loss_of_the_repeated_batch(cfg, lane_pull):
  """M noise draws per scene (each map encoded once): the loss of the batch with each scene M times."""
  small = data_config.default_data_config()
  small.max_agents, small.max_polygons = 8, 48
  graphdef, params = nnx.split(_model(cfg))
  scene, sched = _to_jax(_batch(REAL_110[:2], 8, 48, small)), diffusion.linear_schedule(50)

  @functools.partial(jax.jit, static_argnums=2)
  def loss(params, scene, noise_draws):
    return hl_objective.hl_loss(nnx.merge(graphdef, params), scene, _norm(cfg), sched, jax.random.key(3), 0.1, 0.0,
                                train=False, loss_weighting="min_snr", t_sampling="importance",
                                noise_draws=noise_draws, lane_pull=lane_pull)

  drawn, metrics = loss(params, scene, 3)
  repeated, metrics_ref = loss(params, jax.tree_util.tree_map(lambda x: jnp.repeat(x, 3, axis=0), scene), 1)
  np.testing.assert_allclose(drawn, repeated, rtol=1e-5)
  np.testing.assert_allclose(metrics["entropy"], metrics_ref["entropy"], rtol=1e-5)
  with pytest.raises(ValueError, match="noise_draws=0"):
    loss(params, scene, 0)


@pytest.mark.parametrize("name", ["paper", "grounded"])   # the paper's denoiser and the default's
def test_a_tiny_model_overfits_a_few_scenes(name):
  small = data_config.default_data_config()
  small.max_agents, small.max_polygons = 8, 48
  batch = _batch(REAL_110, 8, 48, small)
  sched = diffusion.linear_schedule(50)
  cfg = CONFIGS[name]   # grounded: also the self-conditioned, staged loss (two passes, the second reading the first)
  weighting = "min_snr" if name == "grounded" else "eps"
  graphdef, params = nnx.split(_model(cfg, 1))
  tx = optax.adam(3e-3)
  opt = tx.init(params)
  scene, key = _to_jax(batch), jax.random.key(0)  # the same noise and steps every time: memorisable

  @jax.jit
  def step(params, opt, scene, sched):  # data as arguments: closed-over arrays get constant-folded
    def loss_fn(p):
      return hl_objective.hl_loss(nnx.merge(graphdef, p), scene, _norm(cfg), sched, key, 0.1, 0.0, train=False,
                                  loss_weighting=weighting)[1]["mse"]
    loss, g = jax.value_and_grad(loss_fn)(params)
    upd, opt = tx.update(g, opt, params)
    return optax.apply_updates(params, upd), opt, loss

  losses = []
  for _ in range(60):   # about 0.03 (paper) and 0.005 (grounded) of the first loss by then
    params, opt, loss = step(params, opt, scene, sched)
    losses.append(float(loss))
  assert losses[-1] < 0.1 * losses[0], (losses[0], losses[-1])


def test_packed_polygons_give_the_dense_encoder_and_loss():
  """An all-pairs map encoder over the batch's valid polygons and pairs packed into lists gives the same
  embeddings, loss and gradients as over the padded grids, on real maps of different sizes. Each half of
  the batch packs apart (what a batch sharded over two devices runs; its step: `sharded_step_check.py`)."""
  scene = _batch(REAL_110 + REAL_110[:1], 16, 96)
  keep = scene.pl_valid & (np.arange(96) < [[96], [40], [60], [20]])   # the first 40, 60, 20 polygons of three
  scene = dataclasses.replace(scene, pl_valid=keep, pt_valid=scene.pt_valid & keep[..., None],
                              pl_edge=np.where(keep[:, :, None] & keep[:, None, :], scene.pl_edge, 0))
  assert len(set(scene.pl_valid.sum(-1).tolist())) == 4      # four map sizes, padded to the largest
  packed = map_encoder.pack_polygons(scene, CFG.pl2pl_radius_m)
  n, e = packed.shape
  assert packed.shards == 1 and int(packed.polygon_valid.sum()) == int(keep.sum()) <= n < keep.size
  all_pairs = map_encoder.pack_polygons(scene, 1e9)
  assert 0 < int(packed.valid.sum()) <= e and int(packed.valid.sum()) <= int(all_pairs.valid.sum())
  assert int(all_pairs.valid.sum()) <= all_pairs.shape[1] < keep.size * 96
  halves = map_encoder.pack_polygons(scene, CFG.pl2pl_radius_m, shards=2)
  assert halves.shards == 2 and halves.polygon_valid.sum(-1).tolist() == keep.reshape(2, -1).sum(-1).tolist()
  assert halves.valid.sum() == packed.valid.sum()            # the same pairs, split by half
  assert halves.polygon.max() < 2 * 96                       # indices local to the half
  with pytest.raises(ValueError, match="3 shards do not divide a batch of 4"):
    map_encoder.pack_polygons(scene, CFG.pl2pl_radius_m, shards=3)
  graphdef, params = nnx.split(_model(CFG))
  sched = diffusion.linear_schedule(50)

  @jax.jit
  def run(params, scene, packed):
    model = nnx.merge(graphdef, params)
    ctx = model.map_encoder(scene, NORM.mean[:2], NORM.std[:2], packed=packed)
    loss = lambda p: hl_objective.hl_loss(nnx.merge(graphdef, p), scene, NORM, sched, jax.random.key(1),  # noqa: E731
                                          0.1, 0.0, train=False, packed=packed)[0]
    return ctx, jax.value_and_grad(loss)(params)

  ctx_ref, (loss_ref, grads_ref) = run(params, _to_jax(scene), None)
  for pack in (packed,):   # packed per device: tests/sharded_step_check.py
    ctx, (loss, grads) = run(params, _to_jax(scene), pack)
    np.testing.assert_allclose(ctx.polygons, ctx_ref.polygons, atol=2e-5)
    assert not np.asarray(ctx.polygons)[~keep].any()              # padded polygons stay zero
    np.testing.assert_allclose(ctx.summary, ctx_ref.summary, atol=2e-5)
    np.testing.assert_allclose(loss, loss_ref, rtol=1e-5)
    for g, g_ref in zip(jax.tree_util.tree_leaves(grads), jax.tree_util.tree_leaves(grads_ref)):
      np.testing.assert_allclose(g, g_ref, atol=1e-5 * (1.0 + float(np.abs(g_ref).max())))
  top_k = _model(dataclasses.replace(CFG, pl2pl_neighbors=8)).map_encoder
  assert top_k.pack(scene) is None
  with pytest.raises(ValueError, match="all-pairs map encoder"):
    top_k(_to_jax(scene), NORM.mean[:2], NORM.std[:2], packed=packed)


def test_the_input_side_computed_apart_gives_the_same_encoding():
  """A one-layer encoder's input side (`input_side`, what training computes once per scene when it is
  frozen) given back to the encoder gives its output, over padded grids and packed polygons, on real
  maps of different sizes; computed as a batch of one-polygon maps it is the same per polygon; an
  encoder whose input side is not a constant of each polygon refuses it."""
  scene = _batch(REAL_110, 16, 96)
  keep = scene.pl_valid & (np.arange(96) < [[96], [40], [60]])
  scene = _to_jax(dataclasses.replace(scene, pl_valid=keep, pt_valid=scene.pt_valid & keep[..., None],
                                      pl_edge=np.where(keep[:, :, None] & keep[:, None, :], scene.pl_edge, 0)))
  for cfg in (GROUNDED,):   # the default's: metric, relative point inputs
    encoder = _model(cfg).map_encoder
    assert encoder.input_side_is_constant
    graphdef, params = nnx.split(encoder)
    # Compiled: eager, the encoder's operations run one by one.
    input_side = jax.jit(lambda p, s: nnx.merge(graphdef, p).input_side(s, NORM.mean[:2], NORM.std[:2]))
    encode = jax.jit(lambda p, s, pk, inputs: nnx.merge(graphdef, p)(s, NORM.mean[:2], NORM.std[:2], packed=pk,
                                                                     inputs=inputs))
    inputs = input_side(params, scene)
    assert inputs.embedding.shape == inputs.attended.shape == (3, 96, cfg.dim)
    assert not np.asarray(inputs.attended)[~keep].any() and np.asarray(inputs.attended)[keep].any()
    packed = encoder.pack(scene)
    for pk in (None, packed):
      ref = encode(params, scene, pk, None)
      out = encode(params, scene, pk, inputs)
      np.testing.assert_allclose(out.polygons, ref.polygons, atol=2e-5)
      np.testing.assert_allclose(out.summary, ref.summary, atol=2e-5)
    # One polygon per row, as `map_input_cache` computes it: the same rows.
    rows = {f: getattr(scene, f)[keep][:, None] for f in ("pt_xy", "pt_heading", "pt_type", "pt_side", "pt_valid",
                                                            "pl_xy", "pl_heading", "pl_type", "pl_intersection",
                                                            "pl_valid")}
    alone = encoder.input_side(SimpleNamespace(**rows, frame_scale=jnp.broadcast_to(scene.frame_scale[:, None],
                                                                                    keep.shape)[keep]),
                               NORM.mean[:2], NORM.std[:2])
    np.testing.assert_allclose(alone.attended[:, 0], np.asarray(inputs.attended)[keep], atol=2e-5)
  two_layers = _model(dataclasses.replace(CFG, map_layers=2)).map_encoder
  assert not two_layers.input_side_is_constant
  with pytest.raises(ValueError, match="one-layer encoder"):
    two_layers(scene, NORM.mean[:2], NORM.std[:2], inputs=inputs)
  with pytest.raises(ValueError, match="not a constant"):
    two_layers.input_side(scene, NORM.mean[:2], NORM.std[:2])


def test_fourier_tables_give_the_exact_map_encoding_to_interpolation_error():
  """`fourier_tables`: the paper's encoder (normalised inputs) with its point, polygon and relation
  embeddings interpolated from tables gives the exact encoder's polygons and summary on real maps to a
  small tolerance, packed (all pairs) or with each polygon's nearest; the metric encoder's point and
  polygon positions (periods from 1 m) stay exact."""
  scene = _batch(REAL_110, 16, 96)
  stats = (NORM.mean[:2], NORM.std[:2])
  for neighbors in (0, 8):
    kwargs = dict(dim=16, heads=2, num_layers=1, num_freq_bands=4, num_latents=2, dropout_rate=0.0,
                  pl2pl_radius_m=150.0, pl2pl_neighbors=neighbors)
    tables = map_encoder.MapEncoder(**kwargs, fourier_tables=256, rngs=nnx.Rngs(0))   # 512 rows and more
    exact = map_encoder.MapEncoder(**kwargs, rngs=nnx.Rngs(0))
    packed = tables.pack(scene)

    def encode(module):   # compiled: eager, the encoder's operations run one by one
      graphdef, params = nnx.split(module)
      return jax.jit(lambda p, s, pk: nnx.merge(graphdef, p)(s, *stats, packed=pk))(params, _to_jax(scene), packed)
    out, ref = encode(tables), encode(exact)
    gap = np.abs(np.asarray(out.polygons - ref.polygons))
    assert 1e-6 < gap.max() < 2e-2 and np.abs(np.asarray(ref.polygons)).max() > 1.0, (neighbors, gap.max())
    np.testing.assert_allclose(out.summary, ref.summary, atol=2e-3)
    assert not np.asarray(out.polygons)[~scene.pl_valid].any()
  metric = map_encoder.MapEncoder(**kwargs, input_mode="metric", fourier_tables=256, rngs=nnx.Rngs(0))
  assert metric.pt_input.table_size == metric.pl_input.table_size == 0 and metric.r_pt2pl.table_size == 256


def test_packed_lists_are_padded_to_few_lengths():
  counts = range(0, 70_000, 7)
  sizes = [map_encoder.bucket_length(n, 1024) for n in counts]
  assert all(s >= max(n, 1024) and (n <= 1024 or s <= 1.25 * n) for n, s in zip(counts, sizes))
  assert len(set(sizes)) <= 4 * 7 + 1   # four lengths per doubling from 1024 to 70k


def test_self_conditioning_reads_the_previous_estimate_where_flagged_only(batch):
  """Self-conditioning (the grounded denoiser): the previous x0 estimate changes the output only for the scenes flagged in
  `has_prev`, each scene as if alone; padding agents and polygons still does not matter."""
  cfg = GROUNDED
  graphdef, params = nnx.split(_model(cfg))

  @jax.jit
  def apply(params, scene, x_t, x0_prev, has_prev):
    beta = jnp.full(x_t.shape[:1], 0.02)
    return nnx.merge(graphdef, params)(scene, x_t, beta, jnp.full(beta.shape, 0.3), _norm(cfg),
                                       x0_prev=x0_prev, has_prev=has_prev)[0]

  scene = _to_jax(batch)
  x_t = jax.random.normal(jax.random.key(0), (2, 16, 2, cfg.state_dim))
  x0_prev = jax.random.normal(jax.random.key(1), x_t.shape)
  valid = np.asarray(batch.agent_valid)
  none = apply(params, scene, x_t, x0_prev, jnp.array([False, False]))
  both = apply(params, scene, x_t, x0_prev, jnp.array([True, True]))
  mixed = apply(params, scene, x_t, x0_prev, jnp.array([True, False]))
  np.testing.assert_allclose(mixed[0][valid[0]], both[0][valid[0]], atol=2e-5)
  np.testing.assert_allclose(mixed[1][valid[1]], none[1][valid[1]], atol=2e-5)
  assert np.abs(np.asarray(both - none)[valid]).mean() > 1e-2
  bigger = _to_jax(_pad(batch, 24, 160))
  pad = lambda x: jnp.pad(x, ((0, 0), (0, 8), (0, 0), (0, 0)))  # noqa: E731
  both_big = apply(params, bigger, pad(x_t), pad(x0_prev), jnp.array([True, True]))
  np.testing.assert_allclose(both_big[:, :16][valid], both[valid], atol=2e-5)


def test_agent_frame_steps_go_along_and_across_the_agents_heading(batch):
  """The grounded denoiser's agent frame: an offset of (1, 0) from the agent-frame head moves both of an
  agent's tokens 10 m along the heading estimate of its initial token, (0, 1) 10 m to its left, whatever the
  agent's heading; the same offset from the position head goes along the scene's x."""
  scene = _to_jax(batch)
  x_t, _ = _inputs(batch)
  b = x_t.shape[0]
  angle = jax.random.uniform(jax.random.key(3), x_t.shape[:3], minval=-np.pi, maxval=np.pi)
  x_t = jnp.concatenate([x_t, jnp.cos(angle)[..., None], jnp.sin(angle)[..., None]], -1)
  ab = jnp.full((b,), 1.0 - 1e-4)
  sqrt_ab, sqrt_1m = jnp.sqrt(ab)[:, None, None, None], jnp.sqrt(1.0 - ab)[:, None, None, None]
  valid = np.asarray(batch.agent_valid)
  norm = _norm(GROUNDED)

  @functools.partial(jax.jit, static_argnums=0)
  def eps_of(graphdef, params, scene, x_t, ab):
    return nnx.merge(graphdef, params)(scene, x_t, jnp.full((b,), 1e-4), ab, norm)[0]

  def step_m(head_name, offset):  # x0 - sqrt(alpha_bar) x_t in metres with one head's offset fixed
    model = _model(GROUNDED)   # the per-layer updates and the agent-frame head start at zero
    model.pos_head[1].kernel[...] = 0.0
    head = model.frame_head if head_name == "frame" else model.pos_head[1]
    head.bias[...] = jnp.tile(jnp.asarray(offset, jnp.float32), 2)
    eps = eps_of(*nnx.split(model), scene, x_t, ab)
    x0 = (x_t - sqrt_1m * eps) / sqrt_ab
    metres = lambda xy: normalize.positions_to_metres(xy, scene.frame_scale, norm)  # noqa: E731
    return np.asarray(metres(x0[..., :2]) - metres(sqrt_ab * x_t[..., :2]))[valid]   # [N, 2 tokens, 2]

  heading = np.asarray(angle[:, :, :1])[valid]                  # [N, 1]: the initial token's, for both tokens
  along = np.stack([np.cos(heading), np.sin(heading)], -1)     # [N, 1, 2]
  left = np.stack([-np.sin(heading), np.cos(heading)], -1)
  np.testing.assert_allclose(step_m("frame", (1.0, 0.0)), 10.0 * np.broadcast_to(along, (len(heading), 2, 2)), atol=2e-3)
  np.testing.assert_allclose(step_m("frame", (0.0, 1.0)), 10.0 * np.broadcast_to(left, (len(heading), 2, 2)), atol=2e-3)
  np.testing.assert_allclose(step_m("position", (1.0, 0.0)), np.broadcast_to([10.0, 0.0], (len(heading), 2, 2)),
                             atol=2e-3)


def test_per_token_noise_levels_and_clean_initial_states(batch):
  """A noise level per token time `[B, 2]`: equal levels give the per-scene result; a clean initial token
  (alpha_bar = 1, staged sampling's second stage) gets finite outputs whose x0 is its input exactly, and
  its goal's prediction depends on that input (the goal is denoised given the initial state)."""
  cfg = GROUNDED
  graphdef, params = nnx.split(_model(cfg))
  sched = diffusion.linear_schedule(50)

  @jax.jit
  def apply(params, scene, x_t, t):
    return nnx.merge(graphdef, params)(scene, x_t, sched.betas[t], sched.alpha_bars[t], _norm(cfg))[0]

  scene = _to_jax(batch)
  valid = np.asarray(batch.agent_valid)
  x_t = jax.random.normal(jax.random.key(0), (2, 16, 2, cfg.state_dim))
  per_scene = apply(params, scene, x_t, jnp.array([7, 30]))
  per_token = apply(params, scene, x_t, jnp.array([[7, 7], [30, 30]]))
  np.testing.assert_allclose(per_token[valid], per_scene[valid], atol=2e-5)
  t = jnp.array([[0, 20], [0, 20]])
  eps = apply(params, scene, x_t, t)
  assert np.isfinite(np.asarray(eps)).all()
  x0 = diffusion.x0_from_eps(sched, x_t, t[:, None, :], eps)
  np.testing.assert_allclose(np.asarray(x0)[:, :, 0][valid], np.asarray(x_t)[:, :, 0][valid], atol=1e-6)
  moved = apply(params, scene, x_t.at[:, :, 0, :2].add(0.5), t)
  assert np.abs(np.asarray(moved - eps)[:, :, 1][valid]).mean() > 1e-3


def test_staged_training_draws_each_stage_and_trains_its_tokens_only():
  """Staged noise (the grounded denoiser): joint draws are (t, t), initial ones (t, T) and goal ones (0, t), and
  only the tokens at t are trained; the staged loss of a tiny model is finite and has gradients."""
  t = jnp.array([5, 5, 5])
  steps, trained = hl_objective.staged_steps(t, jnp.array([0, 1, 2]), 50)
  np.testing.assert_array_equal(steps, [[5, 5], [5, 50], [0, 5]])
  np.testing.assert_array_equal(trained, [[True, True], [True, False], [False, True]])
  small = data_config.default_data_config()
  small.max_agents, small.max_polygons = 8, 48
  cfg = GROUNDED
  graphdef, params = nnx.split(_model(cfg))
  scene, sched = _to_jax(_batch(REAL_110[:2], 8, 48, small)), diffusion.linear_schedule(50)

  def loss(params, scene, sched):   # data as arguments: closed-over arrays get constant-folded
    return hl_objective.hl_loss(nnx.merge(graphdef, params), scene, _norm(cfg), sched, jax.random.key(3), 0.1,
                                0.0, loss_weighting="min_snr", t_sampling="importance", noise_draws=3)[0]

  value, grads = jax.jit(jax.value_and_grad(loss))(params, scene, sched)
  assert np.isfinite(float(value)) and float(value) > 0
  flat = jax.tree_util.tree_leaves(grads)
  assert all(np.isfinite(np.asarray(g)).all() for g in flat)
  assert sum(float(jnp.abs(g).sum()) for g in flat) > 0


def _agents_on_random_lanes(batch: datatypes.Scene, seed: int = 0) -> datatypes.Scene:
  """`batch` with every agent slot a moving vehicle whose initial state and goal lie on centreline points of
  two lanes drawn at random (headings along them, goals up to 2 m across): many goals on lanes their
  initial lane does not lead to."""
  rng = np.random.default_rng(seed)
  d = batch.to_dict()
  b, a = d["agent_valid"].shape
  centre = d["pt_valid"] & (d["pt_side"] == datatypes.CENTER) & np.asarray(batch.lane_polygons)[..., None]
  state = np.zeros((b, a, 2, 4), np.float32)
  for i in range(b):
    lane_pts = np.argwhere(centre[i, :, 1:] & centre[i, :, :-1])                      # (polygon, point) pairs
    for k, (j, n) in enumerate(lane_pts[rng.integers(len(lane_pts), size=2 * a)]):
      u = d["pt_xy"][i, j, n + 1] - d["pt_xy"][i, j, n]
      heading = np.arctan2(u[1], u[0])
      across = rng.uniform(-2.0, 2.0) * (k % 2) * np.array([-np.sin(heading), np.cos(heading)])
      state[i, k // 2, k % 2] = (*(d["pt_xy"][i, j, n] + across), 8.0, heading)
  d.update(agent_state=state, agent_valid=np.ones((b, a), bool), agent_type=np.zeros((b, a), d["agent_type"].dtype))
  return datatypes.Scene.from_dict(d)


def test_routed_lane_pull_puts_goals_on_lanes_their_initial_lane_leads_to(batch):
  """With `LanePull.route_m` (here the plain pull's reach) a goal estimate goes onto a lane the lane graph
  leads to within 6 s (successors and lane changes, at most 2 m backwards) from its agent's initial lane
  where the plain pull would put it on one it does not lead to; initial tokens, speeds and headings are as
  with the plain pull, and every goal that differs from the plain pull's is reachable (Table I's count).
  Same parameters with and without it."""
  cfg = GROUNDED
  plain_pull = LanePull(across_m=6.0, end_m=1e3)   # pulled onto a lane itself
  norm = _norm(cfg)
  placed = _agents_on_random_lanes(batch)
  scene = _to_jax(placed)
  b = placed.agent_valid.shape[0]
  x_t = normalize.normalized_state(scene, norm)
  # The position and heading heads' last layers zeroed: the estimates are where x_t puts them (on lanes).
  graphdef, params = _estimates_at_x_t(cfg)
  ab = jnp.full((b,), 1.0 - 1e-4)

  def x0_of(**fields):
    pull = dataclasses.replace(plain_pull, **fields)
    eps = nnx.merge(graphdef, params)(scene, x_t, jnp.full((b,), 1e-2), ab, norm, position_step=pull)[0]
    x0 = (x_t - jnp.sqrt(1.0 - ab)[:, None, None, None] * eps) / jnp.sqrt(ab)[:, None, None, None]
    return x0, np.asarray(normalize.positions_to_metres(x0[..., :2], scene.frame_scale, norm))

  (plain, plain_m), (routed, routed_m) = x0_of(), x0_of(route_m=6.0)
  np.testing.assert_allclose(np.asarray(routed[..., 2:]), np.asarray(plain[..., 2:]), atol=1e-5)
  np.testing.assert_allclose(routed_m[:, :, 0], plain_m[:, :, 0], atol=1e-4)

  speed = np.asarray(normalize.denormalize_speed(plain[..., 2:3], norm))              # [B, A, 2, 1] m/s

  def reachable(i, xy):   # [A, 2, 2] m -> [A]: the goal reachable along the lane graph (Table I's count)
    one = jax.tree_util.tree_map(lambda x: np.asarray(x)[i], placed)
    state = np.concatenate([xy, speed[i]], -1)
    return np.array([metrics.goal_reachability(state, one, np.arange(len(state)) == k)["reachable"] == 1
                     for k in range(len(state))])

  changed = np.linalg.norm(routed_m[:, :, 1] - plain_m[:, :, 1], axis=-1) > 1e-3      # [B, A]
  assert changed.sum() >= 3                                                           # it has teeth
  now, before = (np.stack([reachable(i, m[i]) for i in range(b)]) for m in (routed_m, plain_m))   # [B, A]
  assert np.all(now[changed])
  assert np.array_equal(now[~changed], before[~changed]) and now.sum() >= before.sum() + 3


def test_still_lane_pull_holds_still_road_users_within_reach_of_a_lane(batch):
  """With `LanePull.still_m=s` a still road user's position estimate (speed estimate under 1 m/s) more than
  s from its nearest lane centreline (any direction; not crosswalks) moves straight towards that nearest
  point, to s from it; every other token is where the pull without it puts it, speeds and headings are
  untouched, and the training objective's pull is the one without it."""
  cfg = GROUNDED
  pull, held = LanePull(across_m=2.5), LanePull(across_m=2.5, still_m=3.0)
  assert held.for_objective() == pull
  norm = _norm(cfg)
  placed = _agents_on_random_lanes(batch, seed=1)
  d = placed.to_dict()
  rng = np.random.default_rng(2)
  b, a = d["agent_valid"].shape
  angle, reach = rng.uniform(0, 2 * np.pi, (b, a, 2)), rng.uniform(0.0, 10.0, (b, a, 2))   # off the lanes
  d["agent_state"][..., :2] += reach[..., None] * np.stack([np.cos(angle), np.sin(angle)], -1)
  d["agent_state"][:, 1::2, :, 2] = 0.0                                                      # half still
  d["agent_type"][:, ::4] = datatypes.PEDESTRIAN
  placed = datatypes.Scene.from_dict(d)
  scene = _to_jax(placed)
  x_t = normalize.normalized_state(scene, norm)
  # The position and heading heads' last layers zeroed: the estimates are where x_t puts them.
  graphdef, params = _estimates_at_x_t(cfg)
  ab = jnp.full((b,), 1.0 - 1e-4)

  @functools.partial(jax.jit, static_argnums=0)
  def x0_of(lane_pull):
    eps = nnx.merge(graphdef, params)(scene, x_t, jnp.full((b,), 1e-2), ab, norm, position_step=lane_pull)[0]
    return (x_t - jnp.sqrt(1.0 - ab)[:, None, None, None] * eps) / jnp.sqrt(ab)[:, None, None, None]

  def metres(x0):
    return np.asarray(normalize.positions_to_metres(x0[..., :2], scene.frame_scale, norm), np.float64)

  net, plain, kept = x0_of(None), x0_of(pull), x0_of(held)
  np.testing.assert_allclose(np.asarray(kept[..., 2:]), np.asarray(net[..., 2:]), atol=1e-5)
  mps = np.asarray(normalize.denormalize_state(net, scene.frame_scale, norm))[..., 2]
  lines = grounding.centerlines(scene)
  start, end = (np.asarray(x, np.float64)[:, None, None] for x in (lines.start, lines.end))   # [B, 1, 1, P, S, 2]
  seg_ok = (np.asarray(lines.valid, bool) & np.asarray(placed.lane_polygons)[..., None])[:, None, None]
  p = metres(net)[..., None, None, :]                                                       # [B, A, 2, 1, 1, 2]
  u = end - start
  frac = np.clip(np.sum((p - start) * u, -1) / np.maximum(np.sum(u * u, -1), 1e-12), 0.0, 1.0)
  foot = start + frac[..., None] * u                                                        # [B, A, 2, P, S, 2]
  gap = np.where(seg_ok, np.linalg.norm(foot - p, axis=-1), np.inf).reshape(b, a, 2, -1)
  nearest = np.take_along_axis(foot.reshape(b, a, 2, -1, 2), np.argmin(gap, -1)[..., None, None], 3)[..., 0, :]
  far = gap.min(-1)                                                                         # [B, A, 2] m
  valid = np.asarray(placed.agent_valid)[..., None]
  road_user = (np.asarray(placed.agent_type) != datatypes.PEDESTRIAN)[..., None]
  should = valid & road_user & (mps < 1.0) & (far > 3.0 + 1e-2)
  assert should.sum() >= 3 and (valid & road_user & (mps < 1.0) & (far < 3.0 - 1e-2)).sum() >= 1   # teeth
  expected = metres(net) + (nearest - metres(net)) * (1.0 - 3.0 / np.maximum(far, 1e-9))[..., None]
  np.testing.assert_allclose(metres(kept)[should], expected[should], atol=2e-3)
  others = valid & ~should & (np.abs(far - 3.0) > 1e-2)
  np.testing.assert_allclose(metres(kept)[others], metres(plain)[others], atol=1e-4)
