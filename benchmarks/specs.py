"""Scenario specs measured: per spec of the library, how many samples satisfy it, what a satisfying sample
costs against a plain sample and against rejection sampling of the unguided model, and how its complete
scenarios collide and leave the road (read back from the AV2 folders written).

  python benchmarks/specs.py --maps=workdirs/hl/synthetic/val --max_maps=20 --name=synthetic_val
  python benchmarks/specs.py --maps=../shared/av2_real --name=av2_real

Writes results/specs_<name>.json (`results/render.py` renders it into docs/specs.md). Per spec: `sample.py
--spec` (`generate.generate(spec=...)`, default sampler and repair) on every map where the spec can hold,
one sample per map; a plain `sample.py` run on the same maps; and the Scenic way, the unguided sampler
(`sampling.UNGUIDED`, HL states only: a lower bound of its cost) drawing `--rejection_draws` scenes per map
with the spec's agents, a draw accepted when it satisfies the spec. Each timed run follows a warm-up run
of the same kind (compiling), so the times are of compiled programs. Run it with nothing else on the machine.
"""

from __future__ import annotations

import datetime
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import jax
import numpy as np
from absl import app, flags

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks import common  # noqa: E402
from tdiff_jax import checkpoint, cli, generate, repair, sampling  # noqa: E402
from tdiff_jax import spec as spec_lib  # noqa: E402
from tdiff_jax.data import av2_io, batches, scene_builder  # noqa: E402

FLAGS = flags.FLAGS
flags.DEFINE_string("maps", None, "folder of AV2 scenario folders", required=True)
flags.DEFINE_string("name", None, "name of the map set (results/specs_<name>.json)", required=True)
flags.DEFINE_integer("max_maps", 0, "the first this many maps (0: all)")
flags.DEFINE_list("specs", [str(p.relative_to(ROOT)) for p in sorted((ROOT / "specs").glob("*.yaml"))], "spec files")
flags.DEFINE_integer("rejection_draws", 16, "unguided draws per map for rejection sampling")
flags.DEFINE_string("hl_workdir", "", "HL model (default: the shipped one)")
flags.DEFINE_string("infill_workdir", "", "infiller (default: the shipped one)")
flags.DEFINE_string("out", str(ROOT / "results"), "folder of the JSON")


def _maps(folder: Path, names: list[str], tmp: Path, tag: str) -> Path:
  """A folder of links to the map folders `names` (a subset the commands read as a maps folder)."""
  out = tmp / tag
  out.mkdir()
  for n in names:
    (out / n).symlink_to((folder / n).resolve(), target_is_directory=True)
  return out


def _generate(hl, infill, maps: Path, tmp: Path, spec=None) -> tuple[dict, float]:
  out = tmp / f"out-{time.monotonic_ns()}"
  t0 = time.perf_counter()
  summary = generate.generate(hl, maps, out, num_per_map=1, progress=False, pictures=False, infill_workdir=infill,
                              spec=spec)
  seconds = time.perf_counter() - t0 - summary["complete_scenarios"]["seconds"]   # generating, not the audit
  shutil.rmtree(out)
  return summary, seconds


def _rejection(model, spec, scenes: list, draws: int, seed: int = 0) -> tuple[int, int, float]:
  """(accepted, drawn, seconds): unguided HL draws with the spec's agents, accepted where the spec holds."""
  stats = model.record["agent_stats"]
  rng = np.random.default_rng(seed)
  items = [generate.plan_agents(s, 0, stats, rng, spec=spec) for s in scenes for _ in range(draws)]
  buckets = (batches.sampler_agent_buckets(model.config.data), model.config.data.polygon_buckets)
  accepted, t0 = 0, time.perf_counter()
  for positions, batch in batches.sampler_batches(items, 8, *buckets):
    dev = jax.tree_util.tree_map(jax.numpy.asarray, batch)
    keys = sampling.keys_at(jax.random.key(seed), np.pad(positions, (0, batch.agent_valid.shape[0] - len(positions)),
                                                         mode="edge"))
    out = repair.sample_states(model, dev, keys, sampling.UNGUIDED)
    state, heading = np.asarray(out.state), np.asarray(out.heading)
    for j, p in enumerate(positions):
      accepted += all(spec_lib.check(spec, state[j], heading[j], items[p]).values())
  return accepted, len(items), time.perf_counter() - t0


