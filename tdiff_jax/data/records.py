"""Scenes as ArrayRecord files: one record per scene, read by index without loading the file.

The preprocessing cache stores each shard as an ArrayRecord file (the random-access record format
Grain reads); a record is one scene's arrays (`datatypes.Scene` fields and its scenario id): a small JSON
header naming each array's dtype and shape, then the arrays' bytes, zlib-compressed as one block
(about 23 kB a scene with the default caps, against 306 kB in memory; decoding takes about 0.5 ms).

`SceneRecords` is a split's records as a random-access source: `len`, `source[i]` (one scene's
arrays), and what the batching needs without reading a record (per-scene polygon and agent counts,
scenario ids), taken from the shards' metadata. It pickles, so Grain's worker processes can open it.
"""

from __future__ import annotations

import json
import zlib
from pathlib import Path
from typing import Sequence

import numpy as np

from tdiff_jax import files

SUFFIX = ".array_record"
_HEADER_BYTES = 4


def encode(arrays: dict[str, np.ndarray]) -> bytes:
  """One scene's arrays (unbatched) -> one record."""
  names = sorted(arrays)
  values = [np.asarray(arrays[k]) for k in names]
  header = json.dumps([[k, v.dtype.str, list(v.shape)] for k, v in zip(names, values)]).encode()
  body = b"".join(v.tobytes(order="C") for v in values)
  return len(header).to_bytes(_HEADER_BYTES, "little") + header + zlib.compress(body, 1)


def decode(record: bytes) -> dict[str, np.ndarray]:
  """A record -> the scene's arrays (read-only views of one decompressed buffer)."""
  n = int.from_bytes(record[:_HEADER_BYTES], "little")
  spec = json.loads(record[_HEADER_BYTES:_HEADER_BYTES + n])
  body = zlib.decompress(record[_HEADER_BYTES + n:])
  out, offset = {}, 0
  for name, dtype, shape in spec:
    dtype = np.dtype(dtype)
    count = int(np.prod(shape, dtype=np.int64))
    out[name] = np.frombuffer(body, dtype, count=count, offset=offset).reshape(shape)
    offset += count * dtype.itemsize
  return out


def write(path: Path | str, records: Sequence[bytes]) -> None:
  """Writes `records` as one ArrayRecord file, atomically (a temporary name, then a rename)."""
  from array_record.python import array_record_module

  path = Path(path)
  try:
    with files.atomic_path(path) as tmp:
      # group_size 1: every record can be read alone (random access, Grain's recommendation).
      writer = array_record_module.ArrayRecordWriter(str(tmp), "group_size:1")
      for r in records:
        writer.write(r)
      writer.close()
  except RuntimeError as e:  # array_record reports I/O failures (a full disk) as RuntimeError
    raise OSError(f"cannot write {path}: {e}") from e


def count(path: Path | str) -> int | None:
  """How many records `path` holds; None if it is missing or unreadable."""
  from array_record.python import array_record_module

  try:
    reader = array_record_module.ArrayRecordReader(str(path))
    n = reader.num_records()
    reader.close()
    return int(n)
  except Exception:  # a missing, cut or foreign file
    return None


class SceneRecords:
  """A split's scenes as a random-access source (`grain.sources.RandomAccessDataSource`).

  `source[i]` decodes scene i (unbatched arrays, scenario id included); `num_agents`, `num_polygons`
  `[N]` and `scenario_ids` `[N]` come from the shards' metadata, so they cost no reads.
  """

  def __init__(self, paths: Sequence[Path | str], num_agents: np.ndarray, num_polygons: np.ndarray,
               scenario_ids: np.ndarray, split: str, manifest: dict, shard_sizes: Sequence[int] | None = None,
               rebuild_hint: str = "rebuild the cache"):
    self.paths = [str(p) for p in paths]
    self.num_agents = np.asarray(num_agents, np.int64)
    self.num_polygons = np.asarray(num_polygons, np.int64)
    self.scenario_ids = np.asarray(scenario_ids)
    self.split, self.manifest = split, manifest
    # First scene index of each shard, to name the file of a record that does not read.
    self.shard_starts = np.cumsum([0, *(shard_sizes if shard_sizes is not None else [len(self.scenario_ids)])])
    self.rebuild_hint = rebuild_hint
    self._source = None

  @property
  def _records(self):
    if self._source is None:  # opened lazily: in each worker process after unpickling
      import grain

      try:
        self._source = grain.sources.ArrayRecordDataSource(self.paths) if self.paths else []
      except Exception as e:  # a file damaged since the split was opened and checked
        bad = [p for p in self.paths if count(p) is None] or self.paths
        raise ValueError(f"{bad[0]}: does not read ({type(e).__name__}: {e}); {self.rebuild_hint}") from e
    return self._source

  def __len__(self) -> int:
    return len(self.scenario_ids)

  def __getitem__(self, index: int) -> dict[str, np.ndarray]:
    source = self._records
    try:
      return decode(source[int(index)])
    except Exception as e:  # array_record and zlib raise their own kinds for a damaged file
      shard = int(np.searchsorted(self.shard_starts, int(index), side="right")) - 1
      where = self.paths[min(shard, len(self.paths) - 1)] if self.paths else "<no shard>"
      raise ValueError(f"{where}: scene {int(index) - self.shard_starts[shard]} of this shard does not read "
                       f"({type(e).__name__}: {e}); {self.rebuild_hint}") from e

  def __getstate__(self):
    return {k: v for k, v in self.__dict__.items() if k != "_source"} | {"_source": None}

  def __repr__(self) -> str:
    return f"SceneRecords({self.split!r}, {len(self)} scenes, {len(self.paths)} files)"
