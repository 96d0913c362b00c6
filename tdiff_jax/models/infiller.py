"""The trajectory infiller f_phi (paper §IV-B, Algorithm 1; reference notes §3).

A deterministic regressor. For each agent, given its initial pose and its goal position, it predicts
the H = 60 positions of AV2 steps 50..109 as

    trajectory = bridge + gamma(h, mode) * offsets,

where the bridge is the straight line from the initial to the goal position and gamma is the
hard-constraint weight of `tdiff_jax.infilling.mode_weights`. Everything happens in the agent's own frame
(origin at its initial position, x along its initial heading), in metres.

The per-agent network (`Infiller.infill_agent`) is written for ONE agent and mapped over the agents
with `jax.vmap`; the map and the other agents are shared inputs. Or it runs once over a batch's packed
list of valid agents (`Infiller.infill_packed`, `pack_agents`), its attention over the listed (agent,
polygon) and (agent, agent) pairs only: the same trajectories without the padded agents and pairs.
As in the official code:
  1. query = learned agent token + type embedding (+ an embedding of the initial and goal speeds of the
     high-level state, which the official code does not use);
  2. stage 1, `num_layers` x [query += MLP(bridge); attention to the map polygons; attention to the
     other agents' initial states], both with relative geometry (distance, angle, heading difference)
     in the agent's frame, within `pl2a_radius_m` / `a2a_radius_m` (optionally only the
     `pl2a_neighbors` nearest polygons, which bounds the per-agent work on large maps);
  3. the query is repeated over the H steps with sinusoidal positions and passes a pre-norm
     temporal transformer (`temporal_layers`, FFN width `temporal_ff`);
  4. coarse = bridge + gamma * MLP(step tokens);
  5. stage 2, `num_layers` x [query = MLP(coarse) first, += mode embedding; map attention; agent
     attention], reusing stage 1's relation embeddings;
  6. trajectory = coarse + gamma * MLP(query) reshaped to [H, 2].
The other agents are represented by their type, initial speed and relative pose (the official code
attends to their hidden query states instead; ours is per-agent, so it vmaps). The polygon
embeddings come from the QCNet-style map encoder without its summary tokens and, as in the official
infiller, without absolute positions (segment lengths, types and relative geometry only).

Shapes: B scenes, A agents, P polygons, H steps, D width.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from flax import nnx, struct

from tdiff_jax import datatypes, geometry
from tdiff_jax.data.normalize import SPEED_SCALE
from tdiff_jax.models import layers, map_encoder, model_config
from tdiff_jax.models.map_encoder import MapContext, MapEncoder, PackedPolygons

NUM_MODES = 4
# Positions enter the MLPs divided by this many metres (the outputs stay in metres).
POSITION_SCALE_M = 10.0


@dataclasses.dataclass(frozen=True)
class InfillModelConfig:
  dim: int = 128
  heads: int = 8
  num_layers: int = 2
  temporal_layers: int = 2
  temporal_ff: int = 128
  map_layers: int = 1
  num_freq_bands: int = 64
  dropout: float = 0.1
  pl2pl_radius_m: float = 150.0
  pl2pl_neighbors: int = 0
  pl2a_radius_m: float = 150.0
  pl2a_neighbors: int = 0   # > 0: only the k nearest polygons within the radius (0: all of them)
  a2a_radius_m: float = 150.0
  # > 0: the relation embeddings interpolated from this many values per input (`layers.FourierEmbedding`)
  fourier_tables: int = 0
  horizon: int = datatypes.HORIZON
  # > 0: the generative infiller (beyond the paper): a flow from noise of this scale (m, at the mode's
  # largest weight) to the displacement from the bridge, sampled in `infilling.FLOW_STEPS` calls.
  flow_noise_m: float = 0.0

  def __post_init__(self):
    layers.check_fourier_tables(self.fourier_tables)

  @classmethod
  def from_config(cls, c: ml_collections.ConfigDict) -> "InfillModelConfig":
    return model_config.from_config(cls, c)


@struct.dataclass
class AgentInputs:
  """One agent's inputs (leading axes allowed): what `jax.vmap` maps over.

  index `[]` its row (to exclude itself from agent attention), xy `[2]` initial position (m, scene
  frame), heading `[]` initial heading (rad), goal `[2]` goal position, speed `[2]` initial and goal
  speed (m/s), type `[]`, mode `[]` hard-constraint mode id; a generative infiller's also `noisy` `[H, 2]`
  (the flow's current displacement from the bridge, agent frame, m) and `flow_time` `[]` (0 noise, 1 data).
  """

  index: jax.Array
  xy: jax.Array
  heading: jax.Array
  goal: jax.Array
  speed: jax.Array
  type: jax.Array
  mode: jax.Array
  noisy: jax.Array | None = None
  flow_time: jax.Array | None = None


@struct.dataclass
class PackedAgents:
  """A batch's valid agents packed into one list, with the (agent, polygon) and (agent, agent) pairs of
  their attention: what the infiller computes instead of the padded `[B, A]` agents and `[B, A, P]`,
  `[B, A, A]` pair grids, most of which is padding when the batch's scenes differ in size.

  `agent` indexes the batch's agents flattened to `[B x A]` (scene b's agent i is b * A + i), in that
  order. The map pairs: `pl_dst` into `agent`'s list (sorted), `pl_src` into the batch's polygons
  flattened to `[B x P]`; the agent pairs: `a_dst` (sorted), `a_src`, both into `agent`'s list. Each list
  is padded to a bucketed length (`map_encoder.bucket_length`) with its `*_valid` False. Built on the
  host by `pack_agents`.
  """
  agent: jax.Array        # [N] int32
  agent_valid: jax.Array  # [N] bool
  pl_dst: jax.Array       # [E] int32
  pl_src: jax.Array       # [E] int32
  pl_valid: jax.Array     # [E] bool
  a_dst: jax.Array        # [F] int32
  a_src: jax.Array        # [F] int32
  a_valid: jax.Array      # [F] bool

  @property
  def shape(self) -> tuple[int, int, int]:
    """(N, E, F): the padded lengths, which the jitted infiller compiles for."""
    return self.agent.shape[-1], self.pl_dst.shape[-1], self.a_dst.shape[-1]


def _distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
  """`[B, Q, K]` distances (m) between points `a` `[B, Q, 2]` and `b` `[B, K, 2]`, as
  `layers.relative_geometry` computes them (float32)."""
  d = (b[:, None] - a[:, :, None]).astype(np.float32)
  return np.sqrt((d * d).sum(-1) + np.float32(1e-12))


def pack_agents(scene: datatypes.Scene, pl2a_radius_m: float, pl2a_neighbors: int,
                a2a_radius_m: float) -> PackedAgents:
  """The packed agents of a batch `scene` `[B, ...]` (numpy, on the host; outside `jit`): every valid
  agent; paired with each valid polygon of its scene within `pl2a_radius_m` of its initial position
  (with `pl2a_neighbors = k > 0`, the k nearest of those) and with every other valid agent within
  `a2a_radius_m`: the dense infiller's masks, listed."""
  valid = np.asarray(scene.agent_valid, bool)
  pl_valid = np.asarray(scene.pl_valid, bool)
  xy = np.asarray(scene.agent_state[..., 0, :2], np.float32)
  b, a = valid.shape
  p = pl_valid.shape[1]
  flat = np.flatnonzero(valid)                           # the valid agents, in [B x A] order
  row = np.full(b * a, -1, np.int64)
  row[flat] = np.arange(len(flat))
  n = map_encoder.bucket_length(len(flat), 16, per_doubling=2)

  dist = _distances(xy, np.asarray(scene.pl_xy, np.float32))                          # [B, A, P]
  cand = valid[:, :, None] & pl_valid[:, None, :] & (dist <= pl2a_radius_m)
  if 0 < pl2a_neighbors < p:  # the k nearest (ties to the lower index, as `lax.top_k`)
    nearest = np.argsort(np.where(cand, dist, np.inf), axis=-1, kind="stable")[..., :pl2a_neighbors]
    keep = np.zeros_like(cand)
    np.put_along_axis(keep, nearest, True, axis=-1)
    cand &= keep
  bi, ai, pi = np.nonzero(cand)                          # row-major: sorted by agent
  dist = _distances(xy, xy)                                                              # [B, A, A]
  pair = valid[:, :, None] & valid[:, None, :] & (dist <= a2a_radius_m) & ~np.eye(a, dtype=bool)
  bj, qj, kj = np.nonzero(pair)

  def padded(values: np.ndarray, length: int, fill: int) -> np.ndarray:
    return np.concatenate([values, np.full(length - len(values), fill)]).astype(np.int32)

  e = map_encoder.bucket_length(len(bi), 256, per_doubling=2)
  f = map_encoder.bucket_length(len(bj), 64, per_doubling=2)
  return PackedAgents(
      agent=padded(flat, n, b * a - 1), agent_valid=np.arange(n) < len(flat),
      pl_dst=padded(row[bi * a + ai], e, n - 1), pl_src=padded(bi * p + pi, e, 0), pl_valid=np.arange(e) < len(bi),
      a_dst=padded(row[bj * a + qj], f, n - 1), a_src=padded(row[bj * a + kj], f, 0), a_valid=np.arange(f) < len(bj))


