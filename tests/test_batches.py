"""Batches: fixed size, deterministic shuffle from (seed, epoch), exact resume, size buckets."""

from __future__ import annotations

import ml_collections
import numpy as np
import pytest

from configs import hl as hl_config
from tdiff_jax import datatypes
from tdiff_jax.data import batches


@pytest.fixture(scope="module")
def train(mixed_cache):
  return batches.load_split(mixed_cache[0], "train")


def _ids(it, n):
  return [tuple(it.next_indices()) for _ in range(n)]


def test_batches_are_scenes_of_fixed_size(train):
  it = batches.BatchIterator(train, batch_size=4, seed=0)
  for _ in range(5):
    b = next(it)
    assert isinstance(b, datatypes.Scene) and b.batch_shape == (4,)
    b.validate()


def test_same_seed_same_batches_and_each_scene_once_per_epoch(train):
  a = _ids(batches.BatchIterator(train, 2, seed=3), 9)
  b = _ids(batches.BatchIterator(train, 2, seed=3), 9)
  c = _ids(batches.BatchIterator(train, 2, seed=4), 9)
  assert a == b and a != c
  per_epoch = len(train) // 2
  for e in range(3):
    epoch = [i for batch in a[e * per_epoch:(e + 1) * per_epoch] for i in batch]
    assert sorted(epoch) == list(range(len(train)))
  assert a[:per_epoch] != a[per_epoch:2 * per_epoch]  # a new order each epoch


def test_resume_continues_exactly(train):
  it = batches.BatchIterator(train, 4, seed=1)
  _ids(it, 5)
  state = dict(it.get_state())
  rest = _ids(it, 4)
  resumed = batches.BatchIterator(train, 4, seed=1)
  resumed.set_state(state)
  assert _ids(resumed, 4) == rest
  with pytest.raises(ValueError, match="seed"):
    batches.BatchIterator(train, 4, seed=2).set_state(state)


def test_remainder_and_bad_sizes(train):
  n = len(train)
  it = batches.BatchIterator(train, 4, shuffle=False, drop_remainder=False)
  sizes = [len(it.next_indices()) for _ in range(it.batches_per_epoch)]
  assert sum(sizes) == n and sizes[-1] == n - 4 * (len(sizes) - 1)
  with pytest.raises(ValueError, match="exceeds"):
    batches.BatchIterator(train, n + 1)
  with pytest.raises(ValueError, match="batch_size"):
    batches.BatchIterator(train, 0)


def test_crop_to_bucket_drops_only_padding(train):
  batch = train.take(np.arange(4))
  cropped = batches.crop_to_bucket(batch, agent_buckets=(16, 32, 64), polygon_buckets=(64, 128, 256))
  cropped.validate()
  n_agents, n_polys = int(batch.agent_valid.sum(-1).max()), int(batch.pl_valid.sum(-1).max())
  assert cropped.num_agents == datatypes.bucket_size(n_agents, (16, 32, 64)) >= n_agents
  assert cropped.num_polygons == datatypes.bucket_size(n_polys, (64, 128, 256)) >= n_polys
  assert cropped.agent_valid.sum() == batch.agent_valid.sum()
  assert cropped.pl_valid.sum() == batch.pl_valid.sum()
  assert (cropped.pl_edge != 0).sum() == (batch.pl_edge != 0).sum()
  np.testing.assert_array_equal(cropped.agent_state, batch.agent_state[:, :cropped.num_agents])
  assert datatypes.bucket_size(500, (16, 32)) == 32


def test_sampler_agent_buckets_from_the_config_or_for_an_older_checkpoint():
  config = hl_config.get_config("default")
  assert batches.sampler_agent_buckets(config.data) == batches.SAMPLER_AGENT_BUCKETS
  assert batches.sampler_agent_buckets(hl_config.get_config("tiny").data) == (32,)
  # A checkpoint's config is its JSON record: tuples come back as lists, and one saved before the option
  # existed has none (the sampler then groups by the finer default: only the padding differs).
  saved = ml_collections.ConfigDict({"agent_buckets": [8, 16, 32, 64], "sampler_agent_buckets": [16, 64]})
  assert batches.sampler_agent_buckets(saved) == (16, 64)
  older = ml_collections.ConfigDict({"agent_buckets": [8, 16, 32, 64]})
  assert batches.sampler_agent_buckets(older) == batches.SAMPLER_AGENT_BUCKETS
  # Each group of a batch sits at the smallest sampler bucket that holds it: a 33-agent scene at 40, not 64.
  assert datatypes.bucket_size(33, batches.sampler_agent_buckets(config.data)) == 40


