"""Exports the default recipe's trained models as the package's pretrained default.

  python results/make_pretrained.py --hl_workdir=workdirs/hl --infill_workdir=workdirs/infill \
      --table1=results/table1_synthetic_val.json --table2=workdirs/infill/eval/table.json \
      --trained_with=COMMIT --machine="..."

Writes `tdiff_jax/pretrained/{hl,infill}/` (`checkpoint.export_model`: the EMA parameters, the record
and the config) and `tdiff_jax/pretrained/pretrained.json`: how the models were made (the commands,
steps, wall times from results/timings.json, the code's commit, the machine) and their Table I
(official convention, of `--table1`, an `evaluate` run recorded by results/render.py) and Table II (of
`--table2`, an `evaluate` table.json of the infiller).
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import jax  # noqa: E402

from tdiff_jax import checkpoint  # noqa: E402


def main() -> None:
  p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  p.add_argument("--hl_workdir", type=Path, required=True)
  p.add_argument("--infill_workdir", type=Path, required=True)
  p.add_argument("--table1", type=Path, required=True, help="results/table1_<name>.json of the HL model")
  p.add_argument("--table2", type=Path, required=True, help="an evaluate table.json with the infiller's Table II")
  p.add_argument("--trained_with", required=True, help="the commit of the code that trained both models")
  p.add_argument("--machine", required=True, help="where they were trained")
  a = p.parse_args()

  timings = {r["command"]: r for r in json.loads((ROOT / "results" / "timings.json").read_text())["runs"]}
  made = {}
  for task, workdir, command in (("hl", a.hl_workdir, "python train.py --config=configs/hl.py"),
                                 ("infill", a.infill_workdir, "python train.py --config=configs/infill.py")):
    out = checkpoint.export_model(workdir, checkpoint.pretrained_dir(task))
    loaded = checkpoint.load_checkpoint(out, task=task)
    made[task] = {"command": command, "step": loaded.record["step"],
                  "parameters": sum(x.size for x in jax.tree_util.tree_leaves(loaded.params)),
                  "bytes": sum(f.stat().st_size for f in out.iterdir()),
                  "train_wall_s": timings.get(command, {}).get("wall_s")}
  table1 = json.loads(a.table1.read_text())
  table2 = json.loads(a.table2.read_text())
  info = {"date": datetime.date.today().isoformat(), "trained_with_commit": a.trained_with, "machine": a.machine,
          "data": "the embedded default: 600 seeded synthetic AV2 worlds (540 train, 60 validation)",
          "models": made,
          "table_i": {k: table1[k] for k in ("command", "scenes", "agents", "sampler", "table_i")},
          "table_ii": {"command": "python -m tdiff_jax.evaluate --hl_workdir= --infill_workdir=workdirs/infill",
                       "scenes": table2["scenes"], "agents": table2["agents"], "modes": table2["table_ii"]}}
  path = checkpoint.PRETRAINED / "pretrained.json"
  path.write_text(json.dumps(info, indent=1) + "\n")
  print(json.dumps(made))


if __name__ == "__main__":
  main()
