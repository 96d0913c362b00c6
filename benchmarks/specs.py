"""Scenario specs measured: per spec of the library, how many samples satisfy it, what a satisfying sample
costs against a plain sample and against rejection sampling of the unguided model, and how its complete
scenarios collide and leave the road (read back from the AV2 folders written).

  python benchmarks/specs.py --maps=workdirs/hl/synthetic/val --max_maps=8 --name=synthetic_val --rejection_draws=16
  python benchmarks/specs.py --maps=../shared/av2_real --name=av2_real --rejection_draws=32
  python benchmarks/specs.py --maps=../shared/av2_real --name=av2_real --pictures=docs/assets/specs

Writes results/specs_<name>.json (`results/render.py` renders it into docs/specs.md). Per spec, on every map
where it can hold, one sample per map: `sample.py --spec` (`generate.generate(spec=...)`, default sampler
and repair); a plain `sample.py` run on the same maps; and the Scenic way, the unguided sampler
(`sampling.UNGUIDED`, HL states only: a lower bound of its cost) drawing `--rejection_draws` scenes per map
with the spec's agents, a draw accepted when some of its agents take the spec's roles (`_holds_somewhere`).
Each timed run follows a warm-up run of the same kind (compiling), so the times are of compiled programs.
Run it with nothing else on the machine. With `--pictures=FOLDER` it measures nothing: it copies the picture
of each spec's first sample that holds the spec with every agent apart and on the road there (<spec>.png).
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
from tdiff_jax import audit, checkpoint, cli, generate, repair, sampling  # noqa: E402
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
flags.DEFINE_string("pictures", "", "instead of measuring, write a picture per spec to this folder")


def _maps(folder: Path, names: list[str], tmp: Path, tag: str) -> Path:
  """A folder of links to the map folders `names` (a subset the commands read as a maps folder)."""
  out = tmp / tag
  out.mkdir()
  for n in names:
    (out / n).symlink_to((folder / n).resolve(), target_is_directory=True)
  return out


def _generate(hl, infill, maps: Path, tmp: Path, spec=None, pictures: bool = False) -> tuple[dict, float, Path]:
  """(summary, seconds generating (not the audit), output folder) of one sample per map."""
  out = tmp / f"out-{time.monotonic_ns()}"
  t0 = time.perf_counter()
  summary = generate.generate(hl, maps, out, num_per_map=1, progress=False, pictures=pictures,
                              infill_workdir=infill, spec=spec)
  return summary, time.perf_counter() - t0 - summary["complete_scenarios"]["seconds"], out


def _picture(hl, infill, maps: Path, tmp: Path, spec, folder: Path) -> str:
  """Copies the picture of the first sample that holds `spec` with every agent apart and on the road (read
  back from its AV2 folder) to folder/<spec>.png; says which it is."""
  summary, _, out = _generate(hl, infill, maps, tmp, spec, pictures=True)
  missed = {m["scenario_id"] for m in summary["spec"]["not_satisfied"]}
  for g in summary["scenarios"]:
    faults = audit.check_scenario(out / "scenarios" / g["scenario_id"])
    if g["scenario_id"] not in missed and not faults["overlap"] and not faults["offroad"]:
      folder.mkdir(parents=True, exist_ok=True)
      shutil.copyfile(out / f"{g['map']}_{g['sample_index']}.png", folder / f"{spec.name}.png")
      return f"{spec.name}.png: map {g['map']}"
  return "none holds the spec with every agent apart and on the road"


def _holds_somewhere(spec, state: np.ndarray, heading: np.ndarray, scene) -> bool:
  """Whether some distinct valid agents of one unguided sample (`state` `[A, 2, 3]`, `heading` `[A, 2]`) take
  the spec's roles: each of its type, making its maneuver, in its speed ranges and region, in its relation
  to the agent taking the related role (the exact predicates of `spec.check`)."""
  valid = np.flatnonzero(scene.agent_valid)
  near = spec_lib.region_distances(state[:, 0, :2], scene) if any(a.region != "any" for a in spec.agents) else {}
  limit = {"intersection": spec_lib.INTERSECTION_M, "crosswalk": spec_lib.CROSSWALK_M}
  fits = [[i for i in valid if scene.agent_type[i] == a.type and spec_lib.maneuver_holds(a.maneuver, state[i], heading[i])
           and all(r is None or r[0] <= state[i, t, 2] <= r[1] for t, r in enumerate(a.speed))
           and (a.region == "any" or near[a.region][i] <= limit[a.region])] for a in spec.agents]
  order = spec_lib.relation_order(spec)

  def assign(pos: int, chosen: dict) -> bool:
    if pos == len(order):
      return True
    k = order[pos]
    r = spec.agents[k].relation
    for i in fits[k]:
      if i not in chosen.values() and (r is None or spec_lib.relation_holds(r.kind, r.distance, state, heading, i,
                                                                             chosen[r.to])):
        if assign(pos + 1, {**chosen, k: i}):
          return True
    return False

  return assign(0, {})


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
      accepted += _holds_somewhere(spec, state[j], heading[j], items[p])
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
    for i, path in enumerate(FLAGS.specs):
      spec = spec_lib.load(ROOT / path, model.config.data.scene.max_agents)
      feasible = [n for n in names if not spec_lib.feasibility(spec, scenes[n])]
      row = {"spec": spec.name, "file": path, "maps": len(names), "feasible_maps": len(feasible)}
      if feasible and FLAGS.pictures:
        picture = _picture(hl, infill, _maps(folder, feasible, tmp, f"pictures{i}"), tmp, spec, Path(FLAGS.pictures))
        print(f"{spec.name}: {picture}", flush=True)
      if feasible and not FLAGS.pictures:
        maps = _maps(folder, feasible, tmp, f"spec{i}")
        feasible_scenes = [scenes[n] for n in feasible]
        # warm-ups: the shapes of these maps' plain and spec batches, and the unguided sampler's
        _generate(hl, infill, maps, tmp)
        _generate(hl, infill, maps, tmp, spec)
        _rejection(model, spec, feasible_scenes, min(FLAGS.rejection_draws, 8))
        plain, plain_s, _ = _generate(hl, infill, maps, tmp)
        summary, seconds, out = _generate(hl, infill, maps, tmp, spec)
        s = summary["spec"]
        accepted, drawn, rej_s = _rejection(model, spec, feasible_scenes, FLAGS.rejection_draws)
        plain_per_sample = plain_s / plain["samples"]
        per_satisfying = seconds / max(s["satisfied"], 1)
        rejection_per_accepted = rej_s / accepted if accepted else None
        row.update({"samples": s["samples"], "satisfied": s["satisfied"], "satisfied_pct": s["satisfied_pct"],
                    "infeasible_placement": len(s["infeasible_maps"]), "predicates_pct": s["predicates_pct"],
                    "seconds_per_sample": seconds / s["samples"], "seconds_per_satisfying": per_satisfying,
                    "plain_seconds_per_sample": plain_per_sample, "cost_vs_plain": per_satisfying / plain_per_sample,
                    "rejection": {"draws": drawn, "accepted": accepted, "seconds": rej_s,
                                  "seconds_per_accepted": rejection_per_accepted,
                                  # no acceptance: at least the time of all draws per accepted sample
                                  "speedup_at_least" if not accepted else "speedup":
                                      (rejection_per_accepted or rej_s) / per_satisfying},
                    "complete_scenarios": summary["complete_scenarios"]["generated"],
                    "plain_complete_scenarios": plain["complete_scenarios"]["generated"]})
      rows.append(row)
      print(json.dumps(row), flush=True)
  if FLAGS.pictures:
    return
  out = Path(FLAGS.out) / f"specs_{FLAGS.name}.json"
  command = "python benchmarks/specs.py " + " ".join(a for a in sys.argv[1:])
  out.write_text(json.dumps({"name": FLAGS.name, "command": command, "date": datetime.date.today().isoformat(),
                             "machine": common.machine(), "specs": rows}, indent=1) + "\n")
  print(out)


if __name__ == "__main__":
  app.run(main)
