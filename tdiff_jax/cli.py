"""The command-line conventions of every entry point: absl flags, and the sampler's options in one place.

Library modules with a command line (`python -m tdiff_jax.evaluate`, `...animate`,
`...plot_metrics`, `...data.preprocess`, `...data.synthetic`) define their flags in a function of a
`flags.FlagValues` and build `main = cli.entry_point(define_flags, run)`:

* `python -m MODULE --flag=...`: an absl app (`--help`, `--helpfull`, absl logging) with the flags on
  the global `flags.FLAGS`, defined only then, so importing a module never defines a flag;
* `MODULE.main(["--flag=...", ...])` from Python (tests, notebooks): the list is parsed on a private
  `FlagValues`, so several modules' flags of the same name never collide.

`run(flag_values, args)` does the work; `args` are the positional arguments. `sample.py` and
`python -m tdiff_jax.evaluate` share `define_sampler_flags` and `sampler_options`.
"""

from __future__ import annotations

import dataclasses
import os
import sys
from pathlib import Path
from typing import Callable, Sequence

from absl import app, flags, logging

DefineFn = Callable[[flags.FlagValues], None]
RunFn = Callable[[flags.FlagValues, list[str]], None]

# A seed's range: `jax.random.key` reads only its low 32 bits (seeds that differ above would draw the same).
MAX_SEED = 2**32 - 1


def define_seed_flag(values: flags.FlagValues) -> None:
  flags.DEFINE_integer("seed", 0, f"random seed (0 to {MAX_SEED})", lower_bound=0, upper_bound=MAX_SEED,
                       flag_values=values)


def compilation_cache_dir() -> Path:
  """Where the command lines keep compiled programs: `$TDIFF_JAX_CACHE_DIR`, else
  `$XDG_CACHE_HOME/tdiff_jax/jax` (`~/.cache/tdiff_jax/jax`)."""
  if os.environ.get("TDIFF_JAX_CACHE_DIR"):
    return Path(os.environ["TDIFF_JAX_CACHE_DIR"]).expanduser()
  return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache").expanduser() / "tdiff_jax" / "jax"


def define_compilation_cache_flag(values: flags.FlagValues) -> None:
  flags.DEFINE_boolean(
      "compilation_cache", os.environ.get("TDIFF_JAX_COMPILATION_CACHE", "1") != "0",
      "keep XLA's compiled programs between runs (JAX's persistent compilation cache, in $TDIFF_JAX_CACHE_DIR "
      "or ~/.cache/tdiff_jax/jax), so a second run compiles nothing it compiled before; --nocompilation_cache "
      "(or TDIFF_JAX_COMPILATION_CACHE=0): compile afresh", flag_values=values)


def use_compilation_cache(enabled: bool) -> Path | None:
  """Turns JAX's persistent compilation cache on in `compilation_cache_dir()` (call before the first
  compile; a cache folder set already, e.g. `JAX_COMPILATION_CACHE_DIR`, is kept); returns the folder, or
  None when off or when the folder cannot be made (then the run compiles as usual, saying why)."""
  if not enabled:
    return None
  import jax
  if jax.config.jax_compilation_cache_dir:
    return Path(jax.config.jax_compilation_cache_dir)
  path = compilation_cache_dir()
  try:
    path.mkdir(parents=True, exist_ok=True)
  except OSError as e:
    print(f"tdiff_jax: no compilation cache ({e}); compiling as usual", file=sys.stderr)
    return None
  jax.config.update("jax_compilation_cache_dir", str(path))
  # Every program: the samplers' many small ones add up on a CPU (a second `sample.py` run on command 1's
  # maps took 36 s with every program cached, 54 s with JAX's default of those taking 1 s or more).
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
  return path


def check_seed(seed: int, name: str = "seed") -> None:
  """Raises ValueError for a seed outside 0 to `MAX_SEED` (the command lines refuse it at parse time)."""
  if not 0 <= seed <= MAX_SEED:
    raise ValueError(f"{name}={seed}: must be between 0 and {MAX_SEED} (a JAX key holds 32 bits of a seed)")


