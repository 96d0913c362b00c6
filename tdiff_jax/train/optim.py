"""AdamW with warmup + cosine decay, gradient clipping, and weight decay on weight matrices only.

As the official code (minGPT-style groups), weight decay applies to linear kernels (including the
Fourier embeddings' per-input weight matrices) and not to biases, norm scales, embeddings, the map
summary latents, the differential-attention lambdas or the Fourier frequencies. Unlike the official
code, every parameter is optimised (its RMSNorm weights never reached the optimiser).

Training keeps every parameter in one vector (`FlatParams`): the optimiser, gradient clipping and EMA
then update one array per step instead of one per parameter (270 for the default model), which takes
a third off the train step's compile time (each per-parameter update is its own fused kernel for XLA)
and a few percent off its run time. The math is the same; checkpoints keep the parameter pytrees
(`flatten_state` / `unflatten_state` convert).

Frozen modules (`train.freeze_map_inputs`, beyond the paper): the
parameters under the named paths keep their initial values. The train step stops their gradient (so
their backward pass is not computed, `frozen_params`), and keeps their values and EMA (`keep_frozen`;
no weight decay either).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from jax.flatten_util import ravel_pytree

DECAYED = ("kernel", "w1", "w2")


# The map encoder's input side (`train.freeze_map_inputs`): the point and polygon input embeddings, the
# point -> polygon relations and attention, and the polygon -> polygon relation embedding (relative geometry
# and topology edge type): most of its work. Its polygon -> polygon attention and map summary still train.
MAP_INPUT_MODULES = tuple(f"map_encoder/{name}" for name in (
    "pt_input", "pt_type", "pt_side", "pl_input", "pl_type", "pl_intersection", "r_pt2pl", "pt2pl", "r_pl2pl",
    "edge_type"))


def frozen_modules(c: ml_collections.ConfigDict) -> tuple[str, ...]:
  """The parameter paths (`module/submodule`, each covering every parameter under it) whose parameters
  training keeps at their initial values (`c`: the train block)."""
  return MAP_INPUT_MODULES if c.get("freeze_map_inputs", False) else ()


def _key_name(key) -> str:
  """One entry of a pytree path (dict key, attribute or sequence index) as text."""
  return str(getattr(key, "key", getattr(key, "name", getattr(key, "idx", key))))


def _path_name(path) -> str:
  return "/".join(_key_name(k) for k in path)


def _is_frozen(path, modules: tuple[str, ...]) -> bool:
  name = _path_name(path)
  return any(name == m or name.startswith(m + "/") for m in modules)


def frozen_mask(params, modules: tuple[str, ...]):
  """A pytree of bools: True for the leaves under the paths `modules`."""
  return jax.tree_util.tree_map_with_path(lambda path, _: _is_frozen(path, modules), params)


def frozen_params(params, modules: tuple[str, ...]):
  """`params` with the gradient of the `modules`' leaves stopped: no backward pass through them."""
  if not modules:
    return params
  return jax.tree_util.tree_map_with_path(
      lambda path, x: jax.lax.stop_gradient(x) if _is_frozen(path, modules) else x, params)


def keep_frozen(new, old, modules: tuple[str, ...], flat: "FlatParams | None" = None):
  """`new` parameters (a pytree, or with `flat` its vector) with the `modules`' leaves taken from `old`:
  their gradient is zero, but weight decay and the EMA's rounding would still move them."""
  if not modules:
    return new
  if flat is not None:
    if not flat.leaf_frozen.any():
      raise ValueError(f"frozen modules {modules}, but the flat layout freezes none: FlatParams.of(params, {modules})")
    return jnp.where(flat.trainable_multiplier() > 0, new, old)
  return jax.tree_util.tree_map_with_path(lambda path, n, o: o if _is_frozen(path, modules) else n, new, old)


def decay_mask(params):
  """A pytree of bools: True where weight decay applies."""
  return jax.tree_util.tree_map_with_path(lambda path, _: _key_name(path[-1]) in DECAYED, params)


