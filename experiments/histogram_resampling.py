"""How much of a Table I JSD is the sampling draw: histograms redrawn from an evaluation's own, rescored.

  python experiments/histogram_resampling.py TABLE_JSON [--draws=2000] [--seed=0] [--name=speed]

Reads the official histograms of one `python -m tdiff_jax.evaluate` run (`table.json`:
`histograms/official/<initial|goal>/<GT|model>/<name>`) and, per endpoint, redraws `--draws` times as
many values as the model's histogram holds (multinomial) from
* the ground truth's histogram: the JS distance of such a draw to the ground truth is what a model with
  exactly the data's distribution would score on this many agents if the ground truth were that
  distribution (a lower bound of the metric's noise; `experiments/data_floor.py` scores other scenes of
  the data instead);
* the model's histogram: the spread of the model's figure over new samples of the same distribution,
  i.e. how far another sampling seed may move it (the mean of these lies above the run's own figure:
  a redraw adds a second draw's noise to the first's; read their spread, not their mean).
Prints, per endpoint, the run's own JS distance and the mean, standard deviation and 5th / 95th
percentiles of both, and the bins where the model's histogram differs most from the ground truth's
(docs/learning_the_map.md, "The speed histogram's sampling spread"). An experiment, not part of the library.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tdiff_jax import metrics  # noqa: E402
from tdiff_jax.evaluate import ENDPOINTS  # noqa: E402


def redrawn(reference: np.ndarray, source: np.ndarray, count: int, draws: int, rng) -> np.ndarray:
  """JS distances to `reference` of `draws` histograms of `count` values drawn from `source`'s bins."""
  p = source / source.sum()
  return np.array([metrics.js_distance(rng.multinomial(count, p).astype(np.float64), reference)
                   for _ in range(draws)])


def main(argv: list[str]) -> None:
  if len(argv) < 2 or argv[1].startswith("--"):
    raise SystemExit(__doc__)
  flags = dict(a[2:].split("=", 1) for a in argv[2:] if a.startswith("--"))
  draws, name = int(flags.get("draws", 2000)), flags.get("name", "speed")
  if name not in metrics.HISTOGRAMS:
    raise SystemExit(f"--name={name!r}: one of {', '.join(metrics.HISTOGRAMS)}")
  table = json.loads(Path(argv[1]).read_text())
  rng = np.random.default_rng(int(flags.get("seed", 0)))
  bins, top = metrics.HISTOGRAMS[name]
  for endpoint in ENDPOINTS:
    hist = table["histograms"]["official"][endpoint]
    gt, model = (np.asarray(hist[who][name], np.float64) for who in ("GT", "model"))
    count = int(model.sum())
    own = metrics.js_distance(model, gt)
    line = [f"{endpoint}: {count} values, JS distance {own:.3f}"]
    for label, source in (("from the ground truth", gt), ("from the model", model)):
      d = redrawn(gt, source, count, draws, rng)
      line.append(f"{label} {d.mean():.3f} +- {d.std():.3f} (5-95 %: {np.percentile(d, 5):.3f} to "
                  f"{np.percentile(d, 95):.3f})")
    print("; ".join(line))
    width = top / bins
    diff = model / model.sum() - gt / gt.sum()
    worst = np.argsort(-np.abs(diff))[:6]
    print("  largest differences (bin: model / ground truth values): " + ", ".join(
        f"[{i * width:g}, {(i + 1) * width:g}): {int(model[i])} / {int(gt[i])}" for i in sorted(worst)))


if __name__ == "__main__":
  main(sys.argv)
