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

Options beyond the paper (`HLModelConfig`; docs/training.md):
* `map_attention="grounded"`: the differential map attention of every layer also sees, for each
  (token, polygon) pair, where the polygon's centreline lies seen from the token's current position
  estimate, in metres (`grounding.relation_features`), embedded into its keys and values, with a
  per-head -log(1 + distance) bias. The first estimate is E[x0 | x_t] = sqrt(alpha_bar_t) x_t under
  the unit-variance prior of the normalised state; with `prediction="x0"` each layer then moves
  it by a learned offset, so later layers look at the lanes near where the agent is going.
  `grounded_neighbors=k` restricts each token to its k nearest polygons. With `lane_routes`, each (token, polygon) pair also gets the length of the shortest route along the
  directed lane graph (successors and lane changes, `grounding.lane_routes`) from the initial to the
  goal position if this token were on this polygon and the other token on one of its nearest lanes:
  the map's topology, which the geometry alone does not show (which lanes lead where).
* `prediction="x0"`: the network predicts the clean state (grounded: positions in metres as the last
  estimate plus a learned offset in units of 10 m) and returns the equivalent epsilon, so samplers
  and losses are unchanged.
* The lane pull (`LanePull`, the call's `lane_pull`; grounded x0 with headings): with `across_m=d` > 0 the
  final position estimate of every moving road user's token (speed estimate at least 1 m/s; not
  pedestrians) is moved across its lane onto the nearest lane centreline (not crosswalks) whose direction
  agrees with its heading estimate (within 60 degrees), when that centreline is at most d metres away
  across it; along the lane it stays. With `clearance_m=c` > 0 a token is not pulled where that would
  bring it nearer than c metres to another agent's token of the same kind (initial or goal, at its pulled
  or its own place) than it was before: two agents side by side between two lanes are not both put on one
  centreline. With `end_m=e` > 0 a token past the end (or before the start) of that centreline, at most e
  metres along it, is also moved back onto its end: the network, short of training, drives agents past
  the end of lanes that leave the map, where the data has none. With `route_m=r` > 0 (needs
  `lane_routes`) a goal token goes onto the nearest lane its heading agrees with that its agent's initial
  lane leads to along the lane graph within the next 6 s (successors and lane changes,
  `_prefer_routed_goals`), from at most r metres across; with no such lane within r the pull is as
  without. A lane prior on the network's output, parameter-free: a call's setting, not the model's, so
  any checkpoint can be sampled with or without it (docs/research_log.md); the trainer passes the
  config's `lane_pull` section.
* `speed_step="noise_scaled"` (x0): the speed is sqrt(alpha_bar) x_t + sqrt(1 - alpha_bar) F (the
  c_skip and c_out of the unit-variance normalised speed), so a stopped agent stays stopped at low
  noise; "fixed": the head gives the clean speed itself.
* `noise_input="log_snr"`: the noise level enters as log(alpha_bar / (1 - alpha_bar)) with Fourier
  periods from 1 to 64 (it spans about -13 to 9), instead of beta_t (whose embeddings for t = 1, 10
  and 30 are nearly identical).
