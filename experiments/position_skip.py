"""Table I of an HL checkpoint sampled with `model.position_skip_m` set (no retraining).

  python experiments/position_skip.py S [evaluate flags...]

e.g. `python experiments/position_skip.py 2 --hl_workdir=workdirs/hl --infill_workdir= --noreport`: the
checkpoint's denoiser with x_t's positions weighed into its x0 estimate by precision, the network's own
error taken as S metres (`HLModelConfig.position_skip_m`; parameter-free, so any checkpoint takes it), then
`python -m tdiff_jax.evaluate`'s tables (docs/learning_the_map.md). An experiment, not part of the library:
it swaps `checkpoint.load_checkpoint` for one that sets the field while `evaluate` runs.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from flax import nnx

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tdiff_jax import checkpoint, evaluate, models  # noqa: E402


def main(argv: list[str]) -> None:
  if not argv:
    raise SystemExit(__doc__)
  skip_m = float(argv[0])
  load = checkpoint.load_checkpoint

  def load_with_skip(*args, **kwargs):
    loaded = load(*args, **kwargs)
    if loaded.config.get("task", "hl") != "hl":
      return loaded
    config = loaded.config.copy_and_resolve_references()
    config.model.position_skip_m = skip_m
    graphdef, _ = models.split_model(nnx.eval_shape(lambda: models.create_model(config)))
    return dataclasses.replace(loaded, graphdef=graphdef, config=config)

  checkpoint.load_checkpoint = load_with_skip
  evaluate.main(argv[1:])


if __name__ == "__main__":
  main(sys.argv[1:])
