"""The sampler's command-line flags, shared by `sample.py` and `python -m tdiff_jax.evaluate`: which models,
which sampler (`sampling.DEFAULT` at the flags' defaults), which guidance weights and repair rounds."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

from absl import flags, logging

from tdiff_jax import checkpoint, files, repair, sampling


def define_sampler_flags(values: flags.FlagValues) -> None:
  """--method, --steps, --guidance, --guidance_mode, --guidance_weights, --repair_rounds, --lane_pull_m."""
  flags.DEFINE_enum("method", "auto", ["auto", *sampling.METHODS],
                    "reverse process: ddim (50 calls at stride 10), ddpm (every step), dpmpp2m (DPM-Solver++(2M)); "
                    "auto: dpmpp2m unguided, ddim guided", flag_values=values)
  flags.DEFINE_integer("steps", 0, "network calls of --method=ddim or dpmpp2m (0: the method's default, "
                       f"ddim stride {sampling.PAPER.stride}, dpmpp2m {sampling.UNGUIDED.solver_steps})", lower_bound=0,
                       flag_values=values)
  flags.DEFINE_list("guidance", list(sampling.DEFAULT.costs), "guidance costs: clearance (centre distance), boxes "
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
  model of `num_steps` diffusion steps: `sampling.DEFAULT` at the flags' defaults, `sampling.UNGUIDED` with
  --guidance=; --method=auto picks the preset's method, and another method or guidance mode keeps the
  preset's calls but not its restarts and final cost steps (measured for the presets only)."""
  costs = tuple(values.guidance if costs is None else costs)
  preset = sampling.DEFAULT if costs else sampling.UNGUIDED
  method = preset.method if values.method == "auto" else values.method
  official = values.guidance_mode == "official"
  calls = values.steps
  by_method = {"ddim": dict(stride=max(1, num_steps // calls) if calls else sampling.PAPER.stride),
               "dpmpp2m": dict(stride=1, solver_steps=calls or sampling.UNGUIDED.solver_steps,
                               solver_max_noise=sampling.UNGUIDED.solver_max_noise),
               "ddpm": dict(stride=1)}[method]
  measured = method == preset.method and (official or not costs)
  return sampling.SamplerOptions(method=method, costs=costs, guidance=values.guidance_mode,
                                 restarts=preset.restarts if measured else 0,
                                 final_cost_steps=sampling.DEFAULT.final_cost_steps if costs and official else 0,
                                 **by_method)


def diffusion_steps(workdir) -> int:
  """The diffusion steps T of the model in `workdir`, from the record of the checkpoint (or exported model)
  that sampling loads, never from an editable config.json beside it. Raises ValueError when it has none."""
  try:
    return int(checkpoint.load_record(workdir)["config"]["diffusion"]["num_steps"])
  except (KeyError, TypeError) as e:
    raise ValueError(f"{workdir}: the model's record names no diffusion.num_steps ({e})") from None


def model_dir(values: flags.FlagValues, name: str, task: str) -> Path | None:
  """Where the `task` model of the workdir flag `name` is loaded from: None for ''; the folder itself when
  it holds a checkpoint; at the flag's default location without one, the pretrained model shipped with
  the package (`checkpoint.pretrained_dir`). A folder given on the command line without a checkpoint
  raises FileNotFoundError saying how to train one."""
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


def guidance_params(values: flags.FlagValues):
  """--guidance_weights as `sampling.GuidanceParams` (a scale of all of them is their common factor); a bad
  weight raises ValueError."""
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
