"""The sampler: one compile, composable with jit and vmap, inpainting, lane headings, guidance lowers its cost."""

from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from tests.av2_samples import DATA, REAL_110
from tdiff_jax import cpu_products, datatypes, diffusion, geometry, guidance, sampling
from tdiff_jax.data import batches, scene_builder
from tdiff_jax.data.normalize import NormStats, denormalize_state
from tdiff_jax.models.grounded_denoiser import GroundedConfig, GroundedDenoiser
from tdiff_jax.models.paper_denoiser import PaperConfig, PaperDenoiser

# The default (grounded) denoiser; `test_the_paper_denoiser_samples_too` covers the paper's.
PAPER = PaperConfig(dim=32, heads=2, num_layers=1, num_freq_bands=4, num_latents=4, dropout=0.0,
                    pl2pl_neighbors=8, max_agents=64)
CFG = GroundedConfig(**dataclasses.asdict(PAPER), grounded_neighbors=8)
NORM_PAPER = NormStats(jnp.array([0.0, 0.0, -0.7]), jnp.array([0.3, 0.3, 0.3]))
NORM_OFFSETS = NORM_PAPER.with_offsets({"mean": [0.0, 0.0], "std": [0.15, 0.15]})
NORM = NORM_OFFSETS.with_heading()     # the default's: goal offsets and headings
SCHED = diffusion.linear_schedule(50)
OPTS = sampling.SamplerOptions(method="ddim", stride=5)


@pytest.fixture(scope="module")
def setup():
  scenes = [scene_builder.load_scene(DATA / sid)[0] for sid in REAL_110]
  stacked = datatypes.stack_scenes(scenes)
  scene = jax.tree_util.tree_map(jnp.asarray, batches.crop_to_bucket(stacked, (16,), (96,)))
  graphdef, params = nnx.split(GroundedDenoiser(CFG, rngs=nnx.Rngs(0)))
  return graphdef, params, scene


@pytest.fixture(scope="module")
def wider(setup):
  """The same scenes padded to the next buckets (32 agents, 128 polygons): another compile."""
  stacked = datatypes.stack_scenes([scene_builder.load_scene(DATA / sid)[0] for sid in REAL_110])
  return jax.tree_util.tree_map(jnp.asarray, batches.crop_to_bucket(stacked, (32,), (128,)))


def test_shapes_padding_and_determinism(setup):
  graphdef, params, scene = setup
  out = sampling.sample(graphdef, params, scene, NORM, SCHED, jax.random.key(0), OPTS)
  chex.assert_shape(out.state, (3, 16, 2, 3))
  chex.assert_shape(out.heading, (3, 16, 2))
  chex.assert_tree_all_finite(out)
  assert float(jnp.abs(out.state[~scene.agent_valid]).max()) == 0.0
  again = sampling.sample(graphdef, params, scene, NORM, SCHED, jax.random.key(0), OPTS)
  np.testing.assert_array_equal(out.state, again.state)
  np.testing.assert_allclose(out.city_xy[scene.agent_valid],
                             (out.state[..., :2] + scene.frame_origin[:, None, None])[scene.agent_valid], rtol=1e-6)


def test_negative_speeds_come_back_as_zero_and_marked(setup):
  graphdef, params, scene = setup
  norm = NORM.replace(mean=NORM.mean.at[2].set(-1.0))   # normalised speed 0 is 0 m/s: about half go below
  out = sampling.sample(graphdef, params, scene, norm, SCHED, jax.random.key(0), OPTS)
  raw = np.asarray(denormalize_state(out.normalized, scene.frame_scale, norm))[..., 2]   # the model's own
  valid = np.asarray(scene.agent_valid)[..., None]
  np.testing.assert_array_equal(out.negative_speed, valid & (raw < 0))
  assert out.negative_speed.sum() >= 4 and (out.state[..., 2] >= 0).all()
  np.testing.assert_allclose(out.state[..., 2], np.where(valid, np.maximum(raw, 0.0), 0.0), rtol=1e-6, atol=1e-6)


def test_the_paper_denoiser_samples_too(setup):
  _, _, scene = setup
  graphdef, params = nnx.split(PaperDenoiser(PAPER, rngs=nnx.Rngs(0)))
  out = sampling.sample(graphdef, params, scene, NORM_PAPER, SCHED, jax.random.key(0), OPTS)
  chex.assert_tree_all_finite(out)
  assert float(jnp.abs(out.state[~scene.agent_valid]).max()) == 0.0


def test_compiles_once_per_bucket_and_options(setup, wider, compiles):
  graphdef, params, scene = setup
  opts = sampling.SamplerOptions(method="ddim", stride=25)   # options of this test only: a fresh count
  before = compiles["jit(sample)"]
  for bucket in (scene, wider):
    for seed in range(2):  # new keys, new weights and conditioning values: no new compile
      shifted = bucket.replace(pl_xy=bucket.pl_xy + seed)
      sampling.sample(graphdef, params, shifted, NORM, SCHED, jax.random.key(seed), opts,
                      sampling.GuidanceParams(scale=0.5 + seed))
  assert compiles["jit(sample)"] - before == 2


def test_works_inside_jit_and_under_vmap(setup):
  graphdef, params, scene = setup
  keys = jax.random.split(jax.random.key(1), 2)
  caller = jax.jit(lambda p, k: sampling.sample(graphdef, p, scene, NORM, SCHED, k, OPTS).state.sum())
  assert np.isfinite(float(caller(params, keys[0])))
  many = jax.vmap(lambda k: sampling.sample(graphdef, params, scene, NORM, SCHED, k, OPTS).state)(keys)
  one = sampling.sample(graphdef, params, scene, NORM, SCHED, keys[1], OPTS).state
  np.testing.assert_allclose(many[1], one, atol=1e-4)


