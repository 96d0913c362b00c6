"""Checkpoints: the one module that talks to orbax.

A checkpoint holds the train state pytree (params, optimiser state, EMA, step, PRNG key) and a JSON
record (step, data-iterator position, the full config, normalisation statistics), so a checkpoint alone
is enough to resume training or to sample. Orbax writes each step into a temporary folder and renames
it when complete, so a run killed mid-save leaves the previous checkpoint as the latest usable one.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import orbax.checkpoint as ocp
from absl import logging as absl_logging


class _QuietOrbax(logging.Filter):
  """Orbax logs every save step by step at INFO; keep its warnings only."""

  def filter(self, record):
    return record.levelno >= logging.WARNING or "orbax" not in record.pathname


def quiet_orbax_logging() -> None:
  """For command-line entry points: hide orbax's INFO chatter from the absl log."""
  absl_logging.get_absl_handler().addFilter(_QuietOrbax())


class Checkpointer:

  def __init__(self, directory: Path | str, keep: int = 3):
    self.directory = Path(directory).absolute()
    self.manager = ocp.CheckpointManager(
        self.directory,
        options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True, enable_async_checkpointing=False))

  def latest_step(self) -> int | None:
    return self.manager.latest_step()

  def save(self, step: int, state: Any, record: dict) -> None:
    self.manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                    record=ocp.args.JsonSave(record)), force=True)
    self.manager.wait_until_finished()

  def restore(self, template: Any, step: int | None = None) -> tuple[Any, dict]:
    """The state (with the template's structure, dtypes and shardings) and the JSON record."""
    step = self.latest_step() if step is None else step
    if step is None:
      raise FileNotFoundError(f"{self.directory}: no checkpoint to restore")
    out = self.manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(template),
                                                             record=ocp.args.JsonRestore()))
    return out["state"], out["record"]

  def restore_record(self, step: int | None = None) -> dict:
    step = self.latest_step() if step is None else step
    if step is None:
      raise FileNotFoundError(f"{self.directory}: no checkpoint to restore")
    return self.manager.restore(step, args=ocp.args.Composite(record=ocp.args.JsonRestore()))["record"]

  def close(self) -> None:
    self.manager.close()
