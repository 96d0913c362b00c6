"""Attention and embedding layers shared by the models (Flax NNX).

All attention is dense over padded sets with boolean masks. A query whose keys are all masked gets
zeros (never NaN, never a uniform average of padding). Dropout takes an explicit key (`None`: off),
so a model call is a pure function of (params, inputs, key).

Shapes: D model width, H heads, Q queries, K keys.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx


def max_along(x: jax.Array, axis: int = -1) -> jax.Array:
  """`jnp.max(x, axis, keepdims=True)`, the same values (NaN propagates as there), as a tree of
  elementwise maxima: XLA's CPU reduce-max runs one element at a time (docs/benchmarks.md). Each level
  takes the maximum of the first and the last ceil(n/2) entries (overlapping by one for odd n)."""
  axis = axis % x.ndim
  while x.shape[axis] > 1:
    n = x.shape[axis]
    h = (n + 1) // 2
    x = jnp.maximum(jax.lax.slice_in_dim(x, 0, h, axis=axis), jax.lax.slice_in_dim(x, n - h, n, axis=axis))
  return x


def masked_softmax(logits: jax.Array, mask: jax.Array, axis: int = -1) -> jax.Array:
  """Softmax over `axis` restricted to `mask`; rows with no valid entry are all zeros."""
  logits = jnp.where(mask, logits, jnp.finfo(logits.dtype).min)
  top = jax.lax.stop_gradient(max_along(logits, axis))   # softmax is shift-invariant
  ex = jnp.where(mask, jnp.exp(logits - top), 0.0)
  total = jnp.sum(ex, axis=axis, keepdims=True)
  return ex / jnp.where(total > 0, total, 1.0)


def segment_softmax(logits: jax.Array, segment: jax.Array, valid: jax.Array, num_segments: int) -> jax.Array:
  """Softmax of `logits` `[E, ...]` over the entries of each segment (`segment` `[E]`, sorted), restricted
  to `valid` `[E]`: `masked_softmax` over a packed list instead of a padded grid. Invalid entries and
  segments without a valid entry get zeros (and no NaN gradients)."""
  ok = valid.reshape(valid.shape + (1,) * (logits.ndim - 1))
  top = jax.ops.segment_max(jnp.where(ok, logits, -jnp.inf), segment, num_segments, indices_are_sorted=True)
  top = jax.lax.stop_gradient(jnp.where(jnp.isfinite(top), top, 0.0))   # softmax is shift-invariant
  ex = jnp.where(ok, jnp.exp(jnp.where(ok, logits, 0.0) - top[segment]), 0.0)
  total = jax.ops.segment_sum(ex, segment, num_segments, indices_are_sorted=True)
  return ex / jnp.where(total > 0, total, 1.0)[segment]


def dropout(x: jax.Array, rate: float, key: jax.Array | None) -> jax.Array:
  if key is None or rate <= 0.0:
    return x
  keep = jax.random.bernoulli(key, 1.0 - rate, x.shape)
  return jnp.where(keep, x / (1.0 - rate), 0.0)


def fold(key: jax.Array | None, i: int) -> jax.Array | None:
  return None if key is None else jax.random.fold_in(key, i)


# pi / 2 in four parts, the first three with 8-bit mantissas, so that j * part is exact in float32 (with
# or without fused multiply-adds) for the multiples |j| < 2 ** 16 of a range reduction (|x| < 1e5).
_HALF_PI_PARTS = (1.5703125, 4.84466552734375e-4, -6.407499313354492e-7, 9.92093629470503e-10)


def wrap_angle(a: jax.Array) -> jax.Array:
  """`a` in radians, less the nearest whole number of turns: in [-pi, pi]. Arithmetic only (XLA's CPU
  runtime evaluates sin, cos and atan2 one element at a time, several times the cost of a vectorised pass)."""
  turns = jnp.round(a * (0.5 / math.pi))
  c1, c2, c3, c4 = _HALF_PI_PARTS
  return (((a - turns * (4.0 * c1)) - turns * (4.0 * c2)) - turns * (4.0 * c3)) - turns * (4.0 * c4)


@jax.custom_jvp
def sincos(x: jax.Array) -> tuple[jax.Array, jax.Array]:
  """`(sin x, cos x)` of a float32 array, vectorised: one range reduction to [-pi/4, pi/4] shared by both
  and Cephes' minimax polynomials (`sinf`, `cosf`): within 1e-7 of the exact values for |x| < 1e5 rad
  (`jnp.sin`: 3e-8, float32's rounding; tests/test_layers.py), less accurate beyond (the inputs here are
  at most a few thousand rad: metres of a map crop times a few cycles per metre). XLA's CPU runtime evaluates
  `jnp.sin` and `jnp.cos` through scalar library calls, and the Fourier embeddings take two per input,
  frequency band and point or pair. The derivative is exact: (cos, -sin)."""
  c1, c2, c3, c4 = _HALF_PI_PARTS
  j = jnp.round(x * (2.0 / math.pi))                  # x = j pi/2 + r
  r = (((x - j * c1) - j * c2) - j * c3) - j * c4
  z = r * r
  sin_r = ((-1.9515295891e-4 * z + 8.3321608736e-3) * z - 1.6666654611e-1) * z * r + r
  cos_r = ((2.443315711809948e-5 * z - 1.388731625493765e-3) * z + 4.166664568298827e-2) * z * z - 0.5 * z + 1.0
  quadrant = j.astype(jnp.int32)
  odd = (quadrant & 1) == 1                           # sin(r + pi/2) = cos r, cos(r + pi/2) = -sin r
  sin = jnp.where(odd, cos_r, sin_r)
  cos = jnp.where(odd, sin_r, cos_r)
  sin = jnp.where((quadrant & 2) == 2, -sin, sin)     # quadrants 2 and 3
  cos = jnp.where(((quadrant + 1) & 2) == 2, -cos, cos)   # quadrants 1 and 2
  return sin, cos


@sincos.defjvp
def _sincos_jvp(primals, tangents):
  (x,), (dx,) = primals, tangents
  sin, cos = sincos(x)
  return (sin, cos), (cos * dx, -sin * dx)


def relative_geometry(p_src: jax.Array, p_dst: jax.Array, heading_src: jax.Array, heading_dst: jax.Array) -> jax.Array:
  """QCNet's relation triple, in metres: [|dp|, angle of dp in dst's frame, wrap(theta_src - theta_dst)].

  Args broadcast against each other; returns `[..., 3]`.
  """
  d = p_src - p_dst
  dist = jnp.sqrt(jnp.sum(d * d, axis=-1) + 1e-12)
  angle = wrap_angle(jnp.arctan2(d[..., 1], d[..., 0]) - heading_dst)
  return jnp.stack([dist, angle, wrap_angle(heading_src - heading_dst)], axis=-1)


class FourierEmbedding(nnx.Module):
  """QCNet's Fourier embedding of I continuous inputs (plus optional categorical embeddings).

  Each scalar x_i -> [cos 2 pi f_i x, sin 2 pi f_i x, x] with F learnable frequencies, then its own
  MLP (2F + 1 -> D, LayerNorm, ReLU, D -> D); the I results and the categorical embeddings are summed
  and go through LayerNorm, ReLU, Linear. `[..., I]` -> `[..., D]`. `freqs` `[I, F]`: initial
  frequencies (default QCNet's 0.02 x N(0, 1), periods of ~50 input units; see `log_spaced_freqs`).

  `table_size` G > 0: a call over at least `TABLE_MIN_ROWS` x G rows evaluates each input's MLP at G
  evenly spaced values spanning that input's range in the call (over the `valid` rows) and interpolates
  linearly between them, instead of evaluating it at every row: a few gathers per row instead of the
  I per-input MLPs, which are most of the work. The result is the exact embedding to interpolation
  error, small where the frequencies are low against the range (relations in metres and radians with
  QCNet's initial frequencies: `tests/test_layers.py` states the bound); smaller calls are exact.
  """

  def __init__(self, num_inputs: int, dim: int, num_freq_bands: int, freqs: jax.Array | None = None,
               table_size: int = 0, *, rngs: nnx.Rngs):
    i, f = num_inputs, num_freq_bands
    check_fourier_tables(table_size)
    self.table_size = table_size
    init = nnx.initializers.xavier_uniform(in_axis=-2, out_axis=-1, batch_axis=(0,))
    if freqs is None:  # QCNet's initialisation, for inputs of order 1
      freqs = 0.02 * jax.random.normal(rngs.params(), (i, f))
    elif freqs.shape != (i, f):
      raise ValueError(f"FourierEmbedding: initial frequencies {freqs.shape}, expected {(i, f)}")
    self.freqs = nnx.Param(jnp.array(freqs, jnp.float32, copy=True))  # never a buffer shared with another module
    self.w1 = nnx.Param(init(rngs.params(), (i, 2 * f + 1, dim)))
    self.b1 = nnx.Param(jnp.zeros((i, dim)))
    self.ln_scale = nnx.Param(jnp.ones((i, dim)))
    self.ln_bias = nnx.Param(jnp.zeros((i, dim)))
    self.w2 = nnx.Param(init(rngs.params(), (i, dim, dim)))
    self.b2 = nnx.Param(jnp.zeros((i, dim)))
    self.out_norm = nnx.LayerNorm(dim, rngs=rngs)
    self.out = nnx.Linear(dim, dim, rngs=rngs)

  def _hidden(self, x: jax.Array) -> list[jax.Array]:
    """Each input's first layer, normalised and rectified: I arrays `[..., D]` of `x` `[..., I]`."""
    phase = 2.0 * math.pi * x[..., None] * self.freqs[...]                       # [..., I, F]
    w1, b1 = self.w1[...], self.b1[...]
    scale, bias = self.ln_scale[...], self.ln_bias[...]
    # One plain matmul per input for the first layer (a batched einsum over the middle axis is slower on CPU).
    hidden = []
    for i in range(w1.shape[0]):
      sin, cos = sincos(phase[..., i, :])
      feats = jnp.concatenate([cos, sin, x[..., i:i + 1]], -1)
      h = feats @ w1[i] + b1[i]
      mu = h.mean(-1, keepdims=True)
      var = ((h - mu) ** 2).mean(-1, keepdims=True)
      hidden.append(jax.nn.relu((h - mu) * jax.lax.rsqrt(var + 1e-5) * scale[i] + bias[i]))
    return hidden

  def _tabulated(self, x: jax.Array, valid: jax.Array | None) -> jax.Array:
    """sum_i MLP_i(x_i) `[..., D]` (before b2), each MLP_i interpolated from `table_size` values."""
    g, num_inputs = self.table_size, x.shape[-1]
    rows = x.reshape(-1, num_inputs)
    ok = jnp.ones(rows.shape[0], bool) if valid is None else jnp.broadcast_to(valid, x.shape[:-1]).reshape(-1)
    lo = jnp.min(jnp.where(ok[:, None], rows, jnp.inf), axis=0)                   # [I]
    hi = jnp.max(jnp.where(ok[:, None], rows, -jnp.inf), axis=0)
    lo = jnp.where(jnp.isfinite(lo), lo, 0.0)                                    # no valid row: any range
    hi = jnp.maximum(jnp.where(jnp.isfinite(hi), hi, 0.0), lo + 1e-6)
    grid = lo + (hi - lo) * jnp.linspace(0.0, 1.0, g)[:, None]                   # [G, I]
    w2 = self.w2[...]
    table = [h @ w2[i] for i, h in enumerate(self._hidden(grid))]               # I x [G, D]
    # Invalid rows may lie outside the range: their positions are clipped (they are masked downstream).
    u = jnp.clip((rows - lo) / (hi - lo) * (g - 1), 0.0, g - 1.0)                # [N, I]
    left = jnp.minimum(u.astype(jnp.int32), g - 2)
    frac = u - left
    out = 0.0
    for i, t in enumerate(table):
      a = t.at[left[:, i]].get(mode="promise_in_bounds")
      b = t.at[left[:, i] + 1].get(mode="promise_in_bounds")
      out = out + a + (b - a) * frac[:, i:i + 1]
    return out.reshape(x.shape[:-1] + (w2.shape[-1],))

  def __call__(self, x: jax.Array, categorical: jax.Array | None = None, valid: jax.Array | None = None) -> jax.Array:
    """`x` `[..., I]`; `categorical` `[..., D]` or None; `valid` (broadcastable to `[...]`): the rows whose
    range a tabulated call spans (default: every row); the other rows' outputs are not meaningful."""
    num_rows = math.prod(x.shape[:-1])
    if self.table_size and num_rows >= TABLE_MIN_ROWS * self.table_size:
      h = self._tabulated(x, valid) + self.b2[...].sum(0)
    else:
      # One matmul for all inputs' second layers: sum_i h_i @ w2_i = [h_1 ... h_I] @ [w2_1; ...; w2_I].
      w2 = self.w2[...]
      h = jnp.concatenate(self._hidden(x), -1) @ w2.reshape(-1, w2.shape[-1]) + self.b2[...].sum(0)
    if categorical is not None:
      h = h + categorical
    return self.out(jax.nn.relu(self.out_norm(h)))


# A tabulated Fourier embedding pays for its G-row table when a call has at least this many times G rows.
TABLE_MIN_ROWS = 2


def check_fourier_tables(size: int, name: str = "model.fourier_tables") -> None:
  """A model config's `fourier_tables` (`FourierEmbedding.table_size`): 0 (exact) or at least 2 values."""
  if not isinstance(size, (int, np.integer)) or size < 0 or size == 1:
    raise ValueError(f"{name} must be 0 (exact) or an integer >= 2, got {size!r}")


def log_spaced_freqs(num_inputs: int, num_freq_bands: int, min_period: float, max_period: float) -> jax.Array:
  """`[I, F]` frequencies whose periods are log-spaced from `min_period` to `max_period` (input units)."""
  periods = jnp.geomspace(min_period, max_period, num_freq_bands)
  return jnp.broadcast_to(1.0 / periods, (num_inputs, num_freq_bands))


def linears(x: jax.Array, *modules: nnx.Linear) -> tuple[jax.Array, ...]:
  """`m(x)` for each of several `nnx.Linear` layers of the same input, as one matmul with their kernels
  side by side (fewer, larger products: what small batches on a CPU spend their time on)."""
  kernel = jnp.concatenate([m.kernel[...] for m in modules], -1)
  y = x @ kernel
  if any(m.bias is not None for m in modules):
    y = y + jnp.concatenate([m.bias[...] if m.bias is not None else jnp.zeros(m.out_features, y.dtype)
                             for m in modules])
  return tuple(jnp.split(y, np.cumsum([m.out_features for m in modules])[:-1].tolist(), -1))


# Attention over at most this many keys (the denoiser's temporal attention over an agent's two tokens)
# takes its scores and weighted values as elementwise products and sums: XLA's CPU backend runs a
# batched matrix product as one small product per batch entry (per scene, agent and head: [2, 16] x
# [16, 2]), each with a fixed cost.
FEW_KEYS = 2


def _few_scores(q: jax.Array, k: jax.Array) -> jax.Array:
  """`einsum("...qhd,...khd->...hqk", q, k)` as sums over d of elementwise products (few keys)."""
  s = jnp.stack([jnp.sum(q * k[..., j:j + 1, :, :], -1) for j in range(k.shape[-3])], -1)   # [..., Q, H, K]
  return jnp.swapaxes(s, -3, -2)


def _few_mix(probs: jax.Array, v: jax.Array) -> jax.Array:
  """`einsum("...hqk,...khd->...qhd", probs, v)` as a sum over the few keys of elementwise products."""
  p = jnp.swapaxes(probs, -3, -2)                                                  # [..., Q, H, K]
  return sum(p[..., j, None] * v[..., j:j + 1, :, :] for j in range(v.shape[-3]))


class MultiHeadAttention(nnx.Module):
  """Standard multi-head attention with shared keys: `[..., Q, D]` x `[..., K, D]`, mask `[..., Q, K]`."""

  def __init__(self, dim: int, heads: int, *, rngs: nnx.Rngs):
    if dim % heads:
      raise ValueError(f"model width {dim} is not divisible by {heads} heads")
    self.heads = heads
    self.q = nnx.Linear(dim, dim, rngs=rngs)
    self.k = nnx.Linear(dim, dim, rngs=rngs)
    self.v = nnx.Linear(dim, dim, rngs=rngs)
    self.out = nnx.Linear(dim, dim, rngs=rngs)

  def __call__(self, x_q: jax.Array, x_kv: jax.Array, mask: jax.Array | None = None,
               dropout_rate: float = 0.0, key: jax.Array | None = None) -> jax.Array:
    h = self.heads
    split = lambda t: t.reshape(t.shape[:-1] + (h, t.shape[-1] // h))  # noqa: E731
    if x_kv is x_q:  # self-attention: one product for q, k and v
      q, k, v = map(split, linears(x_q, self.q, self.k, self.v))
    else:
      q, (k, v) = split(self.q(x_q)), map(split, linears(x_kv, self.k, self.v))
    few = k.shape[-3] <= FEW_KEYS
    logits = (_few_scores(q, k) if few else jnp.einsum("...qhd,...khd->...hqk", q, k)) / math.sqrt(q.shape[-1])
    if mask is None:
      mask = jnp.ones(logits.shape[:-3] + logits.shape[-2:], bool)
    probs = masked_softmax(logits, mask[..., None, :, :])
    probs = dropout(probs, dropout_rate, key)
    o = _few_mix(probs, v) if few else jnp.einsum("...hqk,...khd->...qhd", probs, v)
    return self.out(o.reshape(o.shape[:-2] + (-1,)))


def gelu(x: jax.Array) -> jax.Array:
  """`jax.nn.gelu` (the tanh approximation) to float rounding (within 1e-6; tests/test_layers.py), as
  x sigmoid(2u) with u = sqrt(2/pi) (x + 0.044715 x^3), since 0.5 (1 + tanh u) = sigmoid(2u): XLA's CPU
  backend runs the tanh form's fusion several times slower."""
  c = 2.0 * math.sqrt(2.0 / math.pi)
  return x * jax.lax.logistic(x * (c + (c * 0.044715) * (x * x)))


class FeedForward(nnx.Module):
  def __init__(self, dim: int, hidden: int, activation=gelu, *, rngs: nnx.Rngs):
    self.fc1 = nnx.Linear(dim, hidden, rngs=rngs)
    self.fc2 = nnx.Linear(hidden, dim, rngs=rngs)
    self.activation = activation

  def __call__(self, x: jax.Array, dropout_rate: float = 0.0, key: jax.Array | None = None) -> jax.Array:
    return self.fc2(dropout(self.activation(self.fc1(x)), dropout_rate, key))


class RelationalAttentionLayer(nnx.Module):
  """QCNet's `AttentionLayer` in dense form: each query attends to its own key set with relations.

  x_dst `[..., Q, D]`; the keys either per query, x_src `[..., Q, K, D]`, or shared, x_src
  `[..., S, D]` with `src_index` `[..., Q, K]` into S (None: every query sees all S sources, K = S);
  r `[..., Q, K, D]` relation embeddings; mask `[..., Q, K]`. Pre-LayerNorm on src, dst and r; keys
  and values get W r added; a gated update; post-LayerNorm and residual; then a 4x ReLU FFN block
  with pre- and post-LayerNorm and residual. Shared sources are normalised and projected once per
  source, before they are paired with queries.
  """

  def __init__(self, dim: int, heads: int, dropout_rate: float, *, rngs: nnx.Rngs):
    self.heads, self.dropout_rate = heads, dropout_rate
    self.norm_src = nnx.LayerNorm(dim, rngs=rngs)
    self.norm_dst = nnx.LayerNorm(dim, rngs=rngs)
    self.norm_r = nnx.LayerNorm(dim, rngs=rngs)
    self.q = nnx.Linear(dim, dim, rngs=rngs)
    self.k = nnx.Linear(dim, dim, use_bias=False, rngs=rngs)
    self.v = nnx.Linear(dim, dim, rngs=rngs)
    self.k_r = nnx.Linear(dim, dim, use_bias=False, rngs=rngs)
    self.v_r = nnx.Linear(dim, dim, rngs=rngs)
    self.s = nnx.Linear(dim, dim, rngs=rngs)
    self.g = nnx.Linear(2 * dim, dim, rngs=rngs)
    self.to_out = nnx.Linear(dim, dim, rngs=rngs)
    self.attn_postnorm = nnx.LayerNorm(dim, rngs=rngs)
    self.ff_prenorm = nnx.LayerNorm(dim, rngs=rngs)
    self.ff = FeedForward(dim, 4 * dim, jax.nn.relu, rngs=rngs)
    self.ff_postnorm = nnx.LayerNorm(dim, rngs=rngs)

  def __call__(self, x_dst: jax.Array, x_src: jax.Array, r: jax.Array, mask: jax.Array,
               key: jax.Array | None = None, src_index: jax.Array | None = None) -> jax.Array:
    h = self.heads
    split = lambda t: t.reshape(t.shape[:-1] + (h, t.shape[-1] // h))  # noqa: E731
    dst, src, rel = self.norm_dst(x_dst), self.norm_src(x_src), self.norm_r(r)
    k_src, v_src = linears(src, self.k, self.v)
    if x_src.ndim == x_dst.ndim:  # shared sources: pair them with the queries
      if src_index is None:
        k_src, v_src = k_src[..., None, :, :], v_src[..., None, :, :]
      else:
        pair = jax.vmap(lambda a, i: a[i]) if src_index.ndim == 3 else (lambda a, i: a[i])
        k_src, v_src = pair(k_src, src_index), pair(v_src, src_index)
    q = split(self.q(dst))                                  # [..., Q, H, d]
    k_rel, v_rel = linears(rel, self.k_r, self.v_r)
    k = split(k_src + k_rel)                                # [..., Q, K, H, d]
    v = split(v_src + v_rel)
    logits = jnp.einsum("...qhd,...qkhd->...qhk", q, k) / math.sqrt(q.shape[-1])
    probs = dropout(masked_softmax(logits, mask[..., None, :]), self.dropout_rate, fold(key, 0))
    agg = jnp.einsum("...qhk,...qkhd->...qhd", probs, v).reshape(x_dst.shape)
    return self._update(x_dst, dst, agg, key)

  def packed(self, x: jax.Array, r: jax.Array, dst_index: jax.Array, src_index: jax.Array, valid: jax.Array,
             key: jax.Array | None = None, x_src: jax.Array | None = None) -> jax.Array:
    """The same layer over a list of E (query, key) pairs: queries `x` `[N, D]`, sources `x_src` `[S, D]`
    (None: the queries themselves, self-attention), `dst_index` `[E]` into N (sorted), `src_index` `[E]`
    into S, `valid` `[E]`, relations r `[E, D]`.

    Only the listed pairs are computed, not every (query, key) slot of a padded `[Q, K]` grid: a
    batch of scenes of different sizes packed into one list costs its real pairs. Equal to `__call__`
    with the mask of the same pairs (tested), up to float rounding.
    """
    h, n = self.heads, x.shape[0]
    split = lambda t: t.reshape(t.shape[:-1] + (h, t.shape[-1] // h))  # noqa: E731
    dst, src, rel = self.norm_dst(x), self.norm_src(x if x_src is None else x_src), self.norm_r(r)
    k_src, v_src = linears(src, self.k, self.v)                          # [S, D]
    q = split(self.q(dst))                                                # [N, H, d]
    k_rel, v_rel = linears(rel, self.k_r, self.v_r)                       # [E, D]
    k = split(k_src[src_index] + k_rel)                                  # [E, H, d]
    v = split(v_src[src_index] + v_rel)
    logits = jnp.sum(q[dst_index] * k, -1) / math.sqrt(q.shape[-1])     # [E, H]
    probs = dropout(segment_softmax(logits, dst_index, valid, n), self.dropout_rate, fold(key, 0))
    agg = jax.ops.segment_sum(probs[..., None] * v, dst_index, n, indices_are_sorted=True).reshape(x.shape)
    return self._update(x, dst, agg, key)

  def _update(self, x_dst: jax.Array, dst: jax.Array, agg: jax.Array, key: jax.Array | None) -> jax.Array:
    """The gated update, residual and FFN block after the attention's aggregate `agg` `[..., Q, D]`."""
    gate = jax.nn.sigmoid(self.g(jnp.concatenate([agg, dst], -1)))
    out = self.to_out(agg + gate * (self.s(dst) - agg))
    x = x_dst + self.attn_postnorm(dropout(out, self.dropout_rate, fold(key, 1)))
    ff = self.ff(self.ff_prenorm(x), self.dropout_rate, fold(key, 2))
    return x + self.ff_postnorm(dropout(ff, self.dropout_rate, fold(key, 3)))


class DifferentialAttention(nnx.Module):
  """Differential cross-attention (Ye et al. 2024) as the official `MultiheadDiffAttn`.

  q, k are split into 2H sub-heads of width D/2H, v into H heads of D/H. Per head, two softmax maps
  A1, A2 over the keys give W = A1 - lambda A2, with lambda = exp(lq1.lk1) - exp(lq2.lk2) + lambda_init
  and lambda_init = 0.8 - 0.6 exp(-0.3 depth). The head output is RMSNorm(W V) (trained weight) times
  (1 - lambda_init). Returns the output `[..., Q, D]` and W `[..., H, Q, K]` (for the entropy loss).

  With `relational=True` (the grounded denoiser) each (query, key) pair has a relation embedding r
  `[..., Q, K, D]`: keys get W_k r and values W_v r added (QCNet's relational attention), and both
  maps get a learned per-head multiple of `bias` `[..., Q, K]` (e.g. -log(1 + distance)).
  """

  def __init__(self, dim: int, heads: int, depth: int, relational: bool = False, *, rngs: nnx.Rngs):
    self.heads = heads
    self.sub_dim = dim // heads // 2
    self.lambda_init = 0.8 - 0.6 * math.exp(-0.3 * depth)
    self.q = nnx.Linear(dim, dim, use_bias=False, rngs=rngs)
    self.k = nnx.Linear(dim, dim, use_bias=False, rngs=rngs)
    self.v = nnx.Linear(dim, dim, use_bias=False, rngs=rngs)
    self.out = nnx.Linear(dim, dim, use_bias=False, rngs=rngs)
    init = lambda: nnx.Param(0.1 * jax.random.normal(rngs.params(), (self.sub_dim,)))  # noqa: E731
    self.lambda_q1, self.lambda_k1, self.lambda_q2, self.lambda_k2 = init(), init(), init(), init()
    self.subln = nnx.RMSNorm(2 * self.sub_dim, epsilon=1e-5, rngs=rngs)
    self.relational = relational
    if relational:
      self.k_r = nnx.Linear(dim, dim, use_bias=False, rngs=rngs)
      self.v_r = nnx.Linear(dim, dim, use_bias=False, rngs=rngs)
      self.bias_scale = nnx.Param(jnp.ones((heads, 2)))

  def project_sources(self, x_kv: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The keys and values `[B, S, D]` of sources `x_kv`, to compute once for many calls (`kv=`)."""
    return linears(x_kv, self.k, self.v)

  def __call__(self, x_q: jax.Array, x_kv: jax.Array, mask: jax.Array, r: jax.Array | None = None,
               bias: jax.Array | None = None, src_index: jax.Array | None = None,
               kv: tuple[jax.Array, jax.Array] | None = None) -> tuple[jax.Array, jax.Array]:
    """x_q `[B, Q, D]`, x_kv `[B, S, D]`; mask, bias `[B, Q, K]` and r `[B, Q, K, D]` over each query's
    keys: all S sources (K = S), or with `src_index` `[B, Q, K]` the sources it names. `kv`:
    `project_sources(x_kv)` computed beforehand (the sampler's polygons do not change between steps)."""
    h, d = self.heads, self.sub_dim
    q = self.q(x_q).reshape(x_q.shape[:-1] + (h, 2, d))
    k, v = kv if kv is not None else self.project_sources(x_kv)
    k = k.reshape(x_kv.shape[:-1] + (h, 2, d))
    v = v.reshape(x_kv.shape[:-1] + (h, 2 * d))
    if src_index is None:
      logits = jnp.einsum("...qhsd,...khsd->...hsqk", q, k) / math.sqrt(d)
    else:  # per-query key sets, projected once per source and then gathered
      pair = jax.vmap(lambda a, i: a[i])
      k, v = pair(k, src_index), pair(v, src_index)                       # [B, Q, K, ...]
      logits = jnp.einsum("...qhsd,...qkhsd->...hsqk", q, k) / math.sqrt(d)
    if self.relational:  # pair terms: q . W_k r_qk and the per-head bias
      k_r, v_r = linears(r, self.k_r, self.v_r)
      k_r = k_r.reshape(r.shape[:-1] + (h, 2, d))                          # [..., Q, K, H, 2, d]
      logits = logits + jnp.einsum("...qhsd,...qkhsd->...hsqk", q, k_r) / math.sqrt(d)
      logits = logits + self.bias_scale[...][..., None, None] * bias[..., None, None, :, :]
    probs = masked_softmax(logits, mask[..., None, None, :, :])          # [..., H, 2, Q, K]
    lam = (jnp.exp(jnp.dot(self.lambda_q1[...], self.lambda_k1[...]))
           - jnp.exp(jnp.dot(self.lambda_q2[...], self.lambda_k2[...])) + self.lambda_init)
    w = probs[..., 0, :, :] - lam * probs[..., 1, :, :]                  # [..., H, Q, K]
    if src_index is None:
      o = jnp.einsum("...hqk,...khd->...qhd", w, v)
    else:
      o = jnp.einsum("...hqk,...qkhd->...qhd", w, v)
    if self.relational:
      v_r = v_r.reshape(r.shape[:-1] + (h, 2 * d))                         # [..., Q, K, H, 2d]
      o = o + jnp.einsum("...hqk,...qkhd->...qhd", w, v_r)
    o = self.subln(o) * (1.0 - self.lambda_init)
    return self.out(o.reshape(o.shape[:-2] + (-1,))), w
