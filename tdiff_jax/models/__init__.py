"""The networks, and building one from a training config.

`create_model(config)` is the one place a config becomes a model (the trainer builds it to train, the
checkpoint loader builds its abstract shape to restore into); `split_model` is the functional split
(`nnx.split` once, then plain pure-dict parameters) every jitted function takes.
"""

from __future__ import annotations

import ml_collections
from flax import nnx

TASKS = ("hl", "infill")


def model_spec(config: ml_collections.ConfigDict):
  """The frozen model dataclass of a training config (`HLModelConfig` or `InfillModelConfig`): fields
  the `model` block lacks (a config written before they existed) take their defaults."""
  from tdiff_jax.models.hl_denoiser import HLModelConfig
  from tdiff_jax.models.infiller import InfillModelConfig

  task = config.get("task", "hl")
  if task == "infill":
    return InfillModelConfig.from_config(config.model)
  if task != "hl":
    raise ValueError(f"config.task={task!r}: choose one of {TASKS}")
  return HLModelConfig.from_config(config.model, max_agents=config.data.scene.max_agents)


def create_model(config: ml_collections.ConfigDict) -> nnx.Module:
  """The config's network (`config.task`: "hl" the HL denoiser, "infill" the infiller), seeded by `config.seed`."""
  from tdiff_jax.models.hl_denoiser import HLDenoiser
  from tdiff_jax.models.infiller import Infiller

  model = Infiller if config.get("task", "hl") == "infill" else HLDenoiser
  return model(model_spec(config), rngs=nnx.Rngs(config.seed))


def split_model(model: nnx.Module) -> tuple[nnx.GraphDef, dict]:
  """`(graphdef, params)`: the static graph and the parameters as a pure dict pytree."""
  graphdef, state = nnx.split(model)
  return graphdef, nnx.to_pure_dict(state)
