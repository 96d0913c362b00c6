"""Training curves of a workdir: `python -m tdiff_jax.plot_metrics WORKDIR [--out=PATH]`.

Reads `<WORKDIR>/metrics.jsonl` (written by `train.py`) and draws the train and validation losses
(parameters and EMA), the gradient norm, the learning rate and the steps/s against the step to
`<WORKDIR>/curves.png` (`viz.training_curves`).
"""

from __future__ import annotations

import json
from pathlib import Path

from absl import app, flags

from tdiff_jax import files



def read_metrics(workdir: Path) -> list[dict]:
  """The rows of `metrics.jsonl`; a line cut by a kill mid-write is left out."""
  path = workdir / "metrics.jsonl"
  if not path.exists():
    raise FileNotFoundError(f"{path}: no metrics; is {workdir} a training workdir?")
  rows = []
  for line in path.read_text().splitlines():
    try:
      rows.append(json.loads(line))
    except json.JSONDecodeError:
      continue
  rows = [r for r in rows if isinstance(r, dict) and "step" in r]
  if not rows:
    raise ValueError(f"{path}: no logged step yet")
  return rows


def plot_workdir(workdir: Path | str, out: Path | str | None = None) -> Path:
  from tdiff_jax import viz

  workdir = Path(workdir)
  rows = read_metrics(workdir)
  out = Path(out) if out else workdir / "curves.png"
  return viz.training_curves(rows, out, f"{workdir} (up to step {max(r['step'] for r in rows)})")


def main(argv: list[str]) -> None:
  if len(argv) != 2:
    raise app.UsageError("usage: python -m tdiff_jax.plot_metrics WORKDIR [--out=PATH]")
  try:
    out = flags.FLAGS.out
    print(plot_workdir(files.user_path(argv[1]), files.user_path(out) if out else None))
  except (OSError, ValueError) as e:
    raise SystemExit(f"plot_metrics: {e}") from None


def _define_flags() -> None:  # here, not at import: tests import this module
  flags.DEFINE_string("out", None, "picture path (default <WORKDIR>/curves.png)")


if __name__ == "__main__":
  _define_flags()
  app.run(main)