def test_inpainting_keeps_fixed_agents_exactly(setup):
  graphdef, params, scene = setup
  fixed = scene.agent_state[..., :3]
  # agents 0 and 1 fixed at the start, agent 0 also at the goal, agent 2 only at the goal (with goal
  # offsets, that goal is imposed relative to the sampled initial state)
  mask = jnp.zeros(scene.agent_valid.shape + (2,), bool).at[:, :2, 0].set(True).at[:, 0, 1].set(True)
  mask = mask.at[:, 2, 1].set(True)
  out = sampling.sample(graphdef, params, scene, NORM, SCHED, jax.random.key(2), OPTS,
                        fixed_state=fixed, fixed_mask=mask)
  keep = mask & scene.agent_valid[..., None]
  np.testing.assert_allclose(out.state[keep], fixed[keep], atol=2e-3)
  assert float(jnp.abs(out.state[~mask & scene.agent_valid[..., None]] - fixed[~mask & scene.agent_valid[..., None]]).max()) > 1.0


def test_few_step_solver_samples_inpaints_and_traces_once(setup, compiles):
  graphdef, params, scene = setup
  opts = sampling.SamplerOptions(method="dpmpp2m", solver_steps=6)
  assert opts.network_calls(SCHED.num_steps) == 6
  fixed = scene.agent_state[..., :3]
  mask = jnp.zeros(scene.agent_valid.shape + (2,), bool).at[:, 0].set(True)
  before = compiles["jit(sample)"]
  for seed in range(2):
    out = sampling.sample(graphdef, params, scene, NORM, SCHED, jax.random.key(seed), opts, None, fixed, mask)
    chex.assert_tree_all_finite(out)
    assert float(jnp.abs(out.state[~scene.agent_valid]).max()) == 0.0
    keep = mask & scene.agent_valid[..., None]
    np.testing.assert_allclose(out.state[keep], fixed[keep], atol=2e-3)
  assert compiles["jit(sample)"] - before == 1
  with pytest.raises(ValueError, match="solver_steps must be >= 2"):
    sampling.SamplerOptions(method="dpmpp2m", solver_steps=1)
  # Started at a stated noise level: other steps, so another sample from the same noise.
  late = sampling.SamplerOptions(method="dpmpp2m", solver_steps=6, solver_max_noise=0.5)  # T here: 1.6
  assert late.network_calls(SCHED.num_steps) == 6 and "from noise 0.5" in late.describe()
  other = sampling.sample(graphdef, params, scene, NORM, SCHED, jax.random.key(1), late, None, fixed, mask)
  assert float(jnp.abs(other.state - out.state)[scene.agent_valid].max()) > 1e-3
  with pytest.raises(ValueError, match="solver_max_noise"):
    sampling.SamplerOptions(method="dpmpp2m", solver_max_noise=-1.0)


def test_headings_come_from_lane_centrelines_only(setup):
  """A model without headings in its state (the paper's) gets the nearest lane centreline's."""
  _, _, scene = setup
  graphdef, params = nnx.split(PaperDenoiser(PAPER, rngs=nnx.Rngs(0)))
  out = sampling.sample(graphdef, params, scene, NORM_PAPER, SCHED, jax.random.key(3), OPTS)
  pts, heads, mask = (np.asarray(a) for a in geometry.centerline_points(scene))
  xy, h = np.asarray(out.state[..., :2]), np.asarray(out.heading)
  for b in range(3):
    lane_pts, lane_heads = pts[b][mask[b]], heads[b][mask[b]]
    for a in np.flatnonzero(np.asarray(scene.agent_valid[b])):
      for tok in range(2):
        nearest = np.argmin(((lane_pts - xy[b, a, tok]) ** 2).sum(-1))
        assert h[b, a, tok] == pytest.approx(lane_heads[nearest], abs=1e-5)
  cw = scene.pl_type == datatypes.POLYGON_TYPES.index("PEDESTRIAN")
  assert not bool((mask.reshape(3, scene.num_polygons, -1).any(-1) & np.asarray(cw)).any())


@pytest.mark.parametrize("mode", ["official", "paper"])
def test_guidance_lowers_the_cost_it_targets(setup, mode):
  graphdef, params, scene = setup
  key = jax.random.key(4)
  g = sampling.GuidanceParams(scale=1.0 if mode == "official" else 2.0, clearance_m=40.0)
  plain = sampling.sample(graphdef, params, scene, NORM, SCHED, key, OPTS, g)
  guided = sampling.sample(graphdef, params, scene, NORM, SCHED, key,
                           sampling.SamplerOptions(method="ddim", stride=5, costs=("clearance",), guidance=mode), g)
  before = float(guidance.clearance(plain.state, scene, 40.0))
  after = float(guidance.clearance(guided.state, scene, 40.0))
  assert before > 0 and after < 0.8 * before, (before, after)


def test_lane_offroad_and_custom_costs(setup):
  # Three costs that pull against each other, on the paper's denoiser: an untrained grounded denoiser
  # moves every agent by random offsets of ~10 m at every step, which hides what guidance does.
  _, _, scene = setup
  graphdef, params = nnx.split(PaperDenoiser(PAPER, rngs=nnx.Rngs(0)))
  key = jax.random.key(5)
  plain = sampling.sample(graphdef, params, scene, NORM_PAPER, SCHED, key, OPTS)
  opts = sampling.SamplerOptions(method="ddim", stride=5, costs=("lane", "offroad", "custom"))
  right_of_origin = lambda state, sc: jnp.mean(jax.nn.relu(-state[..., 0]))  # noqa: E731  (x >= 0 wanted)
  g = sampling.GuidanceParams(weights={"clearance": 0.0, "lane": 1.0, "offroad": 1.0, "custom": 1.0})
  guided = sampling.sample(graphdef, params, scene, NORM_PAPER, SCHED, key, opts, g, custom_cost=right_of_origin)
  for cost in (lambda s: guidance.lane_distance(s, scene), lambda s: guidance.offroad(s, scene),
               lambda s: right_of_origin(s, scene)):
    before, after = float(cost(plain.state)), float(cost(guided.state))
    assert before > 0 and after < 0.5 * before, (before, after)
  with pytest.raises(ValueError, match="unknown guidance costs"):
    sampling.SamplerOptions(costs=("teleport",))


