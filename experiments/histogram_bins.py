"""Where a Table I JS distance comes from: the histogram bins of one feature, ground truth against model.

  python experiments/histogram_bins.py EVAL_DIR/table.json [--feature=speed] [--convention=official] [--bins=16]
      [--edges=1,5]

Reads the histograms `python -m tdiff_jax.evaluate` stores in its table.json and prints, per state
(initial, goal) and for the first `--bins` bins, the bin's range, the share of ground-truth and model
states in it, and the bin's share of the JS divergence (`metrics.js_divergence_terms`; the distance
in Table I is the square root of their sum), then the same summed over the ranges that `--edges` cut (for speed in m/s, 1,5: stopped,
slow, moving). For the speed histogram this says whether the gap is in stopped agents, in slow ones or in
the moving ones' mode (docs/learning_the_map.md, "Where the speed gap lies"). An experiment, not part
of the library.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
from absl import app, flags

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tdiff_jax import metrics  # noqa: E402

FLAGS = flags.FLAGS
flags.DEFINE_string("feature", "speed", "speed, lateral_deviation, local_density or nearest_distance")
flags.DEFINE_enum("convention", "official", ["official", "strict"], "the table's convention")
flags.DEFINE_integer("bins", 16, "print the first this many bins (all are summed)")
flags.DEFINE_list("edges", ["1", "5"], "also print the shares summed between these edges (feature units)")


def main(argv: list[str]) -> None:
  if len(argv) != 2:
    raise app.UsageError("usage: histogram_bins.py EVAL_DIR/table.json [--feature=speed]")
  path = Path(argv[1])
  table = json.loads(path.read_text())
  if "histograms" not in table:
    sys.exit(f"{path}: no histograms (not a table.json of `python -m tdiff_jax.evaluate`)")
  spec = table["histogram_bins"].get(FLAGS.feature)
  if spec is None:
    sys.exit(f"{path}: no {FLAGS.feature!r} histogram; it has {', '.join(table['histogram_bins'])}")
  width = spec["upper_edge"] / spec["bins"]
  for state, rows in table["histograms"][FLAGS.convention].items():
    gt = np.asarray(rows["GT"][FLAGS.feature], np.float64)
    model = np.asarray(rows["model"][FLAGS.feature], np.float64)
    if gt.sum() <= 0 or model.sum() <= 0:
      print(f"{state}: an empty histogram")
      continue
    p, q = gt / gt.sum(), model / model.sum()
    term = metrics.js_divergence_terms(gt, model)
    div = float(term.sum())
    print(f"{state}: JS distance {math.sqrt(div):.3f} ({FLAGS.convention}, {FLAGS.feature}, bins of {width:g})")
    print("  bin              GT     model  share of the divergence")
    for i in range(min(FLAGS.bins, len(p))):
      print(f"  {i * width:6.1f} to {(i + 1) * width:<6.1f} {p[i]:6.3f} {q[i]:6.3f}  {term[i] / div:5.2f}")
    rest = term[FLAGS.bins:].sum() / div
    print(f"  the other {max(len(p) - FLAGS.bins, 0)} bins: {p[FLAGS.bins:].sum():.3f} {q[FLAGS.bins:].sum():.3f}  {rest:5.2f}")
    cuts = [0] + [int(round(float(e) / width)) for e in FLAGS.edges] + [len(p)]
    for lo, hi in zip(cuts[:-1], cuts[1:]):
      print(f"  range {lo * width:g} to {hi * width:g}: {p[lo:hi].sum():6.3f} {q[lo:hi].sum():6.3f}  {term[lo:hi].sum() / div:5.2f}")


if __name__ == "__main__":
  app.run(main)
