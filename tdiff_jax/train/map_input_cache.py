"""The map encoder's frozen input side, computed once per training scene instead of once per step.

With `train.freeze_map_inputs` the map encoder's input side (`optim.MAP_INPUT_MODULES`: the input
embeddings and the point -> polygon attention) keeps its initial weights, and in a one-layer encoder
without dropout or Fourier tables it is a constant of each polygon (`MapEncoder.input_side`). Every
train step would otherwise recompute it for the batch's polygons: its forward pass, over every map
point, is about a sixth of the default CPU step. `MapInputCache.build` computes it once for every valid
polygon of the training split, packed into fixed chunks of polygons (one compile, no padding), and
`take` gives the train step a batch's rows (`trainer.train_and_evaluate`).

Its polygon -> polygon relations frozen with it, in an encoder that keeps each polygon's k nearest polygons, the
polygon -> polygon relation embedding is a constant of each map as well (`MapEncoder.pl2pl_relations`:
the key polygons and the embedding of their relative geometry and edge types, about a fifth of the
default CPU step's work, forward and backward): the cache holds every valid polygon's k pairs, computed
a chunk of scenes at a time (the neighbours are a whole map's, not one polygon's).

The cache lives in host memory only, built at the start of every run (a resumed one too) from the
parameters the run trains: nothing on disk can go stale. A split whose polygons would take more than
`trainer.MAP_INPUT_CACHE_MB` is not cached (the step then computes the input side, as without a cache).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from tdiff_jax.models.map_encoder import INPUT_SIDE_FIELDS, MapInputs


@struct.dataclass
class PolygonRows:
  """Polygons of several scenes as a batch of one-polygon maps: what `MapEncoder.input_side` reads of a
  scene (`[R, 1, ...]`, R polygons, with each one's frame scale `[R]`)."""
  pt_xy: jax.Array
  pt_heading: jax.Array
  pt_type: jax.Array
  pt_side: jax.Array
  pt_valid: jax.Array
  pl_xy: jax.Array
  pl_heading: jax.Array
  pl_type: jax.Array
  pl_intersection: jax.Array
  pl_valid: jax.Array
  frame_scale: jax.Array


@struct.dataclass
class PolygonGraph:
  """Whole maps, what `MapEncoder.pl2pl_relations` reads of a scene: `[B, P, ...]` and edges `[B, P, P]`."""
  pl_xy: jax.Array
  pl_heading: jax.Array
  pl_valid: jax.Array
  pl_edge: jax.Array


def cache_bytes(num_polygons: int, dim: int, pl2pl_neighbors: int = 0) -> int:
  """Host memory of a cache of `num_polygons` rows of a `dim`-wide encoder (two float32 vectors each), with
  `pl2pl_neighbors` > 0 their polygon -> polygon pairs too (an int32 index, a flag and a float32 relation each)."""
  return num_polygons * (2 * dim * 4 + pl2pl_neighbors * (4 + 1 + dim * 4))


@dataclasses.dataclass
class MapInputCache:
  """Every valid polygon's input side: scene s's polygons (valid ones first, the scene contract) are rows
  `offsets[s]:offsets[s + 1]` of `rows` `[N, 2, D]` (the embedding, then the point -> polygon output)."""

  rows: np.ndarray     # [N, 2, D] float32
  offsets: np.ndarray  # [S + 1] int64
  # With frozen relations: each polygon's k key polygons (indices into its scene's polygons, 0 where not
  # valid), which are valid, and the pairs' embedded relations.
  pl2pl_index: np.ndarray | None = None     # [N, k] int32
  pl2pl_valid: np.ndarray | None = None     # [N, k] bool
  pl2pl_relation: np.ndarray | None = None  # [N, k, D] float32

  @classmethod
  def build(cls, input_side: Callable[[PolygonRows], MapInputs], source, chunk: int = 512,
            pl2pl_relations: Callable[[PolygonGraph], tuple[jax.Array, jax.Array, jax.Array]] | None = None,
            scenes_per_call: int = 16, min_polygons: int = 32) -> "MapInputCache":
    """Runs `input_side` (the frozen encoder's `input_side(rows, xy_mean, xy_std)`, jitted) over the valid
    polygons of every scene of `source` (a split: `source[s]` a scene's dict of arrays, `num_polygons`
    its valid counts), `chunk` polygons per call; and `pl2pl_relations` (the encoder's, jitted; None: no
    pairs) over its maps, `scenes_per_call` of similar size per call, cropped to at least `min_polygons`
    polygons (more than the encoder's k nearest)."""
    counts = np.asarray(source.num_polygons, np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    parts: dict[str, list[np.ndarray]] = {f: [] for f in (*INPUT_SIDE_FIELDS, "frame_scale")}
    for s in range(len(source)):
      scene, n = source[s], int(counts[s])
      if not (np.all(scene["pl_valid"][:n]) and not np.any(scene["pl_valid"][n:])):
        raise ValueError(f"scene {s} of split {getattr(source, 'split', '?')!r}: its valid polygons do not come "
                         "first (the scene contract); rebuild the cache")
      for f in INPUT_SIDE_FIELDS:
        parts[f].append(np.asarray(scene[f][:n]))
      parts["frame_scale"].append(np.full(n, scene["frame_scale"], np.float32))
    total = int(offsets[-1])
    padded = -(-total // chunk) * chunk
    fields = {}
    for f, arrays in parts.items():
      a = np.concatenate(arrays)
      pad = np.zeros((padded - total,) + a.shape[1:], a.dtype)
      if f == "frame_scale":
        pad += 1.0  # a padding row's scale divides positions
      fields[f] = np.concatenate([a, pad])[:, None] if f != "frame_scale" else np.concatenate([a, pad])
    out = []
    for start in range(0, padded, chunk):
      rows = PolygonRows(**{f: jnp.asarray(v[start:start + chunk]) for f, v in fields.items()})
      inputs = input_side(rows)
      out.append(np.stack([np.asarray(inputs.embedding[:, 0]), np.asarray(inputs.attended[:, 0])], 1))
    rows = np.concatenate(out)[:total] if out else np.zeros((0, 2, 0), np.float32)
    if pl2pl_relations is None:
      return cls(rows, offsets)
    return cls(rows, offsets, *_pair_relations(pl2pl_relations, source, counts, scenes_per_call, min_polygons))

  @property
  def nbytes(self) -> int:
    return int(sum(a.nbytes for a in (self.rows, self.pl2pl_index, self.pl2pl_valid, self.pl2pl_relation)
                   if a is not None))

  def take(self, indices: np.ndarray, num_polygons: int) -> MapInputs:
    """The rows of the scenes `indices` `[B]`, padded with zeros to `num_polygons` (the batch's P):
    `MapInputs` of numpy `[B, P, D]` (and `[B, P, k, ...]` pairs when the cache holds them)."""
    out = np.zeros((len(indices), num_polygons) + self.rows.shape[1:], np.float32)
    pairs = None if self.pl2pl_index is None else [
        np.zeros((len(indices), num_polygons) + a.shape[1:], a.dtype)
        for a in (self.pl2pl_index, self.pl2pl_valid, self.pl2pl_relation)]
    for j, s in enumerate(indices):
      start, stop = self.offsets[s], self.offsets[s + 1]
      out[j, :stop - start] = self.rows[start:stop]
      for a, cached in zip(pairs or (), (self.pl2pl_index, self.pl2pl_valid, self.pl2pl_relation)):
        a[j, :stop - start] = cached[start:stop]
    return MapInputs(out[:, :, 0], out[:, :, 1], *(pairs or ()))


def _pair_relations(pl2pl_relations, source, counts: np.ndarray, scenes_per_call: int, min_polygons: int):
  """`pl2pl_relations` of every map of `source`, the valid polygons' rows in split order: index `[N, k]`,
  valid `[N, k]`, relation `[N, k, D]`. Scenes go in order of size, each call cropped to a multiple of 32
  polygons holding its largest, at least `min_polygons` (a few compiles, little padding)."""
  parts: list[tuple[np.ndarray, ...] | None] = [None] * len(counts)
  order = np.argsort(counts, kind="stable")
  for start in range(0, len(order), scenes_per_call):
    group = order[start:start + scenes_per_call]
    maps = [source[int(s)] for s in group]
    size = min(max(-(-int(counts[group].max()) // 32) * 32, min_polygons), maps[0]["pl_valid"].shape[0])
    while len(maps) < scenes_per_call:  # one batch size: a map without polygons fills the call
      maps.append({**maps[0], "pl_valid": np.zeros_like(maps[0]["pl_valid"])})
    graph = PolygonGraph(*(jnp.asarray(np.stack([m[f][:size] if f != "pl_edge" else m[f][:size, :size]
                                                 for m in maps]))
                           for f in ("pl_xy", "pl_heading", "pl_valid", "pl_edge")))
    index, valid, relation = (np.asarray(a) for a in pl2pl_relations(graph))
    for j, s in enumerate(group):
      n = int(counts[s])
      parts[s] = (index[j, :n].astype(np.int32), valid[j, :n], relation[j, :n].astype(np.float32))
  if not parts:
    return np.zeros((0, 0), np.int32), np.zeros((0, 0), bool), np.zeros((0, 0, 0), np.float32)
  return tuple(np.concatenate([p[i] for p in parts]) for i in range(3))
