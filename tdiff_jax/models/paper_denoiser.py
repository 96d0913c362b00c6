"""The paper's high-level (HL) denoiser: epsilon prediction for every agent's initial and goal state, jointly.

Paper §IV-A and reference notes §2.2-2.5. Each agent is a sequence of two tokens (initial, goal). A
token is the shared linear embedding of its noisy state `[x, y, s]`, concatenated with agent-type,
agent-identity and token-time embeddings and projected to D. The noise level (beta_t, Fourier
embedded) is added before every layer. Each layer, pre-norm with residuals:
  1. cross-attention from every token to the map summary,
  2. temporal self-attention over the agent's two tokens,
  3. social self-attention over the scene's agents at each token (padded agents masked; with
     `self_only` an agent sees only itself, the training-time interaction dropout),
  4. differential cross-attention to the polygon embeddings (padded polygons masked), whose maps feed
     the entropy loss,
  5. FFN.
The head reads the input stream plus every layer's output, flattens the two tokens and predicts
epsilon for position and speed with two small heads.

The interface both HL denoisers share (`grounded_denoiser.GroundedDenoiser` is the default's, beyond the
paper): `encode_map(scene, norm)` once per map, then `denoise(ctx, x_t, beta_t, alpha_bar_t, agent_type,
agent_valid, ...)` -> (epsilon, attention maps) per network call; `__call__` does both. What a denoiser's
state and training are is fixed by its config class (`state_dim`, `heading_state`, `goal_offset`,
`self_condition`, `staged_noise`, `loss_weighting`, `t_sampling`), not by switches.

Shapes: B scenes, A agents, P polygons, D width; states `[B, A, 2, F]`, F = 3 (x, y, speed) or, with
headings, 5 (and cos, sin of the heading).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import ml_collections
from flax import nnx, struct

from tdiff_jax import datatypes
from tdiff_jax.data.normalize import NormStats
from tdiff_jax.models import grounding, layers, model_config
from tdiff_jax.models.map_encoder import MapContext, MapEncoder, MapInputs, PackedPolygons

DENOISERS = ("paper", "grounded")


def per_token(level: jax.Array, feature_axis: bool = False) -> jax.Array:
  """A noise quantity `[B]` or `[B, 2]` (per token time), `[..., D]` with `feature_axis`, shaped to
  broadcast against states `[B, A, 2, F]`: `[B, 1, 1, 1]` or `[B, 1, 2, 1]` (`[B, 1, 1 or 2, D]`)."""
  lead = level.ndim - (1 if feature_axis else 0)
  if lead not in (1, 2):
    raise ValueError(f"noise levels of shape {level.shape}: one per scene [B] or per token time [B, 2]")
  tail = level.shape[lead:]
  return level.reshape(level.shape[:1] + (1,) + ((1,) if lead == 1 else level.shape[1:2]) + (tail or (1,)))


# The fields of earlier versions' models: options measured and dropped (docs/research_log.md), the switches
# that made one denoiser the paper's or the grounded one (now `model.denoiser`), the lane pull's settings (now
# the call's `lane_pull.LanePull`). A checkpoint whose config names one is refused, naming the version that
# reads it (`model_config.older_options_error`).
OLDER_FIELDS = ("token_displacement", "position_skip_m", "social_geometry", "position_step", "position_step_min_m",
                "lane_snap", "goal_kinematic", "map_point_inputs", "map_points_per_polyline", "pl2pl_tables",
                "lane_pull_m", "lane_pull_clearance_m", "lane_pull_end_m", "lane_pull_route_m", "lane_pull_noise_m",
                "map_attention", "lane_routes", "map_inputs", "noise_input", "prediction", "goal_offset",
                "speed_step", "heading_state", "self_condition", "agent_frame", "token_noise")


@dataclasses.dataclass(frozen=True)
class PaperConfig:
  """The paper's denoiser (`model.denoiser="paper"`): sizes only."""

  # What the denoiser is, not options: its state, its normalisation and how it is trained.
  state_dim: ClassVar[int] = 3          # x, y, speed
  heading_state: ClassVar[bool] = False  # the state also holds (cos, sin) of the heading
  goal_offset: ClassVar[bool] = False   # the goal position is diffused as its offset from the initial one
  self_condition: ClassVar[bool] = False  # `denoise` reads the previous x0 estimate (`x0_prev`)
  staged_noise: ClassVar[bool] = False  # trained also on initial states alone and goals given them
  loss_weighting: ClassVar[str] = "eps"  # the loss's weight per noise level (`hl_objective.LOSS_WEIGHTINGS`)
  t_sampling: ClassVar[str] = "uniform"  # how training draws noise levels (`hl_objective.T_SAMPLINGS`)

  dim: int = 128
  heads: int = 8
  num_layers: int = 3
  map_layers: int = 1
  num_freq_bands: int = 64
  num_latents: int = 16
  dropout: float = 0.1
  pl2pl_radius_m: float = 150.0
  pl2pl_neighbors: int = 0
  fourier_tables: int = 0  # > 0: the map encoder's slowly varying embeddings interpolated from tables (`MapEncoder`)
  max_agents: int = 64  # size of the agent-identity embedding

  def __post_init__(self):
    layers.check_fourier_tables(self.fourier_tables)  # otherwise ignored without a word

  @classmethod
  def from_config(cls, c: ml_collections.ConfigDict, max_agents: int):
    return model_config.from_config(cls, c, older=OLDER_FIELDS, max_agents=max_agents)


