"""The README's results tables, rendered from the JSON of record in this folder.

  python results/render.py                     # rewrite the tables between <!-- table:NAME --> markers
  python results/render.py --check             # exit 1 when a file's tables differ from what this renders
  python results/render.py --record workdirs/hl/eval/table.json --name synthetic_val --command "..."
  python results/render.py --record_sample workdirs/hl/samples/summary.json --name synthetic_val --sampler default --command "..."

The figures of record: `table1_<name>.json` (the Table I part of an `evaluate` run's table.json, recorded
with `--record`, and `realism_<name>.json`, its realism table and Table IIs when it has them), `paper.json` (the paper's Table I and II, as printed), `speed/<machine>/` (the JSON of
`python benchmarks/summary.py --out results/speed/<machine>`), `timings.json` (the commands' wall
times, each as `/usr/bin/time -f %e` measured it) and `complete_scenarios.json` (the audit of what
`sample.py` wrote, recorded with `--record_sample`). A test checks that README.md holds exactly
what this script renders (README.md and docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import datetime
import json
import re
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

from benchmarks import summary  # noqa: E402

DATA_LABELS = {"synthetic_val": "synthetic validation maps (60)", "av2_real": "real AV2 validation maps (17)"}
SAMPLERS = {"default": "**default**", "paper": "paper's (`--guidance= --repair_rounds=0`)"}
METRICS = (("collision_rate_pct", "{:.1f}"), ("offroad_rate_pct", "{:.1f}"), ("near_edge_m", "{:.2f}"),
           ("jsd_speed", "{:.3f}"), ("jsd_lateral_deviation", "{:.3f}"), ("jsd_local_density", "{:.3f}"),
           ("jsd_nearest_distance", "{:.3f}"))


def record(table_json: Path, name: str, command: str) -> Path:
  """Keeps the parts of an `evaluate` table.json the README shows, with the command and the date."""
  t = json.loads(table_json.read_text())
  kept = {"name": name, "command": command, "date": datetime.date.today().isoformat(),
          "scenes": t["scenes"], "agents": t["agents"], "skipped": len(t["skipped"]),
          "checkpoint_step": t["hl_checkpoint"]["step"], "sampler": t["hl_checkpoint"]["sampler"]["description"],
          "table_i": t["table_i"]["official"], "shuffled_map_control": t.get("shuffled_map_control")}
  out = HERE / f"table1_{name}.json"
  out.write_text(json.dumps(kept, indent=1) + "\n")
  if "realism" in t:   # the realism of complete scenarios and both infillers' Table II
    realism = {"name": name, "command": command, "date": kept["date"], "scenes": t["scenes"],
               "rollouts_per_map": t["realism"]["rollouts_per_map"], "rows": t["realism"]["rows"],
               "diversity": t["realism"].get("diversity"), "seconds": t["realism"]["seconds"],
               "score_seconds": t["realism"]["score_seconds"],
               "table_ii": t.get("table_ii"), "table_ii_stochastic": t.get("table_ii_stochastic")}
    (HERE / f"realism_{name}.json").write_text(json.dumps(realism, indent=1) + "\n")
  return out


def record_sample(summary_json: Path, name: str, sampler: str, command: str) -> Path:
  """Keeps a `sample.py` summary's audit of the complete scenarios it wrote (`complete_scenarios`) as one row
  of `complete_scenarios.json` (replacing the row of the same maps and sampler)."""
  s = json.loads(summary_json.read_text().strip().splitlines()[-1])   # sample.py's stdout, or its summary.json
  out = HERE / "complete_scenarios.json"
  rows = [r for r in (json.loads(out.read_text())["rows"] if out.exists() else [])
          if (r["name"], r["sampler"]) != (name, sampler)]
  rows.append({"name": name, "sampler": sampler, "command": command, "date": datetime.date.today().isoformat(),
               "samples": s["samples"], "repair": s.get("repair"), "generated": s["complete_scenarios"]["generated"],
               "logged": s["complete_scenarios"]["logged"]})
  rows.sort(key=lambda r: (list(DATA_LABELS).index(r["name"]), list(SAMPLERS).index(r["sampler"])))
  out.write_text(json.dumps({"rows": rows}, indent=1) + "\n")
  return out


def complete() -> str:
  """The audit of complete scenarios as `sample.py` writes them (`complete_scenarios.json`)."""
  lines = ["| maps | sampler | samples | agents | overlap another (%) | road users off the road (%) "
           "| logged: overlap (%) | logged: off the road (%) |", "|---" * 8 + "|"]
  rows = json.loads((HERE / "complete_scenarios.json").read_text())["rows"]
  for r in rows:
    g, lg = r["generated"], r["logged"]
    lines.append(f"| {DATA_LABELS[r['name']]} | {SAMPLERS[r['sampler']]} | {r['samples']} | {g['agents']} | "
                 f"{g['overlap_pct']:.1f} | {g['offroad_pct']:.1f} | {lg['overlap_pct']:.1f} | {lg['offroad_pct']:.1f} |")
  commands = "; ".join(sorted({f"`{r['command']}` ({r['date']})" for r in rows}))
  return "\n".join(lines) + f"\n\nCommands: {commands}."


def _cell(value, fmt: str) -> str:
  return "-" if value is None or value != value else fmt.format(value)


def table1() -> str:
  lines = ["| data | row | states | collision (%) | off-road (%) | near. edge (m) | JSD speed | JSD lat. dev. "
           "| JSD local density | JSD near. dist. | goal reachable (%) | off-road on another map (%) |",
           "|---" * 12 + "|"]
  notes = []
  for name in DATA_LABELS:
    path = HERE / f"table1_{name}.json"
    if not path.exists():
      continue
    r = json.loads(path.read_text())
    for row, label in (("GT", "ground truth"), ("model", "**ours**")):
      for e in ("initial", "goal"):
        v = r["table_i"][e][row]
        control = (r.get("shuffled_map_control") or {}).get(e, {}).get("gt" if row == "GT" else "model", {})
        cells = [_cell(v.get(k), f) for k, f in METRICS]
        lines.append(f"| {DATA_LABELS[name]} | {label} | {e} | " + " | ".join(cells)
                     + f" | {_cell(v.get('goal_reachable_pct'), '{:.1f}')}"
                     + f" | {_cell(control.get('other_map_offroad_pct'), '{:.1f}')} |")
    notes.append(f"{DATA_LABELS[name]}: {r['scenes']} scenes, {r['agents']} agents, checkpoint step "
                 f"{r['checkpoint_step']}, {r['sampler']}, `{r['command']}` ({r['date']})")
  paper = json.loads((HERE / "paper.json").read_text())
  for row, label in (("GT", "ground truth"), ("ours", "paper's model")):
    for e in ("initial", "goal"):
      v = paper["table_i"][e][row]
      cells = [_cell(v.get(k), f) for k, f in METRICS]
      lines.append(f"| AV2 (paper, Table I) | {label} | {e} | " + " | ".join(cells) + " | - | - |")
  return "\n".join(lines) + "\n\n" + "\n".join(f"- {n}" for n in notes)


def table2() -> str:
  """Table II of the shipped infiller (tdiff_jax/pretrained/pretrained.json) beside the paper's."""
  shipped = json.loads((ROOT / "tdiff_jax" / "pretrained" / "pretrained.json").read_text())["table_ii"]
  paper = json.loads((HERE / "paper.json").read_text())["table_ii"]
  lines = ["| hard constraints | ADE (m) | FDE (m) | miss rate (%) | paper: ADE (m) | FDE (m) | miss rate (%) |",
           "|---" * 7 + "|"]
  labels = {"both": "initial and goal", "initial": "initial", "goal": "goal", "none": "none"}
  for mode, label in labels.items():
    ours, theirs = shipped["modes"][mode], paper[mode]
    cells = [_cell(r[k], f) for r in (ours, theirs)
             for k, f in (("ade_m", "{:.2f}"), ("fde_m", "{:.2f}"), ("miss_rate_pct", "{:.2f}"))]
    lines.append(f"| {label} | " + " | ".join(cells) + " |")
  return "\n".join(lines) + (f"\n\nOurs: the shipped infiller on the {shipped['scenes']} synthetic validation scenes "
                             f"({shipped['agents']} agents), `{shipped['command']}`; the paper's: AV2.")


