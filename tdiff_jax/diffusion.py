"""Diffusion schedules and DDPM/DDIM update rules as pure functions.

A `Schedule` holds arrays indexed by the diffusion step t = 0..T, with beta_0 = 0 prepended as in the
official code, so alpha_bar_0 = 1 and step t = 0 is clean data. Every function is jit-able and works on
any leading batch shape: `t` is an int array that broadcasts against the leading axes of `x`
(for the HL model, `x` is `[B, A, 2, 3]` and `t` is `[B]`, one step per scene).
"""

from __future__ import annotations


import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


@struct.dataclass
class Schedule:
  """Arrays of shape `[T + 1]`: betas, alphas, alpha_bars; `num_steps` = T."""

  betas: jax.Array
  alphas: jax.Array
  alpha_bars: jax.Array

  @property
  def num_steps(self) -> int:
    return self.betas.shape[0] - 1



def _from_betas(betas: np.ndarray) -> Schedule:
  betas = np.concatenate([[0.0], np.asarray(betas, np.float64)])
  alphas = 1.0 - betas
  alpha_bars = np.cumprod(alphas)
  f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
  return Schedule(f32(betas), f32(alphas), f32(alpha_bars))


# The paper's (and the official default's) linear betas.
BETA_START, BETA_END = 1e-4, 0.05


def linear_schedule(num_steps: int = 500, beta_start: float = BETA_START, beta_end: float = BETA_END) -> Schedule:
  """Linear betas (the paper's: 1e-4 to 0.05 over T = 500)."""
  return _from_betas(np.linspace(beta_start, beta_end, num_steps))


def schedule_from_config(d) -> Schedule:
  """The paper's linear schedule over a config's `diffusion.num_steps` steps. A checkpoint's older config may
  also name its `schedule` and betas, at the paper's values ("linear", 1e-4, 0.05); other values or fields are
  a ValueError naming them."""
  older = {"schedule": "linear", "beta_start": BETA_START, "beta_end": BETA_END}
  other = sorted(f"diffusion.{k}={d[k]!r}" for k in d.keys()
                 if k != "num_steps" and (k not in older or d[k] != older[k]))
  if other:
    raise ValueError(f"{', '.join(other)}: the diffusion schedule is the paper's, linear betas from {BETA_START} to "
                     f"{BETA_END} over diffusion.num_steps steps")
  return linear_schedule(d.num_steps)


def _at(values: jax.Array, t, x: jax.Array) -> jax.Array:
  """values[t] reshaped to broadcast over the trailing axes of x."""
  v = values[jnp.asarray(t)]
  return v.reshape(v.shape + (1,) * (x.ndim - v.ndim))


def alpha_bar_at(sched: Schedule, t, x: jax.Array) -> jax.Array:
  """alpha_bar_t shaped to broadcast over the trailing axes of x (t per scene `[B]`, per token time, ...)."""
  return _at(sched.alpha_bars, t, x)


def q_sample(sched: Schedule, x0: jax.Array, t, noise: jax.Array) -> jax.Array:
  """Forward noising: x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps."""
  abar = _at(sched.alpha_bars, t, x0)
  return jnp.sqrt(abar) * x0 + jnp.sqrt(1.0 - abar) * noise


def x0_from_eps(sched: Schedule, xt: jax.Array, t, eps: jax.Array) -> jax.Array:
  abar = _at(sched.alpha_bars, t, xt)
  return (xt - jnp.sqrt(1.0 - abar) * eps) / jnp.sqrt(abar)


def eps_from_x0(sched: Schedule, xt: jax.Array, t, x0: jax.Array) -> jax.Array:
  abar = _at(sched.alpha_bars, t, xt)
  return (xt - jnp.sqrt(abar) * x0) / jnp.sqrt(1.0 - abar)


def posterior_mean_variance(sched: Schedule, x0: jax.Array, xt: jax.Array, t) -> tuple[jax.Array, jax.Array]:
  """q(x_{t-1} | x_t, x0): mean and variance beta_t (1 - abar_{t-1}) / (1 - abar_t), for t >= 1."""
  t = jnp.asarray(t)
  beta = _at(sched.betas, t, xt)
  alpha = _at(sched.alphas, t, xt)
  abar = _at(sched.alpha_bars, t, xt)
  abar_prev = _at(sched.alpha_bars, t - 1, xt)
  mean = (jnp.sqrt(abar_prev) * beta / (1.0 - abar)) * x0 + (jnp.sqrt(alpha) * (1.0 - abar_prev) / (1.0 - abar)) * xt
  var = beta * (1.0 - abar_prev) / (1.0 - abar)
  return mean, var


def ddpm_step(sched: Schedule, x0: jax.Array, xt: jax.Array, t, noise: jax.Array) -> jax.Array:
  """One ancestral DDPM step t -> t - 1 from the predicted (possibly clipped or guided) `x0`: a draw
  from the posterior q(x_{t-1} | x_t, x0); no noise is added at t = 1."""
  t = jnp.asarray(t)
  mean, var = posterior_mean_variance(sched, x0, xt, t)
  last = (t <= 1).reshape(t.shape + (1,) * (xt.ndim - t.ndim))
  return mean + jnp.where(last, 0.0, jnp.sqrt(var)) * noise


