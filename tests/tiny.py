"""The tiny HL config the training tests share (its cache: the `tiny_cache` fixture in conftest.py)."""

from __future__ import annotations

from pathlib import Path

from configs import hl as hl_config
from tdiff_jax.data import preprocess, synthetic


def build_tiny_cache(root: Path) -> Path:
  """The tiny config's synthetic worlds, preprocessed into `root / "cache"`."""
  config = hl_config.get_config("tiny")
  synthetic.generate_dataset(root / "synthetic", config.data.synthetic_num, seed=0, workers=1, progress=False)
  preprocess.preprocess(root / "synthetic", root / "cache", config.data.scene, workers=1, progress=False)
  return root / "cache"


def tiny_config(cache: Path, **train):
  config = hl_config.get_config("tiny")
  config.data.cache_dir = str(cache)
  config.train.update(train)
  return config
