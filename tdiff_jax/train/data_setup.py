"""Where training data comes from: a cache, a folder of AV2 scenarios, or synthetic worlds.

* `data.cache_dir` holds a built cache: it is used as is (after checking its data config).
* `data.dir` is an AV2 root (split folders of scenario folders): it is preprocessed into
  `data.cache_dir` (default `<workdir>/cache`) once; reruns resume or reuse it.
* Neither: the embedded default. `data.synthetic_num` synthetic AV2 scenarios (a tenth of them in val/) are
  generated into `<workdir>/synthetic` (once) and preprocessed.
"""

from __future__ import annotations

from pathlib import Path

import ml_collections
from absl import logging

from tdiff_jax import files
from tdiff_jax.data import batches, preprocess, synthetic


def cache_path(c: ml_collections.ConfigDict, workdir: Path | str) -> Path:
  """Where the cache of the `data` config block `c` is (built or not)."""
  return files.user_path(c.cache_dir) if c.cache_dir else Path(workdir) / "cache"


def check_source(c: ml_collections.ConfigDict, workdir: Path | str) -> None:
  """Raises (FileNotFoundError, ValueError) when the `data` block names data that is missing or a built
  cache of another data config: the checks of `prepare_cache` that can refuse, before it writes anything."""
  if c.dir and not files.user_path(c.dir).is_dir():
    raise FileNotFoundError(f"data.dir={files.user_path(c.dir)}: no such directory")
  cache = cache_path(c, workdir)
  if c.cache_dir and not c.dir and (cache / preprocess.MANIFEST).exists():
    batches.check_manifest(batches.read_manifest(cache), c.scene, str(cache))


def prepare_cache(c: ml_collections.ConfigDict, workdir: Path | str) -> Path:
  """Returns a cache directory that matches `c.scene` (the `data` config block)."""
  workdir = Path(workdir)
  check_source(c, workdir)
  cache = cache_path(c, workdir)
  if c.dir:
    source = files.user_path(c.dir)
  elif c.cache_dir and (cache / preprocess.MANIFEST).exists():
    source = None
  else:
    source = workdir / "synthetic"
    logging.info("No data.dir given: generating %d synthetic AV2 scenarios into %s", c.synthetic_num, source)
    synthetic.generate_dataset(source, c.synthetic_num, seed=0)  # a tenth in val/
  if source is not None:
    logging.info("Preprocessing %s into %s", source, cache)
    preprocess.preprocess(source, cache, c.scene)
  batches.check_manifest(batches.read_manifest(cache), c.scene, str(cache))
  return cache
