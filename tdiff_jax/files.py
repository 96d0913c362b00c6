"""Atomic writes: a reader (or a run killed mid-write) sees the old file or folder or the new one, never half.

Everything the project writes goes through `atomic_path`: the content is written to a hidden temporary
beside the target (`.tmp-<name>-<pid>`, so concurrent writers do not collide and folder listings skip
it), then renamed over the target; on any error the temporary is removed. An OS error (a full disk, a
read-only folder) names the target.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
from pathlib import Path
from typing import BinaryIO, Callable, Iterator


@contextlib.contextmanager
def atomic_path(path: Path | str, directory: bool = False) -> Iterator[Path]:
  """Yields a temporary path beside `path` (with `directory`, a created empty folder) to write; when the
  block ends without error it is renamed over `path` (an existing folder replaced), else removed."""
  path = Path(path)
  tmp = path.with_name(f".tmp-{path.stem}-{os.getpid()}{path.suffix}")
  _remove(tmp)
  try:
    if directory:
      tmp.mkdir(parents=True)
    yield tmp
    if directory and path.exists():
      shutil.rmtree(path)
    os.replace(tmp, path)
  except OSError as e:
    raise named_os_error(e, path) from e
  finally:
    _remove(tmp)


def _remove(path: Path) -> None:
  if path.is_dir() and not path.is_symlink():
    shutil.rmtree(path, ignore_errors=True)
  elif path.exists() or path.is_symlink():
    path.unlink()


def atomic_write(path: Path | str, write_fn: Callable[[BinaryIO], object]) -> None:
  """Writes `path` with `write_fn(binary file)`, flushed to disk, atomically."""
  with atomic_path(path) as tmp, open(tmp, "wb") as f:
    write_fn(f)
    f.flush()
    os.fsync(f.fileno())


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
