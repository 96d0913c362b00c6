"""Building a model's frozen config dataclass from the `model` block of an ml_collections config."""

from __future__ import annotations

import dataclasses

import ml_collections

# The last version whose models had the options measured and dropped since (docs/research_log.md): it reads
# a checkpoint whose config names one.
OLDER_VERSION = "0.2.0"


def older_options_error(names: list[str], where: str = "") -> ValueError:
  """The error for a config naming options of earlier versions: which, and the version that reads it."""
  return ValueError(f"{where}{', '.join(sorted(names))}: option(s) of tdiff_jax {OLDER_VERSION} and earlier, "
                    f"measured and dropped since (docs/research_log.md); tdiff_jax {OLDER_VERSION} reads this "
                    f"checkpoint (pip install tdiff_jax=={OLDER_VERSION})")


def from_config(cls, c: ml_collections.ConfigDict, older: tuple[str, ...] = (), **fixed):
  """`cls(**c, **fixed)`; a field of `c` that `cls` does not have is a ValueError naming it: `older` names
  the fields of earlier versions' models (`older_options_error`), any other is a typo.

  `fixed` are fields set by the caller, not by the config block (e.g. the HL model's `max_agents`).
  """
  used = [f"model.{k}" for k in c.keys() if k in older]
  if used:
    raise older_options_error(used, "model config: ")
  fields = {f.name for f in dataclasses.fields(cls)} - set(fixed)
  unknown = set(c.keys()) - fields
  if unknown:
    raise ValueError(f"model config: unknown fields {sorted(unknown)} (of {cls.__name__})")
  return cls(**{k: c[k] for k in c.keys()}, **fixed)
