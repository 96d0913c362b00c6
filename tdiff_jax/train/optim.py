"""AdamW with warmup + cosine decay, gradient clipping, and weight decay on weight matrices only.

As the official code (minGPT-style groups), weight decay applies to linear kernels (including the
Fourier embeddings' per-input weight matrices) and not to biases, norm scales, embeddings, the map
summary latents, the differential-attention lambdas or the Fourier frequencies. Unlike the official
code, every parameter is optimised (its RMSNorm weights never reached the optimiser).
"""

from __future__ import annotations

import jax
import ml_collections
import optax

DECAYED = ("kernel", "w1", "w2")


def decay_mask(params):
  """A pytree of bools: True where weight decay applies."""
  def is_decayed(path, _):
    last = path[-1]
    name = getattr(last, "key", getattr(last, "name", last))
    return str(name) in DECAYED
  return jax.tree_util.tree_map_with_path(is_decayed, params)


def learning_rate_schedule(c: ml_collections.ConfigDict) -> optax.Schedule:
  return optax.warmup_cosine_decay_schedule(
      init_value=0.0, peak_value=c.lr, warmup_steps=max(int(c.warmup_steps), 1),
      decay_steps=max(int(c.num_steps), int(c.warmup_steps) + 1), end_value=c.lr * c.min_lr_ratio)


def make_optimizer(c: ml_collections.ConfigDict, skip_nonfinite: bool = True) -> optax.GradientTransformation:
  """`c` is the `train` config block. With `skip_nonfinite`, a step whose gradient is not finite
  changes neither the parameters nor the optimiser state (`optax.apply_if_finite`; its state's
  `last_finite` says which happened). Training stops at the next log line after such a step."""
  inner = optax.chain(
      optax.clip_by_global_norm(c.grad_clip),
      optax.adamw(learning_rate_schedule(c), b1=0.9, b2=0.999, weight_decay=c.weight_decay, mask=decay_mask),
  )
  return optax.apply_if_finite(inner, max_consecutive_errors=1 << 30) if skip_nonfinite else inner
