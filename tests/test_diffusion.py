"""Diffusion schedules and update rules against closed forms and against each other."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tdiff_jax import diffusion

from tdiff_jax.data import normalize


@pytest.fixture(scope="module")
def sched():
  return diffusion.linear_schedule(500, 1e-4, 0.05)


def test_linear_schedule_matches_the_paper(sched):
  b = np.asarray(sched.betas, np.float64)
  assert sched.num_steps == 500 and b[0] == 0.0
  np.testing.assert_allclose(b[1:], np.linspace(1e-4, 0.05, 500), rtol=1e-6)
  np.testing.assert_allclose(sched.alpha_bars, np.cumprod(1 - b), rtol=1e-5)
  assert 1e-6 < float(sched.alpha_bars[-1]) < 1e-5  # ~2.9e-6: close to pure noise at T


def test_schedule_from_a_config_is_linear():
  import ml_collections
  d = ml_collections.ConfigDict(dict(num_steps=10))
  np.testing.assert_allclose(diffusion.schedule_from_config(d).betas, diffusion.linear_schedule(10).betas)
  d.update(schedule="linear", beta_start=1e-4, beta_end=0.05)   # a checkpoint's older config names them
  np.testing.assert_allclose(diffusion.schedule_from_config(d).betas, diffusion.linear_schedule(10).betas)
  for field, value in (("schedule", "cosine"), ("beta_end", 0.02), ("betas", 1)):
    with pytest.raises(ValueError, match=f"diffusion.{field}=.*the paper's, linear betas"):
      diffusion.schedule_from_config(ml_collections.ConfigDict(dict(num_steps=10, **{field: value})))


def test_forward_noising_and_its_inverses(sched):
  k1, k2 = jax.random.split(jax.random.key(0))
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
  np.testing.assert_allclose(diffusion.ddpm_step(sched, x0, xt, t, jnp.zeros(2)), mean, rtol=1e-6)
  # The posterior mean is also the epsilon-form update (x_t - beta_t / sqrt(1 - abar_t) eps) / sqrt(alpha_t).
  beta, alpha, abar = sched.betas[t], sched.alphas[t], sched.alpha_bars[t]
  np.testing.assert_allclose(mean, (xt - beta / jnp.sqrt(1.0 - abar) * eps_hat) / jnp.sqrt(alpha), rtol=1e-4, atol=1e-6)


def test_ddim_with_eta_one_and_full_stride_is_ddpm(sched):
  key = jax.random.key(1)
  xt = jax.random.normal(key, (6, 3))
  eps_hat = jax.random.normal(jax.random.fold_in(key, 1), xt.shape)
  noise = jax.random.normal(jax.random.fold_in(key, 2), xt.shape)
  step = jax.jit(diffusion.ddim_step)
  for t in (1, 2, 100, 500):
    t = jnp.asarray(t)
    x0 = diffusion.x0_from_eps(sched, xt, t, eps_hat)
    # float32: 1 - abar_{t-1} at t = 2 is 1e-4 (cancellation), x0 at t = 500 is x_t amplified 600x.
    np.testing.assert_allclose(step(sched, x0, eps_hat, t, t - 1, 1.0, noise),
                               diffusion.ddpm_step(sched, x0, xt, t, noise), rtol=2e-3, atol=1e-5)


def test_ddim_deterministic_and_exact_at_the_end(sched):
  xt, eps_hat = jnp.array([0.3, -0.4]), jnp.array([0.5, 0.1])
  t = jnp.asarray(10)
  x0 = diffusion.x0_from_eps(sched, xt, t, eps_hat)
  out = diffusion.ddim_step(sched, x0, eps_hat, t, jnp.asarray(0))  # alpha_bar_0 = 1: returns x0_hat
  np.testing.assert_allclose(out, x0, rtol=1e-6)
  steps = diffusion.ddim_timesteps(500, 10)
  assert len(steps) == 50 and steps[0] == 500 and steps[-1] == 10
  with pytest.raises(ValueError, match="stride"):
    diffusion.ddim_timesteps(500, 0)


def test_importance_sampled_steps_keep_the_min_snr_objective():
  """Drawing t in proportion to min(SNR, gamma) and reweighting leaves the expected loss as under uniform
  draws, and spends almost nothing on t > 300. The stand-in denoiser predicts x0 with a fixed error
  (random per draw), so its epsilon error scales with sqrt(SNR_t) as an x0-predicting network's does."""
  from types import SimpleNamespace

  from tdiff_jax import hl_objective
  sched = diffusion.linear_schedule()
  probs = hl_objective.importance_probs(sched, 5.0)
  assert abs(float(probs.sum()) - 1.0) < 1e-5
  assert float(probs[300:].sum()) < 0.01 and float(probs[:100].sum()) > 0.8

  b, a = 4, 3
  batch = SimpleNamespace(agent_state=jnp.ones((b, a, 2, 4)), frame_scale=jnp.full((b,), 125.0),
                          agent_valid=jnp.ones((b, a), bool), pl_valid=jnp.ones((b, 5), bool))
  norm = normalize.NormStats(jnp.zeros(3), jnp.ones(3))

  x0 = normalize.normalized_state(batch, norm)

  def stand_in(scene, x_t, beta, alpha_bar, norm, self_only=None, key=None):
    ab = alpha_bar[:, None, None, None]
    x0_hat = x0 + 0.3 * jnp.sign(x_t)                                  # off by 0.3 in a random direction
    return (x_t - jnp.sqrt(ab) * x0_hat) / jnp.sqrt(1.0 - ab), [jnp.zeros((b, 1, 2 * a, 5))]

  def mean_loss(t_sampling):
    # One compiled program per objective: run eagerly, vmap compiles every op apart (thousands of small
    # XLA:CPU compiles, one of which has crashed a worker of the parallel suite).
    losses = jax.jit(jax.vmap(lambda k: hl_objective.hl_loss(stand_in, batch, norm, sched, k, 0.0, 0.0, train=False,
                                                             loss_weighting="min_snr", t_sampling=t_sampling)[0]))(
        jax.random.split(jax.random.key(0), 4000))
    return float(losses.mean())
  uniform, importance = mean_loss("uniform"), mean_loss("importance")
  assert abs(importance - uniform) < 0.05 * uniform, (uniform, importance)


