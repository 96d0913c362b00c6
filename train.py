"""Train a tdiff_jax model: python train.py --config=configs/hl.py [--workdir=DIR] [--config.FIELD=VALUE ...]

Rerunning the same command resumes from the workdir's latest checkpoint. On a cluster, run the same
command on every host: under SLURM (or Open MPI) the processes find each other by themselves;
otherwise add --coordinator_address=HOST:PORT --num_processes=N --process_id=I (README, "Training on
real AV2").
"""

import ast

from absl import app, flags, logging
from ml_collections import config_flags

from tdiff_jax import checkpoint, cli, files
from tdiff_jax.train import distributed, trainer

_CONFIG = config_flags.DEFINE_config_file("config", None, "config file, e.g. configs/hl.py or configs/hl.py:av2",
                                          lock_config=True)
_WORKDIR = flags.DEFINE_string("workdir", None, "checkpoints, metrics and data go here (default: workdirs/<task>)")
_COORDINATOR = flags.DEFINE_string("coordinator_address", None,
                                   "several processes: HOST:PORT of process 0 (not needed under SLURM)")
_NUM_PROCESSES = flags.DEFINE_integer("num_processes", None, "several processes: how many", lower_bound=1)
_PROCESS_ID = flags.DEFINE_integer("process_id", None, "several processes: this one's index, 0 to N - 1",
                                          lower_bound=0)
cli.define_compilation_cache_flag(flags.FLAGS)
flags.mark_flags_as_required(["config"])


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments: {argv[1:]}")
  config = _CONFIG.value
  workdir = files.user_path(_WORKDIR.value or f"workdirs/{config.task}")
  logging.set_verbosity(logging.INFO)
  checkpoint.quiet_orbax_logging()
  processes = (_COORDINATOR.value, _NUM_PROCESSES.value, _PROCESS_ID.value)
  try:
    if not distributed.multi_process_requested(*processes):  # one host: the config's CPU devices
      n = distributed.use_cpu_cores(int(config.train.get("cpu_devices", 1)), int(config.train.batch_size))
      if n is not None and n > 1:
        logging.info("CPU split into %d JAX devices (config.train.cpu_devices), each batch sharded over them", n)
    distributed.initialize(*processes)
  except ValueError as e:
    raise SystemExit(f"train.py: {e}") from None
  cli.use_compilation_cache(flags.FLAGS.compilation_cache)
  try:
    trainer.check_config(config)
  except ValueError as e:  # one line, before any work
    raise SystemExit(f"train.py: config error: {e}") from None
  try:
    result = trainer.train_and_evaluate(config, workdir)
  except (OSError, ValueError) as e:  # a full disk, a missing folder, a refused resume, a damaged cache
    raise SystemExit(f"train.py: {e}") from None
  print({k: round(v, 5) if isinstance(v, float) else v for k, v in result.items()})


def parse_flags(argv):
  """absl's parsing, with a misspelt or mistyped --config.FIELD as one line, not a traceback."""
  try:
    return app.parse_flags_with_usage(argv)
  except (AttributeError, KeyError, TypeError, ValueError) as e:
    message = str(e)
    try:   # ml_collections wraps a KeyError's quoted message in an AttributeError
      message = ast.literal_eval(message) if message[:1] in "'\"" else message
    except (SyntaxError, ValueError):
      pass
    raise SystemExit(f"train.py: config error: {' '.join(str(message).split())}") from None


if __name__ == "__main__":
  app.run(main, flags_parser=parse_flags)
