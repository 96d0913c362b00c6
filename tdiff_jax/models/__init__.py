"""The networks, and building one from a training config.

`create_model(config)` is the one place a config becomes a model (the trainer builds it to train, the
checkpoint loader builds its abstract shape to restore into); `split_model` is the functional split
(`nnx.split` once, then plain pure-dict parameters) every jitted function takes.
"""

from __future__ import annotations

import ml_collections
from flax import nnx

TASKS = ("hl", "infill")


def _hl_denoisers() -> dict:
  """`model.denoiser` -> (config class, module class) of the HL denoisers."""
  from tdiff_jax.models.grounded_denoiser import GroundedConfig, GroundedDenoiser
  from tdiff_jax.models.paper_denoiser import PaperConfig, PaperDenoiser

  return {"paper": (PaperConfig, PaperDenoiser), "grounded": (GroundedConfig, GroundedDenoiser)}


def model_spec(config: ml_collections.ConfigDict):
  """The frozen model dataclass of a training config (`PaperConfig`, `GroundedConfig` by `model.denoiser`,
  or `InfillModelConfig`): fields the `model` block lacks take their defaults."""
  from tdiff_jax.models.infiller import InfillModelConfig

  task = config.get("task", "hl")
  if task == "infill":
    return InfillModelConfig.from_config(config.model)
  if task != "hl":
    raise ValueError(f"config.task={task!r}: choose one of {TASKS}")
  block = config.model.to_dict()
  name = block.pop("denoiser", "paper")
  denoisers = _hl_denoisers()
  if name not in denoisers:
    raise ValueError(f"config.model.denoiser={name!r}: choose one of {tuple(denoisers)}")
  return denoisers[name][0].from_config(block, max_agents=config.data.scene.max_agents)


def _build(config: ml_collections.ConfigDict, rngs: nnx.Rngs) -> nnx.Module:
  from tdiff_jax.models.infiller import Infiller

  spec = model_spec(config)
  if config.get("task", "hl") == "infill":
    return Infiller(spec, rngs=rngs)
  module = {cfg: module for cfg, module in _hl_denoisers().values()}[type(spec)]
  return module(spec, rngs=rngs)


def create_model(config: ml_collections.ConfigDict) -> nnx.Module:
  """The config's network (`config.task`: "hl" the HL denoiser `model.denoiser`, "infill" the infiller),
  seeded by `config.seed`."""
  return _build(config, nnx.Rngs(config.seed))


def abstract_model(config: ml_collections.ConfigDict) -> nnx.Module:
  """`create_model(config)` with shapes in place of values (`nnx.eval_shape`), e.g. a template to load
  parameters into. The generators are an argument of the traced function: built inside it, every draw's
  counter update makes JAX describe the tracer's origin, which doubles the time this takes."""
  return nnx.eval_shape(lambda rngs: _build(config, rngs), nnx.Rngs(config.seed))


def split_model(model: nnx.Module) -> tuple[nnx.GraphDef, dict]:
  """`(graphdef, params)`: the static graph and the parameters as a pure dict pytree."""
  graphdef, state = nnx.split(model)
  return graphdef, nnx.to_pure_dict(state)
