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


def _relations(n: int, seed: int = 3) -> np.ndarray:
  """`[n, 3]` relation triples as the map encoder's: a distance in metres (0 to 150) and two angles."""
  rng = np.random.default_rng(seed)
  return np.stack([rng.uniform(0.0, 150.0, n), rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi, np.pi, n)],
                  -1).astype(np.float32)


def _embedding_pair(table_size: int, dim: int = 32, bands: int = 16):
  """A tabulated `FourierEmbedding` (QCNet's initial frequencies) and the exact one with the same weights."""
  from flax import nnx

  tabulated = layers.FourierEmbedding(3, dim, bands, table_size=table_size, rngs=nnx.Rngs(4))
  graphdef, params = nnx.split(tabulated)
  exact = nnx.merge(graphdef, params)
  exact.table_size = 0
  return tabulated, exact


def test_tabulated_fourier_embedding_is_the_exact_one_to_interpolation_error():
  """The tolerance the model configs rely on (`fourier_tables=2048`): relations over 150 m, QCNet's
  initial frequencies, within 3e-3 of the exact embedding, whose outputs are of order 1."""
  tabulated, exact = _embedding_pair(2048)
  x = _relations(3 * 2048)                        # above TABLE_MIN_ROWS x G rows: interpolated
  fast, ref = np.asarray(tabulated(x)), np.asarray(exact(x))
  assert np.abs(ref).max() > 1.0 and not np.array_equal(fast, ref)
  np.testing.assert_allclose(fast, ref, rtol=0, atol=3e-3)
  assert np.abs(fast - ref).mean() < 1e-5
  small = x[:100]                                 # too few rows to pay for a table: the exact embedding
  np.testing.assert_array_equal(np.asarray(tabulated(small)), np.asarray(exact(small)))


def test_tabulated_fourier_embedding_spans_the_valid_rows_only():
  """Invalid rows (padding, far outside the valid range) neither widen the table's range nor change a
  valid row's embedding: the result is that of the valid rows with harmless rows in their place."""
  tabulated, _ = _embedding_pair(512)
  x = _relations(4096)
  valid = np.arange(4096) < 3000
  padded = np.where(valid[:, None], x, np.float32(1e4))
  harmless = np.where(valid[:, None], x, x[:1])   # the first valid row again: the same range
  np.testing.assert_allclose(np.asarray(tabulated(padded, valid=valid))[valid],
                             np.asarray(tabulated(harmless))[valid], rtol=0, atol=1e-6)
  coarse = np.asarray(tabulated(padded))[valid]   # without the mask the range spans the padding: far coarser
  assert np.abs(coarse - np.asarray(tabulated(harmless))[valid]).max() > 1e-2


def test_tabulated_fourier_embedding_gradients_are_the_exact_ones_to_interpolation_error():
  from flax import nnx

  tabulated, exact = _embedding_pair(2048)
  x = _relations(2 * 2048)
  target = jax.random.normal(jax.random.key(5), (x.shape[0], 32))

  def grads(module):
    graphdef, params = nnx.split(module)
    return jax.grad(lambda p: jnp.mean((nnx.merge(graphdef, p)(x) - target) ** 2))(params)

  fast, ref = grads(tabulated), grads(exact)
  for (path, a), b in zip(jax.tree_util.tree_leaves_with_path(fast), jax.tree_util.tree_leaves(ref)):
    scale = float(jnp.max(jnp.abs(b)))
    assert scale > 0, path
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=2e-2 * scale, err_msg=str(path))


def test_fourier_table_size_is_checked():
  from flax import nnx

  for bad in (1, -2):
    with pytest.raises(ValueError, match="fourier_tables must be 0"):
      layers.FourierEmbedding(3, 8, 4, table_size=bad, rngs=nnx.Rngs(0))


@pytest.mark.parametrize("size", [1, 2, 7, 96, 97])
def test_max_along_is_jnp_max_and_masked_softmax_the_library_softmax(size):
  x = jax.random.normal(jax.random.key(size), (3, size, 5))
  for axis in (0, 1, -1):
    np.testing.assert_array_equal(layers.max_along(x, axis), jnp.max(x, axis, keepdims=True))
  assert np.isnan(layers.max_along(x.at[1, size // 2, 2].set(jnp.nan), 1)[1, 0, 2])
  mask = jax.random.bernoulli(jax.random.key(1), 0.6, x.shape).at[0].set(False)   # row 0: nothing valid
  probs = layers.masked_softmax(x, mask, axis=1)
  expected = jnp.where(mask, jax.nn.softmax(jnp.where(mask, x, -jnp.inf), axis=1), 0.0)
  np.testing.assert_allclose(probs[1:], expected[1:], rtol=1e-6, atol=1e-7)
  np.testing.assert_array_equal(probs[0], 0.0)


def test_gelu_is_the_library_tanh_gelu_and_its_gradient():
  x = jnp.linspace(-12.0, 12.0, 20_001)
  np.testing.assert_allclose(np.asarray(jax.jit(layers.gelu)(x)), np.asarray(jax.nn.gelu(x)), rtol=0, atol=1e-6)
  grad = lambda f: jax.vmap(jax.grad(f))(x)  # noqa: E731
  np.testing.assert_allclose(np.asarray(grad(layers.gelu)), np.asarray(grad(jax.nn.gelu)), rtol=0, atol=1e-5)


@pytest.mark.parametrize("num_keys", [1, 2, 3])
def test_attention_over_few_keys_is_the_matrix_product_form(num_keys, monkeypatch):
  """Attention over at most `FEW_KEYS` keys (sums of products) gives the batched products' result."""
  from flax import nnx
  attn = layers.MultiHeadAttention(32, 4, rngs=nnx.Rngs(0))
  rng = np.random.default_rng(0)
  x_q = jnp.asarray(rng.normal(size=(2, 5, 3, 32)), jnp.float32)
  x_kv = jnp.asarray(rng.normal(size=(2, 5, num_keys, 32)), jnp.float32)
  mask = jnp.asarray(rng.uniform(size=(2, 5, 3, num_keys)) < 0.7)
  few = attn(x_q, x_kv, mask)
  monkeypatch.setattr(layers, "FEW_KEYS", 0)
  np.testing.assert_allclose(np.asarray(few), np.asarray(attn(x_q, x_kv, mask)), rtol=0, atol=1e-5)
