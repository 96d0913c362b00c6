"""The high-level (HL) denoiser: epsilon prediction for every agent's initial and goal state, jointly.

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

Shapes: B scenes, A agents, P polygons, D width; states `[B, A, 2, 3]`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import ml_collections
from flax import nnx

from tdiff_jax import types
from tdiff_jax.models import layers, model_config
from tdiff_jax.models.map_encoder import MapContext, MapEncoder

STATE_DIM = 3


@dataclasses.dataclass(frozen=True)
class HLModelConfig:
  dim: int = 128
  heads: int = 8
  num_layers: int = 3
  map_layers: int = 1
  num_freq_bands: int = 64
  num_latents: int = 16
  dropout: float = 0.1
  pl2pl_radius_m: float = 150.0
  pl2pl_neighbors: int = 0
  max_agents: int = 64  # size of the agent-identity embedding

  @classmethod
  def from_config(cls, c: ml_collections.ConfigDict, max_agents: int) -> "HLModelConfig":
    return model_config.from_config(cls, c, max_agents=max_agents)


class DenoiserLayer(nnx.Module):

  def __init__(self, dim: int, heads: int, depth: int, dropout_rate: float, *, rngs: nnx.Rngs):
    self.dropout_rate = dropout_rate
    self.norms = nnx.List([nnx.LayerNorm(dim, rngs=rngs) for _ in range(5)])
    self.summary_attn = layers.MultiHeadAttention(dim, heads, rngs=rngs)
    self.temporal_attn = layers.MultiHeadAttention(dim, heads, rngs=rngs)
    self.social_attn = layers.MultiHeadAttention(dim, heads, rngs=rngs)
    self.map_attn = layers.DifferentialAttention(dim, heads, depth, rngs=rngs)
    self.ff = layers.FeedForward(dim, 4 * dim, rngs=rngs)

  def __call__(self, x: jax.Array, ctx: MapContext, social_mask: jax.Array,
               key: jax.Array | None) -> tuple[jax.Array, jax.Array]:
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
    out, w = self.map_attn(q, ctx.polygons, jnp.broadcast_to(ctx.valid[:, None], (b, a * t, ctx.valid.shape[-1])))
    x = x + drop(out.reshape(x.shape), 3)
    # 5. FFN (no outer dropout, as the official layer)
    x = x + self.ff(self.norms[4](x), rate, layers.fold(key, 4))
    return x, w


class HLDenoiser(nnx.Module):

  def __init__(self, cfg: HLModelConfig, *, rngs: nnx.Rngs):
    d = cfg.dim
    self.cfg = cfg
    self.map_encoder = MapEncoder(d, cfg.heads, cfg.map_layers, cfg.num_freq_bands, cfg.num_latents,
                                  cfg.dropout, cfg.pl2pl_radius_m, cfg.pl2pl_neighbors, rngs=rngs)
    self.state_in = nnx.Linear(STATE_DIM, d, rngs=rngs)
    self.type_emb = nnx.Embed(len(types.AGENT_TYPES), d, rngs=rngs)
    self.id_emb = nnx.Embed(cfg.max_agents, d, rngs=rngs)
    self.time_emb = nnx.Embed(2, d, rngs=rngs)
    self.token_proj = nnx.Linear(4 * d, d, rngs=rngs)
    self.token_norm = nnx.LayerNorm(d, rngs=rngs)
    self.noise_emb = layers.FourierEmbedding(1, d, cfg.num_freq_bands, rngs=rngs)
    self.layers = nnx.List([DenoiserLayer(d, cfg.heads, i, cfg.dropout, rngs=rngs) for i in range(cfg.num_layers)])
    self.trunk = nnx.List([nnx.Linear(2 * d, d, rngs=rngs), nnx.Linear(d, d, rngs=rngs), nnx.Linear(d, d, rngs=rngs)])
    self.pos_head = nnx.List([nnx.Linear(d, d, rngs=rngs), nnx.Linear(d, 4, rngs=rngs)])
    self.speed_head = nnx.List([nnx.Linear(d, d, rngs=rngs), nnx.Linear(d, 2, rngs=rngs)])

  def encode_map(self, scene: types.Scene, state_mean: jax.Array, state_std: jax.Array,
                 key: jax.Array | None = None) -> MapContext:
    """Polygon embeddings and map summary; `state_mean/std` `[3]` are the dataset statistics."""
    return self.map_encoder(scene, state_mean[:2], state_std[:2], key)

  def denoise(self, ctx: MapContext, x_t: jax.Array, beta_t: jax.Array, agent_type: jax.Array,
              agent_valid: jax.Array, agent_id: jax.Array | None = None, self_only: jax.Array | None = None,
              key: jax.Array | None = None) -> tuple[jax.Array, list[jax.Array]]:
    """epsilon `[B, A, 2, 3]` (zero for padded agents) and the map attention `[B, H, 2A, P]` per layer.

    Args:
      x_t: `[B, A, 2, 3]` noisy normalised states. beta_t: `[B]` the noise level of each scene.
      agent_type, agent_valid: `[B, A]`. agent_id: `[B, A]` identity indices (default: row index).
      self_only: `[B]` bool, agents attend only to themselves (interaction dropout).
    """
    b, a = agent_valid.shape
    if agent_id is None:
      agent_id = jnp.broadcast_to(jnp.arange(a), (b, a))
    tok = jnp.concatenate([
        self.state_in(x_t),
        jnp.broadcast_to(self.type_emb(agent_type)[:, :, None], x_t.shape[:3] + (self.cfg.dim,)),
        jnp.broadcast_to(self.id_emb(agent_id)[:, :, None], x_t.shape[:3] + (self.cfg.dim,)),
        jnp.broadcast_to(self.time_emb(jnp.arange(2)), x_t.shape[:3] + (self.cfg.dim,)),
    ], axis=-1)
    m0 = jax.nn.silu(self.token_norm(self.token_proj(tok)))               # [B, A, 2, D]
    noise = self.noise_emb(beta_t[:, None])[:, None, None]                # [B, 1, 1, D]
    social = agent_valid[:, :, None] & agent_valid[:, None, :]
    if self_only is not None:
      social = social & (~self_only[:, None, None] | jnp.eye(a, dtype=bool))
    x, m_sum, maps = m0, m0, []
    for i, layer in enumerate(self.layers):
      x, w = layer(x + noise, ctx, social, layers.fold(key, i))
      m_sum, maps = m_sum + x, maps + [w]
    h = m_sum.reshape(b, a, -1)
    h = jax.nn.leaky_relu(self.trunk[0](h), 0.1)
    h = jax.nn.leaky_relu(self.trunk[1](h), 0.1)
    h = self.trunk[2](h)
    pos = self.pos_head[1](jax.nn.relu(self.pos_head[0](h)))              # [B, A, 4]
    speed = self.speed_head[1](jax.nn.relu(self.speed_head[0](h)))        # [B, A, 2]
    eps = jnp.concatenate([pos.reshape(b, a, 2, 2), speed[..., None]], axis=-1)
    return jnp.where(agent_valid[:, :, None, None], eps, 0.0), maps

  def __call__(self, scene: types.Scene, x_t: jax.Array, beta_t: jax.Array, state_mean: jax.Array,
               state_std: jax.Array, agent_id=None, self_only=None, key=None):
    ctx = self.encode_map(scene, state_mean, state_std, layers.fold(key, 100))
    return self.denoise(ctx, x_t, beta_t, scene.agent_type, scene.agent_valid, agent_id, self_only,
                        layers.fold(key, 101))