def time_fraction(horizon: int) -> jax.Array:
  """h `[H]`: the paper's linearly spaced time vector in [0, 1]."""
  return jnp.linspace(0.0, 1.0, horizon)


def bridge(initial_xy: jax.Array, goal_xy: jax.Array, horizon: int = datatypes.HORIZON) -> jax.Array:
  """The straight line `[..., H, 2]` from `initial_xy` `[..., 2]` to `goal_xy` over H evenly spaced steps."""
  return initial_xy[..., None, :] + time_fraction(horizon)[:, None] * (goal_xy - initial_xy)[..., None, :]


# The paper's hard-constraint modes (HC): which ends of the trajectory are pinned; `mode_weights` row m.
MODES = ("both", "initial", "goal", "none")


def mode_id(mode: str | int) -> int:
  """A mode's index in `MODES` from its name (or a checked index)."""
  if isinstance(mode, int):
    if not 0 <= mode < len(MODES):
      raise ValueError(f"infill mode id {mode} is not in 0..{len(MODES) - 1}")
    return mode
  if mode not in MODES:
    raise ValueError(f"unknown infill mode {mode!r}; choose one of {', '.join(MODES)}")
  return MODES.index(mode)


def mode_weights(mode: jax.Array, horizon: int) -> jax.Array:
  """gamma `[..., H]` for mode ids `[...]` (`MODES` order).

  both: h(1 - h); initial: h; goal: 1 - h; none: 1. A weight of 0 at h = 0 pins the initial position,
  at h = 1 the goal. (Algorithm 1 of the paper prints 1 - h for "initial" and h for "goal"; with its
  bridge anchored at the initial state that would pin the goal in the "initial" mode. We follow the
  modes' meaning, which is also what the official code does.)
  """
  h = time_fraction(horizon)
  table = jnp.stack([h * (1.0 - h), h, 1.0 - h, jnp.ones_like(h)])   # [4, H]
  return table[mode]


