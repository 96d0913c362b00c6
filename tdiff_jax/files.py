"""Atomic writes: a reader (or a run killed mid-write) sees the old file or folder or the new one, never half.

Everything the project writes goes through `atomic_path`: the content is written to a hidden temporary
beside the target (`.tmp-<name>-<pid>`, so concurrent writers do not collide and folder listings skip
it), then renamed over the target; on any error the temporary is removed. An OS error (a full disk, a
read-only folder) names the target.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
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


def sha256(path: Path | str) -> str:
  """The SHA-256 hex digest of a file's bytes, read in blocks."""
  digest = hashlib.sha256()
  with open(path, "rb") as f:
    for block in iter(lambda: f.read(1 << 20), b""):
      digest.update(block)
  return digest.hexdigest()


def check_output_folder(path: Path | str, overwrite: bool, marker: str) -> None:
  """Raises FileExistsError (naming `path`) unless `path` may receive a run's outputs: absent or empty,
  or, with `overwrite`, holding an earlier run's (its `marker` file). Never deletes a folder of other files."""
  path = Path(path)
  if path.exists() and not path.is_dir():
    raise FileExistsError(f"{path} is a file, not an output folder")
  if not path.is_dir() or not any(path.iterdir()):
    return
  if not (path / marker).exists():
    raise FileExistsError(f"{path} is not empty and holds no earlier run's results (no {marker}): choose a new "
                          "or empty output folder")
  if not overwrite:
    raise FileExistsError(f"{path} holds an earlier run's results ({marker}): pass --overwrite to replace them "
                          "whole, or choose another output folder")


@contextlib.contextmanager
def output_folder(path: Path | str, overwrite: bool, marker: str) -> Iterator[Path]:
  """Yields a fresh hidden folder beside `path` for one run's outputs; when the block ends without error it
  becomes `path` whole (`check_output_folder` first; with `overwrite` an earlier run's folder is replaced),
  else it is removed. Runs into one `path` never mix: a run that finds another's results there at the end
  keeps its own under `<path>.<pid>` and raises FileExistsError saying so."""
  path = Path(path)
  check_output_folder(path, overwrite, marker)
  tmp = path.with_name(f".tmp-{path.name}-{os.getpid()}")
  try:
    path.parent.mkdir(parents=True, exist_ok=True)
    _remove(tmp)
    tmp.mkdir()
  except OSError as e:
    raise named_os_error(e, path) from e
  try:
    yield tmp
    old = path.with_name(f".old-{path.name}-{os.getpid()}")
    if overwrite and path.is_dir() and (path / marker).exists():
      os.replace(path, old)   # the earlier run's results, removed once the new ones are in place
    try:
      os.rename(tmp, path)    # fails when `path` is a folder that is not empty: another run's, meanwhile
    except OSError as e:
      if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
        raise named_os_error(e, path) from e
      kept = path.with_name(f"{path.name}.{os.getpid()}")
      os.rename(tmp, kept)
      raise FileExistsError(f"{path} received another run's results while this one ran; this run's results "
                            f"are in {kept}") from None
    finally:
      _remove(old)
  finally:
    _remove(tmp)


def unique_name(name: str, used: set[str]) -> str:
  """`name`, or `<name>-2`, `<name>-3`, ... when it is in `used` (then added): one output per input even
  when inputs share a name (scenario ids repeated across folders)."""
  key, n = name, 1
  while key in used:
    n += 1
    key = f"{name}-{n}"
  used.add(key)
  return key