def test_staged_token_noise_keeps_the_objective():
  """Staged noise (the grounded denoiser's `staged_noise`) trains each token at its own step and weighs it there, so for a
  denoiser whose error at a token depends only on that token's noise level the expected loss is the
  shared-noise one, under importance-sampled steps too; both tokens noised are at the same step."""
  from types import SimpleNamespace

  from tdiff_jax import hl_objective
  sched = diffusion.linear_schedule()
  b, a = 4, 3
  batch = SimpleNamespace(agent_state=jnp.ones((b, a, 2, 4)), frame_scale=jnp.full((b,), 125.0),
                          agent_valid=jnp.ones((b, a), bool), pl_valid=jnp.ones((b, 5), bool))
  norm = normalize.NormStats(jnp.zeros(3), jnp.ones(3))
  x0 = normalize.normalized_state(batch, norm)
  levels = []

  class StandIn:
    def __init__(self, token_noise):
      self.cfg = SimpleNamespace(staged_noise=token_noise == "staged")

    def __call__(self, scene, x_t, beta, alpha_bar, norm, self_only=None, key=None):
      levels.append(alpha_bar)
      ab = alpha_bar[:, None, None, None] if alpha_bar.ndim == 1 else alpha_bar[:, None, :, None]
      x0_hat = x0 + 0.3 * jnp.sign(x_t)       # off by 0.3: the x0 error of an x0-predicting network
      return (x_t - jnp.sqrt(ab) * x0_hat) / jnp.sqrt(jnp.maximum(1.0 - ab, 1e-12)), [jnp.zeros((b, 1, 2 * a, 5))]

  def mean_loss(token_noise):
    model = StandIn(token_noise)
    losses = jax.vmap(lambda k: hl_objective.hl_loss(model, batch, norm, sched, k, 0.0, 0.0, train=False,
                                                     loss_weighting="min_snr", t_sampling="importance")[0])(
        jax.random.split(jax.random.key(0), 4000))
    return float(losses.mean())
  shared = mean_loss("shared")
  for token_noise in ("staged",):
    value = mean_loss(token_noise)
    assert abs(value - shared) < 0.05 * shared, (token_noise, shared, value)
    levels.clear()
    for k in range(30):   # eager calls: the levels the denoiser is given
      hl_objective.hl_loss(StandIn(token_noise), batch, norm, sched, jax.random.key(k), 0.0, 0.0, train=False,
                           loss_weighting="min_snr", t_sampling="importance")
    alpha_bar = np.concatenate([np.asarray(x) for x in levels])   # [30 B, 2]
    noised = (alpha_bar < 1.0) & (alpha_bar > float(sched.alpha_bars[-1]))
    own = noised.all(-1) & (alpha_bar[:, 0] != alpha_bar[:, 1])   # both noised, at different steps
    assert own.mean() == 0.0, (token_noise, own.mean())


