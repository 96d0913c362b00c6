"""The HL training objective (paper eq. 4-6): masked epsilon MSE + lambda_ent x attention entropy.

* One diffusion step t per scene, shared by its agents: t ~ U{1..T} (as the official code), or with
  `t_sampling="importance"` drawn in proportion to the weighting's x0-space weight min(SNR_t, gamma)
  and the loss reweighted so that its expectation is unchanged: the same objective, but no draws are
  spent on steps whose weight is negligible (under min-SNR, t > 300 of the linear schedule).
* The MSE averages over valid agents' 2 x F state entries only, so padding never changes the loss.
  `loss_weighting="eps"` weighs every t alike (the paper); "min_snr" weighs each scene's epsilon error
  by min(SNR_t, gamma) / SNR_t (Hang et al. 2023, min-SNR-gamma), i.e. the x0 error by min(SNR_t, gamma):
  the weighting an x0-predicting network needs (uniform epsilon weights would weigh its x0 error at
  t = 1 ten thousand times more than at t = 100).
* Entropy of the differential map attention W (paper eq. 5): w~ = |w| / ||w||_2 over the valid
  polygons of each query; -w~ log w~ is averaged over the valid polygons (the official code divides
  by the valid-polygon count), then over heads, valid agent tokens and scenes, and summed over layers.
  Unlike the official code, padded agents' queries are excluded.
* Interaction dropout: each scene is self-only (agents see only themselves) with probability
  `self_only_prob`.
* `noise_draws = M > 1` (beyond the paper): each scene's map is encoded once and its state noised M
  times, at M independent steps t; the loss averages the B x M draws. The map encoder is most of a
  training step's cost and does not depend on the noise, so M draws cost little more than one.
* Staged noise (the grounded denoiser, `staged_noise`; beyond the paper): each drawn sample is, with equal
  probability (`STAGES`), both tokens at step t (the paper), the initial token at t with the goal at
  t = T (pure noise: the initial state alone), or the goal token at t with the initial state clean (t = 0:
  the goal given the initial state). Only the tokens at t count in the loss, averaged over them.
* Self-conditioning (the grounded denoiser, `self_condition`; Chen et al. 2023): the denoiser first runs
  without a previous estimate; its x0 estimate (clipped as the sampler clips, no gradient) is then the
  previous estimate of a second pass for half the scenes (`SELF_CONDITION_PROB`), and the loss is the
  second pass's.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp

from tdiff_jax import datatypes, diffusion
from tdiff_jax.data.normalize import NormStats, normalized_state
from tdiff_jax.models import layers
from tdiff_jax.models.paper_denoiser import PaperDenoiser
from tdiff_jax.models.map_encoder import MapInputs, PackedPolygons


def attention_entropy(maps: list[jax.Array], agent_valid: jax.Array, pl_valid: jax.Array) -> jax.Array:
  """Paper eq. 5 over the layers' maps `[B, H, 2A, P]`; scalar."""
  q_valid = jnp.repeat(agent_valid, 2, axis=1)[:, None, :]          # [B, 1, 2A] (agent-major tokens)
  k_valid = pl_valid[:, None, None, :]                               # [B, 1, 1, P]
  n_poly = jnp.maximum(pl_valid.sum(-1), 1)[:, None, None]
  n_q = jnp.maximum(q_valid.sum() * maps[0].shape[1], 1)
  total = 0.0
  for w in maps:
    w = jnp.where(k_valid, jnp.abs(w), 0.0)
    p = w / (jnp.sqrt(jnp.sum(w * w, -1, keepdims=True)) + 1e-6)
    h = -jnp.sum(p * jnp.log(p + 1e-6), -1) / n_poly                 # [B, H, 2A]
    total = total + jnp.sum(jnp.where(q_valid, h, 0.0)) / n_q
  return total