def test_drivable_area_geometry():
  square = jnp.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
  # Two overlapping squares: inside is decided per polygon (a point in both is inside, not even).
  da = jnp.zeros((1, 3, 6, 2)).at[0, 0, :4].set(square).at[0, 1, :4].set(square + 5.0)
  valid = jnp.zeros((1, 3, 6), bool).at[0, :2, :4].set(True)
  scene = datatypes.Scene.zeros(1, 1, 3, 3, 6, batch_shape=(1,)).replace(da_xy=da, da_valid=valid)
  pts = jnp.array([[[2.0, 2.0], [7.0, 7.0], [12.0, 2.0], [-1.0, -1.0], [20.0, 7.0]]])
  for map_ in (scene, geometry.map_geometry(scene), geometry.map_geometry(scene, 8, 16)):
    np.testing.assert_array_equal(geometry.inside_drivable_area(pts, map_), [[True, True, False, False, False]])
    np.testing.assert_allclose(geometry.distance_to_drivable_boundary(pts, map_),
                               [[2.0, 2.0, 2.0, np.sqrt(2.0), 5.0]], atol=1e-4)


def test_compact_map_geometry_gives_the_same_costs(setup):
  """The sampler's flat lists of only the valid drivable-area edges and lane points (8x and more fewer
  entries on these maps) give the padded scene's inside test, distances, headings and guidance costs
  and their gradients, on the real AV2 maps, at points all over them."""
  _, _, scene = setup
  num_edges, num_points = geometry.compact_sizes(scene)
  assert num_edges < scene.da_valid[0].size and num_points < scene.pt_valid[0].size
  compact = geometry.map_geometry(scene, num_edges, num_points)
  chex.assert_shape(compact.edge_start, (3, num_edges, 2))
  xy = jax.random.uniform(jax.random.key(0), (3, 16, 2, 2), minval=-120.0, maxval=120.0)
  for fn in (geometry.inside_drivable_area, geometry.distance_to_drivable_boundary, geometry.lane_headings):
    np.testing.assert_array_equal(fn(xy, compact), fn(xy, scene))
  assert 0.05 < float(geometry.inside_drivable_area(xy, scene).mean()) < 0.95
  state = jnp.concatenate([xy, jnp.full(xy.shape[:-1] + (1,), 5.0)], -1)
  for cost in (guidance.lane_distance, guidance.offroad, guidance.box_clearance):
    value, grad = jax.value_and_grad(cost)(state, scene)
    value_c, grad_c = jax.value_and_grad(lambda s: cost(s, scene, map_geometry=compact))(state)
    np.testing.assert_allclose(value_c, value, rtol=1e-6)
    np.testing.assert_allclose(grad_c, grad, atol=1e-6)


def test_map_queries_equal_a_point_by_point_computation_on_real_maps(setup):
  """The guidance's map queries (computed on x and y apart, for speed) against a plain numpy computation,
  one point at a time, on the real AV2 maps: distance to the drivable area's edge, nearest lane's
  heading, the lane cost."""
  _, _, scene = setup
  geom = geometry.map_geometry(scene, *geometry.compact_sizes(scene))
  num_agents = scene.agent_valid.shape[1]
  xy = jax.random.uniform(jax.random.key(1), (3, num_agents, 2, 2), minval=-120.0, maxval=120.0)
  dist, heads = (np.asarray(f(xy, geom)) for f in (geometry.distance_to_drivable_boundary, geometry.lane_headings))
  state = jnp.concatenate([xy, jnp.full(xy.shape[:-1] + (1,), 5.0)], -1)
  lane_cost = float(guidance.lane_distance(state, scene, map_geometry=geom))
  start, end, lane_xy = (np.asarray(a, np.float64) for a in (geom.edge_start, geom.edge_end, geom.lane_xy))
  edge_valid, lane_valid = np.asarray(geom.edge_valid), np.asarray(geom.lane_valid)
  road_users = np.asarray(scene.road_users)
  excess = []
  for b in range(3):
    s, seg = start[b][edge_valid[b]], (end[b] - start[b])[edge_valid[b]]
    pts, pts_heading = lane_xy[b][lane_valid[b]], np.asarray(geom.lane_heading)[b][lane_valid[b]]
    for a in range(num_agents):
      for tok in range(2):
        q = np.asarray(xy[b, a, tok], np.float64)
        t = np.clip(((q - s) * seg).sum(-1) / np.maximum((seg ** 2).sum(-1), 1e-9), 0.0, 1.0)
        assert dist[b, a, tok] == pytest.approx(np.linalg.norm(s + t[:, None] * seg - q, axis=-1).min(), abs=1e-3)
        d = np.linalg.norm(pts - q, axis=-1)
        assert heads[b, a, tok] == pytest.approx(pts_heading[np.argmin(d)], abs=1e-6)
        soft = -(np.log(np.exp(-10.0 * (d - d.min())).sum()) - 10.0 * d.min()) / 10.0
        if road_users[b, a]:
          excess.append(max(soft - 2.0, 0.0))
  assert lane_cost == pytest.approx(np.mean(excess), rel=1e-4)


