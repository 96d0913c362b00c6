"""Building a model's frozen config dataclass from the `model` block of an ml_collections config."""

from __future__ import annotations

import dataclasses

import ml_collections


def from_config(cls, c: ml_collections.ConfigDict, **fixed):
  """`cls(**c, **fixed)`; a field of `c` that `cls` does not have (a typo) is a ValueError naming it.

  `fixed` are fields set by the caller, not by the config block (e.g. the HL model's `max_agents`).
  """
  fields = {f.name for f in dataclasses.fields(cls)} - set(fixed)
  unknown = set(c.keys()) - fields
  if unknown:
    raise ValueError(f"model config: unknown fields {sorted(unknown)}")
  return cls(**{k: c[k] for k in c.keys()}, **fixed)
