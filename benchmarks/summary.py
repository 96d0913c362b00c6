"""The README's Benchmarks summary: every benchmark that has an official figure, run one after the other,
and one Markdown table of our figure, the official figure, the ratio and the target, read from their JSON.

  python benchmarks/summary.py --out DIR            # runs them (about 30 minutes on a 2-core CPU), then the table
  python benchmarks/summary.py --out DIR --norun    # the table from the JSON of an earlier run in DIR

Each benchmark runs in a process of its own (`python benchmarks/NAME.py ...` as listed in `BENCHMARKS`:
every compile of one process stays in its memory), its JSON written to DIR/<run>.json and its progress
to DIR/<run>.log; a benchmark that fails stops the run with its log's tail. Run it with nothing else on
the machine: the figures are wall-clock throughput. The table names the CPU, the date of the JSON and
each row's command, and says which rows meet their target (issue targets: 5x the official DDIM-50 and
DDPM-500, 4x guided, 10x for the few-step samplers against the official DDIM-50, 1.5x the train step, 2x
the infiller, 3x the preprocessing).
"""

from __future__ import annotations

import datetime
import json
import subprocess
import sys
from pathlib import Path

from absl import app, flags

HERE = Path(__file__).resolve().parent

# (run name, benchmark script and its arguments). The samplers split over processes: compiling every
# mode at both batch sizes in one process has run out of memory for LLVM on a 2-core machine.
BENCHMARKS = (
    ("sampling_paper", ["sampling.py", "--modes", "ddim50,dpmpp2m15", "--batch_sizes", "1,8"]),
    ("sampling_paper_guided", ["sampling.py", "--modes", "ddim50_guided,ddpm500", "--batch_sizes", "8"]),
    ("sampling_default", ["sampling.py", "--config", "default", "--modes", "dpmpp2m11n12r4,ddim50r4f5_guided",
                          "--batch_sizes", "1,8"]),
    ("train_step_paper", ["train_step.py", "--config", "av2", "--batch_sizes", "8", "--modes", "bucketed"]),
    ("infill", ["infill.py", "--batch_sizes", "1,8"]),
    ("preprocess", ["preprocess.py"]),
)

SAMPLER_LABELS = {
    "ddim50": "HL DDIM-50 unguided",
    "ddim50_guided": "HL DDIM-50 guided (clearance, lane, off-road)",
    "ddpm500": "HL DDPM-500",
    "dpmpp2m15": "HL DPM-Solver++(2M) 15 calls, against the official DDIM-50",
    "dpmpp2m11n12r4": "`sample.py`'s unguided default (DPM-Solver++(2M), 15 calls), against the official DDIM-50",
    "ddim50r4f5_guided": "`sample.py`'s guided default (DDIM-50, 4 restarts, 5 final cost steps: 54 calls), "
                         "against the official guided DDIM-50",
}
MODELS = {"av2": "paper (random weights)", "default": "CPU default (random weights)"}

FLAGS = flags.FLAGS
flags.DEFINE_string("out", None, "folder for the benchmarks' JSON and logs", required=True)
flags.DEFINE_bool("run", True, "run the benchmarks first (--norun: the table from DIR's JSON)")


def run_all(out: Path) -> None:
  out.mkdir(parents=True, exist_ok=True)
  for name, (script, *args) in BENCHMARKS:
    command = [sys.executable, str(HERE / script), *args]
    print(f"{name}: {' '.join(['python', 'benchmarks/' + script, *args])}", file=sys.stderr, flush=True)
    with open(out / f"{name}.json.partial", "w") as stdout, open(out / f"{name}.log", "w") as log:
      code = subprocess.run(command, stdout=stdout, stderr=log).returncode
    if code:
      tail = (out / f"{name}.log").read_text().splitlines()[-15:]
      raise SystemExit(f"{name} failed (exit {code}); the end of {out / (name + '.log')}:\n" + "\n".join(tail))
    (out / f"{name}.json.partial").replace(out / f"{name}.json")  # only a finished run's JSON is read


def _command(script_args: list[str]) -> str:
  script, *args = script_args
  return "`" + " ".join(["python", f"benchmarks/{script}", *args]) + "`"