def test_box_clearance_separates_boxes_not_centres():
  """Cars 3 m apart nose to tail on one lane overlap (4 m boxes); cars 3.5 m apart in neighbouring lanes
  do not, although their centres are closer than a 4 m threshold; the gradient pushes along the lane."""
  k = 10
  pt_xy = jnp.zeros((1, 1, 3 * k, 2)).at[0, 0, 2 * k:].set(jnp.stack([jnp.linspace(-50, 50, k), jnp.zeros(k)], -1))
  side = jnp.repeat(jnp.arange(3), k)[None, None]
  lane = dict(pl_valid=jnp.ones((1, 1), bool), pl_type=jnp.zeros((1, 1), jnp.int32), pt_xy=pt_xy,
              pt_heading=jnp.zeros((1, 1, 3 * k)), pt_side=side, pt_valid=jnp.ones((1, 1, 3 * k), bool))
  car = datatypes.AGENT_TYPES.index("vehicle")
  scene = datatypes.Scene.zeros(2, 1, 3 * k, batch_shape=(1,)).replace(
      agent_type=jnp.full((1, 2), car), agent_valid=jnp.ones((1, 2), bool), **lane)
  def state(dx, dy):   # two cars, both tokens alike
    xy = jnp.array([[0.0, 0.0], [dx, dy]])
    return jnp.concatenate([jnp.broadcast_to(xy[None, :, None], (1, 2, 2, 2)), jnp.zeros((1, 2, 2, 1))], -1)
  nose_to_tail = float(guidance.box_clearance(state(3.0, 0.0), scene, 0.0))
  np.testing.assert_allclose(nose_to_tail, 1.0, atol=1e-5)                            # 4 m - 3 m
  assert float(guidance.box_clearance(state(0.0, 3.5), scene, 0.0)) == 0.0            # neighbouring lanes
  assert float(guidance.clearance(state(3.0, 0.0), scene, 2.0)) == 0.0                 # the centre test misses it
  grad = jax.grad(lambda s: guidance.box_clearance(s, scene, 0.0))(state(3.0, 0.5))
  assert float(grad[0, 1, 0, 0]) < 0 and abs(float(grad[0, 1, 0, 1])) < 1e-6          # moves the second car ahead


def test_goal_offsets_must_match_the_normalisation(setup):
  graphdef, params, scene = setup
  with pytest.raises(ValueError, match="goal offsets"):
    sampling.sample(graphdef, params, scene, NORM_PAPER, SCHED, jax.random.key(0), OPTS)


def test_official_guidance_of_goals_leaves_initial_states_with_goal_offsets():
  """With goal offsets the goal's position depends on the initial state's; the official guidance step is
  taken on absolute positions, so a cost on the goals moves the goals only (a stand-in denoiser that
  treats every entry alone makes the unguided initial states the reference)."""
  sched = diffusion.linear_schedule(20)
  scene = datatypes.Scene.zeros(4, 1, 30, batch_shape=(2,)).replace(
      agent_valid=np.array([[True, True, True, False], [True, True, False, False]]),
      frame_scale=np.full((2,), 125.0, np.float32))
  scene = jax.tree_util.tree_map(jnp.asarray, scene)
  denoise = lambda x, t: 0.3 * x  # noqa: E731
  goal_east = lambda state, sc: jnp.mean(jax.nn.relu(60.0 - state[..., 1, 0]))  # noqa: E731  (goals at x >= 60 m)
  g = sampling.GuidanceParams(weights={"clearance": 0.0, "lane": 0.0, "offroad": 0.0, "custom": 1.0})
  key = jax.random.key(3)
  for norm in (NORM_PAPER, NORM):
    run = lambda costs: sampling.sample_with(  # noqa: E731, B023
        denoise, scene, norm, sched, key, sampling.SamplerOptions(method="ddim", stride=2, clip_x0=None, costs=costs),
        g, custom_cost=goal_east)
    plain, guided = run(()), run(("custom",))
    valid = np.asarray(scene.agent_valid)
    np.testing.assert_allclose(guided.state[..., 0, :][valid], plain.state[..., 0, :][valid], rtol=1e-5, atol=1e-4)
    before, after = float(goal_east(plain.state, scene)), float(goal_east(guided.state, scene))
    assert before > 10.0 and after < 0.5 * before, (norm.goal_offset, before, after)


def test_heading_state_samples_headings_and_inpaints_them(setup):
  """With headings in the state, the sample's headings are the model's (cos, sin), fixed headings come
  back exactly, fixed tokens without a heading get the model's, and the statistics must match."""
  _, _, scene = setup
  graphdef, params = setup[:2]
  norm = NORM
  fixed = scene.agent_state                                                             # x, y, speed, heading
  mask = jnp.zeros(scene.agent_valid.shape + (2,), bool).at[:, :2, 0].set(True).at[:, 0, 1].set(True)
  out = sampling.sample(graphdef, params, scene, norm, SCHED, jax.random.key(2), OPTS, fixed_state=fixed,
                        fixed_mask=mask)
  chex.assert_shape(out.normalized, (3, 16, 2, 5))
  chex.assert_shape(out.state, (3, 16, 2, 3))
  chex.assert_tree_all_finite(out)
  valid = np.asarray(scene.agent_valid)[..., None] & np.ones((1, 1, 2), bool)
  keep = np.asarray(mask) & valid
  np.testing.assert_allclose(out.state[keep], fixed[..., :3][keep], atol=2e-3)
  turn = np.asarray(out.heading - fixed[..., 3])
  np.testing.assert_allclose(np.angle(np.exp(1j * turn))[keep], 0.0, atol=1e-4)
  free = valid & ~np.asarray(mask)
  model_heading = np.arctan2(np.asarray(out.normalized[..., 4]), np.asarray(out.normalized[..., 3]))
  np.testing.assert_allclose(np.asarray(out.heading)[free], model_heading[free], atol=1e-5)
  assert float(jnp.abs(out.heading[~scene.agent_valid]).max()) == 0.0
  # three features fix position and speed only: the fixed tokens' headings are the model's
  three = sampling.sample(graphdef, params, scene, norm, SCHED, jax.random.key(2), OPTS, fixed_state=fixed[..., :3],
                          fixed_mask=mask)
  np.testing.assert_allclose(three.state[keep], fixed[..., :3][keep], atol=2e-3)
  model_heading = np.arctan2(np.asarray(three.normalized[..., 4]), np.asarray(three.normalized[..., 3]))
  np.testing.assert_allclose(np.asarray(three.heading)[valid], model_heading[valid], atol=1e-5)
  with pytest.raises(ValueError, match="heading"):
    sampling.sample(graphdef, params, scene, NORM_OFFSETS, SCHED, jax.random.key(0), OPTS)


