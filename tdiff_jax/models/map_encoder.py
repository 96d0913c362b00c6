"""QCNet-style map encoder with a learned map summary (paper §IV-A, reference notes §2.1).

Inputs are a batch of scenes (`datatypes.Scene` with a leading `[B]`). Per polygon and point, the input
features are the position (scene units, z-normalised with the dataset's x/y statistics) and the
orientation, Fourier-embedded, plus type/side (points) and type/intersection (polygons) embeddings
(the HL model's encoder, `input_mode="normalized"`, as the paper). With `input_mode="metric"` positions
enter in metres with initial Fourier periods from 1 m to 250 m and orientations as (cos, sin), so the
embeddings can tell lanes apart at lane scale (the paper's inputs have periods of hundreds of metres
and raw angles). With `absolute_inputs=False` (the infiller's encoder, as the official
code's) a point's only continuous input is the length of its segment to the next point of its
polyline and a polygon's input is its type and intersection embeddings: the encoding is invariant to
translation and rotation, and the point embedding costs a third.
Then `num_layers` x [point -> polygon attention over each polygon's own points, polygon -> polygon
attention], both with relative geometry in metres (distance, angle, heading difference) and, for
polygon pairs, the topology edge type. The polygon output is the input embedding plus every layer's
output. Finally `num_latents` learned tokens attend to [latents, polygons] (one self-attention of
which only the latent rows are needed) and pass an FFN: the map summary (`num_latents = 0`: no
summary, as the infiller's encoder).

Polygon pairs: each polygon attends to the valid polygons within `pl2pl_radius_m` metres and to its
topology neighbours at any distance. With `pl2pl_neighbors = k > 0`, only the k nearest such polygons
(topology neighbours first) are used, which keeps the relation tensor at `[B, P, k]` instead of
`[B, P, P]`; 0 means all pairs.

Output `MapContext`: polygon embeddings `[B, P, D]`, their mask `[B, P]`, summary `[B, L, D]`.
"""

from __future__ import annotations

import dataclasses
import hashlib
from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx, struct

from tdiff_jax import datatypes
from tdiff_jax.models import layers


INPUT_MODES = ("normalized", "metric")


@struct.dataclass
class MapContext:
  polygons: jax.Array  # [B, P, D]
  valid: jax.Array     # [B, P]
  summary: jax.Array   # [B, L, D]



def encode_per_scene(encode: Callable[[datatypes.Scene], MapContext], scene: datatypes.Scene,
                     polygon_buckets: Sequence[int]) -> MapContext:
  """`encode` (a jitted map encoder of a batch) applied to each scene of `scene` alone, at the smallest
  of `polygon_buckets` holding its polygons, the embeddings padded back to the batch's P.

  A batch is padded to its largest map, and the encoder's polygon-pair relations cost the square of
  the polygon count; the encoder is padding-invariant (tested), so this gives the same context for a
  fraction of the work. Scenes with the same map (several samples of one map) are encoded once. Runs
  eagerly over the batch (one compile of `encode` per bucket): call it outside `jit`.
  """
  p = scene.num_polygons
  counts = np.asarray(scene.pl_valid).sum(-1)
  sizes = [min(min((b for b in polygon_buckets if b >= c), default=max(polygon_buckets)), p) for c in counts]
  if len(counts) == 1 and sizes[0] == p:  # nothing to save: one call, no slicing
    return encode(scene)
  host = {f: np.asarray(getattr(scene, f)) for f in (*datatypes.POLYGON_FIELDS, "pl_edge", "frame_scale")}
  keys = [hashlib.sha1(b"".join(a[i].tobytes() for a in host.values())).digest() for i in range(len(counts))]
  if all(size == p for size in sizes) and len(set(keys)) == len(keys):
    return encode(scene)
  done: dict[bytes, MapContext] = {}
  parts = []
  for i, (key, size) in enumerate(zip(keys, sizes)):
    if key not in done:
      one = jax.tree_util.tree_map(lambda x, i=i: x[i:i + 1], scene).crop(num_polygons=size)
      ctx = encode(one)
      done[key] = dataclasses.replace(ctx, polygons=jnp.pad(ctx.polygons, ((0, 0), (0, p - size), (0, 0))),
                                      valid=scene.pl_valid[i:i + 1])
    parts.append(done[key])
  return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *parts)