def bridge_displacement(trajectory: jax.Array, initial_xy: jax.Array, initial_heading: jax.Array,
                        goal_xy: jax.Array) -> jax.Array:
  """`[..., H, 2]` trajectories (m, scene frame) as displacements from their bridge in the agent frame
  (x along `initial_heading` `[...]`): what a generative infiller's flow moves."""
  local = geometry.rotate(trajectory - initial_xy[..., None, :], -initial_heading[..., None])
  goal_local = geometry.rotate(goal_xy - initial_xy, -initial_heading)
  return local - bridge(jnp.zeros_like(goal_local), goal_local, trajectory.shape[-2])


def flow_noise_scale(mode: jax.Array, horizon: int, noise_m: float) -> jax.Array:
  """`[..., H, 1]` the generative infiller's noise scale per step: `noise_m` x the mode's weight gamma
  over its largest, so a pinned end gets none."""
  gamma = mode_weights(mode, horizon)
  return (noise_m * gamma / gamma.max(-1, keepdims=True))[..., None]


def sinusoidal_positions(n: int, dim: int) -> jax.Array:
  """`[n, dim]` sinusoidal encodings of positions 1..n (the official temporal encoding)."""
  pos = jnp.arange(1, n + 1, dtype=jnp.float32)[:, None]
  freq = jnp.exp(-math.log(10000.0) * jnp.arange(0, dim, 2, dtype=jnp.float32) / dim)
  pe = jnp.zeros((n, dim))
  pe = pe.at[:, 0::2].set(jnp.sin(pos * freq))
  return pe.at[:, 1::2].set(jnp.cos(pos * freq))