REALISM_LABELS = {"logged": "logged trajectories (the best possible)", "constant_velocity": "constant velocity",
                  "infiller": "infiller, logged states", "hl_infiller": "**HL + infiller**",
                  "stochastic_infiller": "stochastic infiller, logged states",
                  "hl_stochastic_infiller": "**HL + stochastic infiller**"}
REALISM_FEATURES = ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration",
                    "distance_to_nearest_object", "collision", "time_to_collision", "distance_to_road_edge", "offroad")


def _recorded(prefix: str):
  """(name, record) of each `<prefix>_<name>.json` there is, in `DATA_LABELS` order."""
  for name in DATA_LABELS:
    path = HERE / f"{prefix}_{name}.json"
    if path.exists():
      yield name, json.loads(path.read_text())


def realism() -> str:
  """The realism of complete scenarios (`realism_<name>.json`): every row's meta-metric and feature scores
  and the stochastic infiller's diversity."""
  lines = ["| data | row | meta | speed | accel. | ang. speed | ang. accel. | nearest obj. | collision | TTC "
           "| road edge | off-road |", "|---" * 12 + "|"]
  notes = []
  for name, r in _recorded("realism"):
    for row, v in r["rows"].items():
      lines.append(f"| {DATA_LABELS[name]} | {REALISM_LABELS[row]} | **{v['meta']:.3f}** | "
                   + " | ".join(_cell(v[k], "{:.3f}") for k in REALISM_FEATURES) + " |")
    d = r.get("diversity")
    note = (f"{DATA_LABELS[name]}: {r['rollouts_per_map']} generated scenarios per map, `{r['command']}` "
            f"({r['date']}); the rows took {r['seconds']:.0f} s of the run, of which {r['score_seconds']:.0f} s scoring "
            "and the rest generating")
    if d:
      note += (f"; stochastic infiller, {d['draws']} draws per HL scenario: mean pairwise ADE "
               f"{d['pairwise_ade_m']:.2f} m, {d['fork_multi_lane_pct']:.1f} % of the {d['fork_agents']} agents at a "
               f"fork take more than one lane, largest pinned-goal error {d['pinned_goal_error_max_m']:.0e} m")
    notes.append(note)
  return "\n".join(lines) + "\n\n" + "\n".join(f"- {n}" for n in notes)


