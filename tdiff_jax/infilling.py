"""The infill task (paper Problem 2, §IV-B, Algorithm 1): the public `infill` function, its map
encoding, the training loss and the per-mode errors behind Table II. The network is
`models.infiller.Infiller`; the modes, the bridge and the mode weights live beside it; ADE, FDE and
the miss rate are in `metrics`.

Modes (the paper's hard constraints, HC; `MODES`, `mode_id`):

| id | name      | gamma(h)  | pinned                      |
|----|-----------|-----------|-----------------------------|
| 0  | `both`    | h (1 - h) | initial and goal positions  |
| 1  | `initial` | h         | initial position            |
| 2  | `goal`    | 1 - h     | goal position               |
| 3  | `none`    | 1         | nothing                     |

A pinned end is reproduced exactly (the offset is multiplied by zero there).

Loss (paper §IV-B, official code §3.5): masked squared L2 error over the observed steps of valid agents,
plus `smoothness_weight` (0.5) x the mean step length |x_{k+1} - x_k| of the prediction (the paper's
formula and the official code: first differences, i.e. path length, not acceleration). The mode is
drawn uniformly and independently per agent in training.

The generative infiller (`flow_noise_m > 0`, `configs/infill.py:stochastic`; beyond the paper, whose
trajectories are deterministic given the high-level states): a flow-matching model of the displacement
from the bridge (agent frame). Training draws a flow time t ~ U(0, 1) and noise z per agent and feeds
the network x_t = (1 - t) s z + t x_1 (s: `models.infiller.flow_noise_scale`, zero at pinned ends; x_1 the
ground truth's displacement); the network estimates x_1 (the loss above on its trajectory). Sampling
(`infill` with a key) starts at s z and takes `FLOW_STEPS` Euler steps along (x_1_hat - x_t) / (1 - t).
Every estimate is bridge + gamma x offsets, so the hard constraints hold exactly for every draw.
"""

from __future__ import annotations

import functools
from typing import Sequence

import jax
import jax.numpy as jnp
from flax import nnx

from tdiff_jax import cpu_products, datatypes, metrics, static_args
from tdiff_jax.models import infiller as infiller_lib
from tdiff_jax.models import map_encoder
from tdiff_jax.models.map_encoder import MapContext, PackedPolygons, encode_batch

MODES, mode_id = infiller_lib.MODES, infiller_lib.mode_id  # the modes live beside their weights
FLOW_STEPS = 4   # network calls of the generative infiller's sampler


@functools.partial(cpu_products.jit, static_argnums=0)
def _encode_map_batch(graphdef: nnx.GraphDef, params, scene: datatypes.Scene,
                      packed: PackedPolygons | None) -> MapContext:
  return nnx.merge(graphdef, params).encode_map(scene, packed=packed)


def encode_maps(graphdef: nnx.GraphDef, params, scene: datatypes.Scene, polygon_buckets: Sequence[int]) -> MapContext:
  """The infiller's map encoding of a batch, shared maps once: the same as encoding the padded batch, for
  a fraction of the work. An all-pairs encoder computes the batch's distinct maps in one call over their
  valid polygons and pairs only (`map_encoder.encode_distinct`); one that keeps the k nearest polygons
  encodes each scene alone at its own polygon bucket (`map_encoder.encode_per_scene`). Pass it to
  `infill(map_context=...)`. Call it outside `jit`."""
  radius_m, neighbors = static_args.read_once(graphdef, params, map_encoder.pair_settings)
  pack = lambda maps: map_encoder.packing_for(maps, radius_m, neighbors)  # noqa: E731
  return encode_batch(lambda maps: _encode_map_batch(graphdef, params, maps, pack(maps)), scene,
                      polygon_buckets, all_pairs=neighbors <= 0)


def _agent_pairing(model: nnx.Module) -> tuple[float, int, float]:
  """The infiller's (agent, polygon) radius (m) and neighbours and its (agent, agent) radius (m)."""
  return model.cfg.pl2a_radius_m, model.cfg.pl2a_neighbors, model.cfg.a2a_radius_m


