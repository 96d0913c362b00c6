"""What the project writes, and how it keeps from harming what it did not write.

* Atomic writes: everything goes through `atomic_path`: the content is written to a hidden temporary
  beside the target (`.tmp-<name>-<pid>`, so concurrent writers do not collide and folder listings skip
  it), then renamed over the target; on any error the temporary is removed. An OS error (a full disk, a
  read-only folder) names the target.
* Output folders (`output_folder`): a run's outputs appear whole, with a marker listing what the tool
  wrote; only such a folder, holding nothing else, is ever replaced, and never one that is or holds an input.
* Names from file contents (`safe_name`), strict JSON (`json_text`), a workdir lock (`exclusive_lock`).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import glob
import hashlib
import json
import logging
import math
import os
import re
import shutil
from pathlib import Path
from typing import BinaryIO, Callable, Iterator, Sequence


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


# Written by this tool into every output folder it makes (`output_folder`), listing the files it wrote there:
# the only folders `--overwrite` replaces, and then only while they hold nothing else.
OUTPUT_MARKER = ".tdiff_jax_output.json"


def _written_files(folder: Path) -> list[str]:
  """Every file and link under `folder` (folders not followed through links), as sorted relative paths."""
  out = []
  for root, dirs, names in os.walk(folder):
    rel = Path(root).relative_to(folder)
    out += [(rel / n).as_posix() for n in names]
    out += [(rel / d).as_posix() for d in dirs if (Path(root) / d).is_symlink()]
  return sorted(p for p in out if p != OUTPUT_MARKER)


def _read_marker(folder: Path) -> dict | None:
  """The marker of an output folder this tool wrote, or None (absent, unreadable, or another program's)."""
  try:
    marker = json.loads((folder / OUTPUT_MARKER).read_text())
  except (OSError, ValueError):
    return None
  ok = isinstance(marker, dict) and marker.get("written_by") == "tdiff_jax" and isinstance(marker.get("files"), list)
  return marker if ok else None


def _write_marker(folder: Path, command: str, staging: bool) -> None:
  marker = {"written_by": "tdiff_jax", "command": command, "pid": os.getpid(), "staging": staging,
            "files": [] if staging else _written_files(folder)}
  (folder / OUTPUT_MARKER).write_text(json.dumps(marker, indent=1))


def _foreign_files(folder: Path, marker: dict) -> list[str]:
  """What `folder` holds that its marker does not list: files (or folders) a user added to the tool's results."""
  listed = set(marker["files"])
  implied = {p.as_posix() for f in listed for p in Path(f).parents}   # the listed files' folders
  folders = {(Path(root).relative_to(folder) / d).as_posix() for root, dirs, _ in os.walk(folder) for d in dirs}
  return sorted((set(_written_files(folder)) | folders) - listed - implied)


def resolved(path: Path | str) -> Path:
  """`path` absolute with every symbolic link followed: the folder that a write through it changes."""
  return Path(os.path.realpath(Path(path).expanduser()))


def check_output_folder(path: Path | str, overwrite: bool, inputs: Sequence[Path | str | None] = ()) -> None:
  """Raises FileExistsError (naming `path`) unless `path` (links followed) may receive a run's outputs:
  absent or empty, or, with `overwrite`, an output folder of this tool (its `OUTPUT_MARKER`) holding
  nothing but the files the tool wrote there. Raises ValueError when `path` is, or holds, one of `inputs`
  (the maps, the data, the workdirs): replacing it would delete them. Never deletes anything."""
  target = resolved(path)
  for given in inputs:
    if given is None:
      continue
    source = resolved(given)
    if source == target or target in source.parents:
      raise ValueError(f"--out {path} {'is' if source == target else 'holds'} the input {given}: replacing it "
                       "would delete that input; choose another output folder")
  if target.exists() and not target.is_dir():
    raise FileExistsError(f"{path} is a file, not an output folder")
  if not target.is_dir() or not any(target.iterdir()):
    return
  marker = _read_marker(target)
  if marker is None or marker.get("staging"):
    raise FileExistsError(f"{path} is not empty and is not an output folder of tdiff_jax (no {OUTPUT_MARKER}): "
                          "nothing there is replaced; choose a new or empty output folder")
  if not overwrite:
    raise FileExistsError(f"{path} holds an earlier run's results: pass --overwrite to replace them "
                          "whole, or choose another output folder")
  foreign = _foreign_files(target, marker)
  if foreign:
    shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
    raise FileExistsError(f"{path} holds files that the earlier run did not write ({shown}): --overwrite replaces "
                          "only what tdiff_jax wrote; move them away or choose another output folder")


def _replaceable(folder: Path) -> bool:
  """Whether `folder` is a finished output folder of this tool holding only what the tool wrote there."""
  marker = _read_marker(folder)
  return marker is not None and not marker.get("staging") and not _foreign_files(folder, marker)


def _pid_alive(pid: int) -> bool:
  try:
    os.kill(pid, 0)
  except ProcessLookupError:
    return False
  except (PermissionError, OverflowError, ValueError):
    return True
  return True


def remove_stale_staging(path: Path) -> list[Path]:
  """Removes the staging folders (`.tmp-<name>-<pid>`, `.old-<name>-<pid>`) that killed runs left beside
  `path`: only those holding this tool's marker and whose process is gone. Returns them (each logged)."""
  removed = []
  if not path.parent.is_dir():
    return removed
  for prefix in (".tmp-", ".old-"):
    for folder in path.parent.glob(f"{prefix}{glob.escape(path.name)}-*"):
      pid = folder.name[len(prefix) + len(path.name) + 1:]
      if not pid.isdigit() or folder.is_symlink() or not folder.is_dir() or _pid_alive(int(pid)):
        continue
      if _read_marker(folder) is None:
        continue   # not ours: left alone
      shutil.rmtree(folder, ignore_errors=True)
      logging.warning("removed %s, the staging folder of a run that was stopped (process %s)", folder, pid)
      removed.append(folder)
  return removed


@contextlib.contextmanager
def output_folder(path: Path | str, overwrite: bool, command: str,
                  inputs: Sequence[Path | str | None] = ()) -> Iterator[Path]:
  """Yields a fresh hidden folder beside `path` (links followed) for one run's outputs; when the block ends
  without error the tool's marker is written into it (`OUTPUT_MARKER`: `command` and every file written)
  and it becomes `path` whole (`check_output_folder` first; with `overwrite` an earlier run's folder is
  replaced if it is still only the tool's at the end), else it is removed. Staging folders of killed runs are removed first
  (`remove_stale_staging`). Runs into one `path` never mix: a run that finds another's results there at
  the end keeps its own under `<path>.<pid>` and raises FileExistsError saying so."""
  check_output_folder(path, overwrite, inputs)
  given, path = path, resolved(path)
  tmp = path.with_name(f".tmp-{path.name}-{os.getpid()}")
  try:
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_staging(path)
    _remove(tmp)
    tmp.mkdir()
    _write_marker(tmp, command, staging=True)   # so that a killed run's staging folder is known as ours
  except OSError as e:
    raise named_os_error(e, path) from e
  try:
    yield tmp
    _write_marker(tmp, command, staging=False)
    old = path.with_name(f".old-{path.name}-{os.getpid()}")
    if overwrite and path.is_dir() and _replaceable(path):   # checked again: time has passed
      os.replace(path, old)   # the earlier run's results, removed once the new ones are in place
    try:
      os.rename(tmp, path)    # fails when `path` is a folder that is not empty: another run's, meanwhile
    except OSError as e:
      if e.errno not in (errno.ENOTEMPTY, errno.EEXIST):
        raise named_os_error(e, path) from e
      kept = path.with_name(f"{path.name}.{os.getpid()}")
      os.rename(tmp, kept)
      raise FileExistsError(f"{given} received another run's results while this one ran; this run's results "
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


NAME_LIMIT = 96   # characters of a file name made from file contents (most file systems allow 255 bytes)


def safe_name(name: str) -> str:
  """`name` (read from a file, e.g. a scenario id) as one harmless path component: letters, digits, `.`, `_`
  and `-` only, not hidden, at most `NAME_LIMIT` characters. Names already so are kept; others are cleaned
  and given a short hash of the original, so that distinct names stay distinct."""
  clean = re.sub(r"[^A-Za-z0-9._-]", "_", name).lstrip(".")
  if clean == name and 0 < len(name) <= NAME_LIMIT:
    return name
  digest = hashlib.sha256(name.encode("utf-8", "surrogateescape")).hexdigest()[:10]
  return f"{clean[:NAME_LIMIT - 11]}-{digest}" if clean else digest


NON_FINITE_NOTE = "non_finite_as_null"   # the key under which `json_text` lists the values it wrote as null


def _finite_tree(value, where: str, found: list[str]):
  """`value` with NumPy scalars and arrays as Python values and every NaN or infinity as None (its path in
  `found`)."""
  if isinstance(value, dict):
    return {k: _finite_tree(v, f"{where}.{k}" if where else str(k), found) for k, v in value.items()}
  if isinstance(value, (list, tuple)):
    return [_finite_tree(v, f"{where}[{i}]", found) for i, v in enumerate(value)]
  if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):   # NumPy scalars and arrays
    return _finite_tree(value.tolist(), where, found)
  if isinstance(value, float) and not math.isfinite(value):
    found.append(where)
    return None
  return value


def json_text(value, indent: int | None = None) -> str:
  """`value` as strict JSON (RFC 8259, which has no NaN or Infinity): a non-finite number is written as
  null, and a dict then lists those fields under `NON_FINITE_NOTE`. Used for every JSON file written."""
  found: list[str] = []
  clean = _finite_tree(value, "", found)
  if found and isinstance(clean, dict):
    clean[NON_FINITE_NOTE] = found
  return json.dumps(clean, indent=indent, allow_nan=False)


LOCK_FILE = ".lock"   # in a workdir while a training run holds it


@contextlib.contextmanager
def exclusive_lock(folder: Path | str, what: str) -> Iterator[None]:
  """Holds `folder/.lock` (an advisory `flock`, released by the system when the process ends, however it
  ends) for the block; raises ValueError naming `folder` and the holding process when another holds it."""
  folder = Path(folder)
  try:
    folder.mkdir(parents=True, exist_ok=True)
    handle = open(folder / LOCK_FILE, "a+")
  except OSError as e:
    raise named_os_error(e, folder / LOCK_FILE) from e
  try:
    try:
      fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
      handle.seek(0)
      holder = handle.read().strip() or "another process"
      raise ValueError(f"{folder} is in use by another {what} ({holder}): wait for it to end or choose "
                       "another folder") from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"{what}, process {os.getpid()}")
    handle.flush()
    yield
  finally:
    handle.close()   # releases the lock