def stochastic_table2() -> str:
  """Both infillers' Table II of each `realism_<name>.json` that has them."""
  out = ""
  for name in DATA_LABELS:
    path = HERE / f"realism_{name}.json"
    if not path.exists():
      continue
    r = json.loads(path.read_text())
    det, sto = r.get("table_ii"), r.get("table_ii_stochastic")
    if not (det and sto):
      continue
    out += (f"\n\nTable II on the {DATA_LABELS[name]}, deterministic / stochastic infiller (one draw), "
            f"`{r['command']}`:\n\n"
            "| hard constraints | ADE (m) | FDE (m) | miss rate (%) |\n|---|---|---|---|\n")
    out += "\n".join(f"| {mode} | {det[mode]['ade_m']:.2f} / {sto[mode]['ade_m']:.2f} | {det[mode]['fde_m']:.2f} / "
                     f"{sto[mode]['fde_m']:.2f} | {det[mode]['miss_rate_pct']:.2f} / {sto[mode]['miss_rate_pct']:.2f} |"
                     for mode in det)
  return out.strip()


def speed() -> str:
  parts = []
  for folder in sorted(p for p in (HERE / "speed").iterdir() if p.is_dir()):
    parts.append(summary.table(folder))
  return "\n\n".join(parts)


def timings() -> str:
  t = json.loads((HERE / "timings.json").read_text())
  lines = ["| command | wall time | what it does |", "|---|---|---|"]
  dated = False
  for r in t["runs"]:
    m, sec = divmod(round(r["wall_s"]), 60)
    when = f" (measured {r['date']})" if r.get("date", t["date"]) != t["date"] else ""
    dated |= bool(when)
    lines.append(f"| `{r['command']}` | {m} min {sec:02d} s | {r['what']}{when} |")
  return "\n".join(lines) + (f"\n\nMeasured {t['date']}" + (" (the rows marked otherwise on that day, on a machine of the "
                                                             "same kind)" if dated else "")
                             + f" on {t['machine']}, one after the other, nothing else running.")