def test_sampler_batches_hold_one_size_each_scene_once_padded_to_a_power_of_two(train):
  """Every scene comes once, in a batch of scenes of one agent bucket cropped to it and to its largest
  map's polygon bucket, at most `batch_size` scenes, padded with agentless copies of its first to 1, 2, 4
  or 8 scenes."""
  scenes = [train.take([i]) for i in range(len(train))]
  scenes = [datatypes.Scene(**{f: getattr(s, f)[0] for f in datatypes.SCENE_FIELDS}) for s in scenes]
  a_buckets, p_buckets = (4, 8, 16, 32), (64, 128, 256)
  seen = []
  for positions, batch in batches.sampler_batches(scenes, 8, a_buckets, p_buckets):
    n, b = len(positions), batch.agent_valid.shape[0]
    assert 1 <= n <= 8 and b in (1, 2, 4, 8) and n <= b < 2 * n
    agents = {datatypes.bucket_size(int(scenes[p].agent_valid.sum()), a_buckets) for p in positions}
    polygons = datatypes.bucket_size(max(int(scenes[p].pl_valid.sum()) for p in positions), p_buckets)
    assert agents == {batch.num_agents} and polygons == batch.num_polygons
    for j, p in enumerate(positions):
      np.testing.assert_array_equal(batch.agent_state[j], scenes[p].agent_state[:batch.num_agents])
    assert not batch.agent_valid[n:].any()
    np.testing.assert_array_equal(batch.pl_valid[n:], np.broadcast_to(batch.pl_valid[0], batch.pl_valid[n:].shape))
    seen += positions.tolist()
  assert sorted(seen) == list(range(len(scenes)))
  with pytest.raises(ValueError, match="batch_size"):
    next(batches.sampler_batches(scenes, 0, a_buckets, p_buckets))


def test_grouping_by_size_keeps_the_epoch_and_tightens_batches(train):
  sizes = train.scenes.pl_valid.sum(-1)
  plain = batches.BatchIterator(train, 2, seed=5)
  grouped = batches.BatchIterator(train, 2, seed=5, group_by_size=True)
  a, b = _ids(grouped, 9), _ids(batches.BatchIterator(train, 2, seed=5, group_by_size=True), 9)
  assert a == b                                                  # deterministic from (seed, epoch)
  per_epoch = len(train) // 2
  assert sorted(i for batch in a[:per_epoch] for i in batch) == list(range(len(train)))
  spread = lambda its: np.mean([np.ptp(sizes[list(i)]) for i in its])  # noqa: E731
  assert spread(a[:per_epoch]) < spread(_ids(plain, per_epoch))
  state = grouped.get_state()
  rest = _ids(grouped, 3)
  again = batches.BatchIterator(train, 2, seed=5, group_by_size=True)
  again.set_state(state)
  assert _ids(again, 3) == rest


def test_rare_buckets_are_merged_into_the_smallest_frequent_one_that_holds_them():
  counts = {(32, 64): 500, (32, 96): 400, (16, 64): 300, (16, 96): 20, (8, 64): 1, (64, 64): 3, (16, 256): 2}
  merged = batches.merge_rare_buckets(counts, min_batches=50)
  # (16, 96) fits (32, 96) only; (8, 64) fits three, the smallest is (16, 64); nothing frequent holds
  # 64 agents or 256 polygons, so those stay.
  assert merged == {(16, 96): (32, 96), (8, 64): (16, 64)}
  assert batches.merge_rare_buckets(counts, min_batches=1) == {}


def test_iterator_pads_rare_buckets_to_frequent_ones_and_loses_nothing(train):
  # One scene a batch, two epochs: the fixture's 6 scenes fall in 4 buckets, one of them met twice.
  kw = dict(seed=2, buckets=((8, 16, 32), (32, 64, 96)))
  plain, merging = batches.BatchIterator(train, 1, **kw), batches.BatchIterator(
      train, 1, min_bucket_batches=3, planned_batches=12, **kw)
  shapes = lambda b: (b.num_agents, b.num_polygons)  # noqa: E731
  a, b = [next(plain) for _ in range(12)], [next(merging) for _ in range(12)]
  counts = {}
  for x in a:
    counts[shapes(x)] = counts.get(shapes(x), 0) + 1
  assert merging.merged == batches.merge_rare_buckets(counts, 3) and merging.merged  # the fixture meets a rare one
  for x, y in zip(a, b):
    assert shapes(y) == merging.merged.get(shapes(x), shapes(x))
    assert y.agent_valid.sum() == x.agent_valid.sum() and y.pl_valid.sum() == x.pl_valid.sum()
    np.testing.assert_array_equal(y.agent_state[:, :x.num_agents], x.agent_state)
  assert len({shapes(y) for y in b}) < len({shapes(x) for x in a})


def test_process_shares_assemble_the_global_batch(train):
  buckets = ((8, 16, 32, 64), (64, 128, 256))
  whole = batches.BatchIterator(train, 4, seed=2, buckets=buckets)
  shares = [batches.BatchIterator(train, 4, seed=2, buckets=buckets, process_index=i, process_count=2)
            for i in range(2)]
  for _ in range(3):
    batch, first, second = next(whole), next(shares[0]), next(shares[1])
    assert first.batch_shape == second.batch_shape == (2,)
    # Cropped to the global batch's bucket, so the shares have one shape.
    assert (first.num_agents, first.num_polygons) == (second.num_agents, second.num_polygons) \
        == (batch.num_agents, batch.num_polygons)
    for name in datatypes.SCENE_FIELDS:
      np.testing.assert_array_equal(np.concatenate([getattr(first, name), getattr(second, name)]),
                                    getattr(batch, name))
  with pytest.raises(ValueError, match="evenly over 2 processes"):
    batches.BatchIterator(train, 3, process_count=2)