def _row(workload: str, model: str, batch: str, ours: float, unit: str, official: float, ratio: float, target: float,
         command: str) -> str:
  met = "yes" if ratio >= target else "no"
  return (f"| {workload} | {model} | {batch} | {ours:g} {unit} | {official:g} | {ratio:.2f}x | {target:g}x | {met} "
          f"| {command} |")


def _millions(result: dict) -> str:
  return f"{result['parameters'] / 1e6:.2f} M"


def rows_of(script_args: list[str], result: dict) -> list[str]:
  """The table's rows of one benchmark's JSON: the runs that have an official figure."""
  command = _command(script_args)
  script = script_args[0]
  rows = []
  if script == "sampling.py":
    model = MODELS[result["config"]]
    for r in result["runs"]:
      if r.get("official_scenes_per_s"):
        rows.append(_row(SAMPLER_LABELS.get(r["mode"], r["mode"]), model, str(r["batch_size"]), r["scenes_per_s"],
                         "scenes/s", r["official_scenes_per_s"], r["ratio"], r["target_ratio"], command))
  elif script == "train_step.py":
    for r in result["runs"]:
      if r.get("official_steps_per_s"):
        rows.append(_row("HL train step", f"paper ({_millions(result)} parameters)", str(r["batch_size"]), r["steps_per_s"],
                         "steps/s", r["official_steps_per_s"], r["ratio"], r["target_ratio"], command))
  elif script == "infill.py":
    for r in result["runs"]:
      if r.get("official_scenes_per_s"):
        rows.append(_row("infiller, 4 modes", f"official infiller ({_millions(result)} parameters)", str(r["batch_size"]),
                         r["scenes_per_s"], "scenes/s", r["official_scenes_per_s"], r["ratio"], r["target_ratio"],
                         command))
  elif script == "preprocess.py":
    r = result["real"]["one_core"]
    rows.append(_row("preprocessing, one core", "-", "-", r["ms_per_scenario"], "ms/scene", r["official_ms_per_scenario"],
                     r["ratio"], r["target_ratio"], command))
  return rows


def _machine(results: list[dict]) -> dict:
  """The machine the JSON was measured on (`common.machine`), the first that names its CPU."""
  machines = [r.get("machine", r) for r in results]
  return next((m for m in machines if "cpu" in m), machines[0] if machines else {})


def table(out: Path) -> str:
  lines = ["| workload | model | batch | ours | official | ratio | target | met | command |",
           "|---|---|---|---|---|---|---|---|---|"]
  results, stamps, missing = [], [], []
  for name, script_args in BENCHMARKS:
    path = out / f"{name}.json"
    if not path.exists():
      missing.append(name)
      continue
    result = json.loads(path.read_text())
    results.append(result)
    # The date the JSON records (`common.machine`), else the file's: a checkout sets every file's time.
    stamp = result.get("machine", result).get("date")
    stamps.append(datetime.datetime.fromisoformat(stamp) if stamp else
                  datetime.datetime.fromtimestamp(path.stat().st_mtime, datetime.timezone.utc))
    lines.extend(rows_of(script_args, result))
  if not results:
    raise SystemExit(f"{out}: no benchmark JSON (run without --norun first)")
  m = _machine(results)
  cpu = m.get('cpu', m.get('host', '?'))
  if m.get("cpu_id"):  # the model name alone does not tell a virtual machine's CPU generations apart
    cpu += f" ({m['cpu_id']}; {', '.join(m.get('cpu_features', [])) or 'none of AVX2, AVX-512, AMX'})"
  first, last = f"{min(stamps):%Y-%m-%d}", f"{max(stamps):%Y-%m-%d}"
  head = (f"Measured {first}{f' to {last}' if last != first else ''} on {cpu} ({m.get('host_cpus', '?')} cores, "
          f"{m.get('platform', '?')}, jax {m.get('jax', '?')}); varied scene set, median of each benchmark's passes, "
          "compile apart.")
  if missing:
    head += f" Not run: {', '.join(missing)}."
  return head + "\n\n" + "\n".join(lines)


def main(argv: list[str]) -> None:
  del argv
  out = Path(FLAGS.out)
  if FLAGS.run:
    run_all(out)
  print(table(out))


if __name__ == "__main__":
  app.run(main)
