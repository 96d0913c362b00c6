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
translation and rotation, and the point embedding costs a third. With `fourier_tables=G` the
embeddings whose inputs vary slowly at their frequencies (the point -> polygon and polygon -> polygon
relations, segment lengths, normalised positions; not metric positions) are interpolated from G values
per input spanning each call's range (`layers.FourierEmbedding`): most of the encoder's work per point
and pair saved, the output the exact one's to interpolation error.
Then `num_layers` x [point -> polygon attention over each polygon's own points, polygon -> polygon
attention], both with relative geometry in metres (distance, angle, heading difference) and, for
polygon pairs, the topology edge type. The polygon output is the input embedding plus every layer's
output. Finally `num_latents` learned tokens attend to [latents, polygons] (one self-attention of
which only the latent rows are needed) and pass an FFN: the map summary (`num_latents = 0`: no
summary, as the infiller's encoder).

Polygon pairs: each polygon attends to the valid polygons within `pl2pl_radius_m` metres and to its
topology neighbours at any distance. With `pl2pl_neighbors = k > 0`, only the k nearest such polygons
(topology neighbours first) are used, which keeps the relation tensor at `[B, P, k]` instead of
`[B, P, P]`; 0 means all pairs. An all-pairs encoder given the batch's `pack_polygons` (what training,
`sampling.encode_maps` and `infilling.encode_maps` pass) computes only the valid points, polygons and
polygon pairs, packed into lists across the batch, instead of the padded `[B, P, K]` and `[B, P, P]`
grids: the same output for a fraction of the work when the batch's maps differ in size. A batch sharded
over several devices gets one such list per device (`pack_polygons(..., shards=S)`).

The input side (the input embeddings and the point -> polygon attention) is per polygon: each polygon's
result depends on its own fields alone. With its weights fixed (`train.freeze_map_inputs`), a
one-layer encoder's input side is a constant of each polygon, which `input_side` computes apart
(`MapInputs`) and `__call__(..., inputs=...)` takes instead of computing it (training computes it once
per training scene, `train/map_input_cache.py`).

Output `MapContext`: polygon embeddings `[B, P, D]`, their mask `[B, P]`, summary `[B, L, D]`.
"""

from __future__ import annotations

import dataclasses
import functools
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
class PackedPolygons:
  """A batch's valid polygons packed into one list, with the (query, key) pairs of their polygon ->
  polygon attention: what an all-pairs encoder computes instead of padded `[B, P, ...]` and
  `[B, P, P]` grids, most of which is padding when the batch's maps differ in size.

  `polygon` indexes the batch's polygons flattened to `[B x P]` (scene b's polygon i is b * P + i), in
  that order; `dst`, `src` index `polygon`'s list, sorted by query. Both lists are padded to bucketed
  lengths N and E (`bucket_length`) with `polygon_valid` / `valid` False. Built on the host by
  `pack_polygons`.

  Sharded (`pack_polygons(..., shards=S)`): one such list per consecutive slice of B / S scenes, the
  indices local to the slice, every field with a leading `[S]` axis. The encoder runs the slices side
  by side (`jax.vmap`), so a batch sharded over S devices packs each device's own scenes.
  """
  polygon: jax.Array        # [N] or [S, N] int32
  polygon_valid: jax.Array  # [N] or [S, N] bool
  dst: jax.Array            # [E] or [S, E] int32, the query polygon (index into `polygon`)
  src: jax.Array            # [E] or [S, E] int32, the key polygon
  valid: jax.Array          # [E] or [S, E] bool

  @property
  def shape(self) -> tuple[int, int]:
    """(N, E): the padded lengths, which the jitted encoder compiles for."""
    return self.polygon.shape[-1], self.dst.shape[-1]

  @property
  def shards(self) -> int:
    """S, the number of slices of the batch packed apart (1 for one list)."""
    return self.polygon.shape[0] if self.polygon.ndim == 2 else 1


def bucket_length(count: int, minimum: int, per_doubling: int = 4) -> int:
  """The padded length of a list of `count` entries: the smallest m x 2^k >= count with m in 4..7
  (at most 25 % padding and four lengths per doubling, so few compiles), at least `minimum`.
  `per_doubling` 2: m in (4, 6) (at most 50 % padding, half the lengths)."""
  if per_doubling not in (2, 4):
    raise ValueError(f"bucket_length: per_doubling must be 2 or 4, got {per_doubling}")
  size = minimum
  while size < count:
    size *= 2
  for m in range(4, 8, 4 // per_doubling):  # size / 2 < count <= size: try the steps between
    step = size // 8 * m
    if size >= 8 and step >= max(count, minimum):
      return step
  return size


def packing_for(scene: datatypes.Scene, radius_m: float, neighbors: int, shards: int = 1) -> PackedPolygons | None:
  """`pack_polygons(scene, radius_m, shards)` for an encoder that attends over all pairs (`neighbors <= 0`);
  None for one that keeps the k nearest (its `[B, P, k]` grid is what it computes)."""
  return pack_polygons(scene, radius_m, shards) if neighbors <= 0 else None


def pair_settings(model: nnx.Module) -> tuple[float, int]:
  """A model's map encoder's polygon-pair settings, what `packing_for` takes: radius (m) and neighbours
  (0: all pairs). `model`: any module with a `map_encoder` (the HL denoiser, the infiller)."""
  return model.map_encoder.pl2pl_radius_m, model.map_encoder.pl2pl_neighbors


def _pair_lists(xy: np.ndarray, valid: np.ndarray, edge: np.ndarray, radius_m: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """The valid polygons of `[B, P]` scenes in `[B x P]` order, and their (query, key) pairs as positions
  in that list, sorted by query: the dense `[B, P, P]` mask's rule."""
  b, p = valid.shape
  dist = np.linalg.norm(xy[:, None, :] - xy[:, :, None] + np.float32(1e-9), axis=-1)   # [B, Q, K]
  cand = (valid[:, :, None] & valid[:, None, :] & ~np.eye(p, dtype=bool)
          & ((dist <= radius_m) | (edge > 0)))
  flat = np.flatnonzero(valid)                           # the valid polygons, in [B x P] order
  row = np.full(b * p, -1, np.int64)
  row[flat] = np.arange(len(flat))                       # [B x P] -> packed position
  bi, qi, ki = np.nonzero(cand)                          # row-major: sorted by (scene, query)
  return flat, row[bi * p + qi], row[bi * p + ki]


