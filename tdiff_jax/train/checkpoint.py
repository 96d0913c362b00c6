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

from tdiff_jax import files


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
    self.skipped: list[int] = []  # damaged steps the last `restore()` passed over
    self.manager = ocp.CheckpointManager(
        self.directory,
        options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=True, enable_async_checkpointing=False))

  def latest_step(self) -> int | None:
    return self.manager.latest_step()

  def save(self, step: int, state: Any, record: dict) -> None:
    try:
      self.manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                      record=ocp.args.JsonSave(record)), force=True)
      self.manager.wait_until_finished()
    except OSError as e:  # orbax's own message may not say where (a full disk, a read-only folder)
      raise files.named_os_error(e, self.directory / str(step)) from e

  def restore(self, template: Any, step: int | None = None) -> tuple[Any, dict]:
    """The state (with the template's structure, dtypes and shardings) and the JSON record.

    Without `step`, the newest step that restores: a damaged newer step (a file lost or cut) is
    skipped with a warning naming it and the error, and `skipped` lists such steps afterwards.
    """
    if step is not None:
      return self._restore(template, step)
    steps = sorted(self.manager.all_steps(), reverse=True)
    if not steps:
      raise FileNotFoundError(f"{self.directory}: no checkpoint to restore")
    errors = []
    for s in steps:
      try:
        out = self._restore(template, s)
      except Exception as e:  # orbax and tensorstore raise many kinds for a damaged step
        reason = (str(e).strip().splitlines() or [type(e).__name__])[0][:300]
        absl_logging.warning("%s: checkpoint step %d does not restore, skipped: %s", self.directory, s, reason)
        errors.append((s, reason))
        continue
      self.skipped = [s for s, _ in errors]
      return out
    raise ValueError(f"{self.directory}: no checkpoint step restores ("
                     + "; ".join(f"step {s}: {r}" for s, r in errors) + ")")

  def set_aside_skipped(self) -> None:
    """Renames the damaged steps the last `restore()` skipped to `<step>.damaged`, kept for inspection,
    so that training can save those step numbers again."""
    for s in self.skipped:
      src = self.directory / str(s)
      if src.exists():
        src.rename(self.directory / f"{s}.damaged")
        absl_logging.warning("%s: damaged step %d set aside as %s", self.directory, s, f"{s}.damaged")
    self.skipped = []
    self.manager.reload()

  def _restore(self, template: Any, step: int) -> tuple[Any, dict]:
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