@dataclasses.dataclass(frozen=True)
class FlatParams:
  """The layout of a parameter pytree as one vector `[N]` (leaves in `jax.tree_util` order)."""

  treedef: Any
  unravel: Callable[[jax.Array], Any]   # [N] -> the parameter pytree
  leaf_ends: np.ndarray                 # [L] end offset of each leaf in the vector
  leaf_decayed: np.ndarray              # [L] bool: weight decay applies to the leaf (`decay_mask`)
  leaf_frozen: np.ndarray               # [L] bool: the leaf is frozen (`frozen_mask`)

  @classmethod
  def of(cls, params, frozen: tuple[str, ...] = ()) -> "FlatParams":
    """The layout of `params`; `frozen`: parameter paths whose leaves the train step keeps (`keep_frozen`)."""
    _, unravel = ravel_pytree(params)
    leaves = jax.tree_util.tree_leaves(params)
    return cls(jax.tree_util.tree_structure(params), unravel, np.cumsum([x.size for x in leaves]),
               np.array(jax.tree_util.tree_leaves(decay_mask(params)), bool),
               np.array(jax.tree_util.tree_leaves(frozen_mask(params, frozen)), bool))

  @property
  def size(self) -> int:
    return int(self.leaf_ends[-1])

  def ravel(self, params) -> jax.Array:
    return ravel_pytree(params)[0]

  def _per_element(self, per_leaf: np.ndarray) -> jax.Array:
    """`[N]` the leaf's value of `per_leaf` `[L]` at each element: one fill per run of consecutive leaves
    with the same value, concatenated (computed in the step, not a constant of N floats; a search of
    each element's leaf took 8 ms of a CPU train step per call)."""
    values = np.asarray(per_leaf, np.float32)
    last_of_run = np.append(np.flatnonzero(values[1:] != values[:-1]), len(values) - 1)
    run_ends = self.leaf_ends[last_of_run]
    run_starts = np.concatenate([[0], run_ends[:-1]])
    return jnp.concatenate([jnp.full((int(end - start),), values[i], jnp.float32)
                            for i, start, end in zip(last_of_run, run_starts, run_ends)])

  def decay_multiplier(self) -> jax.Array:
    """`[N]` 1.0 where weight decay applies, else 0.0."""
    return self._per_element(self.leaf_decayed)

  def trainable_multiplier(self) -> jax.Array:
    """`[N]` 0.0 where the parameter is frozen, else 1.0."""
    return self._per_element(~self.leaf_frozen)

  def is_params(self, tree) -> bool:
    return jax.tree_util.tree_structure(tree) == self.treedef


def flatten_state(state, flat: FlatParams):
  """`state` (e.g. a train state) with every subtree shaped like the parameters (params, EMA, Adam's
  moments) as one vector `[N]`; the optimiser state is then `make_optimizer(c, flat=flat)`'s."""
  return jax.tree_util.tree_map(lambda x: flat.ravel(x) if flat.is_params(x) else x, state, is_leaf=flat.is_params)


def unflatten_state(flat_state, template, flat: FlatParams):
  """The inverse of `flatten_state`: `template` (arrays or shapes) gives the pytree form."""
  return jax.tree_util.tree_map(lambda t, x: flat.unravel(x) if flat.is_params(t) else x, template, flat_state,
                                is_leaf=flat.is_params)


def learning_rate_schedule(c: ml_collections.ConfigDict) -> optax.Schedule:
  return optax.warmup_cosine_decay_schedule(
      init_value=0.0, peak_value=c.lr, warmup_steps=max(int(c.warmup_steps), 1),
      decay_steps=max(int(c.num_steps), int(c.warmup_steps) + 1), end_value=c.lr * c.min_lr_ratio)


def make_optimizer(c: ml_collections.ConfigDict, skip_nonfinite: bool = True,
                   flat: FlatParams | None = None) -> optax.GradientTransformation:
  """`c` is the `train` config block. With `skip_nonfinite`, a step whose gradient is not finite
  changes neither the parameters nor the optimiser state (`optax.apply_if_finite`; its state's
  `last_finite` says which happened). Training stops at the next log line after such a step.

  With `flat`, the optimiser of the parameters as one vector (`FlatParams`): the same update, and a
  state of the same structure with each parameter-shaped subtree a vector (`flatten_state`). Frozen
  parameters are the train step's to hold (`keep_frozen`), so that the state's structure does not
  depend on them."""
  schedule = learning_rate_schedule(c)
  if flat is None:
    adamw = optax.adamw(schedule, b1=0.9, b2=0.999, weight_decay=c.weight_decay, mask=decay_mask)
  else:  # optax.adamw's chain, the decay mask applied element by element
    wd = float(c.weight_decay)
    decay = optax.GradientTransformation(lambda params: optax.EmptyState(),
                                         lambda u, state, p: (u + wd * flat.decay_multiplier() * p, state))
    adamw = optax.chain(optax.scale_by_adam(b1=0.9, b2=0.999), optax.masked(decay, True),
                        optax.scale_by_learning_rate(schedule))
  inner = optax.chain(optax.clip_by_global_norm(c.grad_clip), adamw)
  return optax.apply_if_finite(inner, max_consecutive_errors=1 << 30) if skip_nonfinite else inner
