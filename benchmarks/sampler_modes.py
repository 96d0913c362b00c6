"""The sampler modes of the sampling benchmarks, their official figures and targets, and the varied set's batches.

Shared by `benchmarks/sampling.py` and `benchmarks/agent_buckets.py`.
"""

from __future__ import annotations

import scene_set
from tdiff_jax import datatypes, sampling

MODES = {"ddim50": sampling.SamplerOptions("ddim", 10),
         "ddim50_guided": sampling.SamplerOptions("ddim", 10, ("clearance", "lane", "offroad")),
         "ddpm500": sampling.SamplerOptions("ddpm", 1),
         "dpmpp2m15": sampling.SamplerOptions("dpmpp2m", solver_steps=15),
         # The command lines' unguided default of earlier releases: 15 solver calls and 4 restarts of the last (19).
         "dpmpp2m15r4": sampling.SamplerOptions("dpmpp2m", solver_steps=15, restarts=4),
         # The command lines' unguided default: the same low-noise steps without the four calls above noise 12
         # (T is at 584): 11 calls and 4 restarts (15).
         "dpmpp2m11n12r4": sampling.SamplerOptions("dpmpp2m", solver_steps=11, solver_max_noise=12.0, restarts=4),
         # Two 12-call variants of it (README, "Samplers"): 8 solver calls and 4 restarts, or 11 and 1 restart.
         "dpmpp2m8n12r4": sampling.SamplerOptions("dpmpp2m", solver_steps=8, solver_max_noise=12.0, restarts=4),
         "dpmpp2m11n12r1": sampling.SamplerOptions("dpmpp2m", solver_steps=11, solver_max_noise=12.0, restarts=1),
         # The previous guided default: DDIM-50 and 4 restarts of its last call (54 calls).
         "ddim50r4_guided": sampling.SamplerOptions("ddim", 10, ("clearance", "lane", "offroad"), restarts=4),
         # The command lines' guided default: the same and 5 final cost steps (54 calls).
         "ddim50r4f5_guided": sampling.SamplerOptions("ddim", 10, ("clearance", "lane", "offroad"), restarts=4,
                                                      final_cost_steps=sampling.DEFAULT_FINAL_COST_STEPS)}
# Official scenes/s on a 2-core CPU (README, Benchmarks) and the targets, by (mode, batch size).
# DDPM-500 was timed on the 3 real scenes of tests/data; the few-step solvers are held to the official DDIM-50
# (10x), the guided defaults to the official guided DDIM-50 (4x).
FEW_STEP = ("dpmpp2m15", "dpmpp2m15r4", "dpmpp2m11n12r4", "dpmpp2m8n12r4", "dpmpp2m11n12r1")
GUIDED_DEFAULTS = ("ddim50r4_guided", "ddim50r4f5_guided")
OFFICIAL = {("ddim50", 1): 4.11, ("ddim50", 8): 6.34, ("ddim50_guided", 8): 4.56, ("ddpm500", 8): 0.81,
            **{(m, b): {1: 4.11, 8: 6.34}[b] for m in FEW_STEP for b in (1, 8)},
            **{(m, 8): 4.56 for m in GUIDED_DEFAULTS}}
TARGET_RATIO = {"ddim50": 5.0, "ddim50_guided": 4.0, "ddpm500": 5.0, **{m: 10.0 for m in FEW_STEP},
                **{m: 4.0 for m in GUIDED_DEFAULTS}}


def batches_of(scenes: list[datatypes.Scene], batch_size: int, varied: bool = True) -> list[list[datatypes.Scene]]:
  if not varied:  # the real scenes: each alone, or one batch of them repeated, each copy's map encoded
    return [[s] for s in scenes] if batch_size == 1 else [scene_set.repeated(scenes, batch_size, distinct_maps=True)]
  if batch_size == 1:
    return [[s] for s in scenes]
  if batch_size == 8:
    return [[scenes[i] for i in idx] for idx in scene_set.BATCHES_OF_8]
  return [[scenes[(k + i) % len(scenes)] for i in range(batch_size)] for k in range(0, len(scenes), batch_size)]


def sampled_shapes(b: datatypes.Scene, a_buckets, p_buckets, grouped: bool) -> list[tuple[int, int, int]]:
  """(scenes, agents, polygons) of each `sample` call a batch takes: one padded call, or one per agent
  bucket (`sampling.sample_grouped`: 1, 2, 4, 8 ... scenes, at the group's polygon bucket)."""
  if not grouped:
    return [(b.agent_valid.shape[0], b.num_agents, b.num_polygons)]
  return [(len(g.indices), g.num_agents, g.num_polygons)
          for g in sampling.scene_groups(b.agent_valid, a_buckets, b.pl_valid, p_buckets)]