def main(argv):
  del argv
  cli.use_compilation_cache(True)
  hl = Path(FLAGS.hl_workdir) if FLAGS.hl_workdir else checkpoint.pretrained_dir("hl")
  infill = Path(FLAGS.infill_workdir) if FLAGS.infill_workdir else checkpoint.pretrained_dir("infill")
  model = checkpoint.with_lane_pull(checkpoint.load_checkpoint(hl, task="hl"), None)
  folder = Path(FLAGS.maps)
  names = [f.name for f in av2_io.map_folders(folder)]
  names = names[:FLAGS.max_maps] if FLAGS.max_maps else names
  scenes = {n: scene_builder.load_scene(folder / n, model.config.data.scene)[0] for n in names}
  rows = []
  with tempfile.TemporaryDirectory() as tmp_name:
    tmp = Path(tmp_name)
    all_maps = _maps(folder, names, tmp, "all")
    _generate(hl, infill, all_maps, tmp)   # warm-up: every shape compiled
    plain, plain_s = _generate(hl, infill, all_maps, tmp)
    plain_row = {"samples": plain["samples"], "seconds_per_sample": plain_s / plain["samples"],
                 "complete_scenarios": plain["complete_scenarios"]["generated"]}
    print(json.dumps({"plain": plain_row}), flush=True)
    for i, path in enumerate(FLAGS.specs):
      spec = spec_lib.load(ROOT / path, model.config.data.scene.max_agents)
      feasible = [n for n in names if not spec_lib.feasibility(spec, scenes[n])]
      row = {"spec": spec.name, "file": path, "maps": len(names), "feasible_maps": len(feasible)}
      if feasible:
        maps = _maps(folder, feasible, tmp, f"spec{i}")
        # warm-up: the shapes of this spec's batches (its agent counts) and the unguided sampler's
        _generate(hl, infill, maps, tmp, spec)
        _rejection(model, spec, [scenes[n] for n in feasible], FLAGS.rejection_draws)
        summary, seconds = _generate(hl, infill, maps, tmp, spec)
        s = summary["spec"]
        accepted, drawn, rej_s = _rejection(model, spec, [scenes[n] for n in feasible], FLAGS.rejection_draws)
        per_sample = seconds / s["samples"]
        per_satisfying = seconds / max(s["satisfied"], 1)
        rejection_per_accepted = rej_s / accepted if accepted else None
        row.update({"samples": s["samples"], "satisfied": s["satisfied"], "satisfied_pct": s["satisfied_pct"],
                    "infeasible_placement": len(s["infeasible_maps"]), "predicates_pct": s["predicates_pct"],
                    "seconds_per_sample": per_sample, "seconds_per_satisfying": per_satisfying,
                    "cost_vs_plain": per_satisfying / plain_row["seconds_per_sample"],
                    "rejection": {"draws": drawn, "accepted": accepted, "seconds": rej_s,
                                  "seconds_per_accepted": rejection_per_accepted,
                                  # no acceptance: at least the time of all draws per accepted sample
                                  "speedup_at_least" if not accepted else "speedup":
                                      (rejection_per_accepted or rej_s) / per_satisfying},
                    "complete_scenarios": summary["complete_scenarios"]["generated"]})
      rows.append(row)
      print(json.dumps(row), flush=True)
  out = Path(FLAGS.out) / f"specs_{FLAGS.name}.json"
  command = "python benchmarks/specs.py " + " ".join(a for a in sys.argv[1:])
  out.write_text(json.dumps({"name": FLAGS.name, "command": command, "date": datetime.date.today().isoformat(),
                             "machine": common.machine(), "plain": plain_row, "specs": rows}, indent=1) + "\n")
  print(out)


if __name__ == "__main__":
  app.run(main)
