"""Building a model's frozen config dataclass from the `model` block of an ml_collections config."""

from __future__ import annotations

import dataclasses

import ml_collections


def from_config(cls, c: ml_collections.ConfigDict, removed: dict | None = None, moved: tuple[str, ...] = (),
                **fixed):
  """`cls(**c, **fixed)`; a field of `c` that `cls` does not have (a typo) is a ValueError naming it.

  `fixed` are fields set by the caller, not by the config block (e.g. the HL model's `max_agents`).
  `removed`: fields the model no longer has and the value that left them off (an older checkpoint's
  config holds them): at that value they are dropped, at another a ValueError names them. `moved`: fields
  an older config holds that are read elsewhere now (e.g. the lane pull's), dropped here.
  """
  removed = removed or {}
  used = [f"model.{k}={c[k]!r}" for k in c.keys() if k in removed and c[k] != removed[k]]
  if used:
    raise ValueError(f"model config: {', '.join(used)} is an option this version no longer has "
                     "(docs/research_log.md)")
  fields = {f.name for f in dataclasses.fields(cls)} - set(fixed)
  unknown = set(c.keys()) - fields - set(removed) - set(moved)
  if unknown:
    raise ValueError(f"model config: unknown fields {sorted(unknown)}")
  return cls(**{k: c[k] for k in c.keys() if k not in removed and k not in moved}, **fixed)