def _solve(sched, x_t, steps, x0_of, method):
  """Runs DDIM or DPM-Solver++(2M) from x at steps[0] to step 0 with the predictor x0_of(x, t)."""
  prev = np.append(steps[1:], 0)
  x, x0_last, h_last = x_t, jnp.zeros_like(x_t), jnp.zeros(())
  for t, tp in zip(steps, prev):
    x0 = x0_of(x, t)
    if method == "dpmpp2m":
      x, h_last = diffusion.dpmpp_2m_step(sched, x, t, tp, x0, x0_last, h_last)
      x0_last = x0
    else:
      x = diffusion.ddim_step(sched, x0, diffusion.eps_from_x0(sched, x, t, x0), t, tp)
  return x


def _gaussian_flow(sched, s: float = 0.5):
  """Gaussian data N(0, s^2): the exact x0 predictor is linear and the probability-flow ODE maps x_T to
  x_T * s / std(x_T), so a solver's error is measurable exactly. Returns (x0_of, x_T, error of a solution)."""

  def x0_of(x, t):
    abar = sched.alpha_bars[t]
    return jnp.sqrt(abar) * s ** 2 / (abar * s ** 2 + 1.0 - abar) * x

  x_t = jnp.linspace(-3.0, 3.0, 13)
  abar_t = sched.alpha_bars[-1]
  exact = x_t * s / jnp.sqrt(abar_t * s ** 2 + 1.0 - abar_t)
  return x0_of, x_t, lambda x: float(jnp.abs(x - exact).max())


def test_dpm_solver_follows_the_probability_flow_with_few_steps(sched):
  x0_of, x_t, err = _gaussian_flow(sched)
  ddim_50 = err(_solve(sched, x_t, diffusion.ddim_timesteps(500, 10), x0_of, "ddim"))
  steps_15 = diffusion.solver_timesteps(sched, 15)
  assert len(steps_15) == 15 and steps_15[0] == 500 and steps_15[-1] == 1 and (np.diff(steps_15) < 0).all()
  dpm_15 = err(_solve(sched, x_t, steps_15, x0_of, "dpmpp2m"))
  ddim_15 = err(_solve(sched, x_t, steps_15, x0_of, "ddim"))
  assert dpm_15 < 0.6 * ddim_50 and dpm_15 < 0.25 * ddim_15   # second order pays off
  # The first step (no history) is DDIM, and the final step returns the prediction.
  x1, _ = diffusion.dpmpp_2m_step(sched, x_t, 500, 400, x0_of(x_t, 500), x_t * 0, jnp.zeros(()))
  x1_ddim = diffusion.ddim_step(sched, x0_of(x_t, 500), diffusion.eps_from_x0(sched, x_t, 500, x0_of(x_t, 500)), 500, 400)
  np.testing.assert_allclose(x1, x1_ddim, rtol=1e-5, atol=1e-6)
  x0, h = diffusion.dpmpp_2m_step(sched, x_t, 1, 0, x0_of(x_t, 1), x_t, jnp.ones(()))
  np.testing.assert_allclose(x0, x0_of(x_t, 1))
  assert (np.asarray(h) == 0.0).all()


def test_dpm_solver_started_at_a_stated_noise_level(sched):
  # Calls after the first at noise-to-signal ratios from `max_noise` down: the linear schedule's T is
  # at ratio 584, and the same 15 calls solve the Gaussian data's flow about twice as exactly from ratio 10.
  ratio = lambda t: float(np.sqrt((1.0 - sched.alpha_bars[t]) / sched.alpha_bars[t]))  # noqa: E731
  steps = np.asarray(diffusion.solver_timesteps(sched, 15, max_noise=10.0))
  assert len(steps) == 15 and steps[0] == 500 and steps[-1] == 1 and (np.diff(steps) < 0).all()
  assert ratio(steps[1]) == pytest.approx(10.0, rel=0.05) and ratio(steps[2]) < 10.0
  np.testing.assert_array_equal(diffusion.solver_timesteps(sched, 15, max_noise=0.0),
                                diffusion.solver_timesteps(sched, 15))
  # A level above T's starts at T's: the plain spacing.
  np.testing.assert_array_equal(diffusion.solver_timesteps(sched, 15, max_noise=1e4),
                                diffusion.solver_timesteps(sched, 15))
  with pytest.raises(ValueError, match="largest noise level"):
    diffusion.solver_timesteps(sched, 15, max_noise=-1.0)
  x0_of, x_t, err = _gaussian_flow(sched)
  from_t = err(_solve(sched, x_t, diffusion.solver_timesteps(sched, 15), x0_of, "dpmpp2m"))
  from_10 = err(_solve(sched, x_t, steps, x0_of, "dpmpp2m"))
  assert from_10 < 0.6 * from_t, (from_10, from_t)  # about half