def specs() -> str:
  """Scenario specs measured (`specs_<name>.json`, written by `python benchmarks/specs.py`)."""
  lines = ["| maps | spec | feasible maps | satisfied (%) | s per satisfying sample | s per plain sample "
           "| vs. plain | rejection: accepted | vs. rejection | overlap (%) | off-road (%) |", "|---" * 11 + "|"]
  notes = []
  for name, t in _recorded("specs"):
    rows = [r for r in t["specs"] if r.get("samples")]
    label = DATA_LABELS[name].split(" (")[0] + (f" (the first {t['specs'][0]['maps']})" if "max_maps" in t["command"]
                                                else f" ({t['specs'][0]['maps']})")
    for r in t["specs"]:
      if not r.get("samples"):
        lines.append(f"| {label} | `{r['spec']}` | 0 of {r['maps']} | - | - | - | - | - | - | - | - |")
        continue
      rej = r["rejection"]
      if "speedup" in rej:
        x = rej["speedup"]
        speedup = f"{x:.1f}x faster" if x >= 1 else f"{1 / x:.1f}x slower"
      else:   # no draw accepted: a bound only where it says faster
        x = rej["speedup_at_least"]
        speedup = f"none accepted: at least {x:.1f}x faster" if x >= 1 else "none accepted"
      c = r["complete_scenarios"]
      lines.append(f"| {label} | `{r['spec']}` | {r['feasible_maps'] - r['infeasible_placement']} of "
                   f"{r['maps']} | {r['satisfied_pct']:.1f} | {r['seconds_per_satisfying']:.1f} | "
                   f"{r['plain_seconds_per_sample']:.1f} | {r['cost_vs_plain']:.1f}x | {rej['accepted']} of "
                   f"{rej['draws']} | {speedup} | {c['overlap_pct']:.1f} | {c['offroad_pct']:.1f} |")
    rate = {r["spec"]: r["rejection"]["accepted"] / r["rejection"]["draws"] for r in rows}
    rarest = [f"`{n}`" for n in rate if rate[n] == min(rate.values())]
    rarest = (f"no draw accepted under rejection for {', '.join(rarest)}" if min(rate.values()) == 0
              else f"rarest under rejection {', '.join(rarest)}")
    m = t["machine"]
    notes.append(f"{label}: mean cost vs. plain {np.mean([r['cost_vs_plain'] for r in rows]):.1f}x, {rarest}; "
                 f"`{t['command']}` ({t['date']}, {m['cpu']}, {m['host_cpus']} cores)")
  return "\n".join(lines) + "\n\n" + "; ".join(notes) + "."


TABLES = {"table1": table1, "table2": table2, "realism": realism, "stochastic_table2": stochastic_table2, "speed": speed,
          "timings": timings, "complete": complete, "specs": specs}
RENDERED = (ROOT / "README.md", ROOT / "docs" / "benchmarks.md", ROOT / "docs" / "evaluation.md",
            ROOT / "docs" / "specs.md")   # the files whose tables this renders


def render(text: str) -> str:
  for name, fn in TABLES.items():
    pattern = re.compile(rf"(<!-- table:{name} -->\n).*?(<!-- /table -->)", re.S)
    if pattern.search(text):
      body = fn()
      text = pattern.sub(lambda m: m.group(1) + body + "\n" + m.group(2), text)
  return text


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--check", action="store_true")
  parser.add_argument("--record", type=Path)
  parser.add_argument("--name", choices=sorted(DATA_LABELS))
  parser.add_argument("--command", default="")
  parser.add_argument("--record_sample", type=Path, help="a sample.py summary.json (or its stdout)")
  parser.add_argument("--sampler", choices=sorted(SAMPLERS), default="default")
  args = parser.parse_args()
  if args.record:
    print(record(args.record, args.name, args.command))
    return
  if args.record_sample:
    print(record_sample(args.record_sample, args.name, args.sampler, args.command))
    return
  for doc in RENDERED:
    text = doc.read_text()
    new = render(text)
    if args.check and new != text:
      raise SystemExit(f"{doc.relative_to(ROOT)}'s tables differ from results/render.py's: run python results/render.py")
    if new != text:
      doc.write_text(new)


if __name__ == "__main__":
  main()