def ddim_step(sched: Schedule, x0: jax.Array, eps_hat: jax.Array, t, t_prev, eta: float = 0.0,
              noise: jax.Array | None = None) -> jax.Array:
  """One DDIM step t -> t_prev < t (Song et al. eq. 12) from the predicted `x0` (possibly clipped or
  guided) and noise `eps_hat`; eta = 0 is deterministic.

  With x0 = `x0_from_eps(eps_hat)`, eta = 1 and t_prev = t - 1 this is the DDPM ancestral step.
  """
  abar = _at(sched.alpha_bars, t, x0)
  abar_prev = _at(sched.alpha_bars, t_prev, x0)
  sigma = eta * jnp.sqrt((1.0 - abar_prev) / (1.0 - abar) * (1.0 - abar / abar_prev))
  direction = jnp.sqrt(jnp.maximum(1.0 - abar_prev - sigma ** 2, 0.0)) * eps_hat
  out = jnp.sqrt(abar_prev) * x0 + direction
  if noise is not None:
    out = out + sigma * noise
  return out


def ddim_timesteps(num_steps: int, stride: int) -> np.ndarray:
  """Descending steps T, T - stride, ..., down to >= 1 (the official DDIM loop; T/stride network calls)."""
  if stride < 1 or stride > num_steps:
    raise ValueError(f"DDIM stride must be in [1, {num_steps}], got {stride}")
  return np.arange(num_steps, 0, -stride)


def solver_timesteps(sched: Schedule, num_calls: int, max_noise: float = 0.0) -> jax.Array:
  """`[num_calls]` descending integer steps from T to 1, evenly spaced in lambda = log(alpha / sigma).

  The log-SNR spacing puts more steps at low noise, where lane-scale detail is decided (with the
  linear schedule, t <= 30 is noise <= 10 m). Evenly spaced t would make the last step of a
  multistep solver span most of the log-SNR range, and measured worse than DDIM on Gaussian data.
  `max_noise > 0`: the first call stays at T and the others are evenly spaced in lambda from the
  step whose noise-to-signal ratio sigma / alpha is `max_noise` (normalised units, i.e. standard
  deviations of the data) down to 1: the linear schedule's T is at 584, where several calls would
  see nothing but noise. Works on a traced schedule (inside `jit`); `num_calls` is static.
  """
  t_max = sched.num_steps
  if not 2 <= num_calls <= t_max:
    raise ValueError(f"solver steps must be in [2, {t_max}], got {num_calls}")
  if max_noise < 0:
    raise ValueError(f"the solver's largest noise level must be >= 0 (0: from T), got {max_noise}")
  lam = _log_snr_half(sched.alpha_bars[1:])  # decreasing in t = 1..T
  targets = jnp.linspace(lam[-1], lam[0], num_calls)
  if max_noise > 0:  # a level at or above T's: the plain spacing
    start = jnp.minimum(-jnp.log(jnp.asarray(max_noise, lam.dtype)), lam[0])
    late = jnp.concatenate([lam[-1:], jnp.linspace(start, lam[0], num_calls - 1)])
    targets = jnp.where(start > lam[-1], late, targets)
  t = 1.0 + jnp.interp(targets, lam[::-1], jnp.arange(t_max - 1, -1, -1, dtype=lam.dtype))
  steps = jnp.clip(jnp.round(t).astype(jnp.int32), 1, t_max)
  # Strictly decreasing even where rounding merges neighbours: step i <= step i-1 - 1, and room below.
  i = jnp.arange(num_calls, dtype=jnp.int32)
  steps = jax.lax.cummin(steps + i) - i
  return jnp.maximum(steps, num_calls - i).at[0].set(t_max)


def _log_snr_half(abar: jax.Array) -> jax.Array:
  """lambda = log(alpha / sigma) = 0.5 log(abar / (1 - abar)); +inf at abar = 1 (t = 0)."""
  return 0.5 * (jnp.log(abar) - jnp.log1p(-abar))


def dpmpp_2m_step(sched: Schedule, xt: jax.Array, t, t_prev, x0: jax.Array, x0_last: jax.Array,
                  h_last: jax.Array) -> tuple[jax.Array, jax.Array]:
  """One DPM-Solver++(2M) step t -> t_prev < t with data prediction (Lu et al. 2022, Algorithm 2).

  `x0` is the (clipped, guided) prediction at t; `x0_last` and `h_last` are the previous step's
  prediction and log-SNR step, with `h_last = 0` on the first step (then the step is first order,
  which is DDIM). The step to t_prev = 0 returns `x0` (first order: alpha = 1, sigma = 0).
  Returns (x at t_prev, h of this step).
  """
  abar, abar_prev = _at(sched.alpha_bars, t, xt), _at(sched.alpha_bars, t_prev, xt)
  final = abar_prev >= 1.0
  safe_prev = jnp.where(final, abar, abar_prev)
  h = _log_snr_half(safe_prev) - _log_snr_half(abar)
  r = h_last / jnp.where(h > 0, h, 1.0)
  second = h_last > 0
  d = jnp.where(second, x0 + (x0 - x0_last) / (2.0 * jnp.where(second, r, 1.0)), x0)
  sigma_ratio = jnp.sqrt((1.0 - safe_prev) / (1.0 - abar))
  x_prev = sigma_ratio * xt - jnp.sqrt(safe_prev) * jnp.expm1(-h) * d
  return jnp.where(final, x0, x_prev), jnp.where(final, 0.0, h)