def entry_point(define_flags: DefineFn, run: RunFn) -> Callable[[Sequence[str] | None], None]:
  """`main(argv=None)`: without `argv` an absl app on the process's command line, with a list of
  arguments (no program name) the same run on a private `FlagValues`."""

  def main(argv: Sequence[str] | None = None) -> None:
    if argv is None:
      define_flags(flags.FLAGS)
      app.run(lambda args: run(flags.FLAGS, list(args[1:])))
      return
    values = flags.FlagValues()
    define_flags(values)
    try:
      args = values(["main", *argv])
    except flags.Error as e:
      raise app.UsageError(str(e)) from e
    run(values, list(args[1:]))

  return main


def no_arguments(args: list[str]) -> None:
  if args:
    raise app.UsageError(f"unexpected arguments: {args}")


def define_sampler_flags(values: flags.FlagValues) -> None:
  """--method, --steps, --guidance, --guidance_mode, --guidance_weights, --repair_rounds, --lane_pull_m."""
  from tdiff_jax import repair, sampling  # here: data-only entry points never load the model stack
  flags.DEFINE_enum("method", "auto", ["auto", *sampling.METHODS],
                    "reverse process: ddim (50 calls at stride 10), ddpm (every step), dpmpp2m (DPM-Solver++(2M)); "
                    "auto: dpmpp2m unguided, ddim guided", flag_values=values)
  flags.DEFINE_integer("steps", 0, "network calls of --method=ddim or dpmpp2m (0: the method's default, "
                       f"ddim stride {sampling.DEFAULT_DDIM_STRIDE}, dpmpp2m {sampling.DEFAULT_SOLVER_STEPS})", lower_bound=0,
                       flag_values=values)
  flags.DEFINE_list("guidance", list(repair.DEFAULT_GUIDANCE), "guidance costs: clearance (centre distance), boxes "
                    "(type-sized boxes), lane, offroad on the states; paths (boxes apart) and path_offroad along the 6 s "
                    "between them ('' for none, as the paper's Table I)", flag_values=values)
  flags.DEFINE_enum("guidance_mode", "official", ["official", "paper"], "guidance variant: the official code's "
                    "clamped step on x0, or the paper's eq. 3", flag_values=values)
  flags.DEFINE_list("guidance_weights", [], "per-cost guidance weights as cost=weight, e.g. offroad=2,boxes=1 (the rest "
                    "keep sampling.GuidanceParams' defaults: clearance 1, boxes 1, lane 0.1, offroad 1)",
                    flag_values=values)
  flags.DEFINE_integer("repair_rounds", repair.DEFAULT_REPAIR_ROUNDS, "with an infiller: rounds of resampling the agents whose infilled "
                       "trajectories overlap another's or leave the road, the others held (0: the sampler alone, "
                       "as the paper)", lower_bound=0, upper_bound=16, flag_values=values)
  flags.DEFINE_float("lane_pull_m", None, "the denoiser's lane pull (parameter-free, any grounded checkpoint with "
                     "headings): each moving road user's estimate at most this far across a lane its heading "
                     "agrees with is put on that lane's centreline (0: off; default: the checkpoint's, lane_pull in "
                     "its config)", lower_bound=0.0, flag_values=values)


