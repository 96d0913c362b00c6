"""The vectorised trigonometry of the embeddings against float64 references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tdiff_jax.models import layers


@pytest.mark.parametrize("radius", [1.0, 100.0, 1e4, 9.9e4])
def test_sincos_matches_float64(radius):
  x = np.random.default_rng(0).uniform(-radius, radius, 200_000).astype(np.float32)
  x[:4] = [0.0, np.pi / 4, -np.pi / 2, np.pi]    # ends of the reduced range and quadrant borders
  sin, cos = jax.jit(layers.sincos)(x)
  exact = x.astype(np.float64)
  np.testing.assert_allclose(np.asarray(sin), np.sin(exact), rtol=0, atol=1e-7)
  np.testing.assert_allclose(np.asarray(cos), np.cos(exact), rtol=0, atol=1e-7)


def test_sincos_derivative_is_cos_and_minus_sin():
  x = jnp.linspace(-20.0, 20.0, 401)
  d_sin = jax.vmap(jax.grad(lambda v: layers.sincos(v)[0]))(x)
  d_cos = jax.vmap(jax.grad(lambda v: layers.sincos(v)[1]))(x)
  np.testing.assert_allclose(np.asarray(d_sin), np.cos(np.asarray(x, np.float64)), atol=1e-7)
  np.testing.assert_allclose(np.asarray(d_cos), -np.sin(np.asarray(x, np.float64)), atol=1e-7)


def test_wrap_angle_is_the_angle_less_whole_turns():
  a = np.random.default_rng(1).uniform(-200.0, 200.0, 100_000).astype(np.float32)
  wrapped = np.asarray(layers.wrap_angle(a), np.float64)
  assert np.all(np.abs(wrapped) <= np.pi + 1e-6)
  exact = np.angle(np.exp(1j * a.astype(np.float64)))
  gap = np.abs(wrapped - exact)
  np.testing.assert_array_less(np.minimum(gap, 2 * np.pi - gap), 3e-7)   # +-pi: the same angle; 1 ulp


def test_fourier_embedding_matches_library_trigonometry(monkeypatch):
  """The embedding with `sincos` is QCNet's, written with sin and cos, to float rounding."""
  from flax import nnx

  emb = layers.FourierEmbedding(3, 16, 8, freqs=layers.log_spaced_freqs(3, 8, 1.0, 250.0), rngs=nnx.Rngs(0))
  x = jax.random.uniform(jax.random.key(2), (64, 3), minval=-300.0, maxval=300.0)
  fast = emb(x)
  monkeypatch.setattr(layers, "sincos", lambda phase: (jnp.sin(phase), jnp.cos(phase)))
  library = emb(x)
  assert float(jnp.max(jnp.abs(library))) > 0.1
  np.testing.assert_allclose(np.asarray(fast), np.asarray(library), rtol=0, atol=1e-5)