* `map_inputs="metric"`: the map encoder's absolute inputs in metres and (cos, sin) (`MapEncoder`).
* `goal_offset`: the goal token's position in the diffused state is its offset from the initial
  position (`data.normalize`; the trainer adds the offsets' statistics to `NormStats`), so the noise
  and the denoising act on how far and where each agent goes. The grounded geometry is unchanged: it
  works on positions in metres either way.
* `heading_state`: each token's state also holds the agent's heading as (cos, sin) (`NormStats.heading`),
  predicted by a head of its own (as the speed: eps or x0). Grounded, every (token, polygon) pair
  also gets the heading estimate's dot and cross product with the centreline's direction at the nearest
  point: whether the agent would drive along the lane or against it, which the position alone does not
  tell on a two-way road, and which decides where along the lane graph its goal can be. The estimate
  starts at sqrt(alpha_bar) x_t and, with x0, each layer refines it as it refines the position.
* `self_condition` (x0; Chen et al. 2023, "Analog Bits"): the denoiser also reads a previous
  estimate of x0 (the sampler's last step's; in training its own first pass on the same x_t, for half the
  scenes), embedded and added to each token's state embedding with a flag saying whether there is one.
  Grounded, that estimate is also where the position and heading estimates start, instead of
  sqrt(alpha_bar) x_t: at mid noise the map attention then looks at the lanes near where the last step
  put the agent, not near the shrunk noisy state.
* `agent_frame` (grounded x0 with headings): each position update and the position head also step along
  and across the heading estimate of the agent's initial token, and each token reads its displacement to
  the agent's other token in that frame.
* `token_noise="staged"` (a training recipe; `hl_objective`): each drawn training sample is, with equal
  probability, both tokens at one noise level (the paper), the initial token at t with the goal's pure
  noise (t = T: the initial state alone), or the goal token at t given the clean initial state (t = 0).
  The staged draws act as an auxiliary task that teaches the joint model how an agent's goal follows
  from its initial state (it is sampled jointly). The denoiser takes a noise level per scene (`[B]`) or
  per token time (`[B, 2]`, initial and goal).

Shapes: B scenes, A agents, P polygons, D width; states `[B, A, 2, F]`, F = 3 (x, y, speed) or 5 (with
cos and sin of the heading).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import ml_collections
from flax import nnx, struct

from tdiff_jax import datatypes
from tdiff_jax.data.normalize import NormStats, denormalize_speed, positions_from_metres, positions_to_metres
from tdiff_jax.models import grounding, layers, model_config
from tdiff_jax.models.map_encoder import INPUT_MODES, MapContext, MapEncoder, MapInputs, PackedPolygons

STATE_DIM = 3  # x, y, speed; with heading_state also cos and sin of the heading
HEADING_FEATURES = 2  # grounded, with heading_state: heading . lane direction and heading x lane direction
MAP_ATTENTIONS = ("paper", "grounded")
PREDICTIONS = ("eps", "x0")
NOISE_INPUTS = ("beta", "log_snr")
TOKEN_NOISES = ("shared", "staged")
# The noise-level input of a clean token (t = 0, staged): log-SNR is infinite there; this is beyond
# t = 1's (about 9.2) and the Fourier periods' range.
CLEAN_LOG_SNR = 16.0
SPEED_STEPS = ("fixed", "noise_scaled")
# One unit of a position offset output with prediction="x0", in metres.
POSITION_STEP_M = 10.0
# `lane_routes`: the other token's lanes a route may start or end on (its nearest few, within this of
# its nearest, so overlapping lanes in junctions all count), and how far back a route may go.
ROUTE_CANDIDATES = 4
ROUTE_CANDIDATE_M = 0.5
ROUTE_BACKWARD_M = 2.0
# `LanePull.route_m`: a goal is 6 s (AV2 steps 50 -> 109) after the initial state; a route to it is at most
# what the agent's faster speed covers in that time, plus this slack.
ROUTE_HORIZON_S = 6.0
ROUTE_SLACK_M = 10.0
# The lane pull: a lane agrees with a heading within 60 degrees; below this speed a heading says little.
LANE_PULL_AGREE_COS = 0.5
LANE_PULL_MIN_MPS = 1.0


@dataclasses.dataclass(frozen=True)
class LanePull:
  """The lane pull's settings (module docstring), in metres; 0 turns a part off, `across_m=0` the pull."""

  across_m: float = 0.0     # estimates at most this far across a lane their heading agrees with go onto it
  clearance_m: float = 0.0  # ... not where that would bring two agents' tokens nearer than this
  end_m: float = 0.0        # ... and back onto the lane's end from at most this far past it
  route_m: float = 0.0      # ... goals onto lanes their initial lane leads to, from at most this far

  def __post_init__(self):
    for name, value in dataclasses.asdict(self).items():
      if value < 0:
        raise ValueError(f"lane_pull.{name} must be >= 0 (0: off), got {value}")
      if name != "across_m" and value and not self.across_m:
        raise ValueError(f"lane_pull.{name} needs lane_pull.across_m > 0")

  def check(self, cfg: "HLModelConfig") -> None:
    """Raises ValueError when a model of `cfg` cannot be pulled so."""
    if self.across_m and not (cfg.map_attention == "grounded" and cfg.prediction == "x0" and cfg.heading_state):
      raise ValueError("lane_pull.across_m > 0 needs model.map_attention='grounded', prediction='x0' and "
                       "heading_state=True (the lane is the one the heading estimate agrees with)")
    if self.route_m and not cfg.lane_routes:
      raise ValueError("lane_pull.route_m > 0 needs model.lane_routes=True (the lane graph's routes)")

  @classmethod
  def from_config(cls, c: ml_collections.ConfigDict) -> "LanePull | None":
    """The config's `lane_pull` section; None when off (or absent)."""
    pull = cls(**{k: float(v) for k, v in c.get("lane_pull", {}).items()})
    return pull if pull.across_m else None


def per_token(level: jax.Array, feature_axis: bool = False) -> jax.Array:
  """A noise quantity `[B]` or `[B, 2]` (per token time), `[..., D]` with `feature_axis`, shaped to
  broadcast against states `[B, A, 2, F]`: `[B, 1, 1, 1]` or `[B, 1, 2, 1]` (`[B, 1, 1 or 2, D]`)."""
  lead = level.ndim - (1 if feature_axis else 0)
  if lead not in (1, 2):
    raise ValueError(f"noise levels of shape {level.shape}: one per scene [B] or per token time [B, 2]")
  tail = level.shape[lead:]
  return level.reshape(level.shape[:1] + (1,) + ((1,) if lead == 1 else level.shape[1:2]) + (tail or (1,)))


# The fields of earlier versions' models (measured, not adopted: docs/research_log.md; the lane pull's
# settings, now the call's `LanePull`): a checkpoint whose config names one is refused, naming the version
# that reads it (`model_config.older_options_error`).
OLDER_FIELDS = ("token_displacement", "position_skip_m", "social_geometry", "position_step", "position_step_min_m",
                "lane_snap", "goal_kinematic", "map_point_inputs", "map_points_per_polyline", "pl2pl_tables",
                "lane_pull_m", "lane_pull_clearance_m", "lane_pull_end_m", "lane_pull_route_m", "lane_pull_noise_m")


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
  map_attention: str = "paper"
  grounded_neighbors: int = 0  # grounded attention to the k nearest polygons of each token (0: all)
  lane_routes: bool = False  # grounded: each (token, polygon) pair also sees the lane-graph route length
  map_inputs: str = "normalized"
  fourier_tables: int = 0  # > 0: the map encoder's slowly varying embeddings interpolated from tables (`MapEncoder`)
  noise_input: str = "beta"
  prediction: str = "eps"
  goal_offset: bool = False  # the goal position is diffused as its offset from the initial position
  speed_step: str = "fixed"  # x0: the speed head gives x0 (fixed) or a noise-scaled step (above)
  heading_state: bool = False  # the state also holds (cos, sin) of each token's heading
  self_condition: bool = False  # x0: the denoiser also reads its previous estimate of x0 (Chen et al. 2023)
  agent_frame: bool = False  # grounded x0 with headings: also position updates along/across the agent's heading
  token_noise: str = "shared"  # staged: also trained on initial states alone and goals given them
  max_agents: int = 64  # size of the agent-identity embedding

  @property
  def state_dim(self) -> int:
    return STATE_DIM + (2 if self.heading_state else 0)

  def __post_init__(self):
    for name, allowed in (("map_attention", MAP_ATTENTIONS), ("map_inputs", INPUT_MODES),
                          ("noise_input", NOISE_INPUTS), ("prediction", PREDICTIONS),
                          ("speed_step", SPEED_STEPS),
                          ("token_noise", TOKEN_NOISES)):
      if getattr(self, name) not in allowed:
        raise ValueError(f"model.{name}={getattr(self, name)!r}: choose one of {allowed}")
    if self.lane_routes and self.map_attention != "grounded":
      raise ValueError("model.lane_routes=True needs model.map_attention='grounded'")
    # Options that would otherwise be ignored without a word.
    layers.check_fourier_tables(self.fourier_tables)
    if self.agent_frame and not (self.map_attention == "grounded" and self.prediction == "x0" and self.heading_state):
      raise ValueError("model.agent_frame=True needs model.map_attention='grounded', prediction='x0' and "
                       "heading_state=True (the frame is the agent's heading estimate)")
    if self.self_condition and self.prediction == "eps":
      raise ValueError("model.self_condition=True needs model.prediction='x0'")
    if self.speed_step != "fixed" and self.prediction != "x0":
      raise ValueError(f"model.speed_step={self.speed_step!r} needs model.prediction='x0'")

  @classmethod
  def from_config(cls, c: ml_collections.ConfigDict, max_agents: int) -> "HLModelConfig":
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
               pairs: "GroundedPairs | None" = None,
               map_kv: tuple[jax.Array, jax.Array] | None = None) -> tuple[jax.Array, jax.Array]:
    """`pairs`: the grounded map attention's (token, polygon) terms; `map_kv`: this layer's polygon keys
    and values, computed once per map. Returns x and the map attention `[B, H, 2A, P]` (zero for polygons a token does not attend to)."""
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