class MLP(nnx.Module):
  """The official `MLPLayer`: Linear, LayerNorm, ReLU, Linear."""

  def __init__(self, din: int, hidden: int, dout: int, *, rngs: nnx.Rngs):
    self.fc1 = nnx.Linear(din, hidden, rngs=rngs)
    self.norm = nnx.LayerNorm(hidden, rngs=rngs)
    self.fc2 = nnx.Linear(hidden, dout, rngs=rngs)

  def __call__(self, x: jax.Array) -> jax.Array:
    return self.fc2(jax.nn.relu(self.norm(self.fc1(x))))


class TemporalLayer(nnx.Module):
  """Pre-norm transformer encoder layer over the H step tokens (ReLU FFN)."""

  def __init__(self, dim: int, heads: int, ff: int, dropout_rate: float, *, rngs: nnx.Rngs):
    self.dropout_rate = dropout_rate
    self.norm1 = nnx.LayerNorm(dim, rngs=rngs)
    self.attn = layers.MultiHeadAttention(dim, heads, rngs=rngs)
    self.norm2 = nnx.LayerNorm(dim, rngs=rngs)
    self.ff = layers.FeedForward(dim, ff, jax.nn.relu, rngs=rngs)

  def __call__(self, x: jax.Array, key: jax.Array | None) -> jax.Array:
    h = self.norm1(x)
    x = x + layers.dropout(self.attn(h, h, None, self.dropout_rate, layers.fold(key, 0)), self.dropout_rate,
                           layers.fold(key, 1))
    return x + layers.dropout(self.ff(self.norm2(x), self.dropout_rate, layers.fold(key, 2)), self.dropout_rate,
                              layers.fold(key, 3))


