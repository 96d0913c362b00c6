"""tdiff_jax: TrafficDiffuser in JAX/Flax.

The public API (imported lazily, so data-only processes never load the model stack); everything else
is imported from its submodule (e.g. `tdiff_jax.data.batches`, `tdiff_jax.models.grounded_denoiser`):

Scenes
  Scene                  the padded scene contract (`tdiff_jax.datatypes`)
  load_scene             one AV2 scenario folder -> (Scene, SceneInfo)
  BadScenarioError       what a bad scenario raises (names the file and the problem)
  preprocess             AV2 folders -> cache of ArrayRecord shards + manifest

Trained models
  load_checkpoint        a training checkpoint's EMA parameters, statistics and config (`LoadedModel`)
  pretrained_dir         the folder of the shipped pretrained HL model or infiller (`load_checkpoint` reads it)
  LanePull               the lane pull on the grounded denoiser's estimate, a setting of each call
  train_and_evaluate     the trainer behind `python train.py` (HL model or infiller)

High-level scenarios
  sample                 jit-compiled guided reverse process of the HL model (DDIM, DDPM, DPM-Solver++(2M);
                         inpainting, lane headings)
  sample_with            the same reverse process over any denoising function (not jitted)
  encode_maps            a batch's map encodings, shared maps encoded once
  sampler_batches        scenes cut into batches of one size, padded, as `sample.py` samples them
  sampler_agent_buckets  the agent buckets `sampler_batches` cuts by (a config's data section)
  SamplerOptions, GuidanceParams, HLSample (the command lines' samplers: `sampling.DEFAULT`, `UNGUIDED`, `PAPER`)

Trajectories
  infill                 jit-compiled infiller: every agent's 60-step trajectory between its states
  infill_packed          `infill` over a batch of scenes of different sizes: valid agents and pairs only
  INFILL_MODES           the hard-constraint modes, in mode-id order

Complete scenarios
  sample_complete        sample, infill, and resample the agents whose trajectories overlap or leave the road
  CompleteSample

Scenario specs
  spec                   spec files: load, the exact predicates (`check`), placements, the guidance cost;
                         `generate.generate(..., spec=)` samples to a spec

Evaluation
  metrics                realism metrics (Table I, both conventions) and ADE/FDE/miss rate (Table II)
"""

from __future__ import annotations

import importlib

__version__ = "0.3.0"

_EXPORTS = {
    "Scene": "tdiff_jax.datatypes",
    "load_scene": "tdiff_jax.data.scene_builder",
    "BadScenarioError": "tdiff_jax.data.av2_io",
    "preprocess": "tdiff_jax.data.preprocess",
    "load_checkpoint": "tdiff_jax.checkpoint",
    "LoadedModel": "tdiff_jax.checkpoint",
    "pretrained_dir": "tdiff_jax.checkpoint",
    "LanePull": "tdiff_jax.lane_pull",
    "train_and_evaluate": "tdiff_jax.train.trainer",
    "sample": "tdiff_jax.sampling",
    "sample_with": "tdiff_jax.sampling",
    "encode_maps": "tdiff_jax.sampling",
    "sampler_agent_buckets": "tdiff_jax.data.batches",
    "sampler_batches": "tdiff_jax.data.batches",
    "SamplerOptions": "tdiff_jax.sampling",
    "GuidanceParams": "tdiff_jax.sampling",
    "HLSample": "tdiff_jax.sampling",
    "infill": "tdiff_jax.infilling",
    "infill_packed": "tdiff_jax.infilling",
    "sample_complete": "tdiff_jax.repair",
    "CompleteSample": "tdiff_jax.repair",
}
_MODULES = {"metrics": "tdiff_jax.metrics", "spec": "tdiff_jax.spec"}
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
  raise AttributeError(f"module 'tdiff_jax' has no attribute {name!r}; import it from its submodule")


def __dir__():
  return __all__