def pack_polygons(scene: datatypes.Scene, radius_m: float, shards: int = 1) -> PackedPolygons:
  """The packed polygons of a batch `scene` `[B, ...]` for an all-pairs encoder (numpy, on the host;
  outside `jit`): every valid polygon, and each paired with every other valid polygon of its scene
  within `radius_m` metres or joined to it by a topology edge (the dense `[B, P, P]` mask's rule).
  `shards` S > 1 (dividing B): each consecutive slice of B / S scenes packed apart, the lists padded to
  the longest slice's bucketed lengths (`PackedPolygons`), for a batch sharded over S devices."""
  xy = np.asarray(scene.pl_xy, np.float32)
  valid = np.asarray(scene.pl_valid, bool)
  edge = np.asarray(scene.pl_edge)
  b, p = valid.shape
  if shards < 1 or b % shards:
    raise ValueError(f"pack_polygons: {shards} shards do not divide a batch of {b} scenes")
  per = b // shards
  lists = [_pair_lists(xy[i:i + per], valid[i:i + per], edge[i:i + per], radius_m) for i in range(0, b, per)]
  n = bucket_length(max(len(flat) for flat, _, _ in lists), 64)
  e = bucket_length(max(len(dst) for _, dst, _ in lists), 1024)
  last = n - 1                                           # padding pairs at the last row: keeps the order
  pad = lambda a, size, fill: np.concatenate([a, np.full(size - len(a), fill)]).astype(np.int32)  # noqa: E731
  packs = [PackedPolygons(polygon=pad(flat, n, per * p - 1), polygon_valid=np.arange(n) < len(flat),
                          dst=pad(dst, e, last), src=pad(src, e, last), valid=np.arange(e) < len(dst))
           for flat, dst, src in lists]
  return packs[0] if shards == 1 else jax.tree_util.tree_map(lambda *a: np.stack(a), *packs)


# The scene fields the input side reads (with the frame scale): every point and polygon field but the edges.
INPUT_SIDE_FIELDS = ("pt_xy", "pt_heading", "pt_type", "pt_side", "pt_valid", "pl_xy", "pl_heading", "pl_type",
                     "pl_intersection", "pl_valid")


