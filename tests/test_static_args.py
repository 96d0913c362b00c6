"""Static graphdefs hashed once: the jitted calls see the graphdef and compile once per model."""

import jax
import jax.numpy as jnp
from flax import nnx

from tdiff_jax import cpu_products, static_args


def test_a_wrapped_graphdef_is_hashed_once_and_reaches_the_function_as_itself(monkeypatch):
  graphdef, params = nnx.split(nnx.Linear(3, 2, rngs=nnx.Rngs(0)))
  hashes = []
  original = type(graphdef).__hash__
  monkeypatch.setattr(type(graphdef), "__hash__", lambda self: hashes.append(1) or original(self))
  seen = []

  def apply(graphdef, params, x):
    seen.append(type(graphdef))
    return nnx.merge(graphdef, params)(x)

  apply = cpu_products.jit(apply, static_argnames=("graphdef",))
  x = jnp.ones((4, 3))
  outs = [apply(graphdef, params, x) for _ in range(5)]
  assert seen == [type(graphdef)]                     # traced once, with the graphdef itself
  assert apply._cache_size() == 1
  outs.append(apply(graphdef=graphdef, params=params, x=x))   # by keyword (JAX traces that call apart)
  assert len(hashes) == 1                             # hashed once, not per call
  for out in outs:
    assert jnp.allclose(out, nnx.merge(graphdef, params)(x))


def test_hashed_equality_follows_the_value():
  a, b = static_args.Hashed((1, 2)), static_args.Hashed((1, 2))
  assert a == b and hash(a) == hash(b) and a != static_args.Hashed((1, 3))
  assert static_args.hashed(a.value) is static_args.hashed(a.value)
  assert static_args.unwrap(a) == (1, 2) and static_args.unwrap(5) == 5
  assert jax.jit(lambda h, x: x * h.value[0], static_argnums=0)(a, 2.0) == 2.0


def _out_features(model) -> int:
  return model.out_features


def test_a_models_settings_are_read_once_per_graphdef(monkeypatch):
  graphdef, params = nnx.split(nnx.Linear(3, 2, rngs=nnx.Rngs(0)))
  merges = []
  original = nnx.merge
  monkeypatch.setattr(nnx, "merge", lambda *a, **k: merges.append(1) or original(*a, **k))
  assert [static_args.read_once(graphdef, params, _out_features) for _ in range(3)] == [2, 2, 2]
  assert len(merges) == 1
  other, other_params = nnx.split(nnx.Linear(3, 5, rngs=nnx.Rngs(0)))
  assert static_args.read_once(other, other_params, _out_features) == 5