class DenoiserLayer(nnx.Module):

  def __init__(self, dim: int, heads: int, depth: int, dropout_rate: float, grounded: bool = False,
               *, rngs: nnx.Rngs):
    self.dropout_rate = dropout_rate
    self.norms = nnx.List([nnx.LayerNorm(dim, rngs=rngs) for _ in range(5)])
    self.summary_attn = layers.MultiHeadAttention(dim, heads, rngs=rngs)
    self.temporal_attn = layers.MultiHeadAttention(dim, heads, rngs=rngs)
    self.social_attn = layers.MultiHeadAttention(dim, heads, rngs=rngs)
    self.map_attn = layers.DifferentialAttention(dim, heads, depth, relational=grounded, rngs=rngs)
    self.ff = layers.FeedForward(dim, 4 * dim, rngs=rngs)

  def __call__(self, x: jax.Array, ctx: MapContext, social_mask: jax.Array, key: jax.Array | None,
               pairs=None, map_kv: tuple[jax.Array, jax.Array] | None = None) -> tuple[jax.Array, jax.Array]:
    """`pairs`: the grounded map attention's (token, polygon) terms (`grounded_denoiser.GroundedPairs`);
    `map_kv`: this layer's polygon keys and values, computed once per map. Returns x and the map attention
    `[B, H, 2A, P]` (zero for polygons a token does not attend to)."""
    b, a, t, d = x.shape
    rate = self.dropout_rate
    drop = lambda y, i: layers.dropout(y, rate, layers.fold(key, i))  # noqa: E731
    # 1. map summary
    q = self.norms[0](x).reshape(b, a * t, d)
    x = x + drop(self.summary_attn(q, ctx.summary).reshape(x.shape), 0)
    # 2. temporal, over each agent's two tokens
    h = self.norms[1](x)
    x = x + drop(self.temporal_attn(h, h), 1)
    # 3. social, over agents at each token
    h = jnp.swapaxes(self.norms[2](x), 1, 2)                            # [B, 2, A, D]
    x = x + drop(jnp.swapaxes(self.social_attn(h, h, social_mask[:, None]), 1, 2), 2)
    # 4. differential attention to the polygons
    q = self.norms[3](x).reshape(b, a * t, d)
    if pairs is None:
      out, w = self.map_attn(q, ctx.polygons, jnp.broadcast_to(ctx.valid[:, None], (b, a * t, ctx.valid.shape[-1])),
                             kv=map_kv)
    else:
      out, w = self.map_attn(q, ctx.polygons, pairs.mask, pairs.relation, pairs.bias, pairs.index, kv=map_kv)
      if pairs.index is not None:  # back to all polygons, for the entropy loss
        p = ctx.valid.shape[-1]
        w = jnp.sum(w[..., None] * jax.nn.one_hot(pairs.index, p, dtype=w.dtype)[:, None], axis=-2)
    x = x + drop(out.reshape(x.shape), 3)
    # 5. FFN (no outer dropout, as the official layer)
    x = x + self.ff(self.norms[4](x), rate, layers.fold(key, 4))
    return x, w


@struct.dataclass
class HLContext:
  """Everything a denoiser needs of the map, computed once per sampling call."""

  map: MapContext
  heading: jax.Array            # [B, P] polygon headings
  frame_scale: jax.Array        # [B] metres per scene unit
  norm: NormStats               # normalisation of the model state
  lines: grounding.Centerlines | None = None  # each polygon's centreline segments (m), grounded
  routes: jax.Array | None = None  # [B, P, P] lane-graph route lengths (m), grounded
  map_kv: tuple | None = None   # per denoiser layer, the map attention's polygon keys and values [B, P, D]
  lanes: jax.Array | None = None  # [B, P] polygons that are lanes (not crosswalks)


