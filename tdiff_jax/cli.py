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
  """--method, --order, --goal_lag, --stride, --solver_steps, --solver_max_noise, --restarts, --restart_steps,
  --final_cost_steps, --eta, --self_condition_max_t, --guidance, --guidance_mode, --guidance_scale,
  --guidance_weights, --autoguidance, --interaction_guidance, --guide_step, --guide_workdir, --lane_pull_m,
  --lane_pull_noise_m, --lane_pull_clearance_m, --lane_pull_end_m, --lane_pull_route_m."""
  from tdiff_jax import sampling  # here: data-only entry points never load the model stack
  flags.DEFINE_enum("method", "auto", ["auto", *sampling.METHODS],
                    "reverse process: ddim (50 calls at stride 10), ddpm (500), dpmpp2m (DPM-Solver++(2M), "
                    "--solver_steps calls); auto: dpmpp2m unguided, ddim guided", flag_values=values)
  flags.DEFINE_integer("stride", 10, "DDIM stride (500/10 = 50 network calls)", lower_bound=1, flag_values=values)
  flags.DEFINE_enum("order", "joint", list(sampling.ORDERS),
                    "joint: both states of every agent together (the paper); staged: initial states first, then "
                    "goals given them (twice the calls; a model trained with model.token_noise=staged)",
                    flag_values=values)
  flags.DEFINE_integer("goal_lag", 0, "joint order: the goals' steps trail the initial states' by this many steps "
                       "(more calls; a model trained with model.token_noise=independent)", lower_bound=0,
                       flag_values=values)
  flags.DEFINE_integer("solver_steps", sampling.DEFAULT_SOLVER_STEPS, "network calls of --method=dpmpp2m",
                       lower_bound=1, flag_values=values)
  flags.DEFINE_float("solver_max_noise", sampling.DEFAULT_SOLVER_MAX_NOISE, "--method=dpmpp2m: the calls after the "
                     "first start at this noise-to-signal ratio (data standard deviations) instead of spreading from "
                     "step T (0: from T, as earlier releases with --solver_steps=15)", lower_bound=0.0,
                     flag_values=values)
  flags.DEFINE_integer("restarts", -1, "restart sampling: the method's last --restart_steps steps run again this many "
                       "times on the sample noised again (-1: auto, 4 for dpmpp2m unguided and for ddim with official "
                       "guidance, the samplers --method=auto picks; 0 otherwise)", lower_bound=-1, flag_values=values)
  flags.DEFINE_integer("restart_steps", 1, "--restarts: how many of the method's last steps each restart runs",
                       lower_bound=1, flag_values=values)
  flags.DEFINE_integer("final_cost_steps", -1, "guided: this many more guidance steps of the costs on the final "
                       "sample (no network call; official guidance's clamped gradient step); -1: auto (5 with "
                       "official guidance, 0 otherwise; no effect without guidance costs)", lower_bound=-1,
                       flag_values=values)
  flags.DEFINE_float("eta", 0.0, "--method=dpmpp2m: fresh noise per step (0: the ODE solver; 1: the SDE one)",
                     lower_bound=0.0, upper_bound=1.0, flag_values=values)
  flags.DEFINE_integer("self_condition_max_t", 50, "a self-conditioned model reads its previous estimate at steps "
                       "t <= this only (500: every step but the first)", lower_bound=0, flag_values=values)
  flags.DEFINE_list("guidance", [], "guidance costs: clearance (centre distance), boxes (type-sized boxes), lane, "
                    "offroad (default: none, as the paper's Table I)", flag_values=values)
  flags.DEFINE_enum("guidance_mode", "official", ["official", "paper"], "guidance variant", flag_values=values)
  flags.DEFINE_float("guidance_scale", 1.0, "guidance scale", lower_bound=0.0, flag_values=values)
  flags.DEFINE_list("guidance_weights", [], "per-cost guidance weights as cost=weight, e.g. offroad=2,boxes=1 (the rest "
                    "keep sampling.GuidanceParams' defaults: clearance 1, boxes 1, lane 0.1, offroad 1)",
                    flag_values=values)
  flags.DEFINE_float("autoguidance", 1.0, "autoguidance weight w >= 1: each prediction is guide + w (model - guide), "
                     "the guide being --guide_step (1: off)", lower_bound=1.0, flag_values=values)
  flags.DEFINE_float("interaction_guidance", 1.0, "interaction guidance weight >= 1: each prediction is alone + w "
                     "(with the others - alone), alone: the agents ignoring each other (1: off)", lower_bound=1.0,
                     flag_values=values)
  flags.DEFINE_integer("guide_step", None, "autoguidance: the checkpoint step of --guide_workdir that guides",
                       lower_bound=0, flag_values=values)
  flags.DEFINE_string("guide_workdir", "", "autoguidance: the guide's training workdir (default: the HL workdir)",
                      flag_values=values)
  flags.DEFINE_float("lane_pull_m", None, "the denoiser's lane pull (model.lane_pull_m; parameter-free, any grounded "
                     "checkpoint with headings): each moving road user's estimate at most this far across a lane "
                     "its heading agrees with is put on that lane's centreline (0: off; default: the checkpoint's)",
                     lower_bound=0.0, flag_values=values)
  flags.DEFINE_float("lane_pull_noise_m", None, "--lane_pull_m only at noise levels of at most this many metres "
                     "(0: every level; default: the checkpoint's)", lower_bound=0.0, flag_values=values)
  flags.DEFINE_float("lane_pull_clearance_m", None, "--lane_pull_m, but not where it would bring two agents' "
                     "initial (or goal) estimates nearer than this many metres (0: always; default: the "
                     "checkpoint's)", lower_bound=0.0, flag_values=values)
  flags.DEFINE_float("lane_pull_end_m", None, "--lane_pull_m, and a moving road user's estimate at most this many "
                     "metres past the end (or before the start) of that lane's centreline is put back on its end "
                     "(0: across only; default: the checkpoint's)", lower_bound=0.0, flag_values=values)
  flags.DEFINE_float("lane_pull_route_m", None, "--lane_pull_m, and a goal estimate at most this many metres "
                     "across a lane its agent's initial lane leads to along the lane graph within 6 s goes onto "
                     "the nearest such lane (needs a checkpoint with model.lane_routes; 0: off; default: the "
                     "checkpoint's)", lower_bound=0.0, flag_values=values)