def test_maps_encoded_per_scene_give_the_same_samples(setup):
  graphdef, params, scene = setup
  # Pad the batch's polygons to a larger bucket, as a batch with one big map would be.
  d = scene.to_dict()
  pad = 64
  for f in datatypes.POLYGON_FIELDS:
    d[f] = jnp.pad(d[f], [(0, 0), (0, pad)] + [(0, 0)] * (d[f].ndim - 2))
  d["pl_edge"] = jnp.pad(d["pl_edge"], [(0, 0), (0, pad), (0, pad)])
  big = datatypes.Scene.from_dict(d)
  all_pairs = dataclasses.replace(PAPER, pl2pl_neighbors=0)   # its maps are encoded in one packed call
  for graph, par, norm in ((*nnx.split(PaperDenoiser(all_pairs, rngs=nnx.Rngs(0))), NORM_PAPER),
                           (graphdef, params, NORM)):
    ctx = sampling.encode_maps(graph, par, big, norm, (32, 64, 96))
    chex.assert_shape(ctx.polygons, (3, big.num_polygons, PAPER.dim))
    ref = sampling.sample(graph, par, big, norm, SCHED, jax.random.key(4), OPTS)
    got = sampling.sample(graph, par, big, norm, SCHED, jax.random.key(4), OPTS, map_context=ctx)
    np.testing.assert_allclose(got.state, ref.state, atol=2e-3)
  # Two samples of one map share its encoding (3 distinct maps of 4, padded to 4 with an empty one),
  # and each scene still gets its own.
  twice = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, x[:1]]), big)
  ctx = sampling.encode_maps(graph, par, twice, norm, (32, 64, 96))
  np.testing.assert_array_equal(ctx.polygons[3], ctx.polygons[0])
  np.testing.assert_array_equal(ctx.valid, twice.pl_valid)
  assert float(jnp.abs(ctx.polygons[1] - ctx.polygons[0]).max()) > 0.0


def test_products_compile_without_the_library_and_sample_as_xla_default(setup):
  """The sampler is compiled with `cpu_products.COMPILER_OPTIONS` (its products through XLA's own kernels,
  not YNNPACK's, which repack every weight matrix on every call); its samples are those of the same
  function compiled with XLA's default, to float rounding."""
  graphdef, params, scene = setup
  args = (graphdef, params, scene, NORM, SCHED, jax.random.key(3), OPTS)
  assert cpu_products.COMPILER_OPTIONS == {"xla_cpu_experimental_ynn_fusion_type": ""}
  assert "ynn_fusion" not in sampling.sample.lower(*args).compile().as_text()
  default = jax.jit(sampling.sample.__wrapped__, static_argnames=("graphdef", "options", "custom_cost"))
  assert "ynn_fusion" in default.lower(*args).compile().as_text(), "XLA's default no longer uses the library"
  got, ref = sampling.sample(*args), default(*args)
  np.testing.assert_allclose(got.state, ref.state, atol=1e-3)
  np.testing.assert_allclose(got.heading, ref.heading, atol=1e-3)


def test_vmap_over_scenes_equals_sampling_each_scene(setup):
  """`sample` under a caller's vmap over scenes (each a batch of one), with a key per scene."""
  graphdef, params, scene = setup
  keys = jax.random.split(jax.random.key(6), 3)
  one_each = jax.tree_util.tree_map(lambda x: x[:, None], scene)               # [3, 1, ...]
  many = jax.vmap(lambda sc, k: sampling.sample(graphdef, params, sc, NORM, SCHED, k, OPTS).state)(one_each, keys)
  for i in range(3):
    alone = sampling.sample(graphdef, params, jax.tree_util.tree_map(lambda x, i=i: x[i:i + 1], scene), NORM, SCHED,
                            keys[i], OPTS).state
    np.testing.assert_allclose(many[i], alone, atol=1e-4)