LOSS_WEIGHTINGS = ("eps", "min_snr")
# Self-conditioning: the share of scenes whose second pass reads the first pass's estimate, and the
# clip of that estimate (the sampler's default `clip_x0`).
SELF_CONDITION_PROB = 0.5
SELF_CONDITION_CLIP = 3.0
T_SAMPLINGS = ("uniform", "importance")
# Staged noise: what each drawn sample trains, each with probability 1/3.
STAGES = ("joint", "initial", "goal")


def staged_steps(t: jax.Array, stage: jax.Array, num_steps: int) -> tuple[jax.Array, jax.Array]:
  """Per-token steps `[B, 2]` and which tokens are trained `[B, 2]` for drawn steps `t` `[B]` and stages
  `[B]` (indices of `STAGES`): joint (t, t), initial (t, T), goal (0, t)."""
  initial = jnp.where(stage == 2, 0, t)
  goal = jnp.where(stage == 1, num_steps, t)
  trained = jnp.stack([stage != 2, stage != 1], -1)
  return jnp.stack([initial, goal], -1), trained


def importance_probs(sched: diffusion.Schedule, gamma: float) -> jax.Array:
  """`[T]` probabilities of t = 1..T, proportional to min(SNR_t, gamma)."""
  abar = sched.alpha_bars[1:]
  w = jnp.minimum(abar / (1.0 - abar), gamma)
  return w / jnp.sum(w)


def snr_weights(sched: diffusion.Schedule, t: jax.Array, weighting: str, gamma: float) -> jax.Array:
  """Per-scene weight `[B]` of the epsilon error at steps `t` `[B]`."""
  if weighting == "eps":
    return jnp.ones(t.shape)
  if weighting == "min_snr":
    abar = sched.alpha_bars[t]
    snr = abar / (1.0 - abar)
    return jnp.minimum(snr, gamma) / snr
  raise ValueError(f"loss weighting {weighting!r}: choose one of {LOSS_WEIGHTINGS}")