def sampler_options(values: flags.FlagValues, costs: Sequence[str] | None = None):
  """The options the sampler flags ask for (`costs` in place of --guidance, e.g. for a second row);
  --method=auto resolved (`sampling.resolve_method`). Bad values raise ValueError naming them."""
  from tdiff_jax import sampling
  costs = tuple(values.guidance if costs is None else costs)
  method = sampling.resolve_method(values.method, costs)
  restarts = sampling.resolve_restarts(values.restarts, method, costs, values.order, values.goal_lag,
                                       values.guidance_mode)
  return sampling.SamplerOptions(method=method, stride=values.stride if method == "ddim" else 1,
                                 solver_steps=values.solver_steps, solver_max_noise=values.solver_max_noise,
                                 eta=values.eta, costs=costs,
                                 guidance=values.guidance_mode, self_condition_max_t=values.self_condition_max_t,
                                 autoguidance=values.autoguidance,
                                 interaction_guidance=values.interaction_guidance, order=values.order,
                                 goal_lag=values.goal_lag, restarts=restarts, restart_steps=values.restart_steps,
                                 final_cost_steps=sampling.resolve_final_cost_steps(values.final_cost_steps, costs,
                                                                                    values.guidance_mode))


def model_fields(values: flags.FlagValues) -> dict[str, float]:
  """The parameter-free model fields the flags set (`checkpoint.with_model_fields`): --lane_pull_m,
  --lane_pull_noise_m, --lane_pull_clearance_m, --lane_pull_end_m and --lane_pull_route_m when given."""
  from tdiff_jax.models.hl_denoiser import LANE_PULL_OPTIONS   # here: data-only entry points skip the model
  return {name: values[name].value for name in ("lane_pull_m", *LANE_PULL_OPTIONS) if values[name].value is not None}


def guide_model(values: flags.FlagValues, hl_workdir):
  """The autoguidance guide the flags name (a `checkpoint.LoadedModel`), or None when --autoguidance is 1.
  Raises ValueError when a weight is given without a guide step, or a step without a weight."""
  from tdiff_jax import checkpoint, files
  if values.autoguidance == 1.0:
    if values.guide_step is not None:
      raise ValueError(f"--guide_step={values.guide_step} without --autoguidance > 1 guides nothing")
    return None
  if values.guide_step is None:
    raise ValueError(f"--autoguidance={values.autoguidance} needs a guide: --guide_step (and --guide_workdir)")
  workdir = files.user_path(values.guide_workdir) if values.guide_workdir else hl_workdir
  return checkpoint.load_checkpoint(workdir, task="hl", step=values.guide_step)


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
