"""How XLA compiles the samplers' and the infiller's matrix products on a CPU: its own kernels, not YNNPACK's.

XLA's CPU compiler hands each matrix product to the YNNPACK library by default
(`xla_cpu_experimental_ynn_fusion_type`). A sampler's products are small and their weights are arguments
of the call, not constants, so the library repacks every weight matrix on every call; XLA's own kernels
run them about twice as fast (docs/benchmarks.md). `COMPILER_OPTIONS` turns the library's fusions off for
the functions compiled with `jit(fun, ...)` here: `sampling.sample`, `infilling.infill` /
`infill_errors`, the map encodings of both, and the HL model's train step
(`trainer.training_compiler_options`). JAX accepts compiler options on top-level calls only, so `jit`
compiles such a function twice: with the options when it is called at the top level, without them inside
a caller's `jax.jit`, `jax.vmap` or `jax.grad` (whose own options then apply). Only XLA's CPU compiler
reads the option; other backends accept and ignore it.

`TDIFF_JAX_YNN_PRODUCTS=1` in the environment, read at import, keeps XLA's default everywhere (for
measuring the difference, `benchmarks/*.py`). Results differ from the default's by float rounding only.
"""

from __future__ import annotations

import functools
import os

import jax

SWITCH = "TDIFF_JAX_YNN_PRODUCTS"   # "1": XLA's default (YNNPACK's products)

# No library fusion types: products and elementwise operations through XLA's own emitters (a `jax.jit`
# option is parsed as XLA parses the flag of the same name).
COMPILER_OPTIONS: dict[str, str] | None = (
    None if os.environ.get(SWITCH, "0") == "1" else {"xla_cpu_experimental_ynn_fusion_type": ""})


def _at_top_level(args, kwargs) -> bool:
  """Whether a call happens outside any JAX transformation: no argument is a tracer. (A call inside a
  caller's trace whose arguments are all concrete takes the top-level program, and JAX refuses its
  compiler options there with an error naming them: pass an argument, e.g. the params, through the trace.)"""
  return not any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves((args, kwargs)))


class jit:  # noqa: N801  (used as a decorator, like jax.jit)
  """`jax.jit(fun, **jit_kwargs)` compiled with `COMPILER_OPTIONS` at the top level, plainly when traced by
  a caller (JAX allows compiler options on top-level calls only). `lower` is the top-level function's;
  `__wrapped__` is `fun`."""

  def __init__(self, fun, **jit_kwargs):
    self._traced = jax.jit(fun, **jit_kwargs)
    self._top = self._traced if COMPILER_OPTIONS is None else jax.jit(fun, compiler_options=COMPILER_OPTIONS,
                                                                        **jit_kwargs)
    functools.update_wrapper(self, fun)

  def __call__(self, *args, **kwargs):
    return (self._top if _at_top_level(args, kwargs) else self._traced)(*args, **kwargs)

  def lower(self, *args, **kwargs):
    return self._top.lower(*args, **kwargs)
