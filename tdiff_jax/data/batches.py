"""Batches of scenes from the preprocessing cache, streamed with Grain.

`open_split` opens a split's ArrayRecord shards as a random-access source (`records.SceneRecords`)
after checking the manifest against the data config (a cache made with other caps or selection rules,
or in an older format, is refused with the command that rebuilds it); nothing but per-scene counts
is held in memory, so a split of any size streams. `load_split` reads a small split into memory
instead (tests, analysis).

`BatchIterator` is a Grain pipeline over either: `BatchPlan`, a `grain.MapDataset` from the global
batch number to its scene indices (fixed batch size, a deterministic shuffle per epoch drawn from
(seed, epoch), optionally grouping scenes of similar size), then a map that reads this process's
share of each global batch and crops its padding to the size bucket of the whole global batch, then
prefetching in threads. Its state (Grain's) is saved in checkpoints, so a resumed
run sees exactly the batches an uninterrupted one would.
`crop_to_bucket` trims a batch's padding to the smallest configured size bucket, so the model pays
for the agents and polygons a batch has, with one compile per bucket. `merge_rare_buckets` folds the
buckets a run would meet in only a few batches into larger ones it meets often: on a CPU one compile
of the train step costs as much as 50 to 100 steps.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Iterator, Sequence

import grain
import ml_collections
import numpy as np

from tdiff_jax import datatypes
from tdiff_jax.data import config as config_lib
from tdiff_jax.data import preprocess, records


@dataclasses.dataclass
class SceneDataset:
  """All scenes of one split, in memory. `scenes` arrays have a leading `[N]`. Also a random-access
  source for `BatchIterator`, like `records.SceneRecords`."""

  scenes: datatypes.Scene
  scenario_ids: np.ndarray  # [N] str
  manifest: dict
  split: str

  def __len__(self) -> int:
    return int(self.scenes.agent_valid.shape[0])

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    return {k: v[index] for k, v in self.scenes.to_dict().items()}

  @property
  def num_agents(self) -> np.ndarray:
    return self.scenes.agent_valid.sum(-1).astype(np.int64)

  @property
  def num_polygons(self) -> np.ndarray:
    return self.scenes.pl_valid.sum(-1).astype(np.int64)

  def take(self, indices) -> datatypes.Scene:
    indices = np.asarray(indices)
    return datatypes.Scene.from_dict({k: v[indices] for k, v in self.scenes.to_dict().items()})


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
  if manifest.get("format_version") != preprocess.FORMAT_VERSION:
    source = manifest.get("source", "<AV2 root>")
    raise ValueError(f"{where}: cache format {manifest.get('format_version')}, this code reads "
                     f"{preprocess.FORMAT_VERSION}; rebuild the cache with: python -m tdiff_jax.data.preprocess "
                     f"--data_dir {source} --out {where} --force (training rebuilds a cache it made itself)")
  problem = preprocess.manifest_problem(manifest)
  if problem is not None:
    raise ValueError(f"{where}/{preprocess.MANIFEST}: {problem}; {preprocess.rebuild_hint(manifest, where)}")
  theirs = manifest.get("config", {})
  ours = config_lib.scene_config(config).to_dict()
  diff = {k: (theirs.get(k), ours.get(k)) for k in sorted(set(theirs) | set(ours)) if theirs.get(k) != ours.get(k)}
  if diff:
    lines = ", ".join(f"{k}: cache {a!r} vs config {b!r}" for k, (a, b) in diff.items())
    raise ValueError(f"{where}: the cache was built with another data config ({lines}); "
                     "rebuild it or use the matching config")


def _checked_split(cache_dir: Path, split: str, config: ml_collections.ConfigDict | None) -> tuple[dict, list[Path]]:
  config = config_lib.scene_config(config)
  manifest = read_manifest(cache_dir)
  check_manifest(manifest, config, str(cache_dir))
  if split not in manifest["splits"]:
    raise KeyError(f"{cache_dir}: no split {split!r}; the cache has {sorted(manifest['splits'])}")
  paths = [cache_dir / s for s in manifest["splits"][split]["shards"]]
  missing = [str(p.relative_to(cache_dir)) for p in paths if not p.exists() or not p.with_suffix(".json").exists()]
  if missing:
    raise FileNotFoundError(f"{cache_dir}: shards listed in the manifest are missing: {missing[:3]}")
  return manifest, paths


def _check_count(found: int, manifest: dict, cache_dir: Path, split: str) -> None:
  if found != manifest["splits"][split]["scenes"]:
    raise ValueError(f"{cache_dir}/{split}: {found} scenes in the shards, manifest says "
                     f"{manifest['splits'][split]['scenes']}; rebuild the cache")


def open_split(cache_dir: Path | str, split: str, config: ml_collections.ConfigDict | None = None
               ) -> records.SceneRecords:
  """A split of the cache as a streaming random-access source (memory: a few numbers per scene)."""
  cache_dir = Path(cache_dir)
  manifest, paths = _checked_split(cache_dir, split, config)
  metas = []
  for path in paths:  # every shard's checksums: a damaged one is named here, not steps later in a loader
    meta, problem = preprocess.shard_problem(path)
    if problem is not None:
      raise ValueError(f"{problem}; {preprocess.rebuild_hint(manifest, cache_dir)}")
    metas.append(meta)
  ids = np.array([i for m in metas for i in m["scenario_ids"]], dtype=np.str_)
  _check_count(len(ids), manifest, cache_dir, split)
  counts = lambda key: np.array([n for m in metas for n in m[key]], np.int64)  # noqa: E731
  return records.SceneRecords(paths, counts("num_agents"), counts("num_polygons"), ids, split, manifest,
                              [len(m["scenario_ids"]) for m in metas], preprocess.rebuild_hint(manifest, cache_dir))


def load_split(cache_dir: Path | str, split: str, config: ml_collections.ConfigDict | None = None) -> SceneDataset:
  """A split of the cache in memory (about 0.3 MB a scene): for small splits; training streams."""
  cache_dir = Path(cache_dir)
  config = config_lib.scene_config(config)
  manifest, _ = _checked_split(cache_dir, split, config)
  arrays = preprocess.load_arrays(cache_dir / split)
  ids = arrays.pop("scenario_id")
  if len(ids) == 0:
    arrays = preprocess._empty_scene(config)
    ids = np.zeros((0,), np.str_)
  scenes = datatypes.Scene.from_dict(arrays)
  _check_count(len(ids), manifest, cache_dir, split)
  return SceneDataset(scenes, ids, manifest, split)


class BatchPlan(grain.MapDataset):
  """Global batch number -> the scene indices `[B]` of that batch, endlessly, epoch after epoch.

  The order of epoch e is a permutation drawn from `np.random.default_rng([seed, e])`, so batch n
  does not depend on how one got there. With `drop_remainder`, each epoch has `N // batch_size` full
  batches; otherwise its last one is short. `group_by_size` sorts each window of `group_batches`
  batches by scene size (polygons, then agents), then shuffles whole batches: batches hold scenes of
  similar size, so less padding, and every scene still comes once per epoch.
  """

  def __init__(self, num_agents: np.ndarray, num_polygons: np.ndarray, batch_size: int, seed: int = 0,
               shuffle: bool = True, drop_remainder: bool = True, group_by_size: bool = False,
               group_batches: int = 16):
    super().__init__()
    self.n = len(num_agents)
    self.batch_size, self.seed, self.shuffle = batch_size, seed, shuffle
    self.drop_remainder, self.group_by_size, self.group_batches = drop_remainder, group_by_size, group_batches
    # Polygons first, then agents: the polygon pairs dominate the cost.
    self._size = np.asarray(num_polygons, np.int64) * 1000 + np.asarray(num_agents, np.int64)
    self._order_epoch, self._order = None, None

  @property
  def batches_per_epoch(self) -> int:
    return self.n // self.batch_size if self.drop_remainder else -(-self.n // self.batch_size)

  def __len__(self) -> int:
    return sys.maxsize  # endless

  def __getitem__(self, index):
    if isinstance(index, slice):
      return self.slice(index)
    epoch, position = divmod(int(index), self.batches_per_epoch)
    start = position * self.batch_size
    return self.epoch_order(epoch)[start:start + self.batch_size]

  def epoch_order(self, epoch: int) -> np.ndarray:
    if self._order_epoch != epoch:
      rng = np.random.default_rng([self.seed, epoch])
      order = rng.permutation(self.n) if self.shuffle else np.arange(self.n)
      if self.group_by_size:
        order = self._group(order, rng)
      self._order, self._order_epoch = order, epoch
    return self._order

  def _group(self, order: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    bs, window = self.batch_size, self.batch_size * self.group_batches
    chunks = [order[i:i + window] for i in range(0, len(order), window)]
    order = np.concatenate([c[np.argsort(self._size[c], kind="stable")] for c in chunks])
    full = len(order) // bs
    batch_order = rng.permutation(full) if self.shuffle else np.arange(full)
    return np.concatenate([order[:full * bs].reshape(full, bs)[batch_order].reshape(-1), order[full * bs:]])

  def __str__(self) -> str:
    return f"BatchPlan(n={self.n}, batch_size={self.batch_size}, seed={self.seed})"


@dataclasses.dataclass(frozen=True)
class _ReadShare:
  """Global batch indices -> (those indices, this process's share of the batch as a `datatypes.Scene`).

  The crop bucket comes from the whole global batch's counts, so every process crops alike and the
  shares assemble into one global array."""

  source: object  # `records.SceneRecords` or `SceneDataset`
  process_index: int
  process_count: int
  buckets: tuple[tuple[int, ...], tuple[int, ...]] | None
  merge: dict[tuple[int, int], tuple[int, int]] = dataclasses.field(default_factory=dict)  # see `merge_rare_buckets`

  def __call__(self, indices: np.ndarray) -> tuple[np.ndarray, datatypes.Scene]:
    share = len(indices) // self.process_count
    local = indices[self.process_index * share:(self.process_index + 1) * share]
    scenes = [self.source[int(i)] for i in local]
    batch = datatypes.Scene.from_dict({f: np.stack([s[f] for s in scenes]) for f in datatypes.SCENE_FIELDS})
    if self.buckets is not None:
      shape = batch_bucket(self.source, indices, self.buckets)
      batch = _crop(batch, self.merge.get(shape, shape))
    return indices, batch


def batch_bucket(source, indices: np.ndarray, buckets: tuple[Sequence[int], Sequence[int]]) -> tuple[int, int]:
  """The (agents, polygons) size bucket of the batch of scenes `indices` of `source`."""
  return (datatypes.bucket_size(int(source.num_agents[indices].max()), buckets[0]),
          datatypes.bucket_size(int(source.num_polygons[indices].max()), buckets[1]))


def merge_rare_buckets(counts: dict[tuple[int, int], int], min_batches: int) -> dict[tuple[int, int], tuple[int, int]]:
  """Bucket -> the bucket its batches are padded to instead, for buckets met in fewer than `min_batches`.

  `counts`: how many batches of a run fall in each (agents, polygons) bucket. A rare bucket goes to the
  smallest (agents x polygons) bucket that holds it and is met at least `min_batches` times; a rare
  bucket that no frequent one holds stays. Padding is masked, so a merged batch gives the same losses up
  to float rounding; it costs a few padded steps and saves a compile.
  """
  frequent = [s for s, n in counts.items() if n >= min_batches]
  merge = {}
  for shape, n in counts.items():
    if n < min_batches:
      holders = [f for f in frequent if f[0] >= shape[0] and f[1] >= shape[1]]
      if holders:
        merge[shape] = min(holders, key=lambda f: (f[0] * f[1], f))
  return merge


class BatchIterator:
  """Endless batches over a source (`open_split` or `load_split`), epoch after epoch (`BatchPlan`).

  Yields `datatypes.Scene` batches of numpy arrays `[B / process_count, ...]`: this process's share of
  each global batch of `batch_size` scenes, cropped to the size bucket of the global batch when
  `buckets` = (agent buckets, polygon buckets) is given. Two batches are read ahead in threads.
  `get_state()` after n
  batches and `set_state()` in a new iterator continue with batch n + 1. With `min_bucket_batches` and
  `planned_batches`, buckets that the first `planned_batches` batches meet fewer than
  `min_bucket_batches` times are padded to a larger, frequent one (`merge_rare_buckets`; `self.merged`).
  """

  def __init__(self, source, batch_size: int, seed: int = 0, shuffle: bool = True, drop_remainder: bool = True,
               group_by_size: bool = False, group_batches: int = 16,
               buckets: tuple[Sequence[int], Sequence[int]] | None = None, process_index: int = 0,
               process_count: int = 1, min_bucket_batches: int = 0,
               planned_batches: int = 0):
    if batch_size < 1:
      raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if len(source) == 0:
      raise ValueError(f"split {source.split!r} has no scenes")
    if drop_remainder and batch_size > len(source):
      raise ValueError(f"batch_size {batch_size} exceeds the {len(source)} scenes of split {source.split!r}")
    if batch_size % process_count or (not drop_remainder and len(source) % batch_size % process_count):
      raise ValueError(f"batch_size {batch_size} must split evenly over {process_count} processes")
    self.source, self.batch_size, self.seed = source, batch_size, seed
    self.process_index, self.process_count = process_index, process_count
    self.plan = BatchPlan(source.num_agents, source.num_polygons, batch_size, seed, shuffle, drop_remainder,
                          group_by_size, group_batches)
    buckets = None if buckets is None else (tuple(buckets[0]), tuple(buckets[1]))
    self.merged: dict[tuple[int, int], tuple[int, int]] = {}
    if buckets is not None and min_bucket_batches > 0 and planned_batches > 0:
      counts: dict[tuple[int, int], int] = {}
      for i in range(planned_batches):  # sizes only: no scene is read
        shape = batch_bucket(source, self.plan[i], buckets)
        counts[shape] = counts.get(shape, 0) + 1
      self.merged = merge_rare_buckets(counts, min_bucket_batches)
    read = _ReadShare(source, process_index, process_count, buckets, self.merged)
    self._dataset = self.plan.map(read).to_iter_dataset(grain.ReadOptions(num_threads=2, prefetch_buffer_size=2))
    self._iter = None

  @property
  def batches_per_epoch(self) -> int:
    return self.plan.batches_per_epoch

  def _iterator(self):
    if self._iter is None:
      self._iter = iter(self._dataset)
    return self._iter

  def get_state(self) -> dict:
    """JSON-serialisable: the seed and Grain's iterator state."""
    return {"seed": self.seed, "grain": self._iterator().get_state()}

  def set_state(self, state: dict) -> None:
    if state.get("seed", self.seed) != self.seed:
      raise ValueError(f"iterator state is for seed {state['seed']}, this iterator has seed {self.seed}")
    if "grain" not in state:  # written before the Grain pipeline: {"epoch", "position"}
      state = {"grain": {"next_index": int(state["epoch"]) * self.batches_per_epoch + int(state["position"])}}
    self._iterator().set_state(state["grain"])

  def next_indices(self) -> np.ndarray:
    """The global scene indices of the next batch (the batch itself is read and dropped)."""
    return next(self._iterator())[0]

  def next_with_indices(self) -> tuple[np.ndarray, datatypes.Scene]:
    """The next batch (as `next`) and the source indices `[B / process_count]` of its scenes."""
    indices, batch = next(self._iterator())
    share = len(indices) // self.process_count
    return indices[self.process_index * share:(self.process_index + 1) * share], batch

  def __iter__(self) -> Iterator[datatypes.Scene]:
    return self

  def __next__(self) -> datatypes.Scene:
    return next(self._iterator())[1]


# The sampler's agent buckets for the config of a checkpoint saved before the config held them.
SAMPLER_AGENT_BUCKETS = (4, 8, 12, 16, 24, 32, 40, 48, 64)


def sampler_agent_buckets(data_config) -> tuple[int, ...]:
  """The agent buckets sampler batches are cut by (`sampler_batches`): the data config's
  `sampler_agent_buckets`, or `SAMPLER_AGENT_BUCKETS` for an older checkpoint's config (they change only
  the padding, not the samples)."""
  return tuple(data_config.get("sampler_agent_buckets", SAMPLER_AGENT_BUCKETS))


def sampler_batches(scenes: Sequence[datatypes.Scene], batch_size: int, agent_buckets: Sequence[int],
                    polygon_buckets: Sequence[int]) -> Iterator[tuple[np.ndarray, datatypes.Scene]]:
  """The batches `sample.py` and `evaluate` sample: `(positions, batch)` for unbatched scenes.

  Scenes are ordered by agent bucket, then polygon count, smallest first (their given order otherwise),
  and cut into batches of at most `batch_size` scenes of one agent bucket. `positions` `[n]`: the batch's
  scenes in `scenes`. `batch` `[B, A, ...]`: those scenes stacked, cropped to their agent bucket and the
  polygon bucket of the largest map, and padded to B = the next power of two (at most `batch_size`) with
  copies of its first scene without agents, so a run compiles a few batch shapes, not one per count; its
  first n scenes are the real ones. A scene's samples depend on its own key only, never on its batch.
  """
  if batch_size < 1:
    raise ValueError(f"batch_size must be >= 1, got {batch_size}")
  agents = [datatypes.bucket_size(int(s.agent_valid.sum()), agent_buckets) for s in scenes]
  polygons = [int(s.pl_valid.sum()) for s in scenes]
  order = sorted(range(len(scenes)), key=lambda i: (agents[i], polygons[i]))
  while order:
    same = [i for i in order[:batch_size] if agents[i] == agents[order[0]]]
    order = order[len(same):]
    batch = crop_to_bucket(datatypes.stack_scenes([scenes[i] for i in same]), agent_buckets, polygon_buckets)
    num = min(1 << (len(same) - 1).bit_length(), max(batch_size, len(same)))
    if num > len(same):   # agentless copies of the first scene (its map is encoded once)
      copies = [0] * (num - len(same))
      pad = batch.replace(agent_valid=np.zeros_like(batch.agent_valid))
      batch = datatypes.Scene(**{f: np.concatenate([getattr(batch, f), getattr(pad, f)[copies]])
                                 for f in datatypes.SCENE_FIELDS})
    yield np.asarray(same, np.int64), batch


def crop_to_bucket(batch: datatypes.Scene, agent_buckets: Sequence[int], polygon_buckets: Sequence[int]) -> datatypes.Scene:
  """Trims agent and polygon padding to the smallest bucket that holds every valid entry.

  Valid agents and polygons are packed first (the scene contract), so cropping drops only padding.
  Buckets above the arrays' cap are clipped to the cap.
  """
  return _crop(batch, (datatypes.bucket_size(int(batch.agent_valid.sum(-1).max()), agent_buckets),
                       datatypes.bucket_size(int(batch.pl_valid.sum(-1).max()), polygon_buckets)))


def _crop(batch: datatypes.Scene, shape: tuple[int, int]) -> datatypes.Scene:
  """`batch` cropped to `shape` = (agents, polygons), each at most its cap."""
  return batch.crop(min(shape[0], batch.num_agents), min(shape[1], batch.num_polygons))
