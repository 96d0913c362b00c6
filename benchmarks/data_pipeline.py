"""The training input pipeline at scale: memory and throughput against the dataset's size, and two
training processes next to one.

  python benchmarks/data_pipeline.py [--sizes 1000,10000] [--steps 40] [--workdir DIR]

Generates max(--sizes) synthetic AV2 scenarios once (kept in --workdir, default a temporary folder;
a dataset of N scenes is the first N of them), preprocesses one cache per size, then, each in a fresh
process so peak resident memory is its own:
  * input: `batches.BatchIterator` alone (Grain: read, decode, stack, crop) at the training batch size,
    batches/s after a warm-up, and peak memory;
  * train: the default HL config (`configs/hl.py`) for --steps steps on that cache, every batch padded
    to the caps (one size bucket, so every run compiles the same program): steps/s after the first
    logged interval (compilation), and peak memory of the whole training process;
  * in_memory: the reference, what the loader before streaming did: the whole split read into memory
    (`batches.load_split`), its peak memory;
  * two_processes (smallest size): the same training as two processes connected with jax.distributed
    on this machine (sharing its cores, each reading half of every batch) next to one process.
Prints one JSON object; "ratio" fields divide ours by the reference.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from absl import app, flags

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # configs/
import common  # noqa: E402


# Training runs pad every batch to the caps (one size bucket), so each compiles the same one program
# whatever batches it meets: compilation's memory is then equal and the difference is the data's.
ONE_BUCKET = {"agent_buckets": (64,), "polygon_buckets": (256,)}


def child_input(cache: str, batch_size: int, batches_to_time: int) -> dict:
  from configs import hl as hl_config
  from tdiff_jax.train import trainer
  from tdiff_jax.data import batches

  config = hl_config.get_config("default")
  source = batches.open_split(cache, "train", config.data.scene)
  it = trainer.batch_iterator(source, batch_size, config, train=True)
  for _ in range(5):
    next(it)
  t0 = time.perf_counter()
  for _ in range(batches_to_time):
    next(it)
  dt = time.perf_counter() - t0
  return {"batches_per_s": round(batches_to_time / dt, 1), "ms_per_batch": round(1e3 * dt / batches_to_time, 2),
          "peak_rss_mb": round(common.peak_rss_mb(), 1)}


def child_in_memory(cache: str) -> dict:
  from configs import hl as hl_config
  from tdiff_jax.data import batches

  base = common.peak_rss_mb()
  ds = batches.load_split(cache, "train", hl_config.get_config("default").data.scene)
  return {"scenes": len(ds), "peak_rss_mb": round(common.peak_rss_mb(), 1), "before_load_mb": round(base, 1)}


def child_train(cache: str, workdir: str, steps: int) -> dict:
  from configs import hl as hl_config
  from tdiff_jax.train import trainer

  config = hl_config.get_config("default")
  config.data.cache_dir = cache
  config.train.update(dict(num_steps=steps, log_every=5, eval_every=10 ** 9, checkpoint_every=10 ** 9))
  config.data.update(ONE_BUCKET)
  trainer.train_and_evaluate(config, workdir)
  return {**steady_rate(Path(workdir)), "peak_rss_mb": round(common.peak_rss_mb(), 1)}


def steady_rate(workdir: Path) -> dict:
  """Training steps/s over the logged intervals after the first (which holds the compilation)."""
  rows = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
  rates = [r["steps_per_s"] for r in rows if "steps_per_s" in r][1:]
  return {"steps_per_s": round(sum(rates) / len(rates), 3) if rates else None}


def run_child(*args: str) -> dict:
  done = subprocess.run([sys.executable, __file__, "--child=" + ",".join(args)], capture_output=True, text=True, cwd=ROOT,
                        env={**os.environ, "JAX_PLATFORMS": os.environ.get("JAX_PLATFORMS", "cpu")})
  if done.returncode:
    raise RuntimeError(f"child {args[0]} failed:\n{done.stderr[-3000:]}")
  return json.loads(done.stdout.strip().splitlines()[-1])


def two_processes(cache: Path, workdir: Path, steps: int) -> dict:
  with socket.socket() as sock:
    sock.bind(("localhost", 0))
    port = sock.getsockname()[1]
  cmd = [sys.executable, "train.py", "--config=configs/hl.py", f"--workdir={workdir}",
         f"--config.data.cache_dir={cache}", f"--config.train.num_steps={steps}", "--config.train.log_every=5",
         f"--config.train.eval_every={10 ** 9}", f"--config.train.checkpoint_every={10 ** 9}",
         "--config.data.agent_buckets=(64,)", "--config.data.polygon_buckets=(256,)",
         f"--coordinator_address=localhost:{port}", "--num_processes=2"]
  env = {**os.environ, "JAX_PLATFORMS": "cpu"}
  procs = [subprocess.Popen(cmd + [f"--process_id={i}"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True) for i in range(2)]
  errors = [p.communicate()[1] for p in procs]
  for p, err in zip(procs, errors):
    if p.returncode:
      raise RuntimeError(f"two-process training failed:\n{err[-3000:]}")
  return steady_rate(workdir)


def build_caches(work: Path, sizes: list[int]) -> dict[int, Path]:
  from tdiff_jax.data import preprocess, synthetic

  pool = work / "synthetic"
  have = len(list((pool / "train").glob("*"))) if (pool / "train").exists() else 0
  if have < max(sizes):
    print(f"generating {max(sizes)} synthetic scenarios into {pool}", file=sys.stderr)
    synthetic.generate_dataset(pool, max(sizes), seed=0, val_fraction=0.0, progress=False)
  folders = sorted((pool / "train").iterdir())
  caches = {}
  for n in sizes:
    root = work / f"data_{n}"
    (root / "train").mkdir(parents=True, exist_ok=True)
    for f in folders[:n]:
      link = root / "train" / f.name
      if not link.exists():
        link.symlink_to(f, target_is_directory=True)
    caches[n] = work / f"cache_{n}"
    print(f"preprocessing {n} scenarios into {caches[n]}", file=sys.stderr)
    preprocess.preprocess(root, caches[n], progress=False)  # resumes: a rerun reuses the shards
  return caches


FLAGS = flags.FLAGS
flags.DEFINE_list("sizes", ["1000", "10000"], "dataset sizes (scenes)")
flags.DEFINE_integer("steps", 40, "training steps per run")
flags.DEFINE_integer("batch_size", 16, "input batch size (the default config's)")
flags.DEFINE_integer("input_batches", 200, "batches timed for the input alone")
flags.DEFINE_string("workdir", "", "keep the datasets and caches here (default: a temporary folder)")
flags.DEFINE_list("child", [], "internal: run one measurement in this process (kind,arguments)")


def main(argv: list[str]) -> None:
  del argv
  args = FLAGS
  if args.child:
    kind, *rest = args.child
    if kind == "input":
      out = child_input(rest[0], args.batch_size, args.input_batches)
    elif kind == "in_memory":
      out = child_in_memory(rest[0])
    else:
      out = child_train(rest[0], rest[1], args.steps)
    print(json.dumps(out))
    return

  sizes = sorted(int(s) for s in args.sizes)
  with tempfile.TemporaryDirectory() as tmp:
    work = Path(args.workdir) if args.workdir else Path(tmp)
    work.mkdir(parents=True, exist_ok=True)
    caches = build_caches(work, sizes)
    result: dict = {"machine": common.machine(),
                    "batch_size": args.batch_size, "steps": args.steps, "sizes": {}}
    for n in sizes:
      row = {"input": run_child("input", str(caches[n])),
             "train": run_child("train", str(caches[n]), tempfile.mkdtemp(dir=work, prefix=f"train_{n}_")),
             "in_memory": run_child("in_memory", str(caches[n]))}
      row["input_batches_per_train_step"] = round(row["input"]["batches_per_s"] / row["train"]["steps_per_s"], 1)
      row["ratio_train_peak_to_in_memory_split"] = round(row["train"]["peak_rss_mb"] / row["in_memory"]["peak_rss_mb"], 2)
      result["sizes"][str(n)] = row
      print(json.dumps({n: row}), file=sys.stderr)
    small, large = str(sizes[0]), str(sizes[-1])
    result["train_peak_growth_pct"] = round(
        100 * (result["sizes"][large]["train"]["peak_rss_mb"] / result["sizes"][small]["train"]["peak_rss_mb"] - 1), 1)
    result["in_memory_peak_growth_pct"] = round(
        100 * (result["sizes"][large]["in_memory"]["peak_rss_mb"] / result["sizes"][small]["in_memory"]["peak_rss_mb"] - 1), 1)
    one = result["sizes"][small]["train"]["steps_per_s"]
    two = two_processes(caches[sizes[0]], Path(tempfile.mkdtemp(dir=work, prefix="two_")), args.steps)
    result["two_processes"] = {"scenes": sizes[0], "one_process_steps_per_s": one,
                               "two_processes_steps_per_s": two["steps_per_s"],
                               "ratio": round(two["steps_per_s"] / one, 2) if one and two["steps_per_s"] else None}
  common.report(result)


if __name__ == "__main__":
  app.run(main)