def test_a_scene_sample_does_not_depend_on_its_batch_or_padding(setup):
  """A scene's sample comes from its own key and its guidance from its own costs: cropped to its own
  agents and polygons, or sampled with the other scenes of a padded batch, it is the same, guided and with
  fixed tokens too (`data.batches.sampler_batches` relies on it)."""
  graphdef, params, scene = setup
  # Scene 0 keeps 3 agents; the batch is padded to 32 agents and, as if one of its maps were larger, to 128
  # polygons.
  valid = np.asarray(scene.agent_valid).copy()
  valid[0, 3:] = False
  big = scene.replace(agent_valid=jnp.asarray(valid))
  d = big.to_dict()
  for f in datatypes.AGENT_FIELDS:
    d[f] = jnp.pad(d[f], [(0, 0), (0, 16)] + [(0, 0)] * (d[f].ndim - 2))
  for f in datatypes.POLYGON_FIELDS:
    d[f] = jnp.pad(d[f], [(0, 0), (0, 32)] + [(0, 0)] * (d[f].ndim - 2))
  d["pl_edge"] = jnp.pad(d["pl_edge"], [(0, 0), (0, 32), (0, 32)])
  big = datatypes.Scene.from_dict(d)
  polygons = int(np.asarray(big.pl_valid).sum(-1).max())
  assert polygons <= 96 and big.num_polygons == 128
  fixed = jnp.zeros(big.agent_valid.shape + (2, 3)).at[:, 0].set(big.agent_state[:, 0, :, :3])
  mask = jnp.zeros(big.agent_valid.shape + (2,), bool).at[:, 0, 0].set(True)
  guided = sampling.SamplerOptions("ddim", 5, ("boxes", "lane", "offroad"))  # each scene guided on its own
  keys = sampling.scene_keys(jax.random.key(8), 3)
  ref = sampling.sample(graphdef, params, big, NORM, SCHED, keys, guided, None, fixed, mask)
  # Scene 0 alone, cropped to its 4-agent and 96-polygon buckets, its map encoded apart (`encode_maps`).
  first = jax.tree_util.tree_map(lambda x: x[:1], big).crop(num_agents=4, num_polygons=96)
  maps = sampling.encode_maps(graphdef, params, first, NORM, (64, 96))
  alone = sampling.sample(graphdef, params, first, NORM, SCHED, keys[:1], guided, None, fixed[:1, :4], mask[:1, :4],
                          map_context=maps, map_geometry=geometry.map_geometry(first, *geometry.compact_sizes(first)))
  np.testing.assert_allclose(alone.state[0], ref.state[0, :4], atol=2e-3)
  np.testing.assert_array_equal(alone.valid[0], ref.valid[0, :4])
  # The last scene alone, with its own key.
  last = sampling.sample(graphdef, params, jax.tree_util.tree_map(lambda x: x[2:], big), NORM, SCHED, keys[2:],
                         guided, None, fixed[2:], mask[2:])
  np.testing.assert_allclose(last.state[0], ref.state[2], atol=2e-3)
  # A raw uint32 key works as a typed one.
  raw = sampling.scene_keys(jax.random.PRNGKey(8), 3)
  np.testing.assert_array_equal(jax.random.key_data(raw), jax.random.key_data(keys))


def _reference_reverse_process(denoise, x, keys, sched, steps, method):
  """Textbook DDIM (eta 0) / ancestral DDPM in float64 numpy, drawing each scene's noise from its own key."""
  abar, beta, alpha = (np.asarray(a, np.float64) for a in (sched.alpha_bars, sched.betas, sched.alphas))
  x = np.asarray(x, np.float64)
  for t, tp in zip(steps, list(steps[1:]) + [0]):
    keys, noise = list(keys), []
    for i, k in enumerate(keys):
      keys[i], k_noise, _ = jax.random.split(k, 3)
      noise.append(np.asarray(jax.random.normal(k_noise, x.shape[1:])))
    eps = np.asarray(denoise(x, t), np.float64)
    x0 = (x - np.sqrt(1 - abar[t]) * eps) / np.sqrt(abar[t])
    if method == "ddim":
      x = np.sqrt(abar[tp]) * x0 + np.sqrt(1 - abar[tp]) * eps
    else:
      mean = (np.sqrt(abar[t - 1]) * beta[t] * x0 + np.sqrt(alpha[t]) * (1 - abar[t - 1]) * x) / (1 - abar[t])
      var = beta[t] * (1 - abar[t - 1]) / (1 - abar[t])
      x = mean + (np.sqrt(var) * np.stack(noise) if t > 1 else 0.0)
  return x


@pytest.mark.parametrize("method", ["ddim", "ddpm"])
def test_sampler_core_runs_the_exact_update_rules_on_a_hand_made_denoiser(method):
  """`sample_with` over a stand-in denoiser (eps = 0.3 x + 0.002 t) reproduces the textbook updates."""
  sched = diffusion.linear_schedule(20)
  scene = datatypes.Scene.zeros(3, 1, 30, batch_shape=(2,)).replace(
      agent_valid=np.array([[True, True, False], [True, False, False]]), frame_scale=np.full((2,), 125.0, np.float32))
  scene = jax.tree_util.tree_map(jnp.asarray, scene)
  denoise = lambda x, t: 0.3 * x + 0.002 * jnp.asarray(t, jnp.float32).reshape(-1, 1, 1, 1)  # noqa: E731
  opts = sampling.SamplerOptions(method=method, stride=4, clip_x0=None)
  key = jax.random.key(7)
  out = jax.jit(lambda k: sampling.sample_with(denoise, scene, NORM_PAPER, sched, k, opts))(key)
  steps = diffusion.ddim_timesteps(20, 4) if method == "ddim" else np.arange(20, 0, -1)
  # Scene b's noise comes from fold_in(key, b): its first split starts the chain, its second draws x_T.
  keys, x_init = [], []
  for b in range(2):
    k, k_init = jax.random.split(jax.random.fold_in(key, b))
    keys.append(k)
    x_init.append(np.asarray(jax.random.normal(k_init, (3, 2, 3))))
  live = np.asarray(scene.agent_valid)[..., None, None]
  x_init = np.where(live, np.stack(x_init), 0.0)

  def masked_denoise(x, t):
    return np.where(live, np.asarray(denoise(jnp.asarray(x, jnp.float32), np.full((2,), t))), 0.0)
  ref = np.where(live, _reference_reverse_process(masked_denoise, x_init, keys, sched, steps, method), 0.0)
  np.testing.assert_allclose(out.normalized, ref, rtol=1e-4, atol=1e-4)
  assert np.abs(ref).max() > 0.1   # a real trajectory, not zeros


