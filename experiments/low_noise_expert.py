"""Table I of an HL checkpoint whose lowest noise levels are denoised by a second checkpoint (an expert).

  python experiments/low_noise_expert.py EXPERT_WORKDIR SWITCH_T [evaluate flags...]

e.g. `python experiments/low_noise_expert.py W 30 --hl_workdir=workdirs/hl --infill_workdir=`: every
sampler call runs the `--hl_workdir` checkpoint's denoiser for t > SWITCH_T and the EXPERT_WORKDIR
checkpoint's (same architecture; e.g. the base fine-tuned with `train.max_t=SWITCH_T`) for t <= SWITCH_T,
each with its own map encoding, then prints `python -m tdiff_jax.evaluate`'s tables
(docs/learning_the_map.md). An experiment, not part of the library: it swaps `sampling.sample` for the
two-network version while `evaluate` runs, and computes both denoisers at every step.
"""

from __future__ import annotations

import functools
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
from flax import nnx

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tdiff_jax import checkpoint, evaluate, sampling  # noqa: E402


def two_network_sample(expert_params, switch_t: int):
  """A drop-in for `sampling.sample` (the same signature) that hands t <= `switch_t` to the expert."""

  @functools.partial(jax.jit, static_argnames=("graphdef", "options", "custom_cost"))
  def sample(graphdef, params, scene, norm, sched, key, options=sampling.SamplerOptions(), guidance_params=None,
             fixed_state=None, fixed_mask=None, custom_cost=None, map_context=None, map_geometry=None,
             guide_params=None, guide_map_context=None):
    if guide_params is not None:
      raise ValueError("low_noise_expert.py: written without autoguidance")
    base, expert = nnx.merge(graphdef, params), nnx.merge(graphdef, expert_params)
    if base.cfg.self_condition:  # its denoise_fn passes no previous estimate: the sample would silently differ
      raise ValueError("low_noise_expert.py: written for checkpoints without model.self_condition")
    ctx_base = base.encode_map(scene, norm, map_context=map_context)
    ctx_expert = expert.encode_map(scene, norm)

    def denoise_fn(x, t):  # x [B, A, 2, F], t [B]
      args = (x, sched.betas[t], sched.alpha_bars[t], scene.agent_type, scene.agent_valid)
      low = jnp.asarray(t).reshape(-1, 1, 1, 1) <= switch_t
      return jnp.where(low, expert.denoise(ctx_expert, *args)[0], base.denoise(ctx_base, *args)[0])

    return sampling.sample_with(denoise_fn, scene, norm, sched, key, options, guidance_params, fixed_state,
                                fixed_mask, custom_cost, map_geometry)

  return sample


def main(argv: list[str]) -> None:
  if len(argv) < 2:
    raise SystemExit(__doc__)
  expert = checkpoint.load_checkpoint(argv[0], task="hl")
  sampling.sample = two_network_sample(expert.params, int(argv[1]))   # what sample_grouped calls
  evaluate.main(argv[2:])


if __name__ == "__main__":
  main(sys.argv[1:])
