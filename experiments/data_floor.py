"""How close a perfect generator can come: Table I's histograms of other draws of the data, scored
against the validation split's ground truth.

  python experiments/data_floor.py HL_WORKDIR [--blocks=9]

A generator that samples the data's own distribution still differs from the validation split's 60
scenes by sampling noise: its agents are other draws. This scores, for each of `--blocks` disjoint
blocks of the training split, as many scenes as the validation split holds, its ground truth's
official JSDs (speed, lateral deviation, local density, nearest distance; initial / goal) against the
validation ground truth's, and its goal reachability (`metrics.goal_reachability`): the values a
model whose samples were those scenes would get in Table I, with other maps. Prints one line per block
and the mean, min and max (docs/learning_the_map.md, "What a perfect generator scores"). An
experiment, not part of the library.
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tdiff_jax import checkpoint, datatypes, metrics  # noqa: E402
from tdiff_jax.data import av2_io, batches, scene_builder  # noqa: E402
from tdiff_jax.evaluate import ENDPOINTS, batch_metrics, training_val_split  # noqa: E402


def score(folders, data) -> tuple[dict, dict]:
  """The ground truth's accumulators per endpoint and its reachability counts over `folders`."""
  acc = dict.fromkeys(ENDPOINTS)
  reach = dict.fromkeys(metrics.REACHABILITY_COUNTS, 0)
  for c in range(0, len(folders), 8):
    chunk = [scene_builder.load_scene(f, data.scene)[0] for f in folders[c:c + 8]]
    for s in chunk:
      for k, v in metrics.goal_reachability(np.asarray(s.agent_state), s).items():
        reach[k] += v
    batch = batches.crop_to_bucket(datatypes.stack_scenes(chunk), data.agent_buckets, data.polygon_buckets)
    batch = jax.tree_util.tree_map(jnp.asarray, batch)
    out = batch_metrics(batch.agent_state, batch.agent_state[..., 3], batch)["gt"]   # Table I's GT row
    for name in ENDPOINTS:
      acc[name] = metrics.add(acc[name], out[name])
  return acc, reach


def main(argv: list[str]) -> None:
  if len(argv) < 2 or argv[1].startswith("--"):
    raise SystemExit(__doc__)
  workdir = Path(argv[1])
  flags = dict(a[2:].split("=", 1) for a in argv[2:] if a.startswith("--"))
  data = checkpoint.load_checkpoint(workdir, task="hl").config.data
  val = training_val_split(workdir)
  train = av2_io.map_folders(val.parent / "train")
  val_folders = av2_io.map_folders(val)
  n = len(val_folders)
  ref, ref_reach = score(val_folders, data)
  print(f"validation: {n} scenes, goal reachable {metrics.reachability_pct(ref_reach):.1f} %")
  rows = []
  for b in range(min(int(flags.get("blocks", 9)), len(train) // n)):
    acc, reach = score(train[b * n:(b + 1) * n], data)
    row = {f"{h}/{e}": metrics.js_distance(acc[e][f"official/hist_{h}"], ref[e][f"official/hist_{h}"])
           for h in metrics.HISTOGRAMS for e in ENDPOINTS}
    row["reachable"] = metrics.reachability_pct(reach)
    rows.append(row)
    print(f"train block {b}: " + ", ".join(f"{k} {v:.3f}" for k, v in row.items()), flush=True)
  for stat in (np.mean, np.min, np.max):
    print(f"{stat.__name__}: " + ", ".join(f"{k} {stat([r[k] for r in rows]):.3f}" for k in rows[0]))


if __name__ == "__main__":
  main(sys.argv)
