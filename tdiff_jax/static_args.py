"""Static arguments of jitted calls, hashed once: an `nnx.GraphDef` costs milliseconds to hash.

`jax.jit` hashes every static argument on every call to find the compiled program. A model's
`nnx.GraphDef` recomputes its hash from its whole node list each time (Flax 0.12: 1.4 ms for the
paper's denoiser, 2.3 ms for the CPU default's, on a 2-core Zen 4 AMD EPYC), and a batch-1 sampling
call passes it twice (the map encoding and the sampler): a few percent of a scene's sampling. `hashed`
wraps it in an object whose hash is computed once; `cpu_products.jit` passes the wrapped graphdef to
`jax.jit` and the function sees the graphdef itself, so callers change nothing. `read_once` reads a
model's static settings (e.g. the map encoder's pair radius, which host code needs to pack a batch)
once per graphdef instead of merging the model on every call (5 ms for the paper's denoiser).
"""

from __future__ import annotations

import collections
import threading
from typing import Any, Callable, TypeVar

from flax import nnx

T = TypeVar("T")

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


_SETTINGS: "collections.OrderedDict[tuple[Hashed, Callable], Any]" = collections.OrderedDict()


def read_once(graphdef: nnx.GraphDef, params, read: Callable[[nnx.Module], T]) -> T:
  """`read(nnx.merge(graphdef, params))` for a `read` of the model's static settings (attributes and config,
  not parameter values), merged once per graphdef and `read` (a module-level function: the cache's key)."""
  key = (hashed(graphdef), read)
  with _LOCK:
    if key in _SETTINGS:
      return _SETTINGS[key]
  value = read(nnx.merge(graphdef, params))
  with _LOCK:
    _SETTINGS[key] = value
    while len(_SETTINGS) > _RECENT_SIZE:
      _SETTINGS.popitem(last=False)
  return value
