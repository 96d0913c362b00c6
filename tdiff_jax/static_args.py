"""Static arguments of jitted calls, hashed once: an `nnx.GraphDef` costs milliseconds to hash.

`jax.jit` hashes every static argument on every call to find the compiled program. A model's
`nnx.GraphDef` recomputes its hash from its whole node list each time (Flax 0.12: 1.4 ms for the
paper's denoiser, 2.3 ms for the CPU default's, on a 2-core Zen 4 AMD EPYC), and a batch-1 sampling
call passes it twice (the map encoding and the sampler): a few percent of a scene's sampling. `hashed`
wraps it in an object whose hash is computed once; `cpu_products.jit` passes the wrapped graphdef to
`jax.jit` and the function sees the graphdef itself, so callers change nothing.
"""

from __future__ import annotations

import collections
import threading
from typing import Any

# The wrappers of the graphdefs seen lately, by identity: a graphdef is immutable, so one wrapper per
# object serves every call with it. Each entry holds its graphdef, so an id is never reused while cached.
_RECENT: "collections.OrderedDict[int, Hashed]" = collections.OrderedDict()
_RECENT_SIZE = 32
_LOCK = threading.Lock()   # the grouped sampler calls from several host threads


class Hashed:
  """`value` with its hash computed once; equal to another `Hashed` of an equal value."""

  __slots__ = ("value", "_hash")

  def __init__(self, value: Any):
    self.value = value
    self._hash = hash(value)

  def __hash__(self) -> int:
    return self._hash

  def __eq__(self, other: object) -> bool:
    return (isinstance(other, Hashed) and self._hash == other._hash
            and (self.value is other.value or self.value == other.value))

  def __repr__(self) -> str:
    return f"Hashed({type(self.value).__name__})"


def hashed(value: Any) -> Hashed:
  """The `Hashed` wrapper of `value`, the same object for the same `value` while it is among the last
  `_RECENT_SIZE` wrapped (so its hash is computed once, not per call)."""
  with _LOCK:
    wrapper = _RECENT.get(id(value))
    if wrapper is not None and wrapper.value is value:
      _RECENT.move_to_end(id(value))
      return wrapper
  wrapper = Hashed(value)
  with _LOCK:
    _RECENT[id(value)] = wrapper
    while len(_RECENT) > _RECENT_SIZE:
      _RECENT.popitem(last=False)
  return wrapper


def unwrap(value: Any) -> Any:
  """The value a `Hashed` wraps; anything else as it is."""
  return value.value if isinstance(value, Hashed) else value