class PaperDenoiser(nnx.Module):
  """The paper's denoiser (module docstring)."""

  MAP_INPUTS: ClassVar[str] = "normalized"  # the map encoder's absolute inputs (`MapEncoder`)
  GROUNDED: ClassVar[bool] = False  # the map attention reads each (token, polygon) pair's geometry

  def __init__(self, cfg: PaperConfig, *, rngs: nnx.Rngs):
    d = cfg.dim
    self.cfg = cfg
    self.map_encoder = MapEncoder(d, cfg.heads, cfg.map_layers, cfg.num_freq_bands, cfg.num_latents,
                                  cfg.dropout, cfg.pl2pl_radius_m, cfg.pl2pl_neighbors,
                                  input_mode=self.MAP_INPUTS, fourier_tables=cfg.fourier_tables, rngs=rngs)
    self.state_in = nnx.Linear(cfg.state_dim, d, rngs=rngs)
    self.type_emb = nnx.Embed(len(datatypes.AGENT_TYPES), d, rngs=rngs)
    self.id_emb = nnx.Embed(cfg.max_agents, d, rngs=rngs)
    self.time_emb = nnx.Embed(2, d, rngs=rngs)
    self.token_proj = nnx.Linear(4 * d, d, rngs=rngs)
    self.token_norm = nnx.LayerNorm(d, rngs=rngs)
    self.noise_emb = layers.FourierEmbedding(1, d, cfg.num_freq_bands, self._noise_freqs(), rngs=rngs)
    self.layers = nnx.List([DenoiserLayer(d, cfg.heads, i, cfg.dropout, self.GROUNDED, rngs=rngs)
                            for i in range(cfg.num_layers)])
    self._create_layer_extras(rngs)
    self.trunk = nnx.List([nnx.Linear(2 * d, d, rngs=rngs), nnx.Linear(d, d, rngs=rngs), nnx.Linear(d, d, rngs=rngs)])
    self.pos_head = nnx.List([nnx.Linear(d, d, rngs=rngs), nnx.Linear(d, 4, rngs=rngs)])
    self.speed_head = nnx.List([nnx.Linear(d, d, rngs=rngs), nnx.Linear(d, 2, rngs=rngs)])
    self._create_head_extras(rngs)

  # Where a denoiser beyond the paper adds modules (in this order, so the paper's modules start alike).
  def _noise_freqs(self) -> jax.Array | None:
    return None

  def _create_layer_extras(self, rngs: nnx.Rngs) -> None:
    pass

  def _create_head_extras(self, rngs: nnx.Rngs) -> None:
    pass

  def encode_map(self, scene: datatypes.Scene, norm: NormStats, key: jax.Array | None = None,
                 map_context: MapContext | None = None, packed: PackedPolygons | None = None,
                 map_inputs: MapInputs | None = None) -> HLContext:
    """Polygon embeddings and map summary; `norm`: the dataset's normalisation statistics.

    `map_context`: the map encoder's output for `scene`, when it was computed apart (`sampling.encode_maps`
    encodes each scene at its own polygon bucket); otherwise the map encoder runs here, over the packed
    polygons `packed` when given (`map_encoder.pack_polygons`, all-pairs encoders), taking the encoder's
    input side from `map_inputs` when given (`MapEncoder.input_side`, computed apart).
    """
    if norm.goal_offset != self.cfg.goal_offset:
      raise ValueError(f"the {type(self).__name__} {'diffuses' if self.cfg.goal_offset else 'does not diffuse'} "
                       f"goal offsets but the normalisation statistics {'have' if norm.goal_offset else 'lack'} them")
    if norm.heading != self.cfg.heading_state:
      raise ValueError(f"the {type(self).__name__} {'has' if self.cfg.heading_state else 'has no'} headings in "
                       f"its state but the normalisation statistics {'have' if norm.heading else 'lack'} them")
    if map_context is None:
      map_context = self.map_encoder(scene, norm.mean[:2], norm.std[:2], key, packed, map_inputs)
    # The polygons' keys and values of every layer's map attention, once per map instead of once per step.
    map_kv = tuple(layer.map_attn.project_sources(map_context.polygons) for layer in self.layers)
    return HLContext(map_context, scene.pl_heading, scene.frame_scale, norm, map_kv=map_kv,
                     lanes=scene.lane_polygons)

  def _tokens(self, state: jax.Array, agent_type: jax.Array, agent_id: jax.Array | None) -> jax.Array:
    """`[B, A, 2, D]`: each token's embedded state `state` with its agent's type and identity and its time."""
    b, a = agent_type.shape
    if agent_id is None:
      agent_id = jnp.broadcast_to(jnp.arange(a), (b, a))
    shape = state.shape[:3] + (self.cfg.dim,)
    tok = jnp.concatenate([
        state,
        jnp.broadcast_to(self.type_emb(agent_type)[:, :, None], shape),
        jnp.broadcast_to(self.id_emb(agent_id)[:, :, None], shape),
        jnp.broadcast_to(self.time_emb(jnp.arange(2)), shape),
    ], axis=-1)
    return jax.nn.silu(self.token_norm(self.token_proj(tok)))

  @staticmethod
  def _social_mask(agent_valid: jax.Array, self_only: jax.Array | None) -> jax.Array:
    """`[B, A, A]` which agents each agent attends to: valid ones, only itself where `self_only` `[B]`."""
    social = agent_valid[:, :, None] & agent_valid[:, None, :]
    if self_only is not None:
      social = social & (~self_only[:, None, None] | jnp.eye(agent_valid.shape[1], dtype=bool))
    return social

  def _trunk(self, m_sum: jax.Array) -> jax.Array:
    """`[B, A, D]` the head's shared trunk over an agent's two tokens `[B, A, 2, D]`."""
    h = m_sum.reshape(m_sum.shape[0], m_sum.shape[1], -1)
    h = jax.nn.leaky_relu(self.trunk[0](h), 0.1)
    h = jax.nn.leaky_relu(self.trunk[1](h), 0.1)
    return self.trunk[2](h)

  def denoise(self, ctx: HLContext, x_t: jax.Array, beta_t: jax.Array, alpha_bar_t: jax.Array,
              agent_type: jax.Array, agent_valid: jax.Array, agent_id: jax.Array | None = None,
              self_only: jax.Array | None = None, key: jax.Array | None = None) -> tuple[jax.Array, list[jax.Array]]:
    """epsilon `[B, A, 2, F]` (zero for padded agents) and the map attention `[B, H, 2A, P]` per layer.

    Args:
      x_t: `[B, A, 2, F]` noisy normalised states (F = `cfg.state_dim`). beta_t, alpha_bar_t: `[B]` the noise
        level of each scene, or `[B, 2]` one per token time (initial, goal); the paper's denoiser reads beta_t.
      agent_type, agent_valid: `[B, A]`. agent_id: `[B, A]` identity indices (default: row index).
      self_only: `[B]` bool, agents attend only to themselves (interaction dropout).
    """
    b, a = agent_valid.shape
    m0 = self._tokens(self.state_in(x_t), agent_type, agent_id)             # [B, A, 2, D]
    noise = per_token(self.noise_emb(beta_t[..., None]), feature_axis=True)  # [B, 1, 1 or 2, D]
    social = self._social_mask(agent_valid, self_only)
    x, m_sum, maps = m0, m0, []
    for i, layer in enumerate(self.layers):
      x, w = layer(x + noise, ctx.map, social, layers.fold(key, i), None, ctx.map_kv[i])
      m_sum, maps = m_sum + x, maps + [w]
    h = self._trunk(m_sum)
    pos = self.pos_head[1](jax.nn.relu(self.pos_head[0](h))).reshape(b, a, 2, 2)
    speed = self.speed_head[1](jax.nn.relu(self.speed_head[0](h)))[..., None]   # [B, A, 2, 1]
    out = jnp.concatenate([pos, speed], axis=-1)
    return jnp.where(agent_valid[:, :, None, None], out, 0.0), maps

  def __call__(self, scene: datatypes.Scene, x_t: jax.Array, beta_t: jax.Array, alpha_bar_t: jax.Array,
               norm: NormStats, agent_id=None, self_only=None, key=None, packed: PackedPolygons | None = None,
               map_inputs: MapInputs | None = None, **denoise_args):
    """`encode_map` then `denoise` (`denoise_args`: the denoiser's own, e.g. the grounded one's `x0_prev`)."""
    ctx = self.encode_map(scene, norm, layers.fold(key, 100), packed=packed, map_inputs=map_inputs)
    return self.denoise(ctx, x_t, beta_t, alpha_bar_t, scene.agent_type, scene.agent_valid, agent_id, self_only,
                        layers.fold(key, 101), **denoise_args)
