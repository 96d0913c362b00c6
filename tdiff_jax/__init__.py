"""tdiff_jax: TrafficDiffuser in JAX/Flax.

The public API (imported lazily, so data-only processes never load the model stack):

Scenes and data
  Scene                  the padded scene contract (`tdiff_jax.datatypes`)
  load_scene             one AV2 scenario folder -> (Scene, SceneInfo)
  BadScenarioError       what a bad scenario raises (names the file and the problem)
  default_data_config    caps and agent-selection rules
  preprocess             AV2 folders -> cache of ArrayRecord shards + manifest
  open_split             a cached split, streamed (checked against the data config)
  load_split             a small cached split in memory
  BatchIterator          deterministic, resumable batches (Grain; a process's share of each batch)
  crop_to_bucket         trim a batch's padding to a size bucket
  sampler_agent_buckets  the agent buckets `sample_grouped` groups a batch by (a config's data section)
  datatypes, geometry    the scene contract's module; planar geometry on scenes (metres)

Diffusion and the HL model
  diffusion              schedules and DDPM/DDIM/DPM-Solver++ updates (pure functions)
  HLDenoiser, HLModelConfig, MapContext
  create_model           a training config's network (HL denoiser or infiller)
  NormStats, hl_loss, normalized_state, denormalize_state

Sampling
  sample                 jit-compiled guided reverse process of the HL model (DDIM, DDPM, DPM-Solver++(2M);
                         inpainting, lane headings)
  sample_grouped         `sample` over a batch of scenes of different sizes: on a CPU each group at its own
                         buckets, the groups side by side on the host's cores; on an accelerator one call
  sample_with            the same reverse process over any denoising function (not jitted)
  encode_maps            a batch's map encodings over each map's valid polygons, shared maps once
  SamplerOptions, GuidanceParams, HLSample
  guidance               guidance costs in metres (clearance, boxes, lane distance, off-road)
  load_checkpoint        a training checkpoint's EMA parameters, statistics and config (`LoadedModel`)
  with_model_fields      a loaded HL checkpoint with parameter-free model fields set (e.g. the lane pull)

Trajectory infilling
  infill                 jit-compiled infiller: every agent's 60-step trajectory between its states
  infill_packed          `infill` over a batch of scenes of different sizes: valid agents and pairs only
  INFILL_MODES           the hard-constraint modes, in mode-id order
  Infiller, InfillModelConfig

Evaluation
  metrics                realism metrics (Table I, both conventions) and ADE/FDE/miss rate (Table II)
  evaluate               module: Table I / Table II for checkpoints on a split (`evaluate.evaluate`,
                         `python -m tdiff_jax.evaluate`)

Training
  train_and_evaluate     the trainer behind `python train.py` (HL model or infiller)
"""

from __future__ import annotations

import importlib

__version__ = "0.1.0"

_EXPORTS = {
    "Scene": "tdiff_jax.datatypes",
    "create_model": "tdiff_jax.models",
    "sample_with": "tdiff_jax.sampling",
    "LoadedModel": "tdiff_jax.checkpoint",
    "load_scene": "tdiff_jax.data.scene_builder",
    "BadScenarioError": "tdiff_jax.data.av2_io",
    "default_data_config": "tdiff_jax.data.config",
    "preprocess": "tdiff_jax.data.preprocess",
    "open_split": "tdiff_jax.data.batches",
    "load_split": "tdiff_jax.data.batches",
    "BatchIterator": "tdiff_jax.data.batches",
    "crop_to_bucket": "tdiff_jax.data.batches",
    "sampler_agent_buckets": "tdiff_jax.data.batches",
    "HLDenoiser": "tdiff_jax.models.hl_denoiser",
    "HLModelConfig": "tdiff_jax.models.hl_denoiser",
    "MapContext": "tdiff_jax.models.map_encoder",
    "NormStats": "tdiff_jax.data.normalize",
    "hl_loss": "tdiff_jax.hl_objective",
    "normalized_state": "tdiff_jax.data.normalize",
    "denormalize_state": "tdiff_jax.data.normalize",
    "train_and_evaluate": "tdiff_jax.train.trainer",
    "sample": "tdiff_jax.sampling",
    "sample_grouped": "tdiff_jax.sampling",
    "encode_maps": "tdiff_jax.sampling",
    "SamplerOptions": "tdiff_jax.sampling",
    "GuidanceParams": "tdiff_jax.sampling",
    "HLSample": "tdiff_jax.sampling",
    "load_checkpoint": "tdiff_jax.checkpoint",
    "with_model_fields": "tdiff_jax.checkpoint",
    "infill": "tdiff_jax.infill",
    "infill_packed": "tdiff_jax.infill",
    "Infiller": "tdiff_jax.models.infiller",
    "InfillModelConfig": "tdiff_jax.models.infiller",
}
_MODULES = {"diffusion": "tdiff_jax.diffusion", "datatypes": "tdiff_jax.datatypes", "geometry": "tdiff_jax.geometry",
            "guidance": "tdiff_jax.guidance", "metrics": "tdiff_jax.metrics", "evaluate": "tdiff_jax.evaluate"}
_ALIASES = {"INFILL_MODES": ("tdiff_jax.models.infiller", "MODES")}

__all__ = sorted(list(_EXPORTS) + list(_MODULES) + list(_ALIASES))


def __getattr__(name: str):
  if name in _MODULES:
    return importlib.import_module(_MODULES[name])
  if name in _ALIASES:
    module, attr = _ALIASES[name]
    return getattr(importlib.import_module(module), attr)
  if name in _EXPORTS:
    module = importlib.import_module(_EXPORTS[name])
    return getattr(module, name)
  raise AttributeError(f"module 'tdiff_jax' has no attribute {name!r}")


def __dir__():
  return __all__