@struct.dataclass
class MapInputs:
  """A one-layer encoder's input side for each polygon row (leading axes R: `[B, P]`, or `[N]` polygons):
  `embedding`, the polygon's input embedding, and `attended`, the point -> polygon attention's output
  (`MapEncoder.input_side`). Zero rows for padding.

  Optionally (`[B, P]` rows of an encoder that keeps each polygon's k nearest, its relation embedding
  frozen: `MapEncoder.pl2pl_relations`) the polygon -> polygon pairs: each polygon's k key polygons
  (indices into P, 0 where not valid), which are valid, and the embedded relations of the pairs."""
  embedding: jax.Array  # [*R, D]
  attended: jax.Array   # [*R, D]
  pl2pl_index: jax.Array | None = None     # [B, P, k] int32
  pl2pl_valid: jax.Array | None = None     # [B, P, k] bool
  pl2pl_relation: jax.Array | None = None  # [B, P, k, D]


@struct.dataclass
class MapContext:
  polygons: jax.Array  # [B, P, D]
  valid: jax.Array     # [B, P]
  summary: jax.Array   # [B, L, D]

  def crop(self, num_polygons: int) -> "MapContext":
    """The first `num_polygons` polygon rows, as `Scene.crop` crops a scene (valid rows come first, so
    cropping to at least the valid count drops only padding; the summary does not depend on padding)."""
    return self.replace(polygons=self.polygons[:, :num_polygons], valid=self.valid[:, :num_polygons])



def _map_keys(scene: datatypes.Scene) -> list[bytes]:
  """A digest of each scene's map (its polygon fields, edges and frame scale): equal maps, equal keys."""
  host = {f: np.asarray(getattr(scene, f)) for f in (*datatypes.POLYGON_FIELDS, "pl_edge", "frame_scale")}
  return [hashlib.sha1(b"".join(a[i].tobytes() for a in host.values())).digest()
          for i in range(scene.pl_valid.shape[0])]


def encode_distinct(encode: Callable[[datatypes.Scene], MapContext], scene: datatypes.Scene) -> MapContext:
  """`encode` (a jitted encoder of a batch over its packed polygons, `pack_polygons`, which computes the
  valid polygons and pairs only, whatever the padding) applied once to the distinct maps of `scene`, in
  one call: one call's larger operations keep both cores busier than a call per map, and a map shared
  by several scenes (several samples of one map) is encoded once. The distinct maps are padded to 1, 2,
  4, 8, ... with maps without polygons (no work once packed), so a few batch sizes compile. The same
  context as encoding the padded batch (tested). Call it outside `jit`."""
  keys = _map_keys(scene)
  rows: dict[bytes, int] = {}
  for i, key in enumerate(keys):
    rows.setdefault(key, i)
  distinct = list(rows.values())
  n = 1 << (len(distinct) - 1).bit_length()
  if n == len(keys) and len(distinct) == len(keys):
    return encode(scene)
  maps = jax.tree_util.tree_map(lambda x: x[np.array(distinct + [distinct[0]] * (n - len(distinct)))], scene)
  empty = np.arange(n) >= len(distinct)
  maps = maps.replace(pl_valid=maps.pl_valid & ~empty[:, None], pt_valid=maps.pt_valid & ~empty[:, None, None])
  ctx = encode(maps)
  slot = {key: j for j, key in enumerate(rows)}
  ctx = jax.tree_util.tree_map(lambda x: x[np.array([slot[key] for key in keys])], ctx)
  return dataclasses.replace(ctx, valid=scene.pl_valid)


def encode_batch(encode: Callable[[datatypes.Scene], MapContext], scene: datatypes.Scene,
                 polygon_buckets: Sequence[int], all_pairs: bool) -> MapContext:
  """A batch's map encoding for the least work, shared maps once: an all-pairs encoder (which packs its
  polygons) encodes the distinct maps in one call (`encode_distinct`), one that keeps the k nearest
  polygons each scene at its own polygon bucket (`encode_per_scene`). Call it outside `jit`."""
  return encode_distinct(encode, scene) if all_pairs else encode_per_scene(encode, scene, polygon_buckets)


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
  keys = _map_keys(scene)
  if all(size == p for size in sizes) and len(set(keys)) == len(keys):
    return encode(scene)
  done: dict[bytes, MapContext] = {}
  parts = []
  for i, (key, size) in enumerate(zip(keys, sizes)):
    if key not in done:
      ctx = encode(_one_scene(scene, i, num_polygons=size))
      done[key] = dataclasses.replace(ctx, polygons=jnp.pad(ctx.polygons, ((0, 0), (0, p - size), (0, 0))),
                                      valid=scene.pl_valid[i:i + 1])
    parts.append(done[key])
  return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs), *parts)