def test_a_self_conditioned_sampler_passes_each_step_its_previous_estimate():
  """With `self_conditioned`, the denoiser gets the previous step's x0 (none at the first step, nor above
  `self_condition_max_t`): a stand-in that predicts x0 = previous x0 + 0.1 (0 without one) ends at 0.1 x
  the number of calls with one, on every valid token."""
  sched = diffusion.linear_schedule(20)
  scene = datatypes.Scene.zeros(3, 1, 30, batch_shape=(2,)).replace(
      agent_valid=np.array([[True, True, False], [True, False, False]]), frame_scale=np.full((2,), 125.0, np.float32))
  scene = jax.tree_util.tree_map(jnp.asarray, scene)

  def denoise(x, t, x0_prev, has_prev):
    x0 = jnp.where(has_prev[:, None, None, None], x0_prev + 0.1, 0.0)
    return diffusion.eps_from_x0(sched, x, t, x0)

  # DDIM stride 4: t = 20, 16, 12, 8, 4; DPM-Solver++ 6 calls, all at t <= 20.
  for method, max_t, with_prev in (("ddim", 20, 4), ("dpmpp2m", 20, 5), ("ddim", 12, 3), ("ddim", 0, 0)):
    opts = sampling.SamplerOptions(method=method, stride=4, solver_steps=6, self_condition_max_t=max_t)
    out = jax.jit(lambda k, opts=opts: sampling.sample_with(denoise, scene, NORM_PAPER, sched, k, opts,
                                                          self_conditioned=True))(jax.random.key(0))
    valid = np.asarray(scene.agent_valid)
    np.testing.assert_allclose(np.asarray(out.normalized)[valid], 0.1 * with_prev, atol=1e-4)
    assert np.abs(np.asarray(out.normalized)[~valid]).max() == 0.0


def test_restarts_run_the_last_step_again_on_the_renoised_sample():
  """restarts (restart sampling): after the method's steps, the sample is noised again and the last step
  runs again, a self-conditioned denoiser reading the sample. A stand-in that predicts x0 = previous
  estimate + 0.1 ends 0.1 higher per restart; one whose x0 is exact keeps its exact sample; padding
  stays zero; the command lines' default restarts only their default samplers."""
  sched = diffusion.linear_schedule(20)
  scene = datatypes.Scene.zeros(3, 1, 30, batch_shape=(2,)).replace(
      agent_valid=np.array([[True, True, False], [True, False, False]]), frame_scale=np.full((2,), 125.0, np.float32))
  scene = jax.tree_util.tree_map(jnp.asarray, scene)
  valid = np.asarray(scene.agent_valid)

  def counting(x, t, x0_prev, has_prev):
    return diffusion.eps_from_x0(sched, x, t, jnp.where(has_prev[:, None, None, None], x0_prev + 0.1, 0.0))

  def exact(x, t):
    return diffusion.eps_from_x0(sched, x, t, jnp.full_like(x, 0.5))

  # DPM-Solver++ 6 calls (5 with a previous estimate), DDIM stride 4 (5 calls, 4 with one).
  for method, with_prev, restarts in (("dpmpp2m", 5, 3), ("ddim", 4, 2)):
    opts = sampling.SamplerOptions(method=method, stride=4, solver_steps=6, restarts=restarts)
    run = lambda fn, opts=opts, **kw: np.asarray(jax.jit(lambda k: sampling.sample_with(  # noqa: E731
        fn, scene, NORM_PAPER, sched, k, opts, **kw).normalized)(jax.random.key(0)))
    out = run(counting, self_conditioned=True)
    np.testing.assert_allclose(out[valid], 0.1 * (with_prev + restarts), atol=1e-4)
    assert np.abs(out[~valid]).max() == 0.0
    np.testing.assert_allclose(run(exact)[valid], 0.5, atol=1e-4)
    assert opts.network_calls(20) == (6 if method == "dpmpp2m" else 5) + restarts
  default = sampling.SamplerOptions(method="dpmpp2m", restarts=4)
  assert default.network_calls(500) == 19 and "4 restarts" in default.describe()
  with pytest.raises(ValueError, match="restart"):
    sampling.SamplerOptions(method="dpmpp2m", restarts=-1)


def test_restarts_keep_fixed_agents_and_move_the_others(setup):
  """The HL model with restarts: deterministic, padding zero, fixed tokens returned exactly, the free ones
  moved by the restarts."""
  graphdef, params, scene = setup
  fixed = scene.agent_state[..., :3] + 1.0
  mask = jnp.zeros(scene.agent_valid.shape + (2,), bool).at[:, 0, 0].set(True)
  out = {}
  for r in (0, 2):
    opts = sampling.SamplerOptions(method="dpmpp2m", solver_steps=4, restarts=r)
    out[r] = sampling.sample(graphdef, params, scene, NORM, SCHED, jax.random.key(3), opts,
                             fixed_state=fixed, fixed_mask=mask)
  again = sampling.sample(graphdef, params, scene, NORM, SCHED, jax.random.key(3),
                          sampling.SamplerOptions(method="dpmpp2m", solver_steps=4, restarts=2),
                          fixed_state=fixed, fixed_mask=mask)
  chex.assert_trees_all_equal(out[2].state, again.state)
  np.testing.assert_allclose(out[2].state[:, 0, 0], fixed[:, 0, 0], atol=1e-4)
  valid = np.asarray(scene.agent_valid)
  assert np.abs(np.asarray(out[2].state)[~valid]).max() == 0.0
  free = valid & ~np.asarray(mask[..., 0])
  assert np.abs(np.asarray(out[2].state - out[0].state)[free]).max() > 1e-3


