"""The command-line conventions of every entry point: absl flags, seeds, the compilation cache.

Library modules with a command line (`python -m tdiff_jax.evaluate`, `...animate`,
`...plot_metrics`, `...data.preprocess`, `...data.synthetic`) define their flags in a function of a
`flags.FlagValues` and build `main = cli.entry_point(define_flags, run)`:

* `python -m MODULE --flag=...`: an absl app (`--help`, `--helpfull`, absl logging) with the flags on
  the global `flags.FLAGS`, defined only then, so importing a module never defines a flag;
* `MODULE.main(["--flag=...", ...])` from Python (tests, notebooks): the list is parsed on a private
  `FlagValues`, so several modules' flags of the same name never collide.

`run(flag_values, args)` does the work; `args` are the positional arguments. The sampler's flags, which
`sample.py` and `python -m tdiff_jax.evaluate` share, are `tdiff_jax.sampler_flags`.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Callable, Sequence

from absl import app, flags

DefineFn = Callable[[flags.FlagValues], None]
RunFn = Callable[[flags.FlagValues, list[str]], None]

# A seed's range: `jax.random.key` reads only its low 32 bits (seeds that differ above would draw the same).
MAX_SEED = 2**32 - 1


def define_seed_flag(values: flags.FlagValues) -> None:
  flags.DEFINE_integer("seed", 0, f"random seed (0 to {MAX_SEED})", lower_bound=0, upper_bound=MAX_SEED,
                       flag_values=values)


def compilation_cache_dir() -> Path:
  """Where the command lines keep compiled programs: `$TDIFF_JAX_CACHE_DIR`, else
  `$XDG_CACHE_HOME/tdiff_jax/jax` (`~/.cache/tdiff_jax/jax`)."""
  if os.environ.get("TDIFF_JAX_CACHE_DIR"):
    return Path(os.environ["TDIFF_JAX_CACHE_DIR"]).expanduser()
  return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache").expanduser() / "tdiff_jax" / "jax"


def define_compilation_cache_flag(values: flags.FlagValues) -> None:
  flags.DEFINE_boolean(
      "compilation_cache", os.environ.get("TDIFF_JAX_COMPILATION_CACHE", "1") != "0",
      "keep XLA's compiled programs between runs (JAX's persistent compilation cache, in $TDIFF_JAX_CACHE_DIR "
      "or ~/.cache/tdiff_jax/jax), so a second run compiles nothing it compiled before; --nocompilation_cache "
      "(or TDIFF_JAX_COMPILATION_CACHE=0): compile afresh", flag_values=values)


def use_compilation_cache(enabled: bool) -> Path | None:
  """Turns JAX's persistent compilation cache on in `compilation_cache_dir()` (call before the first
  compile; a cache folder set already, e.g. `JAX_COMPILATION_CACHE_DIR`, is kept); returns the folder, or
  None when off or when the folder cannot be made (then the run compiles as usual, saying why)."""
  if not enabled:
    return None
  import jax
  if jax.config.jax_compilation_cache_dir:
    return Path(jax.config.jax_compilation_cache_dir)
  path = compilation_cache_dir()
  try:
    path.mkdir(parents=True, exist_ok=True)
  except OSError as e:
    print(f"tdiff_jax: no compilation cache ({e}); compiling as usual", file=sys.stderr)
    return None
  jax.config.update("jax_compilation_cache_dir", str(path))
  # Every program: the samplers' many small ones add up on a CPU (a second `sample.py` run on command 1's
  # maps took 36 s with every program cached, 54 s with JAX's default of those taking 1 s or more).
  jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
  return path


def check_seed(seed: int, name: str = "seed") -> None:
  """Raises ValueError for a seed outside 0 to `MAX_SEED` (the command lines refuse it at parse time)."""
  if not 0 <= seed <= MAX_SEED:
    raise ValueError(f"{name}={seed}: must be between 0 and {MAX_SEED} (a JAX key holds 32 bits of a seed)")


def entry_point(define_flags: DefineFn, run: RunFn) -> Callable[[Sequence[str] | None], None]:
  """`main(argv=None)`: without `argv` an absl app on the process's command line, with a list of
  arguments (no program name) the same run on a private `FlagValues`."""

  def main(argv: Sequence[str] | None = None) -> None:
    if argv is None:
      define_flags(flags.FLAGS)
      app.run(lambda args: run(flags.FLAGS, list(args[1:])))
      return
    values = flags.FlagValues()
    define_flags(values)
    try:
      args = values(["main", *argv])
    except flags.Error as e:
      raise app.UsageError(str(e)) from e
    run(values, list(args[1:]))

  return main


def no_arguments(args: list[str]) -> None:
  if args:
    raise app.UsageError(f"unexpected arguments: {args}")
