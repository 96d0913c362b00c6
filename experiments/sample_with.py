"""Table I of an HL checkpoint sampled with parameter-free model fields set (no retraining).

  python experiments/sample_with.py FIELD=VALUE [FIELD=VALUE ...] [evaluate flags...]

FIELD is one of `checkpoint.PARAMETER_FREE_FIELDS` (HL model fields that add no weights, so any
checkpoint of a model they apply to takes them), e.g.

  python experiments/sample_with.py position_skip_m=2 --hl_workdir=workdirs/hl --infill_workdir= --noreport

then `python -m tdiff_jax.evaluate`'s tables with those flags (docs/learning_the_map.md). The lane pull's
fields are also `evaluate`'s and `sample.py`'s flags (`--lane_pull_m`, `--lane_pull_noise_m`). An
experiment, not part of the library: it swaps `checkpoint.load_checkpoint` for one that sets the fields
while `evaluate` runs.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tdiff_jax import checkpoint, evaluate  # noqa: E402


def main(argv: list[str]) -> None:
  fields = dict(a.split("=", 1) for a in argv if not a.startswith("-") and "=" in a)
  if not fields or set(fields) - set(checkpoint.PARAMETER_FREE_FIELDS):
    raise SystemExit(__doc__)
  rest = [a for a in argv if a.startswith("-") or "=" not in a]
  load = checkpoint.load_checkpoint

  def load_with_fields(*args, **kwargs):
    loaded = load(*args, **kwargs)
    return checkpoint.with_model_fields(loaded, fields) if loaded.task == "hl" else loaded

  checkpoint.load_checkpoint = load_with_fields
  evaluate.main(rest)


if __name__ == "__main__":
  main(sys.argv[1:])