def test_final_cost_steps_descend_the_costs_on_the_sample_without_network_calls():
  """final_cost_steps: after the last call, more official guidance steps on the sample itself. With an
  exact stand-in (every x0 estimate 0.5, x = 19 m) and a custom cost wanting x >= 40 m: the cost falls with
  every step count, no network call is added, fixed tokens stay as given, padding stays zero; the
  option needs guidance costs."""
  sched = diffusion.linear_schedule(20)
  scene = datatypes.Scene.zeros(3, 1, 30, batch_shape=(2,)).replace(
      agent_valid=np.array([[True, True, False], [True, False, False]]), frame_scale=np.full((2,), 125.0, np.float32))
  scene = jax.tree_util.tree_map(jnp.asarray, scene)
  valid = np.asarray(scene.agent_valid)
  calls = []

  def exact(x, t):
    calls.append(1)   # counted at trace time: one per network call site in the traced program
    return diffusion.eps_from_x0(sched, x, t, jnp.full_like(x, 0.5))

  beyond_40m = lambda state, sc: jnp.mean(jax.nn.relu(40.0 - state[..., 0]))  # noqa: E731
  g = sampling.GuidanceParams(scale=0.02, weights={"custom": 1.0})
  fixed = jnp.zeros((2, 3, 2, 3)).at[0, 1, 1, 0].set(-5.0)
  mask = jnp.zeros((2, 3, 2), bool).at[0, 1, 1].set(True)
  costs, traced = [], []
  for steps in (0, 3, 10):
    opts = sampling.SamplerOptions(method="ddim", stride=4, costs=("custom",), final_cost_steps=steps)
    calls.clear()
    out = jax.jit(lambda k, opts=opts: sampling.sample_with(
        exact, scene, NORM_PAPER, sched, k, opts, g, fixed, mask, custom_cost=beyond_40m))(jax.random.key(0))
    traced.append(len(calls))
    state = np.asarray(out.state)
    costs.append(float(np.maximum(40.0 - state[..., 0], 0.0)[valid & ~np.asarray(mask)[..., 0]].mean()))
    assert state[0, 1, 1, 0] == pytest.approx(-5.0, abs=1e-4)      # the fixed goal
    assert np.abs(state[~valid]).max() == 0.0
  assert costs[0] > costs[1] > costs[2], costs
  assert traced[0] == traced[1] == traced[2]
  assert "10 final cost steps" in sampling.SamplerOptions(costs=("lane",), final_cost_steps=10).describe()
  for bad in (dict(final_cost_steps=-1, costs=("lane",)), dict(final_cost_steps=2)):
    with pytest.raises(ValueError, match="final_cost_steps"):
      sampling.SamplerOptions(**bad)


def test_path_costs_see_the_6_seconds_between_the_states():
  """Two cars whose states are far apart but whose paths cross at the same time: the states' box cost is
  0, the path cost is not, and its gradient moves them apart; a U-turn whose ends are on the road but whose
  path bulges off it has a path off-road cost."""
  car = datatypes.AGENT_TYPES.index("vehicle")
  scene = datatypes.Scene.zeros(2, 1, 4, batch_shape=(1,)).replace(
      agent_type=jnp.full((1, 2), car), agent_valid=jnp.ones((1, 2), bool))
  # East-bound from (-30, 0) to (30, 0) and north-bound from (0, -30) to (0, 30), both at 10 m/s: they meet at 3 s.
  state = jnp.array([[[[-30.0, 0.0, 10.0], [30.0, 0.0, 10.0]], [[0.0, -30.0, 10.0], [0.0, 30.0, 10.0]]]])
  heading = jnp.array([[[0.0, 0.0], [np.pi / 2, np.pi / 2]]])
  xy, _ = guidance.hermite_paths(state, heading)
  np.testing.assert_allclose(xy[0, 0, 6], [0.0, 0.0], atol=1e-4)                 # mid-way at the crossing
  crossing = float(guidance.path_overlap(state, heading, scene, 0.0))
  assert crossing > 0 and float(guidance.box_clearance(state, scene, 0.0)) == 0.0
  later = state.at[0, 1, :, 1].add(20.0)                                          # the second car 2 s later
  assert float(guidance.path_overlap(later, heading, scene, 0.0)) < 0.2 * crossing
  near_miss = state.at[0, 1, :, 1].add(1.0)                                       # 0.1 s later: still overlapping
  before = float(guidance.path_overlap(near_miss, heading, scene, 0.0))
  grad = jax.grad(lambda s: guidance.path_overlap(s, heading, scene, 0.0))(near_miss)
  assert before > 0 and float(guidance.path_overlap(near_miss - grad, heading, scene, 0.0)) < 0.95 * before
  # A U-turn inside a 10 m square: from (0, -3) east-bound to (0, 3) west-bound at 10 m/s bulges out east.
  square = jnp.array([[-5.0, -5.0], [5.0, -5.0], [5.0, 5.0], [-5.0, 5.0]])
  ring = jnp.zeros((1, 1, 4, 2)).at[0, 0].set(square)
  one = scene.replace(agent_valid=jnp.array([[True, False]]), da_xy=ring, da_valid=jnp.ones((1, 1, 4), bool))
  u_turn = jnp.array([[[[0.0, -3.0, 10.0], [0.0, 3.0, 10.0]], [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]]])
  u_heading = jnp.array([[[0.0, np.pi], [0.0, 0.0]]])
  assert float(guidance.offroad(u_turn, one)) == 0.0
  assert float(guidance.path_offroad(u_turn, u_heading, one)) > 1.0


def test_the_command_lines_run_the_named_samplers():
  """`sampling.DEFAULT` is what `sample.py` and `evaluate` run with their default flags, `UNGUIDED` what
  --guidance= runs, `PAPER` what --guidance= --method=ddim runs; another method or guidance mode keeps no
  restarts or final cost steps (measured for the presets only)."""
  from absl import flags
  from tdiff_jax import sampler_flags

  def options(*argv):
    values = flags.FlagValues()
    sampler_flags.define_sampler_flags(values)
    values(["prog", *argv])
    return sampler_flags.sampler_options(values)

  assert options() == sampling.DEFAULT and sampling.DEFAULT.network_calls(500) == 54
  assert options("--guidance=") == sampling.UNGUIDED and sampling.UNGUIDED.network_calls(500) == 15
  assert options("--guidance=", "--method=ddim") == sampling.PAPER and sampling.PAPER.network_calls(500) == 50
  paper_mode = options("--guidance_mode=paper")
  assert (paper_mode.restarts, paper_mode.final_cost_steps, paper_mode.costs) == (0, 0, sampling.DEFAULT.costs)
  assert options("--method=dpmpp2m", "--steps=8").solver_steps == 8 and options("--steps=25").stride == 20
