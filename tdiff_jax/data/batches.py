"""Batches of scenes from the preprocessing cache.

`load_split` reads a split's shards into memory after checking the manifest against the data config
(a cache made with other caps or selection rules is refused). `BatchIterator` yields `types.Scene`
batches of numpy arrays with a leading `[B]`: fixed batch size, a deterministic shuffle per epoch
drawn from (seed, epoch), optionally grouping scenes of similar size into the same batch, and a
position that can be saved and restored to resume exactly.
`crop_to_bucket` trims a batch's padding to the smallest configured size bucket, so the model pays
for the agents and polygons a batch has, with one compile per bucket.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Iterator, Sequence

import ml_collections
import numpy as np

from tdiff_jax import types
from tdiff_jax.data import config as config_lib
from tdiff_jax.data import preprocess


@dataclasses.dataclass
class SceneDataset:
  """All scenes of one split, in memory. `scenes` arrays have a leading `[N]`."""

  scenes: types.Scene
  scenario_ids: np.ndarray  # [N] str
  manifest: dict
  split: str

  def __len__(self) -> int:
    return int(self.scenes.agent_valid.shape[0])

  def take(self, indices) -> types.Scene:
    indices = np.asarray(indices)
    return types.Scene.from_dict({k: v[indices] for k, v in self.scenes.to_dict().items()})


def read_manifest(cache_dir: Path | str) -> dict:
  path = Path(cache_dir) / preprocess.MANIFEST
  if not path.exists():
    raise FileNotFoundError(f"{path}: no manifest; build the cache with python -m tdiff_jax.data.preprocess")
  try:
    return json.loads(path.read_text())
  except json.JSONDecodeError as e:
    raise ValueError(f"{path}: broken manifest ({e})") from e


def check_manifest(manifest: dict, config: ml_collections.ConfigDict, where: str) -> None:
  """Raises ValueError naming each field where the cache and the config disagree."""
  theirs = manifest.get("config", {})
  ours = config.to_dict()
  diff = {k: (theirs.get(k), ours.get(k)) for k in sorted(set(theirs) | set(ours)) if theirs.get(k) != ours.get(k)}
  if diff:
    lines = ", ".join(f"{k}: cache {a!r} vs config {b!r}" for k, (a, b) in diff.items())
    raise ValueError(f"{where}: the cache was built with another data config ({lines}); "
                     "rebuild it or use the matching config")
  if manifest.get("format_version") != preprocess.FORMAT_VERSION:
    raise ValueError(f"{where}: cache format {manifest.get('format_version')}, this code reads "
                     f"{preprocess.FORMAT_VERSION}; rebuild the cache")


def load_split(cache_dir: Path | str, split: str, config: ml_collections.ConfigDict | None = None) -> SceneDataset:
  cache_dir = Path(cache_dir)
  config = config or config_lib.default_data_config()
  manifest = read_manifest(cache_dir)
  check_manifest(manifest, config, str(cache_dir))
  if split not in manifest["splits"]:
    raise KeyError(f"{cache_dir}: no split {split!r}; the cache has {sorted(manifest['splits'])}")
  expected = manifest["splits"][split]["shards"]
  missing = [s for s in expected if not (cache_dir / s).exists()]
  if missing:
    raise FileNotFoundError(f"{cache_dir}: shards listed in the manifest are missing: {missing[:3]}")
  arrays = preprocess.load_arrays(cache_dir / split)
  ids = arrays.pop("scenario_id")
  scenes = types.Scene.from_dict(arrays)
  if len(ids) != manifest["splits"][split]["scenes"]:
    raise ValueError(f"{cache_dir}/{split}: {len(ids)} scenes in the shards, manifest says "
                     f"{manifest['splits'][split]['scenes']}; rebuild the cache")
  return SceneDataset(scenes, ids, manifest, split)


class BatchIterator:
  """Endless batches over a dataset, epoch after epoch.

  The order of epoch e is a permutation drawn from `np.random.default_rng([seed, e])`, so it does
  not depend on how the iterator got there: `get_state()` after n batches and `set_state()` in a
  new iterator continue with batch n + 1. With `drop_remainder`, each epoch yields
  `len(dataset) // batch_size` full batches; otherwise the last one is short.
  """

  def __init__(self, dataset: SceneDataset, batch_size: int, seed: int = 0, shuffle: bool = True,
               drop_remainder: bool = True, group_by_size: bool = False, group_batches: int = 16):
    if batch_size < 1:
      raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if len(dataset) == 0:
      raise ValueError(f"split {dataset.split!r} has no scenes")
    if drop_remainder and batch_size > len(dataset):
      raise ValueError(f"batch_size {batch_size} exceeds the {len(dataset)} scenes of split {dataset.split!r}")
    self.dataset, self.batch_size, self.seed = dataset, batch_size, seed
    self.shuffle, self.drop_remainder = shuffle, drop_remainder
    self.group_by_size, self.group_batches = group_by_size, group_batches
    self.epoch, self.position = 0, 0
    self._order_epoch, self._order = None, None
    # Scene size for grouping: polygons first, then agents (the polygon pairs dominate the cost).
    self._size = (dataset.scenes.pl_valid.sum(-1).astype(np.int64) * 1000
                  + dataset.scenes.agent_valid.sum(-1).astype(np.int64))

  @property
  def batches_per_epoch(self) -> int:
    n = len(self.dataset)
    return n // self.batch_size if self.drop_remainder else -(-n // self.batch_size)

  def epoch_order(self, epoch: int) -> np.ndarray:
    if self._order_epoch != epoch:
      n = len(self.dataset)
      rng = np.random.default_rng([self.seed, epoch])
      order = rng.permutation(n) if self.shuffle else np.arange(n)
      if self.group_by_size:
        order = self._group(order, rng)
      self._order, self._order_epoch = order, epoch
    return self._order

  def _group(self, order: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Sorts each window of `group_batches` batches by scene size, then shuffles whole batches.

    Batches then hold scenes of similar size, so `crop_to_bucket` trims more padding; every scene
    still appears once per epoch, in an order fixed by (seed, epoch).
    """
    bs, window = self.batch_size, self.batch_size * self.group_batches
    chunks = [order[i:i + window] for i in range(0, len(order), window)]
    order = np.concatenate([c[np.argsort(self._size[c], kind="stable")] for c in chunks])
    full = len(order) // bs
    batch_order = rng.permutation(full) if self.shuffle else np.arange(full)
    return np.concatenate([order[:full * bs].reshape(full, bs)[batch_order].reshape(-1), order[full * bs:]])

  def get_state(self) -> dict[str, int]:
    return {"epoch": self.epoch, "position": self.position, "seed": self.seed}

  def set_state(self, state: dict[str, int]) -> None:
    if state.get("seed", self.seed) != self.seed:
      raise ValueError(f"iterator state is for seed {state['seed']}, this iterator has seed {self.seed}")
    self.epoch, self.position = int(state["epoch"]), int(state["position"])

  def next_indices(self) -> np.ndarray:
    if self.position >= self.batches_per_epoch:
      self.epoch, self.position = self.epoch + 1, 0
    order = self.epoch_order(self.epoch)
    start = self.position * self.batch_size
    self.position += 1
    return order[start:start + self.batch_size]

  def __iter__(self) -> Iterator[types.Scene]:
    return self

  def __next__(self) -> types.Scene:
    return self.dataset.take(self.next_indices())


def bucket_size(count: int, buckets: Sequence[int]) -> int:
  for b in sorted(buckets):
    if count <= b:
      return b
  return max(buckets)


def crop_to_bucket(batch: types.Scene, agent_buckets: Sequence[int], polygon_buckets: Sequence[int]) -> types.Scene:
  """Trims agent and polygon padding to the smallest bucket that holds every valid entry.

  Valid agents and polygons are packed first (the scene contract), so cropping drops only padding.
  Buckets above the arrays' cap are clipped to the cap.
  """
  a_cap, p_cap = batch.num_agents, batch.num_polygons
  a = min(bucket_size(int(batch.agent_valid.sum(-1).max()), agent_buckets), a_cap)
  p = min(bucket_size(int(batch.pl_valid.sum(-1).max()), polygon_buckets), p_cap)
  return batch.crop(a, p)