class Infiller(nnx.Module):

  def __init__(self, cfg: InfillModelConfig, *, rngs: nnx.Rngs):
    d, h = cfg.dim, cfg.horizon
    self.cfg = cfg
    self.map_encoder = MapEncoder(d, cfg.heads, cfg.map_layers, cfg.num_freq_bands, 0, cfg.dropout,
                                  cfg.pl2pl_radius_m, cfg.pl2pl_neighbors, absolute_inputs=False,
                                  fourier_tables=cfg.fourier_tables, rngs=rngs)
    self.agent_token = nnx.Param(0.02 * jax.random.normal(rngs.params(), (d,)))
    self.type_emb = nnx.Embed(len(datatypes.AGENT_TYPES), d, rngs=rngs)
    self.speed_emb = nnx.Linear(2, d, rngs=rngs)
    self.bridge_emb = MLP(2 * h, d, d, rngs=rngs)
    self.r_pl2a = layers.FourierEmbedding(3, d, cfg.num_freq_bands, table_size=cfg.fourier_tables, rngs=rngs)
    self.r_a2a = layers.FourierEmbedding(4, d, cfg.num_freq_bands, table_size=cfg.fourier_tables, rngs=rngs)
    attn = lambda: nnx.List([layers.RelationalAttentionLayer(d, cfg.heads, cfg.dropout, rngs=rngs)  # noqa: E731
                             for _ in range(cfg.num_layers)])
    self.pl2a_1, self.a2a_1, self.pl2a_2, self.a2a_2 = attn(), attn(), attn(), attn()
    self.temporal = nnx.List([TemporalLayer(d, cfg.heads, cfg.temporal_ff, cfg.dropout, rngs=rngs)
                              for _ in range(cfg.temporal_layers)])
    self.coarse_head = MLP(d, d, 2, rngs=rngs)
    self.coarse_emb = MLP(2 * h, d, d, rngs=rngs)
    self.mode_emb = nnx.Embed(NUM_MODES, d, rngs=rngs)
    self.refine_head = MLP(d, d, 2 * h, rngs=rngs)
    if cfg.flow_noise_m > 0:  # the generative infiller reads the flow's state in its second stage
      self.noisy_emb = MLP(2 * h + 1, d, d, rngs=rngs)

  def pack(self, scene: datatypes.Scene) -> PackedAgents:
    """`pack_agents` of a host batch with this model's radii and neighbour count (on the host)."""
    cfg = self.cfg
    return pack_agents(scene, cfg.pl2a_radius_m, cfg.pl2a_neighbors, cfg.a2a_radius_m)

  def encode_map(self, scene: datatypes.Scene, key: jax.Array | None = None,
                 packed: PackedPolygons | None = None) -> MapContext:
    """Polygon embeddings `[B, P, D]` (relative geometry only: invariant to where the map lies); `packed`:
    the batch's packed polygons (`map_encoder.pack_polygons`) for an all-pairs map encoder."""
    zero, one = jnp.zeros(2), jnp.ones(2)
    return self.map_encoder(scene, zero, one, key, packed)

  def infill_agent(self, polygons: jax.Array, scene: datatypes.Scene, agent: AgentInputs,
                   key: jax.Array | None = None) -> jax.Array:
    """One agent's trajectory `[H, 2]` in metres, scene frame.

    Args:
      polygons: `[P, D]` this scene's polygon embeddings (shared by all agents).
      scene: one unbatched scene; its map geometry and its agents' initial states are the shared
        context (`agent_state[:, 0]`, `agent_type`, `agent_valid`).
      agent: this agent's inputs (unbatched).
      key: dropout key (None: deterministic).
    """
    cfg = self.cfg
    # Relations in the agent's frame, in metres.
    r_pl = layers.relative_geometry(scene.pl_xy, agent.xy, scene.pl_heading, agent.heading)      # [P, 3]
    pl_mask = scene.pl_valid & (r_pl[:, 0] <= cfg.pl2a_radius_m)
    k = cfg.pl2a_neighbors
    if 0 < k < pl_mask.shape[0]:  # the k nearest polygons: [k] instead of [P] relations per agent
      _, nearest = jax.lax.top_k(-jnp.where(pl_mask, r_pl[:, 0], jnp.inf), k)
      polygons, r_pl, pl_mask = polygons[nearest], r_pl[nearest], pl_mask[nearest]
    r_pl = self.r_pl2a(r_pl)                                                                     # [P or k, D]
    others_xy, others_heading = scene.agent_state[:, 0, :2], scene.agent_state[:, 0, 3]
    r_a = layers.relative_geometry(others_xy, agent.xy, others_heading, agent.heading)            # [A, 3]
    a_mask = (scene.agent_valid & (r_a[:, 0] <= cfg.a2a_radius_m)
              & (jnp.arange(scene.agent_valid.shape[0]) != agent.index))
    r_a = self.r_a2a(jnp.concatenate([r_a, scene.agent_state[:, 0, 2:3] / SPEED_SCALE], -1))      # [A, D]
    x_a = self.type_emb(scene.agent_type)                                                        # [A, D]

    def attend(q, pl_layer, a_layer, i):
      q = pl_layer(q[None], polygons, r_pl[None], pl_mask[None], layers.fold(key, 2 * i), src_index=None)[0]
      return a_layer(q[None], x_a, r_a[None], a_mask[None], layers.fold(key, 2 * i + 1), src_index=None)[0]

    return self._trajectory(agent, attend, key)

  def infill_packed(self, polygons: jax.Array, scene: datatypes.Scene, agents: AgentInputs, packed: PackedAgents,
                    key: jax.Array | None = None) -> jax.Array:
    """Every agent's trajectory `[B, A, H, 2]` (zeros for padded agents), computed on the packed list of
    the batch's valid agents and their real pairs (`pack_agents`): the same trajectories as
    `infill_agent` mapped over the padded batch, to float rounding (tested).

    Args:
      polygons: `[B, P, D]` the batch's polygon embeddings.
      scene: the batch of scenes.
      agents: `[B, A]` the agents' inputs.
      packed: `pack_agents(scene, ...)` with this model's radii.
      key: dropout key (None: deterministic).
    """
    b, a = scene.agent_valid.shape
    p = scene.pl_valid.shape[1]
    agent = jax.tree_util.tree_map(lambda x: x.reshape((b * a,) + x.shape[2:])[packed.agent], agents)   # [N]
    pl_xy, pl_heading = scene.pl_xy.reshape(b * p, 2), scene.pl_heading.reshape(b * p)
    r_pl = layers.relative_geometry(pl_xy[packed.pl_src], agent.xy[packed.pl_dst], pl_heading[packed.pl_src],
                                    agent.heading[packed.pl_dst])
    r_pl = self.r_pl2a(r_pl, valid=packed.pl_valid)                                              # [E, D]
    others = scene.agent_state[..., 0, :].reshape(b * a, -1)[packed.agent[packed.a_src]]         # [F, 4]
    r_a = layers.relative_geometry(others[:, :2], agent.xy[packed.a_dst], others[:, 3], agent.heading[packed.a_dst])
    r_a = self.r_a2a(jnp.concatenate([r_a, others[:, 2:3] / SPEED_SCALE], -1), valid=packed.a_valid)  # [F, D]
    x_pl, x_a = polygons.reshape(b * p, -1), self.type_emb(agent.type)                           # [B x P, D], [N, D]

    def attend(q, pl_layer, a_layer, i):
      q = pl_layer.packed(q, r_pl, packed.pl_dst, packed.pl_src, packed.pl_valid, layers.fold(key, 2 * i), x_src=x_pl)
      return a_layer.packed(q, r_a, packed.a_dst, packed.a_src, packed.a_valid, layers.fold(key, 2 * i + 1), x_src=x_a)

    traj = self._trajectory(agent, attend, key)                                                  # [N, H, 2]
    target = jnp.where(packed.agent_valid, packed.agent, b * a)   # padding rows: past the end, dropped
    out = jnp.zeros((b * a,) + traj.shape[1:], traj.dtype).at[target].set(traj, mode="drop")
    return out.reshape((b, a) + traj.shape[1:])

  def _trajectory(self, agent: AgentInputs, attend: Callable, key: jax.Array | None) -> jax.Array:
    """The network around its attention: trajectories `[..., H, 2]` (metres, scene frame) of agents
    `[...]` (one agent, or a packed list). `attend(q [..., D], pl_layer, a_layer, i) -> q` runs one map and
    one agent attention layer for the queries (`infill_agent`'s dense, `infill_packed`'s packed)."""
    cfg = self.cfg
    horizon = cfg.horizon
    flat = lambda x: x.reshape(x.shape[:-2] + (-1,))  # noqa: E731  [..., H, 2] -> [..., 2H]
    gamma = mode_weights(agent.mode, horizon)[..., None]                                          # [..., H, 1]
    goal_local = geometry.rotate(agent.goal - agent.xy, -agent.heading)                           # [..., 2]
    bridge_local = bridge(jnp.zeros_like(goal_local), goal_local, horizon)                        # [..., H, 2]

    q = (self.agent_token[...] + self.type_emb(agent.type)
         + self.speed_emb(agent.speed / SPEED_SCALE - 1.0))                                      # [..., D]
    bridge_emb = self.bridge_emb(flat(bridge_local) / POSITION_SCALE_M)
    for i, (pl_layer, a_layer) in enumerate(zip(self.pl2a_1, self.a2a_1)):
      q = attend(q + bridge_emb, pl_layer, a_layer, i)

    steps = q[..., None, :] + sinusoidal_positions(horizon, cfg.dim)                             # [..., H, D]
    for i, layer in enumerate(self.temporal):
      steps = layer(steps, layers.fold(key, 100 + i))
    coarse = bridge_local + gamma * self.coarse_head(steps)                                      # [..., H, 2]

    q = self.coarse_emb(flat(coarse) / POSITION_SCALE_M)
    if cfg.flow_noise_m > 0:
      q = q + self.noisy_emb(jnp.concatenate([flat(agent.noisy) / POSITION_SCALE_M, agent.flow_time[..., None]], -1))
    mode = self.mode_emb(agent.mode)
    for i, (pl_layer, a_layer) in enumerate(zip(self.pl2a_2, self.a2a_2)):
      q = attend(q + mode, pl_layer, a_layer, 10 + i)
    local = coarse + gamma * self.refine_head(q).reshape(q.shape[:-1] + (horizon, 2))
    return agent.xy[..., None, :] + geometry.rotate(local, agent.heading[..., None])

  def __call__(self, scene: datatypes.Scene, initial_heading: jax.Array, mode: jax.Array,
               key: jax.Array | None = None, map_context: MapContext | None = None,
               packed: PackedPolygons | None = None, packed_agents: PackedAgents | None = None,
               noisy: jax.Array | None = None, flow_time: jax.Array | None = None) -> jax.Array:
    """Trajectories `[B, A, H, 2]` (metres, scene frame; zeros for padded agents).

    Args:
      scene: a batch of scenes; `agent_state[..., 0, :]` / `[..., 1, :]` are the initial / goal states.
      initial_heading: `[B, A]` initial headings (rad).
      mode: `[B, A]` hard-constraint mode ids.
      key: dropout key (None: deterministic).
      map_context: `encode_map(scene)` computed apart (e.g. per scene); default: encoded here.
      packed: the packed polygons for `encode_map` (all-pairs map encoders).
      packed_agents: `pack_agents(scene, ...)`: the agents and pairs computed packed (`infill_packed`)
        instead of mapped over the padded batch; the same trajectories.
      noisy, flow_time: a generative infiller's (`flow_noise_m > 0`) flow state `[B, A, H, 2]` (displacements
        from the bridge, agent frame: `bridge_displacement`) and time `[B, A]`; it then returns its estimate
        of the data's trajectories (`infilling.infill` runs the flow).
    """
    if (self.cfg.flow_noise_m > 0) != (noisy is not None):
      raise ValueError("a generative infiller (flow_noise_m > 0) takes noisy and flow_time; a deterministic one neither")
    b, a = scene.agent_valid.shape
    if map_context is None:
      map_context = self.encode_map(scene, layers.fold(key, 0), packed)
    polygons = map_context.polygons
    agents = AgentInputs(
        index=jnp.broadcast_to(jnp.arange(a), (b, a)), xy=scene.agent_state[..., 0, :2],
        heading=initial_heading, goal=scene.agent_state[..., 1, :2], speed=scene.agent_state[..., :, 2],
        type=scene.agent_type, mode=mode, noisy=noisy, flow_time=flow_time)
    if packed_agents is not None:
      return self.infill_packed(polygons, scene, agents, packed_agents, layers.fold(key, 1))
    keys = None if key is None else jax.random.split(jax.random.fold_in(key, 1), (b, a))

    def per_scene(polygons_s, scene_s, agents_s, keys_s):
      per_agent = lambda ag, k: self.infill_agent(polygons_s, scene_s, ag, k)  # noqa: E731
      return jax.vmap(per_agent)(agents_s, keys_s) if keys_s is not None else \
          jax.vmap(lambda ag: per_agent(ag, None))(agents_s)

    traj = jax.vmap(per_scene)(polygons, scene, agents, keys)
    return jnp.where(scene.agent_valid[..., None, None], traj, 0.0)
