"""`host.drop_compiled_near_map_limit`: compiled programs dropped near the memory-map limit, and only then."""

import sys

import pytest

from tdiff_jax import host


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="memory maps are read from /proc")
def test_compiled_programs_dropped_near_the_map_limit_and_only_there(capsys, compiles):
  import jax
  import jax.numpy as jnp

  held, limit = host.memory_maps()
  assert 0 < held < limit

  def double(x):
    return 2.0 * x
  double = jax.jit(double)
  x, before = jnp.ones(3), compiles["jit(double)"]
  double(x).block_until_ready()
  assert not host.drop_compiled_near_map_limit(share=1.0)
  double(x).block_until_ready()
  assert compiles["jit(double)"] - before == 1           # kept: not compiled again
  assert capsys.readouterr().err == ""
  assert host.drop_compiled_near_map_limit(share=0.0)   # every process is above no share of its limit
  assert "vm.max_map_count" in capsys.readouterr().err
  assert float(double(x)[0]) == 2.0                      # dropped: compiled again when called
  assert compiles["jit(double)"] - before == 2

