"""Atomic file writes: a reader (or a run killed mid-write) sees the old file or the new one, never half.

The bytes go to a temporary file beside the target (named after the process, so concurrent writers do
not collide), are flushed to disk and renamed over the target; on any error, a kill included, the
temporary file is removed. An OS error (a full disk, a read-only folder) names the target file.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import BinaryIO, Callable


def atomic_write(path: Path | str, write_fn: Callable[[BinaryIO], object]) -> None:
  """Writes `path` with `write_fn(binary file)`, atomically."""
  path = Path(path)
  tmp = path.with_name(path.name + f".tmp{os.getpid()}")
  try:
    with open(tmp, "wb") as f:
      write_fn(f)
      f.flush()
      os.fsync(f.fileno())
    os.replace(tmp, path)
  except OSError as e:
    raise named_os_error(e, path) from e
  finally:
    if tmp.exists():
      tmp.unlink()


def atomic_write_text(path: Path | str, text: str) -> None:
  """Writes `text` (UTF-8) to `path`, atomically."""
  atomic_write(path, lambda f: f.write(text.encode()))


def named_os_error(e: OSError, path: Path | str) -> OSError:
  """`e` as the same kind of OSError, naming `path` (a full disk's write error names no file)."""
  code = e.errno if e.errno is not None else errno.EIO
  return OSError(code, f"cannot write {path}: {e.strerror or e}")  # OSError(errno) picks the subclass


def user_path(path: str | os.PathLike) -> Path:
  """A path flag as a `Path`, with `~` expanded (a shell leaves `--out=~/x` as it is)."""
  return Path(path).expanduser()
