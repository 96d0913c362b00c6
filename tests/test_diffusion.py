"""Diffusion schedules and update rules against closed forms and against each other."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tdiff_jax import diffusion


@pytest.fixture(scope="module")
def sched():
  return diffusion.linear_schedule(500, 1e-4, 0.05)


def test_linear_schedule_matches_the_paper(sched):
  b = np.asarray(sched.betas, np.float64)
  assert sched.num_steps == 500 and b[0] == 0.0
  np.testing.assert_allclose(b[1:], np.linspace(1e-4, 0.05, 500), rtol=1e-6)
  np.testing.assert_allclose(sched.alpha_bars, np.cumprod(1 - b), rtol=1e-5)
  assert 1e-6 < float(sched.alpha_bars[-1]) < 1e-5  # ~2.9e-6: close to pure noise at T


def test_cosine_schedule_closed_form():
  s = diffusion.cosine_schedule(100)
  t = np.arange(101) / 100
  f = np.cos((t + 0.008) / 1.008 * np.pi / 2) ** 2
  np.testing.assert_allclose(s.alpha_bars[:-1], (f / f[0])[:-1], rtol=1e-4, atol=1e-6)
  with pytest.raises(ValueError, match="unknown diffusion schedule"):
    diffusion.make_schedule("quadratic", 10)


def test_forward_noising_and_its_inverses(sched):
  k1, k2 = jax.random.split(jax.random.PRNGKey(0))
  x0 = jax.random.normal(k1, (4, 5, 2, 3))
  eps = jax.random.normal(k2, x0.shape)
  t = jnp.array([1, 10, 250, 500])
  xt = diffusion.q_sample(sched, x0, t, eps)
  abar = np.asarray(sched.alpha_bars)[np.asarray(t)][:, None, None, None]
  np.testing.assert_allclose(xt, np.sqrt(abar) * x0 + np.sqrt(1 - abar) * eps, rtol=1e-5, atol=1e-6)
  np.testing.assert_allclose(diffusion.x0_from_eps(sched, xt, t, eps), x0, atol=2e-3)
  np.testing.assert_allclose(diffusion.eps_from_x0(sched, xt, t, x0), eps, atol=2e-3)


def test_posterior_is_the_gaussian_product(sched):
  x0, xt = jnp.full((3,), 0.7), jnp.array([-1.0, 0.2, 1.5])
  for t in (2, 50, 499):
    mean, var = diffusion.posterior_mean_variance(sched, x0, xt, jnp.asarray(t))
    b = float(sched.betas[t])
    a = 1 - b
    ap = float(sched.alpha_bars[t - 1])
    prec = 1 / (1 - ap) + a / b  # N(x_{t-1}; sqrt(ap) x0, 1-ap) * N(xt; sqrt(a) x_{t-1}, b)
    np.testing.assert_allclose(var, 1 / prec, rtol=1e-4)
    np.testing.assert_allclose(mean, (np.sqrt(ap) * 0.7 / (1 - ap) + np.sqrt(a) * np.asarray(xt) / b) / prec,
                               rtol=1e-4, atol=1e-6)


def test_ddpm_mean_is_the_posterior_mean_of_the_predicted_x0(sched):
  xt, eps_hat = jnp.array([0.3, -0.4]), jnp.array([0.5, 0.1])
  t = jnp.asarray(37)
  x0 = diffusion.x0_from_eps(sched, xt, t, eps_hat)
  mean, _ = diffusion.posterior_mean_variance(sched, x0, xt, t)
  np.testing.assert_allclose(diffusion.ddpm_step(sched, xt, t, eps_hat, jnp.zeros(2)), mean, rtol=1e-4, atol=1e-6)


def test_ddim_with_eta_one_and_full_stride_is_ddpm(sched):
  key = jax.random.PRNGKey(1)
  xt = jax.random.normal(key, (6, 3))
  eps_hat = jax.random.normal(jax.random.fold_in(key, 1), xt.shape)
  noise = jax.random.normal(jax.random.fold_in(key, 2), xt.shape)
  step = jax.jit(diffusion.ddim_step)
  for t in (1, 2, 100, 500):
    t = jnp.asarray(t)
    np.testing.assert_allclose(step(sched, xt, t, t - 1, eps_hat, 1.0, noise),
                               diffusion.ddpm_step(sched, xt, t, eps_hat, noise), rtol=1e-4, atol=1e-5)


def test_ddim_deterministic_and_exact_at_the_end(sched):
  xt, eps_hat = jnp.array([0.3, -0.4]), jnp.array([0.5, 0.1])
  t = jnp.asarray(10)
  out = diffusion.ddim_step(sched, xt, t, jnp.asarray(0), eps_hat)  # alpha_bar_0 = 1: returns x0_hat
  np.testing.assert_allclose(out, diffusion.x0_from_eps(sched, xt, t, eps_hat), rtol=1e-6)
  steps = diffusion.ddim_timesteps(500, 10)
  assert len(steps) == 50 and steps[0] == 500 and steps[-1] == 10
  with pytest.raises(ValueError, match="stride"):
    diffusion.ddim_timesteps(500, 0)