def hl_loss(model: PaperDenoiser, batch: datatypes.Scene, norm: NormStats, sched: diffusion.Schedule,
            key: jax.Array, entropy_weight: float, self_only_prob: float,
            train: bool = True, loss_weighting: str = "eps", min_snr_gamma: float = 5.0,
            t_sampling: str = "uniform", noise_draws: int = 1, packed: PackedPolygons | None = None,
            map_inputs: MapInputs | None = None, lane_pull=None) -> tuple[jax.Array, dict[str, jax.Array]]:
  """Loss and metrics for a batch. `train=False` turns dropout and interaction dropout off. `packed`:
  the batch's packed polygons (`map_encoder.pack_polygons`) for an all-pairs map encoder. `map_inputs`: the
  map encoder's input side of the batch computed apart (`MapEncoder.input_side`; a frozen one).
  `lane_pull`: the lane pull on the grounded denoiser's position estimate (`lane_pull.LanePull`; the
  config's `lane_pull` section), applied as `LanePull.for_objective`.

  Metrics: `loss`, the weighted `mse` it contains, `entropy`, and `eps_mse` (unweighted, comparable
  across weightings).
  """
  if noise_draws < 1:
    raise ValueError(f"noise_draws={noise_draws}: at least 1")
  k_t, k_eps, k_mode, k_drop = jax.random.split(key, 4)
  # Only the map arguments given: a denoiser (or a test's stand-in) without packing need not know them.
  map_args = {k: v for k, v in (("packed", packed), ("map_inputs", map_inputs)) if v is not None}
  pull_args = {} if lane_pull is None else {"position_step": lane_pull.for_objective()}
  x0 = normalized_state(batch, norm)
  self_conditioned = getattr(getattr(model, "cfg", None), "self_condition", False)
  two_stage = noise_draws > 1 or self_conditioned   # the map encoded once, then the denoiser (once or twice)
  if two_stage:
    ctx = model.encode_map(batch, norm, layers.fold(k_drop if train else None, 100), **map_args)
  if noise_draws > 1:  # [B] scenes -> [B x M] draws, each scene's M copies adjacent
    repeat = lambda tree: jax.tree_util.tree_map(lambda x: jnp.repeat(x, noise_draws, axis=0), tree)  # noqa: E731
    x0 = repeat(x0)
    ctx = ctx.replace(**{f.name: repeat(getattr(ctx, f.name)) for f in dataclasses.fields(ctx) if f.name != "norm"})
    batch = repeat(batch)
  b = batch.agent_valid.shape[0]
  num_t = sched.num_steps

  def draw_steps(k):  # steps [B] and the reweighting that keeps the loss's expectation that of uniform t
    if t_sampling == "importance":
      probs = importance_probs(sched, min_snr_gamma)
      t = 1 + jax.random.choice(k, sched.num_steps, (b,), p=probs)
      return t, 1.0 / (num_t * probs[t - 1])                # E_q[reweight x loss] = E_uniform{1..T}[loss]
    if t_sampling == "uniform":
      return jax.random.randint(k, (b,), 1, num_t + 1), jnp.ones((b,))
    raise ValueError(f"t_sampling {t_sampling!r}: choose one of {T_SAMPLINGS}")

  t, reweight = draw_steps(k_t)
  eps = jax.random.normal(k_eps, x0.shape)
  staged = getattr(getattr(model, "cfg", None), "staged_noise", False)
  trained = jnp.ones((b, 2), bool)
  t_tok = t   # the denoiser's steps: [B], or [B, 2] per token time when staged
  t_weight, reweight_tok = t, reweight   # what weighs the loss: per scene [B], or per token [B, 2]
  if staged:
    stage = jax.random.randint(jax.random.fold_in(key, 11), (b,), 0, len(STAGES))
    t_tok, trained = staged_steps(t, stage, sched.num_steps)
  t_state = t_tok if t_tok.ndim == 1 else t_tok[:, None, :]  # broadcasts against [B, A, 2, F]
  x_t = diffusion.q_sample(sched, x0, t_state, eps)
  self_only = jax.random.bernoulli(k_mode, self_only_prob, (b,)) if train else None
  if not two_stage:  # a model called on the batch as a whole (the HL denoiser, or a stand-in in a test)
    eps_hat, maps = model(batch, x_t, sched.betas[t_tok], sched.alpha_bars[t_tok], norm,
                          self_only=self_only, key=k_drop if train else None, **map_args, **pull_args)
  else:
    denoise = functools.partial(model.denoise, ctx, x_t, sched.betas[t_tok], sched.alpha_bars[t_tok], batch.agent_type,
                                batch.agent_valid, self_only=self_only, **pull_args)
    previous = {}
    if self_conditioned:
      # A first pass without a previous estimate, no gradient through it, clipped as the sampler clips;
      # half the scenes then see it (Chen et al. 2023), the others learn the sampler's first step.
      eps_first, _ = denoise(key=layers.fold(k_drop if train else None, 102))
      x0_first = jnp.clip(diffusion.x0_from_eps(sched, x_t, t_state, jax.lax.stop_gradient(eps_first)),
                          -SELF_CONDITION_CLIP, SELF_CONDITION_CLIP)
      has_prev = jax.random.bernoulli(jax.random.fold_in(key, 7), SELF_CONDITION_PROB, (b,))
      previous = {"x0_prev": x0_first, "has_prev": has_prev}
    eps_hat, maps = denoise(key=layers.fold(k_drop if train else None, 101), **previous)
  valid = batch.agent_valid[:, :, None, None] & trained[:, None, :, None]   # [B, A, 2, 1]
  n = jnp.maximum(valid.sum() * x0.shape[-1], 1)
  sq = jnp.where(valid, (eps - eps_hat) ** 2, 0.0)
  w = reweight_tok * snr_weights(sched, t_weight, loss_weighting, min_snr_gamma)
  w = w[:, None, None, None] if w.ndim == 1 else w[:, None, :, None]          # [B, 1, 1 or 2, 1]
  mse = jnp.sum(w * sq) / n
  ent = attention_entropy(maps, batch.agent_valid, batch.pl_valid)
  loss = mse + entropy_weight * ent
  return loss, {"loss": loss, "mse": mse, "entropy": ent, "eps_mse": jnp.sum(sq) / n}
