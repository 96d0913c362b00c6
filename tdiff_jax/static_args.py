"""A model's static settings (attributes and config, not parameter values), read once per graphdef.

Host code needs some of them before a jitted call (e.g. the map encoder's pair radius, to pack a
batch); merging the model to read them costs milliseconds (5 ms for the paper's denoiser), so
`read_once` keeps the answer per graphdef object.
"""

from __future__ import annotations

import collections
from typing import Any, Callable, TypeVar

from flax import nnx

T = TypeVar("T")

# (graphdef, read) -> value, by the graphdef's identity; each entry holds its graphdef, so an id is never
# reused while cached.
_SETTINGS: "collections.OrderedDict[tuple[int, Callable], tuple[nnx.GraphDef, Any]]" = collections.OrderedDict()
_SIZE = 32


def read_once(graphdef: nnx.GraphDef, params, read: Callable[[nnx.Module], T]) -> T:
  """`read(nnx.merge(graphdef, params))` for a `read` of the model's static settings, merged once per
  graphdef object and `read` (a module-level function: the cache's key)."""
  key = (id(graphdef), read)
  hit = _SETTINGS.get(key)
  if hit is not None and hit[0] is graphdef:
    return hit[1]
  value = read(nnx.merge(graphdef, params))
  _SETTINGS[key] = (graphdef, value)
  while len(_SETTINGS) > _SIZE:
    _SETTINGS.popitem(last=False)
  return value
