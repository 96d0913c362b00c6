"""The networks, and building one from a training config.

`create_model(config)` is the one place a config becomes a model (the trainer builds it to train, the
checkpoint loader builds its abstract shape to restore into); `split_model` is the functional split
(`nnx.split` once, then plain pure-dict parameters) every jitted function takes.
"""

from __future__ import annotations

import ml_collections
from flax import nnx

TASKS = ("hl", "infill")


def create_model(config: ml_collections.ConfigDict) -> nnx.Module:
  """The config's network (`config.task`: "hl" the HL denoiser, "infill" the infiller), seeded by `config.seed`."""
  from tdiff_jax.models.hl_denoiser import HLDenoiser, HLModelConfig
  from tdiff_jax.models.infiller import InfillModelConfig, Infiller

  task = config.get("task", "hl")
  if task == "infill":
    return Infiller(InfillModelConfig.from_config(config.model), rngs=nnx.Rngs(config.seed))
  if task != "hl":
    raise ValueError(f"config.task={task!r}: choose one of {TASKS}")
  cfg = HLModelConfig.from_config(config.model, max_agents=config.data.scene.max_agents)
  return HLDenoiser(cfg, rngs=nnx.Rngs(config.seed))


def split_model(model: nnx.Module) -> tuple[nnx.GraphDef, dict]:
  """`(graphdef, params)`: the static graph and the parameters as a pure dict pytree."""
  graphdef, state = nnx.split(model)
  return graphdef, nnx.to_pure_dict(state)
