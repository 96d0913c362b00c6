"""The command-line conventions of every entry point: absl flags, and the sampler's options in one place.

Library modules with a command line (`python -m tdiff_jax.evaluate`, `...map_diagnostics`, `...animate`,
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

from typing import Callable, Sequence

from absl import app, flags

DefineFn = Callable[[flags.FlagValues], None]
RunFn = Callable[[flags.FlagValues, list[str]], None]

# A seed's range: `jax.random.key` reads only its low 32 bits (seeds that differ above would draw the same).
MAX_SEED = 2**32 - 1


def define_seed_flag(values: flags.FlagValues) -> None:
  flags.DEFINE_integer("seed", 0, f"random seed (0 to {MAX_SEED})", lower_bound=0, upper_bound=MAX_SEED,
                       flag_values=values)


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
  """--method, --steps, --guidance, --guidance_mode, --guidance_scale, --guidance_weights, --lane_pull_m."""
  from tdiff_jax import sampling  # here: data-only entry points never load the model stack
  flags.DEFINE_enum("method", "auto", ["auto", *sampling.METHODS],
                    "reverse process: ddim (50 calls at stride 10), ddpm (every step), dpmpp2m (DPM-Solver++(2M)); "
                    "auto: dpmpp2m unguided, ddim guided", flag_values=values)
  flags.DEFINE_integer("steps", 0, "network calls of --method=ddim or dpmpp2m (0: the method's default, "
                       f"ddim stride {sampling.DEFAULT_DDIM_STRIDE}, dpmpp2m {sampling.DEFAULT_SOLVER_STEPS})", lower_bound=0,
                       flag_values=values)
  flags.DEFINE_list("guidance", [], "guidance costs: clearance (centre distance), boxes (type-sized boxes), lane, "
                    "offroad (default: none, as the paper's Table I)", flag_values=values)
  flags.DEFINE_enum("guidance_mode", "official", ["official", "paper"], "guidance variant: the official code's "
                    "clamped step on x0, or the paper's eq. 3", flag_values=values)
  flags.DEFINE_float("guidance_scale", 1.0, "guidance scale", lower_bound=0.0, flag_values=values)
  flags.DEFINE_list("guidance_weights", [], "per-cost guidance weights as cost=weight, e.g. offroad=2,boxes=1 (the rest "
                    "keep sampling.GuidanceParams' defaults: clearance 1, boxes 1, lane 0.1, offroad 1)",
                    flag_values=values)
  flags.DEFINE_float("lane_pull_m", None, "the denoiser's lane pull (model.lane_pull_m; parameter-free, any grounded "
                     "checkpoint with headings): each moving road user's estimate at most this far across a lane "
                     "its heading agrees with is put on that lane's centreline (0: off; default: the checkpoint's)",
                     lower_bound=0.0, flag_values=values)


def sampler_options(values: flags.FlagValues, costs: Sequence[str] | None = None, num_steps: int = 500):
  """The options the sampler flags ask for (`costs` in place of --guidance, e.g. for a second row), for a
  model of `num_steps` diffusion steps; --method=auto resolved (`sampling.resolve_method`), restarts and
  final cost steps the measured defaults (`sampling.default_restarts`, `default_final_cost_steps`)."""
  from tdiff_jax import sampling
  costs = tuple(values.guidance if costs is None else costs)
  method = sampling.resolve_method(values.method, costs)
  calls = values.steps
  if method == "ddim":
    stride = max(1, num_steps // calls) if calls else sampling.DEFAULT_DDIM_STRIDE
    return sampling.SamplerOptions(method="ddim", stride=stride, costs=costs, guidance=values.guidance_mode,
                                   restarts=sampling.default_restarts(method, costs, values.guidance_mode),
                                   final_cost_steps=sampling.default_final_cost_steps(costs, values.guidance_mode))
  solver = dict(solver_steps=calls or sampling.DEFAULT_SOLVER_STEPS,
                solver_max_noise=sampling.DEFAULT_SOLVER_MAX_NOISE) if method == "dpmpp2m" else {}
  return sampling.SamplerOptions(method=method, stride=1, costs=costs, guidance=values.guidance_mode,
                                 restarts=sampling.default_restarts(method, costs, values.guidance_mode),
                                 final_cost_steps=sampling.default_final_cost_steps(costs, values.guidance_mode),
                                 **solver)


def diffusion_steps(workdir) -> int:
  """The diffusion steps T of the model trained in `workdir` (its config.json; 500, the paper's, without one)."""
  import json
  from pathlib import Path
  try:
    return int(json.loads((Path(workdir) / "config.json").read_text())["diffusion"]["num_steps"])
  except (OSError, ValueError, KeyError, TypeError):
    return 500


def model_fields(values: flags.FlagValues) -> dict[str, float]:
  """The parameter-free model fields the flags set (`checkpoint.with_model_fields`): --lane_pull_m when given."""
  return {} if values.lane_pull_m is None else {"lane_pull_m": values.lane_pull_m}


def guidance_params(values: flags.FlagValues):
  """--guidance_scale and --guidance_weights as `sampling.GuidanceParams`; a bad weight raises ValueError."""
  from tdiff_jax import sampling
  params = sampling.GuidanceParams(scale=values.guidance_scale)
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