def _trajectories(model: infiller_lib.Infiller, scene: datatypes.Scene, initial_heading: jax.Array, mode: jax.Array,
                  key: jax.Array | None, map_context: MapContext | None,
                  packed_agents: infiller_lib.PackedAgents | None) -> jax.Array:
  """The model's trajectories `[B, A, H, 2]`: one call (deterministic), or the flow's `FLOW_STEPS` Euler
  steps from noise drawn with `key` (generative; None: key 0)."""
  cfg = model.cfg
  if cfg.flow_noise_m <= 0:
    return model(scene, initial_heading, mode, None, map_context, packed_agents=packed_agents)
  if map_context is None:
    map_context = model.encode_map(scene)
  key = jax.random.key(0) if key is None else key
  keys = jax.random.split(key, mode.shape[0]) if key.ndim == 0 else key     # one per scene
  z = jax.vmap(lambda k: jax.random.normal(k, mode.shape[1:] + (cfg.horizon, 2)))(keys)
  x = infiller_lib.flow_noise_scale(mode, cfg.horizon, cfg.flow_noise_m) * z
  xy, goal = scene.agent_state[..., 0, :2], scene.agent_state[..., 1, :2]

  def step(i, carry):   # a loop, not unrolled: the network compiles once
    x, _ = carry
    traj = model(scene, initial_heading, mode, None, map_context, packed_agents=packed_agents, noisy=x,
                 flow_time=jnp.full(mode.shape, i / FLOW_STEPS))
    # Euler: dx = (x_1_hat - x) / (1 - t) dt with dt = 1 / FLOW_STEPS; the last step lands on x_1_hat.
    return x + (infiller_lib.bridge_displacement(traj, xy, initial_heading, goal) - x) / (FLOW_STEPS - i), traj

  return jax.lax.fori_loop(0, FLOW_STEPS, step, (x, jnp.zeros_like(x)))[1]


@functools.partial(cpu_products.jit, static_argnums=0)
def infill(graphdef: nnx.GraphDef, params, scene: datatypes.Scene, initial_heading: jax.Array, mode: jax.Array,
           key: jax.Array | None = None, map_context: MapContext | None = None,
           packed_agents: infiller_lib.PackedAgents | None = None) -> jax.Array:
  """Infills every agent's trajectory between its initial and goal state: deterministic with the paper's
  infiller, one draw per `key` with a generative one (`flow_noise_m > 0`).

  Args:
    graphdef, params: the infiller (`load_infiller` or `nnx.split` of an `Infiller`).
    scene: a batch of scenes `[B, ...]`; per agent, `agent_state[..., 0, :]` is the initial and
      `agent_state[..., 1, :]` the goal state (x, y in metres, speed in m/s), e.g. a high-level sample.
    initial_heading: `[B, A]` initial headings (rad): the agent frames.
    mode: `[B, A]` (or broadcastable) mode ids, see `MODES`.
    key: a generative infiller's noise: one key, or `[B]` keys (one per scene: a scene's draw then does not
      depend on the batch it is in); None: key 0. The deterministic infiller ignores it.
    map_context: the map encoding computed apart (`encode_maps`); default: encoded here.
    packed_agents: the batch's valid agents and their pairs listed (`pack_agents`, on the host): only
      they are computed, not the padded agents and pairs; the same trajectories (`infill_packed`).
  Returns:
    `[B, A, H, 2]` positions in metres, scene frame, for AV2 steps 50..109 (zeros for padded agents).

  Compiled once per shape (static `graphdef`); works inside a caller's `jax.jit` and under `jax.vmap`.
  """
  model = nnx.merge(graphdef, params)
  mode = jnp.broadcast_to(jnp.asarray(mode, jnp.int32), scene.agent_valid.shape)
  return _trajectories(model, scene, initial_heading, mode, key, map_context, packed_agents)


def pack_agents(graphdef: nnx.GraphDef, params, scene: datatypes.Scene) -> infiller_lib.PackedAgents:
  """The infiller's packed agents of a batch (`models.infiller.pack_agents` with its radii): numpy, on
  the host, for `infill(packed_agents=...)`. The model's settings are read once per graphdef."""
  return infiller_lib.pack_agents(scene, *static_args.read_once(graphdef, params, _agent_pairing))


def infill_packed(graphdef: nnx.GraphDef, params, scene: datatypes.Scene, initial_heading: jax.Array,
                  mode: jax.Array, key: jax.Array | None = None, *, polygon_buckets: Sequence[int]) -> jax.Array:
  """`infill` over a batch of scenes of different sizes without paying for the largest: the maps encoded
  once over their valid polygons (`encode_maps`), then one call over the batch's valid agents and their
  real (agent, polygon) and (agent, agent) pairs, packed into lists (`pack_agents`) instead of padded
  to the batch's largest scene (`polygon_buckets`: as `encode_maps`). Returns `[B, A, H, 2]` as `infill` on the padded batch (the same
  trajectories to float tolerance, tested). Host-level: call it outside `jit`."""
  mode = jnp.broadcast_to(jnp.asarray(mode, jnp.int32), scene.agent_valid.shape)
  maps = encode_maps(graphdef, params, scene, polygon_buckets)
  return infill(graphdef, params, scene, initial_heading, mode, key, map_context=maps,
                packed_agents=pack_agents(graphdef, params, scene))