class MapEncoder(nnx.Module):

  def __init__(self, dim: int, heads: int, num_layers: int, num_freq_bands: int, num_latents: int,
               dropout_rate: float, pl2pl_radius_m: float, pl2pl_neighbors: int, absolute_inputs: bool = True,
               input_mode: str = "normalized", *, rngs: nnx.Rngs):
    if input_mode not in INPUT_MODES:
      raise ValueError(f"map encoder input_mode {input_mode!r}: choose one of {INPUT_MODES}")
    self.dropout_rate = dropout_rate
    self.absolute_inputs = absolute_inputs
    self.input_mode = input_mode
    self.pl2pl_radius_m = pl2pl_radius_m
    self.pl2pl_neighbors = pl2pl_neighbors
    if not absolute_inputs:
      self.pt_input = layers.FourierEmbedding(1, dim, num_freq_bands, rngs=rngs)
    elif input_mode == "metric":  # x, y (m), cos, sin
      freqs = jnp.concatenate([layers.log_spaced_freqs(2, num_freq_bands, 1.0, 250.0),
                               layers.log_spaced_freqs(2, num_freq_bands, 2.0, 8.0)])
      self.pt_input = layers.FourierEmbedding(4, dim, num_freq_bands, freqs, rngs=rngs)
      self.pl_input = layers.FourierEmbedding(4, dim, num_freq_bands, freqs, rngs=rngs)
    else:
      self.pt_input = layers.FourierEmbedding(3, dim, num_freq_bands, rngs=rngs)
      self.pl_input = layers.FourierEmbedding(3, dim, num_freq_bands, rngs=rngs)
    self.pt_type = nnx.Embed(len(datatypes.POINT_TYPES), dim, rngs=rngs)
    self.pt_side = nnx.Embed(len(datatypes.POINT_SIDES), dim, rngs=rngs)
    self.pl_type = nnx.Embed(len(datatypes.POLYGON_TYPES), dim, rngs=rngs)
    self.pl_intersection = nnx.Embed(len(datatypes.INTERSECTION_FLAGS), dim, rngs=rngs)
    self.r_pt2pl = layers.FourierEmbedding(3, dim, num_freq_bands, rngs=rngs)
    self.r_pl2pl = layers.FourierEmbedding(3, dim, num_freq_bands, rngs=rngs)
    self.edge_type = nnx.Embed(len(datatypes.EDGE_TYPES), dim, rngs=rngs)
    self.pt2pl = nnx.List([layers.RelationalAttentionLayer(dim, heads, dropout_rate, rngs=rngs)
                           for _ in range(num_layers)])
    self.pl2pl = nnx.List([layers.RelationalAttentionLayer(dim, heads, dropout_rate, rngs=rngs)
                           for _ in range(num_layers)])
    self.num_latents = num_latents
    if num_latents:
      self.latents = nnx.Param(jax.random.normal(rngs.params(), (num_latents, dim)))
      self.summary_attn = layers.MultiHeadAttention(dim, heads, rngs=rngs)
      self.summary_norm1 = nnx.LayerNorm(dim, rngs=rngs)
      self.summary_norm2 = nnx.LayerNorm(dim, rngs=rngs)
      self.summary_ff = layers.FeedForward(dim, 2 * dim, rngs=rngs)

  def _pl2pl_neighbours(self, scene: datatypes.Scene):
    """Key indices `[B, P, K]` (None: all P polygons) and mask `[B, P, K]` for polygon -> polygon attention."""
    p = scene.pl_xy
    dist = jnp.linalg.norm(p[:, :, None] - p[:, None, :] + 1e-9, axis=-1)       # [B, P, P]
    n = p.shape[1]
    edge = scene.pl_edge.astype(jnp.int32)
    cand = (scene.pl_valid[:, :, None] & scene.pl_valid[:, None, :] & ~jnp.eye(n, dtype=bool)
            & ((dist <= self.pl2pl_radius_m) | (edge > 0)))
    k = self.pl2pl_neighbors
    if k <= 0 or k >= n:
      return None, cand  # all pairs
    score = jnp.where(cand, dist - jnp.where(edge > 0, 1e6, 0.0), jnp.inf)
    _, idx = jax.lax.top_k(-score, k)
    return idx, jnp.take_along_axis(cand, idx, axis=-1)

  def __call__(self, scene: datatypes.Scene, xy_mean: jax.Array, xy_std: jax.Array,
               key: jax.Array | None = None) -> MapContext:
    scale = scene.frame_scale[:, None, None]
    norm_xy = lambda xy: (xy / scale[..., None] - xy_mean) / xy_std  # noqa: E731

    # Input embeddings.
    pt_cat = self.pt_type(scene.pt_type) + self.pt_side(scene.pt_side)
    pl_cat = self.pl_type(scene.pl_type) + self.pl_intersection(scene.pl_intersection)
    if self.absolute_inputs and self.input_mode == "metric":
      angle = lambda h: jnp.stack([jnp.cos(h), jnp.sin(h)], -1)  # noqa: E731
      x_pt = self.pt_input(jnp.concatenate([scene.pt_xy, angle(scene.pt_heading)], -1), pt_cat)   # [B, P, K, 4]
      x_pl = self.pl_input(jnp.concatenate([scene.pl_xy, angle(scene.pl_heading)], -1), pl_cat)
    elif self.absolute_inputs:
      pt_in = jnp.concatenate([norm_xy(scene.pt_xy), scene.pt_heading[..., None]], -1)   # [B, P, K, 3]
      x_pt = self.pt_input(pt_in, pt_cat)
      pl_in = jnp.concatenate([norm_xy(scene.pl_xy[:, :, None])[:, :, 0], scene.pl_heading[..., None]], -1)
      x_pl = self.pl_input(pl_in, pl_cat)
    else:
      k = scene.pt_xy.shape[-2]
      seg = jnp.linalg.norm(scene.pt_xy[..., 1:, :] - scene.pt_xy[..., :-1, :] + 1e-12, axis=-1)
      last = (jnp.arange(1, k) % (k // datatypes.POLYLINES_PER_POLYGON)) == 0   # crossing to the next polyline
      seg = jnp.concatenate([jnp.where(last, 0.0, seg), jnp.zeros_like(seg[..., :1])], -1)   # [B, P, K]
      x_pt = self.pt_input(seg[..., None], pt_cat)
      x_pl = pl_cat

    # Relations in metres.
    r_pt2pl = layers.relative_geometry(scene.pt_xy, scene.pl_xy[:, :, None], scene.pt_heading,
                                       scene.pl_heading[:, :, None])
    r_pt2pl = self.r_pt2pl(r_pt2pl)                                                       # [B, P, K, D]
    idx, nb_mask = self._pl2pl_neighbours(scene)
    edge = scene.pl_edge.astype(jnp.int32)
    if idx is None:  # all pairs: sources broadcast against queries
      src_xy, src_heading = scene.pl_xy[:, None], scene.pl_heading[:, None]
    else:
      gather = jax.vmap(lambda a, i: a[i])  # [B, P, ...], [B, P, K] -> [B, P, K, ...]
      src_xy, src_heading = gather(scene.pl_xy, idx), gather(scene.pl_heading, idx)
      edge = jnp.take_along_axis(edge, idx, axis=2)
    r_pl2pl = layers.relative_geometry(src_xy, scene.pl_xy[:, :, None], src_heading, scene.pl_heading[:, :, None])
    r_pl2pl = self.r_pl2pl(r_pl2pl, self.edge_type(edge))                                 # [B, P, K, D]

    x_sum = x_pl
    for i, (pt2pl, pl2pl) in enumerate(zip(self.pt2pl, self.pl2pl)):
      x_pl = pt2pl(x_pl, x_pt, r_pt2pl, scene.pt_valid, layers.fold(key, 2 * i))
      x_pl = pl2pl(x_pl, x_pl, r_pl2pl, nb_mask, layers.fold(key, 2 * i + 1), src_index=idx)
      x_sum = x_sum + x_pl
    x_sum = jnp.where(scene.pl_valid[..., None], x_sum, 0.0)
    if not self.num_latents:
      return MapContext(x_sum, scene.pl_valid, x_sum[:, :0])

    # Map summary: latents attend to [latents, valid polygons].
    b = x_sum.shape[0]
    latents = jnp.broadcast_to(self.latents[...], (b,) + self.latents.shape)
    tokens = jnp.concatenate([latents, x_sum], axis=1)
    token_mask = jnp.concatenate([jnp.ones(latents.shape[:2], bool), scene.pl_valid], axis=1)
    attn = self.summary_attn(latents, tokens, jnp.broadcast_to(token_mask[:, None], (b, latents.shape[1], token_mask.shape[1])))
    summary = self.summary_norm1(latents + attn)
    summary = summary + self.summary_ff(self.summary_norm2(summary))
    return MapContext(x_sum, scene.pl_valid, summary)
