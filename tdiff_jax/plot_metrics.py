"""Training curves of a workdir: `python -m tdiff_jax.plot_metrics WORKDIR [--out=PATH]`.

Reads `<WORKDIR>/metrics.jsonl` (written by `train.py`) and draws the train and validation losses
(parameters and EMA), the gradient norm, the learning rate and the steps/s against the step to
`<WORKDIR>/curves.png` (`viz.training_curves`).
"""

from __future__ import annotations

import json
from pathlib import Path

from absl import app, flags

from tdiff_jax import cli, files



def read_metrics(workdir: Path) -> list[dict]:
  """The rows of `metrics.jsonl` (a non-finite value, written as null, back as NaN: a gap in the curve); a line
  cut by a kill mid-write is left out."""
  path = workdir / "metrics.jsonl"
  if not path.exists():
    raise FileNotFoundError(f"{path}: no metrics; is {workdir} a training workdir?")
  rows = []
  for line in path.read_text().splitlines():
    try:
      row = json.loads(line)
      rows.append({k: float("nan") if v is None else v for k, v in row.items()} if isinstance(row, dict) else row)
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


def define_flags(values: flags.FlagValues) -> None:
  flags.DEFINE_string("out", None, "picture path (default <WORKDIR>/curves.png)", flag_values=values)


def run(f: flags.FlagValues, args: list[str]) -> None:
  if len(args) != 1:
    raise app.UsageError("usage: python -m tdiff_jax.plot_metrics WORKDIR [--out=PATH]")
  try:
    print(plot_workdir(files.user_path(args[0]), files.user_path(f.out) if f.out else None))
  except (OSError, ValueError) as e:
    raise SystemExit(f"plot_metrics: {e}") from None


main = cli.entry_point(define_flags, run)


if __name__ == "__main__":
  main()