@functools.partial(jax.jit, static_argnames=("num_polygons",))
def _one_scene(scene: datatypes.Scene, row: int, num_polygons: int) -> datatypes.Scene:
  """Scene `row` of a batch as a batch of one, cropped to `num_polygons`: one call (slicing its two dozen
  fields eagerly took about 5 ms a scene, half the encoding of its map)."""
  return jax.tree_util.tree_map(lambda x: jax.lax.dynamic_slice_in_dim(x, row, 1), scene).crop(
      num_polygons=num_polygons)


class MapEncoder(nnx.Module):

  def __init__(self, dim: int, heads: int, num_layers: int, num_freq_bands: int, num_latents: int,
               dropout_rate: float, pl2pl_radius_m: float, pl2pl_neighbors: int, absolute_inputs: bool = True,
               input_mode: str = "normalized", fourier_tables: int = 0, *, rngs: nnx.Rngs):
    if input_mode not in INPUT_MODES:
      raise ValueError(f"map encoder input_mode {input_mode!r}: choose one of {INPUT_MODES}")
    self.dropout_rate = dropout_rate
    self.absolute_inputs = absolute_inputs
    self.input_mode = input_mode
    self.pl2pl_radius_m = pl2pl_radius_m
    self.pl2pl_neighbors = pl2pl_neighbors
    # Tabulated where the inputs vary slowly at QCNet's initial frequencies (`layers.FourierEmbedding`):
    # relations in metres and radians, segment lengths and normalised positions; not metric positions,
    # whose periods start at 1 m.
    smooth = dict(table_size=fourier_tables)
    if not absolute_inputs:
      self.pt_input = layers.FourierEmbedding(1, dim, num_freq_bands, **smooth, rngs=rngs)
    elif input_mode == "metric":  # x, y (m), cos, sin
      freqs = jnp.concatenate([layers.log_spaced_freqs(2, num_freq_bands, 1.0, 250.0),
                               layers.log_spaced_freqs(2, num_freq_bands, 2.0, 8.0)])
      self.pt_input = layers.FourierEmbedding(4, dim, num_freq_bands, freqs, rngs=rngs)
      self.pl_input = layers.FourierEmbedding(4, dim, num_freq_bands, freqs, rngs=rngs)
    else:
      self.pt_input = layers.FourierEmbedding(3, dim, num_freq_bands, **smooth, rngs=rngs)
      self.pl_input = layers.FourierEmbedding(3, dim, num_freq_bands, **smooth, rngs=rngs)
    self.pt_type = nnx.Embed(len(datatypes.POINT_TYPES), dim, rngs=rngs)
    self.pt_side = nnx.Embed(len(datatypes.POINT_SIDES), dim, rngs=rngs)
    self.pl_type = nnx.Embed(len(datatypes.POLYGON_TYPES), dim, rngs=rngs)
    self.pl_intersection = nnx.Embed(len(datatypes.INTERSECTION_FLAGS), dim, rngs=rngs)
    self.r_pt2pl = layers.FourierEmbedding(3, dim, num_freq_bands, **smooth, rngs=rngs)
    self.r_pl2pl = layers.FourierEmbedding(3, dim, num_freq_bands, **smooth, rngs=rngs)
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

  def pack(self, scene: datatypes.Scene) -> PackedPolygons | None:
    """`pack_polygons` of a batch for this encoder (on the host): None unless it attends over all pairs."""
    return packing_for(scene, self.pl2pl_radius_m, self.pl2pl_neighbors)

  def pl2pl_relations(self, scene: datatypes.Scene) -> tuple[jax.Array, jax.Array, jax.Array]:
    """The polygon -> polygon pairs of an encoder that keeps each polygon's k nearest: key indices `[B, P, k]`
    (0 where not valid), which are valid `[B, P, k]`, and the embedded relations `[B, P, k, D]` (relative
    geometry in metres and the topology edge type). A constant of each map when `r_pl2pl` and `edge_type`
    are frozen (`train.freeze_map_inputs`): training then computes it once per scene. `scene` needs
    `pl_xy`, `pl_heading`, `pl_valid` and `pl_edge` only."""
    idx, nb_mask = self._pl2pl_neighbours(scene)
    if idx is None:
      raise ValueError("pl2pl_relations: this map encoder attends over all polygon pairs (pl2pl_neighbors = 0)")
    gather = jax.vmap(lambda a, i: a[i])  # [B, P, ...], [B, P, K] -> [B, P, K, ...]
    edge = jnp.take_along_axis(scene.pl_edge.astype(jnp.int32), idx, axis=2)
    r = layers.relative_geometry(gather(scene.pl_xy, idx), scene.pl_xy[:, :, None], gather(scene.pl_heading, idx),
                                 scene.pl_heading[:, :, None])
    return jnp.where(nb_mask, idx, 0), nb_mask, self.r_pl2pl(r, self.edge_type(edge), nb_mask)

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

  @property
  def input_side_is_constant(self) -> bool:
    """Whether the input side, its weights fixed, is a constant of each polygon (`input_side`): one layer
    (a second layer's point -> polygon attention reads the trained polygon -> polygon output), no dropout,
    and exact Fourier embeddings (a tabulated one's grid spans each call's inputs)."""
    tables = [m.table_size for m in (getattr(self, "pt_input", None), getattr(self, "pl_input", None), self.r_pt2pl)
              if m is not None]
    return len(self.pt2pl) == 1 and self.dropout_rate == 0 and not any(tables)

  def _rows(self, scene: datatypes.Scene, packed: PackedPolygons | None) -> tuple[dict[str, jax.Array], jax.Array]:
    """The polygon fields the input side reads, with leading axes `[B, P]` (or `[N]`, the valid polygons
    of `packed`), the encoder's point subset, and each row's frame scale."""
    b, p = scene.pl_valid.shape
    rows = {f: getattr(scene, f) for f in INPUT_SIDE_FIELDS}
    scale = jnp.broadcast_to(scene.frame_scale[:, None], (b, p))
    if packed is not None:  # rows: the valid polygons, [B, P, ...] -> [N, ...]
      rows = {f: v.reshape((b * p,) + v.shape[2:])[packed.polygon] for f, v in rows.items()}
      rows["pt_valid"] = rows["pt_valid"] & packed.polygon_valid[:, None]
      rows["pl_valid"] = rows["pl_valid"] & packed.polygon_valid
      scale = scale.reshape(-1)[packed.polygon]
    return rows, scale

  def input_side(self, scene: datatypes.Scene, xy_mean: jax.Array, xy_std: jax.Array) -> MapInputs:
    """The input side of each polygon of `scene` `[B, P, ...]` (`MapInputs` `[B, P, D]`, zero for padding),
    for `__call__(..., inputs=...)`; only where `input_side_is_constant`."""
    if not self.input_side_is_constant:
      raise ValueError("the map encoder's input side is not a constant of each polygon (more than one layer, "
                       "dropout, or tabulated Fourier embeddings)")
    rows, scale = self._rows(scene, None)
    x_pt, x_pl, r_pt2pl = self._inputs(rows, scale, xy_mean, xy_std)
    attended = self.pt2pl[0](x_pl, x_pt, r_pt2pl, rows["pt_valid"])
    valid = rows["pl_valid"][..., None]
    return MapInputs(jnp.where(valid, x_pl, 0.0), jnp.where(valid, attended, 0.0))

  def _inputs(self, rows: dict[str, jax.Array], scale: jax.Array, xy_mean: jax.Array, xy_std: jax.Array):
    """Point and polygon input embeddings and the point -> polygon relations of polygon rows: `rows` holds
    the polygon fields of the scene contract with leading axes R (`[B, P]`, or `[N]` packed), `scale`
    `[*R]` each row's frame scale. Returns x_pt `[*R, K, D]`, x_pl `[*R, D]`, r_pt2pl `[*R, K, D]`."""
    norm_xy = lambda xy, s: (xy / s[..., None] - xy_mean) / xy_std  # noqa: E731
    pt_cat = self.pt_type(rows["pt_type"]) + self.pt_side(rows["pt_side"])
    pl_cat = self.pl_type(rows["pl_type"]) + self.pl_intersection(rows["pl_intersection"])
    pt_xy, pt_heading, pl_xy, pl_heading = rows["pt_xy"], rows["pt_heading"], rows["pl_xy"], rows["pl_heading"]
    pt_valid, pl_valid = rows["pt_valid"], rows["pl_valid"]
    if self.absolute_inputs and self.input_mode == "metric":
      angle = lambda h: jnp.stack([jnp.cos(h), jnp.sin(h)], -1)  # noqa: E731
      x_pt = self.pt_input(jnp.concatenate([pt_xy, angle(pt_heading)], -1), pt_cat)     # [*R, K, 4] in
      x_pl = self.pl_input(jnp.concatenate([pl_xy, angle(pl_heading)], -1), pl_cat)
    elif self.absolute_inputs:
      x_pt = self.pt_input(jnp.concatenate([norm_xy(pt_xy, scale[..., None]), pt_heading[..., None]], -1), pt_cat,
                           pt_valid)
      x_pl = self.pl_input(jnp.concatenate([norm_xy(pl_xy, scale), pl_heading[..., None]], -1), pl_cat, pl_valid)
    else:
      k = pt_xy.shape[-2]
      seg = jnp.linalg.norm(pt_xy[..., 1:, :] - pt_xy[..., :-1, :] + 1e-12, axis=-1)
      last = (jnp.arange(1, k) % (k // datatypes.POLYLINES_PER_POLYGON)) == 0   # crossing to the next polyline
      seg = jnp.concatenate([jnp.where(last, 0.0, seg), jnp.zeros_like(seg[..., :1])], -1)   # [*R, K]
      x_pt = self.pt_input(seg[..., None], pt_cat, pt_valid)
      x_pl = pl_cat
    # Relations in metres.
    r_pt2pl = layers.relative_geometry(pt_xy, pl_xy[..., None, :], pt_heading, pl_heading[..., None])
    return x_pt, x_pl, self.r_pt2pl(r_pt2pl, valid=pt_valid)

  def _polygon_features(self, scene: datatypes.Scene, xy_mean: jax.Array, xy_std: jax.Array,
                        key: jax.Array | None, packed: PackedPolygons | None, inputs: MapInputs | None) -> jax.Array:
    """The polygon embeddings `[B, P, D]` (zero for padding) over padded grids or one packed list."""
    b, p = scene.pl_valid.shape
    if inputs is None:
      rows, scale = self._rows(scene, packed)
      x_pt, x_pl, r_pt2pl = self._inputs(rows, scale, xy_mean, xy_std)
    else:  # the polygons' rows of the precomputed input side; no point is read
      rows = {"pl_xy": scene.pl_xy, "pl_heading": scene.pl_heading}
      x_pl, attended = inputs.embedding, inputs.attended
      if packed is not None:
        rows = {f: v.reshape((b * p,) + v.shape[2:])[packed.polygon] for f, v in rows.items()}
        x_pl, attended = (v.reshape(b * p, -1)[packed.polygon] for v in (x_pl, attended))

    if packed is not None:  # the listed pairs only
      xy, heading = rows["pl_xy"], rows["pl_heading"]
      dst, src = packed.polygon[packed.dst], packed.polygon[packed.src]       # [E] into [B x P]
      pair_edge = scene.pl_edge.astype(jnp.int32).reshape(-1)[dst * p + src % p]   # edge[scene, query, key]
      r_pl2pl = layers.relative_geometry(xy[packed.src], xy[packed.dst], heading[packed.src], heading[packed.dst])
      r_pl2pl = self.r_pl2pl(r_pl2pl, self.edge_type(pair_edge), packed.valid)            # [E, D]
    elif inputs is not None and inputs.pl2pl_relation is not None:  # the k nearest pairs, computed apart
      idx, nb_mask, r_pl2pl = inputs.pl2pl_index, inputs.pl2pl_valid, inputs.pl2pl_relation
    elif 0 < self.pl2pl_neighbors < p:
      idx, nb_mask, r_pl2pl = self.pl2pl_relations(scene)                                  # [B, P, K, D]
    else:  # all pairs: sources broadcast against queries
      idx, nb_mask = self._pl2pl_neighbours(scene)
      r_pl2pl = layers.relative_geometry(scene.pl_xy[:, None], scene.pl_xy[:, :, None], scene.pl_heading[:, None],
                                         scene.pl_heading[:, :, None])
      r_pl2pl = self.r_pl2pl(r_pl2pl, self.edge_type(scene.pl_edge.astype(jnp.int32)), nb_mask)   # [B, P, P, D]

    x_sum = x_pl
    for i, (pt2pl, pl2pl) in enumerate(zip(self.pt2pl, self.pl2pl)):
      x_pl = attended if inputs is not None else pt2pl(x_pl, x_pt, r_pt2pl, rows["pt_valid"], layers.fold(key, 2 * i))
      if packed is not None:
        x_pl = pl2pl.packed(x_pl, r_pl2pl, packed.dst, packed.src, packed.valid, layers.fold(key, 2 * i + 1))
      else:
        x_pl = pl2pl(x_pl, x_pl, r_pl2pl, nb_mask, layers.fold(key, 2 * i + 1), src_index=idx)
      x_sum = x_sum + x_pl
    if packed is not None:  # back to [B, P, D]; padding rows go to a slot past the end and are dropped
      target = jnp.where(packed.polygon_valid, packed.polygon, b * p)
      x_sum = jnp.zeros((b * p, x_sum.shape[-1]), x_sum.dtype).at[target].set(x_sum, mode="drop")
      x_sum = x_sum.reshape(b, p, -1)
    return jnp.where(scene.pl_valid[..., None], x_sum, 0.0)

  def _sharded_polygon_features(self, scene: datatypes.Scene, xy_mean: jax.Array, xy_std: jax.Array,
                                key: jax.Array | None, packed: PackedPolygons, inputs: MapInputs | None) -> jax.Array:
    """`_polygon_features` of each of the S slices of a sharded pack, side by side: the batch `[B, ...]`
    viewed as `[S, B / S, ...]` (a batch sharded over S devices keeps each slice on its device), each
    slice with its own list and dropout key."""
    s = packed.shards
    b, p = scene.pl_valid.shape
    sliced = lambda x: x.reshape((s, b // s) + x.shape[1:])  # noqa: E731
    scenes, slice_inputs = jax.tree_util.tree_map(sliced, (scene, inputs))

    def one(scene_s, packed_s, inputs_s, i):
      return self._polygon_features(scene_s, xy_mean, xy_std, layers.fold(key, i), packed_s, inputs_s)

    x_sum = jax.vmap(one)(scenes, packed, slice_inputs, jnp.arange(s))   # [S, B / S, P, D]
    return x_sum.reshape((b, p) + x_sum.shape[3:])

  def __call__(self, scene: datatypes.Scene, xy_mean: jax.Array, xy_std: jax.Array,
               key: jax.Array | None = None, packed: PackedPolygons | None = None,
               inputs: MapInputs | None = None) -> MapContext:
    """`packed`: `pack_polygons(scene, pl2pl_radius_m[, shards])` (an all-pairs encoder's): the points,
    polygons and polygon pairs are computed for the batch's valid ones only, packed (per slice of the
    batch when sharded), not for its padded grids; the same output as without. `inputs`:
    `input_side(scene, ...)` computed apart (`[B, P, D]`), used instead of computing it, and with its
    `pl2pl_*` fields `pl2pl_relations(scene)`; the same output to float rounding."""
    if packed is not None and self.pl2pl_neighbors > 0:
      raise ValueError(f"packed polygons are for an all-pairs map encoder; this one keeps the "
                       f"{self.pl2pl_neighbors} nearest (pl2pl_neighbors)")
    if inputs is not None and not self.input_side_is_constant:
      raise ValueError("precomputed map inputs need a one-layer encoder without dropout or Fourier tables")
    if packed is not None and packed.shards > 1:
      x_sum = self._sharded_polygon_features(scene, xy_mean, xy_std, key, packed, inputs)
    else:
      x_sum = self._polygon_features(scene, xy_mean, xy_std, key, packed, inputs)
    b = scene.pl_valid.shape[0]
    if not self.num_latents:
      return MapContext(x_sum, scene.pl_valid, x_sum[:, :0])

    # Map summary: latents attend to [latents, valid polygons].
    latents = jnp.broadcast_to(self.latents[...], (b,) + self.latents.shape)
    tokens = jnp.concatenate([latents, x_sum], axis=1)
    token_mask = jnp.concatenate([jnp.ones(latents.shape[:2], bool), scene.pl_valid], axis=1)
    attn = self.summary_attn(latents, tokens, jnp.broadcast_to(token_mask[:, None], (b, latents.shape[1], token_mask.shape[1])))
    summary = self.summary_norm1(latents + attn)
    summary = summary + self.summary_ff(self.summary_norm2(summary))
    return MapContext(x_sum, scene.pl_valid, summary)