@dataclasses.dataclass(frozen=True)
class GroundedPairs:
  """The (token, polygon) pairs of the grounded map attention: all P polygons or K nearest per token."""

  relation: jax.Array          # [B, 2A, K, D] embedded relative geometry
  bias: jax.Array              # [B, 2A, K] -log(1 + distance in m)
  mask: jax.Array              # [B, 2A, K]
  index: jax.Array | None      # [B, 2A, K] polygon indices (None: K = P, all polygons)
  displacement: jax.Array | None = None  # [B, 2A, K, 2] from the token's estimate to the centreline (m)


@struct.dataclass
class HLContext:
  """Everything the denoiser needs of the map, computed once per sampling call."""

  map: MapContext
  lines: grounding.Centerlines  # each polygon's centreline segments (m), for the grounded attention
  heading: jax.Array            # [B, P] polygon headings
  frame_scale: jax.Array        # [B] metres per scene unit
  norm: NormStats               # normalisation of the model state
  routes: jax.Array | None = None  # [B, P, P] lane-graph route lengths (m), with `lane_routes`
  map_kv: tuple | None = None   # per denoiser layer, the map attention's polygon keys and values [B, P, D]
  lanes: jax.Array | None = None  # [B, P] polygons that are lanes (not crosswalks)



class HLDenoiser(nnx.Module):

  def __init__(self, cfg: HLModelConfig, *, rngs: nnx.Rngs):
    d = cfg.dim
    self.cfg = cfg
    grounded = cfg.map_attention == "grounded"
    self.map_encoder = MapEncoder(d, cfg.heads, cfg.map_layers, cfg.num_freq_bands, cfg.num_latents,
                                  cfg.dropout, cfg.pl2pl_radius_m, cfg.pl2pl_neighbors,
                                  input_mode=cfg.map_inputs, fourier_tables=cfg.fourier_tables, rngs=rngs)
    self.state_in = nnx.Linear(cfg.state_dim, d, rngs=rngs)
    self.type_emb = nnx.Embed(len(datatypes.AGENT_TYPES), d, rngs=rngs)
    self.id_emb = nnx.Embed(cfg.max_agents, d, rngs=rngs)
    self.time_emb = nnx.Embed(2, d, rngs=rngs)
    self.token_proj = nnx.Linear(4 * d, d, rngs=rngs)
    self.token_norm = nnx.LayerNorm(d, rngs=rngs)
    noise_freqs = (layers.log_spaced_freqs(1, cfg.num_freq_bands, 1.0, 64.0) if cfg.noise_input == "log_snr"
                   else None)
    self.noise_emb = layers.FourierEmbedding(1, d, cfg.num_freq_bands, noise_freqs, rngs=rngs)
    self.layers = nnx.List([DenoiserLayer(d, cfg.heads, i, cfg.dropout, grounded, rngs=rngs)
                            for i in range(cfg.num_layers)])
    if grounded:
      num_features = (grounding.NUM_FEATURES + (grounding.NUM_ROUTE_FEATURES if cfg.lane_routes else 0)
                      + (HEADING_FEATURES if cfg.heading_state else 0))
      self.relation_emb = nnx.List([nnx.Linear(num_features, d, rngs=rngs), nnx.LayerNorm(d, rngs=rngs),
                                    nnx.Linear(d, d, rngs=rngs)])
      if cfg.prediction != "eps":  # per-layer refinement of the position estimate, starting at zero
        self.position_updates = nnx.List([nnx.Linear(d, 2, kernel_init=nnx.initializers.zeros, rngs=rngs)
                                          for _ in range(cfg.num_layers)])
        if cfg.heading_state:  # and of the heading estimate
          self.heading_updates = nnx.List([nnx.Linear(d, 2, kernel_init=nnx.initializers.zeros, rngs=rngs)
                                           for _ in range(cfg.num_layers)])
    self.trunk = nnx.List([nnx.Linear(2 * d, d, rngs=rngs), nnx.Linear(d, d, rngs=rngs), nnx.Linear(d, d, rngs=rngs)])
    self.pos_head = nnx.List([nnx.Linear(d, d, rngs=rngs), nnx.Linear(d, 4, rngs=rngs)])
    self.speed_head = nnx.List([nnx.Linear(d, d, rngs=rngs), nnx.Linear(d, 2, rngs=rngs)])
    if cfg.heading_state:
      self.heading_head = nnx.List([nnx.Linear(d, d, rngs=rngs), nnx.Linear(d, 4, rngs=rngs)])
    if cfg.self_condition:  # the previous x0 estimate and whether there is one (created after the
      # paper's modules, so that those start as without self-conditioning)
      self.previous_in = nnx.Linear(cfg.state_dim + 1, d, rngs=rngs)
    if cfg.agent_frame:  # created last, as above: the other token's displacement in the agent's frame, and
      # position updates along and across the agent's heading (per layer and the head's), zero at first
      self.frame_emb = nnx.List([nnx.Linear(4, d, rngs=rngs), nnx.LayerNorm(d, rngs=rngs),
                                 nnx.Linear(d, d, rngs=rngs)])
      self.frame_updates = nnx.List([nnx.Linear(d, 2, kernel_init=nnx.initializers.zeros, rngs=rngs)
                                     for _ in range(cfg.num_layers)])
      self.frame_head = nnx.Linear(d, 4, kernel_init=nnx.initializers.zeros, rngs=rngs)

  def encode_map(self, scene: datatypes.Scene, norm: NormStats, key: jax.Array | None = None,
                 map_context: MapContext | None = None, packed: PackedPolygons | None = None,
                 map_inputs: MapInputs | None = None) -> HLContext:
    """Polygon embeddings, map summary and centrelines; `norm`: the dataset's normalisation statistics.

    `map_context`: the map encoder's output for `scene`, when it was computed apart (`sampling.encode_maps`
    encodes each scene at its own polygon bucket); otherwise the map encoder runs here, over the packed
    polygons `packed` when given (`map_encoder.pack_polygons`, all-pairs encoders), taking the encoder's
    input side from `map_inputs` when given (`MapEncoder.input_side`, computed apart).
    """
    if norm.goal_offset != self.cfg.goal_offset:
      raise ValueError(f"model.goal_offset={self.cfg.goal_offset} but the normalisation statistics "
                       f"{'have' if norm.goal_offset else 'lack'} goal offsets")
    if norm.heading != self.cfg.heading_state:
      raise ValueError(f"model.heading_state={self.cfg.heading_state} but the normalisation statistics "
                       f"{'have' if norm.heading else 'lack'} headings")
    lines = grounding.centerlines(scene)
    routes = grounding.lane_routes(scene, lines) if self.cfg.lane_routes else None
    if map_context is None:
      map_context = self.map_encoder(scene, norm.mean[:2], norm.std[:2], key, packed, map_inputs)
    # The polygons' keys and values of every layer's map attention, once per map instead of once per step.
    map_kv = tuple(layer.map_attn.project_sources(map_context.polygons) for layer in self.layers)
    return HLContext(map_context, lines, scene.pl_heading, scene.frame_scale, norm, routes, map_kv,
                     scene.lane_polygons)

  def _pairs(self, ctx: HLContext, position_m: jax.Array, heading: jax.Array | None = None) -> GroundedPairs:
    """The grounded attention's pairs for token positions `[B, A, 2, 2]` (m) and, with `heading_state`,
    heading estimates `[B, A, 2, 2]` (cos, sin; not unit vectors: their length says how sure)."""
    b, a = position_m.shape[:2]
    feats, dist, arc = grounding.relation_features(jax.lax.stop_gradient(position_m).reshape(b, 2 * a, 2),
                                                   ctx.lines)
    if heading is not None:  # along (+1) or against (-1) the lane, and how far across
      h = jax.lax.stop_gradient(heading).reshape(b, 2 * a, 1, 2)
      lane = feats[..., grounding.DIRECTION]                                          # [B, 2A, P, 2]
      feats = jnp.concatenate([feats, jnp.sum(h * lane, -1, keepdims=True),
                               (h[..., 0] * lane[..., 1] - h[..., 1] * lane[..., 0])[..., None]], -1)
    valid = jnp.broadcast_to(ctx.map.valid[:, None], dist.shape)                  # [B, 2A, P]
    # Ties (each crosswalk is stored twice, once per direction) are broken by the polygon's heading,
    # at the millimetre, so the choice never depends on the polygons' order.
    tie = 1e-3 * (layers.wrap_angle(ctx.heading) + jnp.pi) / (2 * jnp.pi)           # [B, P]
    order = -jnp.where(valid, dist + tie[:, None], jnp.inf)
    if ctx.routes is not None:
      feats = jnp.concatenate([feats, self._route_features(ctx, order, dist, arc)], -1)
    index = None
    k = self.cfg.grounded_neighbors
    if 0 < k < dist.shape[-1]:  # the k nearest polygons of each token
      _, index = jax.lax.top_k(order, k)
      pick = lambda x: jnp.take_along_axis(x, index.reshape(index.shape + (1,) * (x.ndim - 3)), axis=2)  # noqa: E731
      feats, dist, valid = pick(feats), pick(dist), pick(valid)
    lin1, norm, lin2 = self.relation_emb
    displacement = feats[..., :2] * grounding.FEATURE_SCALE_M   # zero for a polygon without a centreline
    return GroundedPairs(lin2(jax.nn.relu(norm(lin1(feats)))), -jnp.log1p(dist), valid, index, displacement)

  def _route_features(self, ctx: HLContext, order: jax.Array, dist: jax.Array, arc: jax.Array) -> jax.Array:
    """`[B, 2A, P, 3]` route features of every (token, polygon) pair (`grounding.route_features`).

    For token (a, t) and polygon j: the shortest route (m) along the lane graph from the agent's initial
    position to its goal, with token t's foot point on j and the other token's on one of its
    `ROUTE_CANDIDATES` nearest polygons (those within `ROUTE_CANDIDATE_M` of its nearest): the shortest
    route that goes at most `ROUTE_BACKWARD_M` backwards, inf if none.
    Args: order `[B, 2A, P]` (larger = nearer, -inf for padded polygons), dist and arc `[B, 2A, P]` (m).
    """
    b, q, p = dist.shape
    a = q // 2
    _, near = jax.lax.top_k(order, min(ROUTE_CANDIDATES, p))                      # [B, 2A, C]
    near_dist = jnp.take_along_axis(dist, near, -1)
    near_arc = jnp.take_along_axis(arc, near, -1)
    candidate = (near_dist <= near_dist[..., :1] + ROUTE_CANDIDATE_M) & jnp.isfinite(
        jnp.take_along_axis(order, near, -1))
    swap = lambda x: x.reshape(b, a, 2, -1)[:, :, ::-1].reshape(b, q, -1)  # noqa: E731  the other token's
    other, other_arc, other_ok = swap(near), swap(near_arc), swap(candidate)      # [B, 2A, C]
    rows = jnp.arange(b)[:, None, None, None]
    polygon = jnp.arange(p)[None, None, :, None]                                  # [1, 1, P, 1]
    is_goal = jnp.tile(jnp.arange(2) == 1, a)[None, :, None, None]                # [1, 2A, 1, 1]
    # initial token on polygon j: route j -> other's lane; goal token on j: other's lane -> j
    start = jnp.where(is_goal, other[:, :, None, :], polygon)
    end = jnp.where(is_goal, polygon, other[:, :, None, :])
    start_arc = jnp.where(is_goal, other_arc[:, :, None, :], arc[..., None])
    end_arc = jnp.where(is_goal, arc[..., None], other_arc[:, :, None, :])
    route = ctx.routes[rows, start, end] - start_arc + end_arc                   # [B, 2A, P, C]
    route = jnp.where(other_ok[:, :, None, :] & (route >= -ROUTE_BACKWARD_M), route, jnp.inf)
    return grounding.route_features(route.min(-1))

  @staticmethod
  def _displacement(position_m: jax.Array, emb: nnx.List, frame: jax.Array) -> jax.Array:
    """`[B, A, 2, D]`: each token's displacement to its agent's other token, from `[B, A, 2, 2]` m, along and
    across the agent's heading (`frame`, `_agent_frame`), embedded by `emb`."""
    d = jax.lax.stop_gradient(position_m[:, :, ::-1] - position_m)
    dist = jnp.sqrt(jnp.sum(d * d, -1, keepdims=True) + 1e-12)
    local = HLDenoiser._to_frame(d, frame)
    feats = jnp.concatenate([local / grounding.FEATURE_SCALE_M, dist / grounding.FEATURE_SCALE_M, jnp.log1p(dist)], -1)
    lin1, norm, lin2 = emb
    return lin2(jax.nn.relu(norm(lin1(feats))))

  @staticmethod
  def _unit_heading(heading: jax.Array) -> jax.Array:
    """Heading estimates `[..., 2]` (not unit: shrunk by the noise) as unit (cos, sin); no gradient."""
    h = jax.lax.stop_gradient(heading)
    return h * jax.lax.rsqrt(jnp.sum(h * h, -1, keepdims=True) + 1e-4)

  @staticmethod
  def _agent_frame(heading: jax.Array) -> jax.Array:
    """`[B, A, 1, 2]` the unit (cos, sin) of each agent's heading estimate at its initial token, from the
    heading estimates `[B, A, 2, 2]`; held fixed for the gradient."""
    return HLDenoiser._unit_heading(heading[:, :, :1])

  @staticmethod
  def _to_world(local: jax.Array, frame: jax.Array) -> jax.Array:
    """(along, across) the agent's heading `[B, A, 2, 2]` -> (x, y) in the scene frame."""
    c, s = frame[..., :1], frame[..., 1:]
    return jnp.concatenate([c * local[..., :1] - s * local[..., 1:], s * local[..., :1] + c * local[..., 1:]], -1)

  @staticmethod
  def _to_frame(xy: jax.Array, frame: jax.Array) -> jax.Array:
    """(x, y) in the scene frame `[B, A, 2, 2]` -> (along, across) the agent's heading: `_to_world`'s inverse."""
    c, s = frame[..., :1], frame[..., 1:]
    return jnp.concatenate([c * xy[..., :1] + s * xy[..., 1:], -s * xy[..., :1] + c * xy[..., 1:]], -1)

  def denoise(self, ctx: HLContext, x_t: jax.Array, beta_t: jax.Array, alpha_bar_t: jax.Array,
              agent_type: jax.Array, agent_valid: jax.Array, agent_id: jax.Array | None = None,
              self_only: jax.Array | None = None, key: jax.Array | None = None, x0_prev: jax.Array | None = None,
              has_prev: jax.Array | None = None, lane_pull: LanePull | None = None
              ) -> tuple[jax.Array, list[jax.Array]]:
    """epsilon `[B, A, 2, F]` (zero for padded agents) and the map attention `[B, H, 2A, P]` per layer.

    Args:
      x_t: `[B, A, 2, F]` noisy normalised states (F = `cfg.state_dim`). beta_t, alpha_bar_t: `[B]` the noise level of each
        scene (beta_t is the paper's noise input; alpha_bar_t sets the others and the x0 conversion), or
        `[B, 2]` one per token time (initial, goal; alpha_bar_t = 1 for a clean token, whose epsilon is then
        x_t less the network's x0 estimate, so that x0 from it is x_t exactly).
      agent_type, agent_valid: `[B, A]`. agent_id: `[B, A]` identity indices (default: row index).
      self_only: `[B]` bool, agents attend only to themselves (interaction dropout).
      x0_prev: `[B, A, 2, F]` with `self_condition`: the previous estimate of x0 (the sampler's last step's,
        or in training the network's own first pass, without gradient), where `has_prev` `[B]` (default:
        all scenes when x0_prev is given, none when not). Grounded, it is also the first position and
        heading estimate, instead of sqrt(alpha_bar) x_t.
      lane_pull: the lane pull on the final position estimate (module docstring); None: none.
    """
    cfg = self.cfg
    b, a = agent_valid.shape
    if agent_id is None:
      agent_id = jnp.broadcast_to(jnp.arange(a), (b, a))
    sqrt_ab = per_token(jnp.sqrt(alpha_bar_t))
    sqrt_1m = per_token(jnp.sqrt(1.0 - alpha_bar_t))
    state = self.state_in(x_t)
    start = sqrt_ab * x_t   # E[x0 | x_t] under the unit-variance prior
    if cfg.self_condition:
      if has_prev is None:
        has_prev = jnp.full((b,), x0_prev is not None)
      prev = jnp.where(has_prev[:, None, None, None], x0_prev, 0.0) if x0_prev is not None else jnp.zeros_like(x_t)
      flag = jnp.broadcast_to(has_prev[:, None, None, None].astype(x_t.dtype), x_t.shape[:3] + (1,))
      state = state + self.previous_in(jnp.concatenate([prev, flag], -1))
      start = jnp.where(has_prev[:, None, None, None], prev, start)
    elif x0_prev is not None:
      raise ValueError("x0_prev given to a denoiser without model.self_condition")
    tok = jnp.concatenate([
        state,
        jnp.broadcast_to(self.type_emb(agent_type)[:, :, None], x_t.shape[:3] + (cfg.dim,)),
        jnp.broadcast_to(self.id_emb(agent_id)[:, :, None], x_t.shape[:3] + (cfg.dim,)),
        jnp.broadcast_to(self.time_emb(jnp.arange(2)), x_t.shape[:3] + (cfg.dim,)),
    ], axis=-1)
    m0 = jax.nn.silu(self.token_norm(self.token_proj(tok)))               # [B, A, 2, D]
    log_snr = jnp.minimum(jnp.log(alpha_bar_t) - jnp.log1p(-alpha_bar_t), CLEAN_LOG_SNR)
    level = log_snr if cfg.noise_input == "log_snr" else beta_t
    noise = per_token(self.noise_emb(level[..., None]), feature_axis=True)  # [B, 1, 1 or 2, D]
    social = agent_valid[:, :, None] & agent_valid[:, None, :]
    if self_only is not None:
      social = social & (~self_only[:, None, None] | jnp.eye(a, dtype=bool))
    grounded = cfg.map_attention == "grounded"
    position = (positions_to_metres(start[..., :2], ctx.frame_scale, ctx.norm)
                if grounded else None)                                     # [B, A, 2, 2] m
    # The heading estimate the grounded pairs see: from the same start as the position estimate.
    heading = start[..., 3:5] if grounded and cfg.heading_state else None
    x, m_sum, maps = m0, m0, []
    for i, layer in enumerate(self.layers):
      pairs = self._pairs(ctx, position, heading) if grounded else None
      frame = self._agent_frame(heading) if cfg.agent_frame else None
      extra = self._displacement(position, self.frame_emb, frame) if frame is not None else 0.0
      map_kv = ctx.map_kv[i] if ctx.map_kv is not None else None
      x, w = layer(x + noise + extra, ctx.map, social, layers.fold(key, i), pairs, map_kv)
      m_sum, maps = m_sum + x, maps + [w]
      if grounded and cfg.prediction != "eps":
        update = self.position_updates[i](x)
        if frame is not None:
          update = update + self._to_world(self.frame_updates[i](x), frame)
        position = position + POSITION_STEP_M * update
        if heading is not None:
          heading = heading + self.heading_updates[i](x)
    h = m_sum.reshape(b, a, -1)
    h = jax.nn.leaky_relu(self.trunk[0](h), 0.1)
    h = jax.nn.leaky_relu(self.trunk[1](h), 0.1)
    h = self.trunk[2](h)
    pos_hidden = jax.nn.relu(self.pos_head[0](h))
    pos = self.pos_head[1](pos_hidden).reshape(b, a, 2, 2)
    if cfg.agent_frame:  # plus an offset along and across the agent's heading
      pos = pos + self._to_world(self.frame_head(pos_hidden).reshape(b, a, 2, 2), self._agent_frame(heading))
    speed = self.speed_head[1](jax.nn.relu(self.speed_head[0](h)))[..., None]   # [B, A, 2, 1]
    if cfg.heading_state:  # as the speed: eps or x0; grounded x0: the last estimate plus the head's offset
      direction = self.heading_head[1](jax.nn.relu(self.heading_head[0](h))).reshape(b, a, 2, 2)
      if heading is not None and cfg.prediction == "x0":
        direction = heading + direction
      speed = jnp.concatenate([speed, direction], -1)                     # [B, A, 2, 3]
    if cfg.prediction == "eps":
      out = jnp.concatenate([pos, speed], axis=-1)
    else:
      if cfg.speed_step == "noise_scaled":
        speed = speed.at[..., :1].set(sqrt_ab * x_t[..., 2:3] + sqrt_1m * speed[..., :1])
      if grounded:
        metres = position + POSITION_STEP_M * pos
        if lane_pull is not None and lane_pull.across_m > 0:
          metres = self._lane_pull(ctx, metres, speed, agent_type, agent_valid, lane_pull)
        pos = positions_from_metres(metres, ctx.frame_scale, ctx.norm)
      x0 = jnp.concatenate([pos, speed], axis=-1)
      out = (x_t - sqrt_ab * x0) / jnp.where(sqrt_1m > 0.0, sqrt_1m, 1.0)
    return jnp.where(agent_valid[:, :, None, None], out, 0.0), maps

  def _lane_pull(self, ctx: HLContext, position_m: jax.Array, speed: jax.Array, agent_type: jax.Array,
                 agent_valid: jax.Array, pull: LanePull) -> jax.Array:
    """`[B, A, 2, 2]` (m): `position_m` with each moving road user's token moved across its lane onto the
    nearest lane centreline that agrees with its heading, from at most `across_m` across, and onto its
    end from at most `end_m` past it (module docstring). `speed`: `[B, A, 2, 3]` the final
    speed (normalised) and heading (cos, sin) estimates; `agent_type`, `agent_valid` `[B, A]` (pedestrians
    stay where they are)."""
    pull.check(self.cfg)
    b, a = position_m.shape[:2]
    feats, dist, arc = grounding.relation_features(position_m.reshape(b, 2 * a, 2), ctx.lines)   # [B, 2A, P, .]
    lane = feats[..., grounding.DIRECTION]
    heading = speed[..., 1:3].reshape(b, 2 * a, 1, 2)
    heading = heading / jnp.sqrt(jnp.sum(heading ** 2, -1, keepdims=True) + 1e-12)
    disp = feats[..., :2] * grounding.FEATURE_SCALE_M                  # to the nearest centreline point
    along = jnp.sum(disp * lane, -1, keepdims=True) * lane              # nonzero only past a centreline's end
    across = disp - along                                               # its part across the lane
    step = across
    if pull.end_m > 0:                                         # and back onto the end from at most e past it
      step = jnp.where(jnp.sum(along ** 2, -1, keepdims=True) <= pull.end_m ** 2, disp, across)
    agrees = ctx.lanes[:, None] & (jnp.sum(heading * lane, -1) > LANE_PULL_AGREE_COS) & (dist < 1e3)
    across2 = jnp.sum(across ** 2, -1)
    ok = agrees & (across2 <= pull.across_m ** 2)
    mps = denormalize_speed(speed[..., 0], ctx.norm)
    road_user = jnp.broadcast_to((agent_type != datatypes.PEDESTRIAN)[:, :, None], (b, a, 2)).reshape(b, 2 * a)
    moving = (mps.reshape(b, 2 * a) >= LANE_PULL_MIN_MPS) & road_user
    if pull.route_m > 0:
      ok = self._prefer_routed_goals(ctx, ok, agrees & (across2 <= pull.route_m ** 2), moving,
                                     mps.reshape(b, 2 * a), dist, arc)
    nearest = jnp.argmin(jnp.where(ok, dist, jnp.inf), axis=-1)[..., None, None]   # [B, 2A, 1, 1]
    move = jnp.take_along_axis(step, nearest, axis=2)[:, :, 0]                    # [B, 2A, 2]
    pulled = ok.any(-1) & moving
    moved = position_m + jnp.where(pulled[..., None], move, 0.0).reshape(b, a, 2, 2)
    if pull.clearance_m > 0:
      # A token is not pulled where it would end nearer than c to another token of its kind, at that one's
      # pulled or its own place, than before: no pair then ends nearer than min(c, their distance before).
      def distance(p, q):                                               # [B, A, 2, 2] each -> [B, 2, A, A]
        p, q = jnp.swapaxes(p, 1, 2), jnp.swapaxes(q, 1, 2)
        return jnp.sqrt(jnp.sum((p[:, :, :, None] - q[:, :, None]) ** 2, -1) + 1e-12)
      before = distance(position_m, position_m)
      pair = (agent_valid[:, :, None] & agent_valid[:, None, :] & ~jnp.eye(a, dtype=bool))[:, None]
      crowded = jnp.zeros_like(pair)
      for after in (distance(moved, moved), distance(moved, position_m)):
        crowded = crowded | (pair & (after < pull.clearance_m) & (after < before))
      moved = jnp.where(jnp.swapaxes(crowded.any(-1), 1, 2)[..., None], position_m, moved)
    return moved

  @staticmethod
  def _prefer_routed_goals(ctx: HLContext, ok: jax.Array, ok_routed: jax.Array, moving: jax.Array, mps: jax.Array,
                           dist: jax.Array, arc: jax.Array) -> jax.Array:
    """`ok` `[B, 2A, P]` (the lanes each token may be pulled onto) with each goal's replaced by the lanes
    of `ok_routed` (those within `route_m`) that its initial token's lane leads to, where it has
    one: by a route at most `ROUTE_BACKWARD_M` backwards and at most as long as the faster of the agent's
    speed estimates covers in `ROUTE_HORIZON_S`, plus `ROUTE_SLACK_M` (the opposite lane, reached only
    round a junction, is no goal for the next 6 s). The initial token's lane is the one its pull puts it
    on or, not pulled, its nearest lane. `moving` `[B, 2A]` says which tokens are pulled, `mps` `[B, 2A]`
    their speed estimates (m/s); dist and arc `[B, 2A, P]` (m) from `grounding.relation_features`."""
    b, q, p = dist.shape
    initial = lambda x: x.reshape(b, q // 2, 2, *x.shape[2:])[:, :, 0]  # noqa: E731  [B, A, ...]
    ok0, dist0, arc0 = initial(ok), initial(dist), initial(arc)
    pulled = ok0.any(-1) & initial(moving)
    lane_dist = jnp.where(ctx.lanes[:, None] & (dist0 < 1e3), dist0, jnp.inf)
    lane0 = jnp.where(pulled, jnp.argmin(jnp.where(ok0, dist0, jnp.inf), -1), jnp.argmin(lane_dist, -1))   # [B, A]
    start_arc = jnp.take_along_axis(arc0, lane0[..., None], -1)                                             # [B, A, 1]
    route = jnp.take_along_axis(ctx.routes, lane0[..., None], axis=1) - start_arc + arc[:, 1::2]            # [B, A, P]
    reach = ROUTE_HORIZON_S * jnp.max(mps.reshape(b, q // 2, 2), -1, keepdims=True) + ROUTE_SLACK_M        # [B, A, 1]
    routed = ((route >= -ROUTE_BACKWARD_M) & (route <= reach)
              & jnp.isfinite(lane_dist).any(-1, keepdims=True))
    narrowed = ok_routed[:, 1::2] & routed
    goal_ok = jnp.where(narrowed.any(-1, keepdims=True), narrowed, ok[:, 1::2])
    return jnp.stack([ok0, goal_ok], axis=2).reshape(b, q, p)

  def __call__(self, scene: datatypes.Scene, x_t: jax.Array, beta_t: jax.Array, alpha_bar_t: jax.Array,
               norm: NormStats, agent_id=None, self_only=None, key=None, packed: PackedPolygons | None = None,
               x0_prev=None, has_prev=None, map_inputs: MapInputs | None = None, lane_pull: LanePull | None = None):
    ctx = self.encode_map(scene, norm, layers.fold(key, 100), packed=packed, map_inputs=map_inputs)
    return self.denoise(ctx, x_t, beta_t, alpha_bar_t, scene.agent_type, scene.agent_valid, agent_id, self_only,
                        layers.fold(key, 101), x0_prev, has_prev, lane_pull)