def sampler_options(values: flags.FlagValues, costs: Sequence[str] | None = None, num_steps: int = 500):
  """The options the sampler flags ask for (`costs` in place of --guidance, e.g. for a second row), for a
  model of `num_steps` diffusion steps; --method=auto resolved (`sampling.resolve_method`), restarts and
  final cost steps the measured defaults (`sampling.default_restarts`, `default_final_cost_steps`)."""
  from tdiff_jax import sampling
  costs = tuple(values.guidance if costs is None else costs)
  method = sampling.resolve_method(values.method, costs)
  calls = values.steps
  by_method = {"ddim": dict(stride=max(1, num_steps // calls) if calls else sampling.DEFAULT_DDIM_STRIDE),
               "dpmpp2m": dict(stride=1, solver_steps=calls or sampling.DEFAULT_SOLVER_STEPS,
                               solver_max_noise=sampling.DEFAULT_SOLVER_MAX_NOISE),
               "ddpm": dict(stride=1)}[method]
  return sampling.SamplerOptions(method=method, costs=costs, guidance=values.guidance_mode,
                                 restarts=sampling.default_restarts(method, costs, values.guidance_mode),
                                 final_cost_steps=sampling.default_final_cost_steps(costs, values.guidance_mode),
                                 **by_method)


def diffusion_steps(workdir) -> int:
  """The diffusion steps T of the model in `workdir`, from the record of the checkpoint (or exported model)
  that sampling loads, never from an editable config.json beside it. Raises ValueError when it has none."""
  from tdiff_jax import checkpoint
  try:
    return int(checkpoint.load_record(workdir)["config"]["diffusion"]["num_steps"])
  except (KeyError, TypeError) as e:
    raise ValueError(f"{workdir}: the model's record names no diffusion.num_steps ({e})") from None


def model_dir(values: flags.FlagValues, name: str, task: str) -> Path | None:
  """Where the `task` model of the workdir flag `name` is loaded from: None for ''; the folder itself when
  it holds a checkpoint; at the flag's default location without one, the pretrained model shipped with
  the package (`checkpoint.pretrained_dir`). A folder given on the command line without a checkpoint
  raises FileNotFoundError saying how to train one."""
  from tdiff_jax import checkpoint, files
  if not values[name].value:
    return None
  path = files.user_path(values[name].value)
  if checkpoint.has_checkpoint(path):
    return path
  if values[name].present:
    raise FileNotFoundError(f"no checkpoint in {path / 'checkpoints'}; train one first: "
                            f"python train.py --config=configs/{task}.py --workdir={path}")
  logging.info("%s holds no checkpoint: using the pretrained %s model shipped with tdiff_jax (python train.py "
               "--config=configs/%s.py trains your own there)", path, task, task)
  return checkpoint.pretrained_dir(task)


def validation_maps(workdir: Path, model: Path | None = None) -> Path:
  """The validation split of the data the model in `model` (default: `workdir`) was trained on.

  `<workdir>/synthetic/val` when it exists or the model was trained on synthetic worlds (no data.dir or
  data.cache_dir; then its recipe's validation worlds are generated there first, seeded as training
  generated them), else the `val` folder of the AV2 root its config.json names (`data.dir`), else of the
  folder its cache was built from (`data.cache_dir`, the `source` of the cache's manifest). Raises
  ValueError when none exists.
  """
  import json
  from tdiff_jax import files
  from tdiff_jax.data import batches, synthetic
  own = workdir / "synthetic" / "val"
  if own.is_dir():
    return own
  tried = [str(own)]
  config_file = Path(model or workdir) / "config.json"
  data = json.loads(config_file.read_text()).get("data", {}) if config_file.is_file() else {}
  if data and not data.get("dir") and not data.get("cache_dir") and data.get("synthetic_num"):
    logging.info("generating the validation worlds of %s's synthetic data into %s", model or workdir, own.parent)
    synthetic.generate_dataset(own.parent, data["synthetic_num"], seed=0, splits=("val",))
    return own
  roots = []
  if data.get("dir"):
    roots.append(files.user_path(data["dir"]))
  elif data.get("cache_dir"):
    cache = files.user_path(data["cache_dir"])
    try:
      source = batches.read_manifest(cache).get("source")
    except FileNotFoundError:
      source = None
    if source:
      roots.append(Path(source))
    else:
      tried.append(f"the source of the cache {cache}")
  for root in roots:
    if (root / "val").is_dir():
      return root / "val"
    tried.append(str(root / "val"))
  raise ValueError(f"no validation split of {model or workdir}'s training data found (tried {', '.join(tried)}); "
                   "pass the maps to use (--data, --maps)")


def guidance_params(values: flags.FlagValues):
  """--guidance_weights as `sampling.GuidanceParams` (a scale of all of them is their common factor); a bad
  weight raises ValueError."""
  from tdiff_jax import sampling
  params = sampling.GuidanceParams()
  weights = dict(params.weights)
  for item in values.guidance_weights:
    name, _, value = item.partition("=")
    if name not in weights:
      raise ValueError(f"--guidance_weights: unknown cost {name!r}; choose from {sorted(weights)}")
    try:
      weights[name] = float(value)
    except ValueError:
      raise ValueError(f"--guidance_weights: {item!r} is not cost=weight") from None
    if weights[name] < 0:
      raise ValueError(f"--guidance_weights: {item!r}: a weight must be >= 0")
  return dataclasses.replace(params, weights=weights)