def infill_batch(graphdef: nnx.GraphDef, params, scene: datatypes.Scene, initial_heading: jax.Array,
                 mode: jax.Array, key: jax.Array | None = None, *, polygon_buckets: Sequence[int]) -> jax.Array:
  """A batch's trajectories `[B, A, H, 2]` the fastest way for the backend: on a CPU `infill_packed`
  (its work follows the real pairs); on an accelerator one padded `infill` call with the maps encoded
  first, whose dense grids run faster there than the lists' gathers and segment sums (docs/benchmarks.md:
  1114 against 760 scenes/s at batch 256 on one GPU). The same trajectories. Host-level."""
  if jax.default_backend() == "cpu":
    return infill_packed(graphdef, params, scene, initial_heading, mode, key, polygon_buckets=polygon_buckets)
  maps = encode_maps(graphdef, params, scene, polygon_buckets)
  return infill(graphdef, params, scene, initial_heading, mode, key, map_context=maps)


def sample_modes(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
  """Training modes: uniform over the four, independently per agent."""
  return jax.random.randint(key, shape, 0, len(MODES))


def infill_loss(model: infiller_lib.Infiller, batch: datatypes.Scene, key: jax.Array, smoothness_weight: float,
                train: bool = True, mode: jax.Array | None = None, packed: PackedPolygons | None = None
                ) -> tuple[jax.Array, dict]:
  """Loss and metrics on a batch with ground-truth trajectories (`agent_future`).

  The initial heading is the ground truth's. `mode` `[B, A]` defaults to uniformly drawn modes. A
  generative infiller estimates the ground truth from its flow state at a random time (module docstring).
  `packed`: the batch's packed polygons (`map_encoder.pack_polygons`) for an all-pairs map encoder.
  """
  mode_key, drop_key = jax.random.split(key)
  if mode is None:
    mode = sample_modes(mode_key, batch.agent_valid.shape)
  valid = batch.agent_future_valid & batch.agent_valid[..., None]                            # [B, A, H]
  heading = batch.agent_state[..., 0, 3]
  flow = {}
  if model.cfg.flow_noise_m > 0:  # the flow's state at a random time between noise and the ground truth
    time_key, noise_key = jax.random.split(jax.random.fold_in(key, 1))
    x1 = infiller_lib.bridge_displacement(batch.agent_future, batch.agent_state[..., 0, :2], heading,
                                          batch.agent_state[..., 1, :2])
    x1 = jnp.where(valid[..., None], x1, 0.0)   # unobserved steps: on the bridge
    t = jax.random.uniform(time_key, mode.shape)
    z = infiller_lib.flow_noise_scale(mode, model.cfg.horizon, model.cfg.flow_noise_m) * jax.random.normal(
        noise_key, x1.shape)
    flow = {"noisy": (1 - t)[..., None, None] * z + t[..., None, None] * x1, "flow_time": t}
  pred = model(batch, heading, mode, drop_key if train else None, packed=packed, **flow)     # [B, A, H, 2]
  sq = jnp.sum((pred - batch.agent_future) ** 2, -1)
  recon = jnp.sum(jnp.where(valid, sq, 0.0)) / jnp.maximum(valid.sum(), 1)
  step = jnp.sqrt(jnp.sum(jnp.diff(pred, axis=-2) ** 2, -1) + 1e-12)                         # [B, A, H-1]
  n_agents = jnp.maximum(batch.agent_valid.sum(), 1)
  smooth = jnp.sum(jnp.where(batch.agent_valid, step.mean(-1), 0.0)) / n_agents
  loss = recon + smoothness_weight * smooth
  ade, fde, _ = metrics.displacement_errors(pred, batch.agent_future, valid)
  agent = batch.agent_valid
  logged = {"loss": loss, "recon": recon, "smoothness": smooth,
            "ade": jnp.sum(jnp.where(agent, ade, 0.0)) / n_agents,
            "fde": jnp.sum(jnp.where(agent, fde, 0.0)) / n_agents}
  return loss, logged


@functools.partial(cpu_products.jit, static_argnums=0)
def infill_errors(graphdef: nnx.GraphDef, params, scene: datatypes.Scene, map_context: MapContext | None = None,
                  key: jax.Array | None = None) -> dict:
  """Per mode, per agent ADE/FDE against the ground truth, with the ground-truth endpoints given (a
  generative infiller: one draw per mode with `key`, as `infill`).

  Returns {"ade": [M, B, A], "fde": [M, B, A], "valid": [B, A]} for the M = 4 modes of `MODES`.
  The map is encoded once for the four modes (or given: `encode_maps`).
  """
  model = nnx.merge(graphdef, params)
  valid = scene.agent_future_valid & scene.agent_valid[..., None]
  ctx = model.encode_map(scene) if map_context is None else map_context

  def one(mode):
    pred = _trajectories(model, scene, scene.agent_state[..., 0, 3], jnp.full(scene.agent_valid.shape, mode, jnp.int32),
                         key, ctx, None)
    ade, fde, _ = metrics.displacement_errors(pred, scene.agent_future, valid)
    return ade, fde

  ade, fde = jax.lax.map(one, jnp.arange(len(MODES)))
  return {"ade": ade, "fde": fde, "valid": scene.agent_valid & valid.any(-1)}
