"""`host.use_huge_pages`: the command starts again once, unchanged but for the allocator tunable;
`host.drop_compiled_near_map_limit`: compiled programs dropped near the memory-map limit, and only then."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tdiff_jax import host

ROOT = Path(__file__).resolve().parent.parent

# Prints one JSON line per start of the process, then the arguments it ends with.
SCRIPT = f"""
import json, os, sys
sys.path.insert(0, {str(ROOT)!r})
print(json.dumps({{"start": os.environ.get("GLIBC_TUNABLES")}}), flush=True)
from tdiff_jax import host
host.use_huge_pages()
print(json.dumps({{"end": os.environ.get("GLIBC_TUNABLES"), "argv": sys.argv[1:],
                   "marker": os.environ.get("MARKER")}}))
"""


def _run(tmp_path, env_changes):
  script = tmp_path / "probe.py"
  script.write_text(SCRIPT)
  env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", host.SWITCH)}
  env.update(env_changes, MARKER="kept")
  out = subprocess.run([sys.executable, str(script), "a b", "--flag=1"], env=env, capture_output=True, text=True,
                       check=True).stdout
  return [json.loads(line) for line in out.splitlines()]


def test_restarts_once_with_the_tunable_and_the_same_command(tmp_path):
  lines = _run(tmp_path, {})
  starts, end = [line for line in lines if "start" in line], lines[-1]
  assert end["argv"] == ["a b", "--flag=1"] and end["marker"] == "kept"
  if host.huge_pages_available():
    assert [s["start"] for s in starts] == [None, host.TUNABLE]   # started again, once
    assert end["end"] == host.TUNABLE
  else:  # nothing to gain here: the process goes on unchanged
    assert [s["start"] for s in starts] == [None] and end["end"] is None


def test_keeps_other_tunables_and_respects_the_switch(tmp_path):
  lines = _run(tmp_path, {"GLIBC_TUNABLES": "glibc.malloc.arena_max=2"})
  want = "glibc.malloc.arena_max=2:" + host.TUNABLE if host.huge_pages_available() else "glibc.malloc.arena_max=2"
  assert lines[-1]["end"] == want
  lines = _run(tmp_path, {host.SWITCH: "0"})
  assert len(lines) == 2 and lines[-1]["end"] is None   # one start, nothing set


def test_not_available_when_the_kernel_has_huge_pages_off(tmp_path, monkeypatch):
  if not sys.platform.startswith("linux") or "glibc" not in os.confstr("CS_GNU_LIBC_VERSION"):
    pytest.skip("glibc on Linux only")
  mode = tmp_path / "enabled"
  monkeypatch.setattr(host, "_THP_MODE", mode)
  mode.write_text("always madvise [never]\n")
  assert not host.huge_pages_available()
  mode.write_text("always [madvise] never\n")
  version = tuple(int(v) for v in os.confstr("CS_GNU_LIBC_VERSION").split()[1].split(".")[:2])
  assert host.huge_pages_available() == (version >= (2, 35))
  monkeypatch.setattr(host, "_THP_MODE", tmp_path / "missing")
  assert not host.huge_pages_available()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="memory maps are read from /proc")
def test_compiled_programs_dropped_near_the_map_limit_and_only_there(capsys):
  import jax
  import jax.numpy as jnp

  held, limit = host.memory_maps()
  assert 0 < held < limit
  double = jax.jit(lambda x: 2.0 * x)
  double(jnp.ones(3)).block_until_ready()
  assert not host.drop_compiled_near_map_limit(share=1.0) and double._cache_size() == 1
  assert capsys.readouterr().err == ""
  assert host.drop_compiled_near_map_limit(share=0.0)   # every process is above no share of its limit
  assert double._cache_size() == 0
  assert "vm.max_map_count" in capsys.readouterr().err
  assert float(double(jnp.ones(3))[0]) == 2.0            # compiled again when called

