"""Preprocessing throughput: scenarios per second, real and synthetic, on one core and on all cores.

  python benchmarks/preprocess.py [--copies 40] [--synthetic 160] [--repeats 10] [--runs 5]

Prints one JSON object. "one_core" times `load_scene` (parquet columns + map JSON -> scene arrays) in
this process after a warm-up, `--runs` times (`--repeats` passes over the scenarios each; the median
run is reported, every run beside it); "all_cores" times the whole `preprocess` command (process pool start,
shard writing and the manifest included) over a folder of scenarios. Real scenarios are the AV2
samples in tests/data (three with 110 steps), each copied `--copies` times for the all-core run.
The per-phase split shows where one scenario's time goes; "ratio" is the official one-core time per
real scenario divided by ours (above 1: we are faster).
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from absl import app, flags

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))   # the repository, installed or not

import common  # noqa: E402
from tdiff_jax.data import av2_io, config as config_lib, preprocess, scene_builder, synthetic  # noqa: E402

REAL = Path(__file__).resolve().parent.parent / "tests" / "data"
# The official preprocessing (pandas on the parquet, the JSON map), one core, the same kind of 2-core
# CPU, measured once; the speed target is 3 times faster.
OFFICIAL_MS_PER_SCENARIO = 28.0
TARGET_RATIO = 3.0


def one_core(folders: list[Path], repeats: int, runs: int = 1) -> dict:
  """`runs` timed runs of `repeats` passes over `folders` (after a warm-up pass): the median run's
  milliseconds per scenario and the median of each phase, with every run's figure (this machine's
  spread between runs of a fraction of a second is wide, so one run says little)."""
  cfg = config_lib.default_data_config()
  for f in folders:  # warm-up: imports, caches
    scene_builder.load_scene(f, cfg)
  n = repeats * len(folders)
  per_run, phase_runs = [], []
  for _ in range(runs):
    phases = {"read_parquet": 0.0, "read_map": 0.0, "build_scene": 0.0}
    t0 = time.perf_counter()
    for _ in range(repeats):
      for f in folders:
        a = time.perf_counter()
        files = av2_io.find_scenario_files(f)
        tracks = av2_io.load_tracks(files)
        b = time.perf_counter()
        lanes, polylines, map_data = av2_io.load_map(files)
        c = time.perf_counter()
        scene_builder.build_scene(av2_io.RawScenario(files, tracks, lanes, polylines, map_data=map_data), cfg)
        d = time.perf_counter()
        phases["read_parquet"] += b - a
        phases["read_map"] += c - b
        phases["build_scene"] += d - c
    per_run.append(1e3 * (time.perf_counter() - t0) / n)
    phase_runs.append({k: 1e3 * v / n for k, v in phases.items()})
  ms = float(np.median(per_run))
  return {"scenarios": n, "runs": runs, "scenarios_per_s": round(1e3 / ms, 1), "ms_per_scenario": round(ms, 2),
          "ms_per_scenario_runs": [round(x, 2) for x in per_run],
          "ms_per_phase": {k: round(float(np.median([r[k] for r in phase_runs])), 2) for k in phase_runs[0]}}


def all_cores(root: Path, out: Path) -> dict:
  n = sum(len(f) for f in av2_io.discover_splits(root, "train").values())
  t0 = time.perf_counter()
  manifest = preprocess.preprocess(root, out, workers=os.cpu_count(), progress=False)
  total = time.perf_counter() - t0
  scenes = sum(s["scenes"] for s in manifest["splits"].values())
  return {"workers": os.cpu_count(), "scenarios": n, "scenes_written": scenes,
          "scenarios_per_s": round(n / total, 1), "wall_s": round(total, 2)}


FLAGS = flags.FLAGS
flags.DEFINE_integer("copies", 150, "copies of each real sample for the all-core run")
flags.DEFINE_integer("synthetic", 450, "synthetic scenarios")
flags.DEFINE_integer("repeats", 10, "one-core passes over the real samples per timed run")
flags.DEFINE_integer("runs", 5, "timed one-core runs (the median is reported)")


def main(argv: list[str]) -> None:
  del argv
  args = FLAGS

  real = [d for d in av2_io.list_scenario_folders(REAL) if len(list(d.glob("*.parquet")))]
  real110 = []
  for d in real:
    try:
      scene_builder.load_scene(d)
      real110.append(d)
    except av2_io.BadScenarioError:
      pass
  result = {"machine": common.machine()}
  with tempfile.TemporaryDirectory() as tmp:
    tmp = Path(tmp)
    real_root = tmp / "real"
    real_root.mkdir()
    for k in range(args.copies):
      for d in real110:
        shutil.copytree(d, real_root / f"{d.name}-{k}")
    syn_root = tmp / "synthetic"
    synthetic.generate_dataset(syn_root, args.synthetic, seed=0, val_fraction=0.0, progress=False)
    syn_folders = av2_io.list_scenario_folders(syn_root / "train")
    real_one = one_core(real110, args.repeats, args.runs)
    real_one.update(official_ms_per_scenario=OFFICIAL_MS_PER_SCENARIO, target_ratio=TARGET_RATIO,
                    ratio=round(OFFICIAL_MS_PER_SCENARIO / real_one["ms_per_scenario"], 2))
    result["real"] = {"one_core": real_one, "all_cores": all_cores(real_root, tmp / "c1")}
    result["synthetic"] = {"one_core": one_core(syn_folders[:30], 1, args.runs),
                           "all_cores": all_cores(syn_root, tmp / "c2")}
  result["peak_rss_mb"] = round(common.peak_rss_mb(), 1)
  common.report(result)


if __name__ == "__main__":
  app.run(main)
