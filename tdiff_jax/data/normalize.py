"""The model's agent state and its z-normalisation statistics.

The paper's per-token state is `[x, y, s]` with x, y in scene units (metres / frame scale) and
s = speed / 15 - 1. It is z-normalised with a mean and std computed on the training split's valid
agents, pooled over the initial and goal tokens (reference notes §1.6). The statistics live in the
dataset manifest and, later, in every checkpoint.

With goal offsets (`NormStats.offset_mean/offset_std`, the HL model's `goal_offset`), the goal token's
position is instead its offset from the agent's initial position (scene units), z-normalised with the
offsets' own statistics: the diffusion then noises and denoises how far and where each agent goes,
not two unrelated places. Everything that converts between the model state and metres goes through
`normalized_state`, `denormalize_state` and `positions_to_metres`/`positions_from_metres`.

With headings (`NormStats.heading`, the HL model's `heading_state`; beyond the paper, which generates
no heading), each token's state also holds the unit vector (cos, sin) of the agent's heading, not
z-normalised (its entries already have variance about 1/2): the model then says which way each agent
travels, which the lane an agent stands on leaves open on two-way roads.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

SPEED_SCALE = 15.0
GOAL_HORIZON_S = 5.9  # AV2 steps 50 -> 109 at 10 Hz (`datatypes.INITIAL_STEP`, `GOAL_STEP`)
MODEL_FEATURES = ("x / frame_scale", "y / frame_scale", "speed / 15 - 1")


def model_features(agent_state, frame_scale, xp=np):
  """`[..., A, 2, 4]` raw states, `[...]` scales -> `[..., A, 2, 3]` unnormalised model state."""
  scale = xp.asarray(frame_scale)[..., None, None, None]
  xy = agent_state[..., 0:2] / scale
  s = agent_state[..., 2:3] / SPEED_SCALE - 1.0
  return xp.concatenate([xy, s], axis=-1)


def normalization_stats(agent_state: np.ndarray, agent_valid: np.ndarray,
                        frame_scale: np.ndarray) -> dict[str, list[float]]:
  """Mean and std `[3]` of the model state over valid agents and both tokens (float64 sums)."""
  x = _state_rows(agent_state, agent_valid, frame_scale)
  return {**_mean_std(x, "normalisation"), "count": int(len(x))}


def _mean_std(x: np.ndarray, what: str) -> dict[str, list[float]]:
  """Mean and std over the rows of `x` `[N, F]` (std 1 for a constant feature, which must not divide)."""
  if len(x) == 0:
    raise ValueError(f"no valid agents to compute {what} statistics from")
  std = x.std(0)
  return {"mean": x.mean(0).tolist(), "std": np.where(std < 1e-6, 1.0, std).tolist()}


def offset_stats(agent_state: np.ndarray, agent_valid: np.ndarray, frame_scale: np.ndarray) -> dict[str, list[float]]:
  """Mean and std `[2]` of the goal's offset from the initial position (scene units) over valid agents."""
  return _mean_std(_offset_rows(agent_state, agent_valid, frame_scale), "goal-offset")


def _state_rows(agent_state, agent_valid, frame_scale) -> np.ndarray:
  feats = model_features(np.asarray(agent_state, np.float64), np.asarray(frame_scale, np.float64))
  return feats[np.asarray(agent_valid)].reshape(-1, feats.shape[-1])


def _offset_rows(agent_state, agent_valid, frame_scale) -> np.ndarray:
  feats = model_features(np.asarray(agent_state, np.float64), np.asarray(frame_scale, np.float64))
  return (feats[..., 1, :2] - feats[..., 0, :2])[np.asarray(agent_valid)]


# Streaming statistics: each preprocessing shard records the moments (count, mean, sum of squared
# deviations) of its rows; `merge_moments` combines shards exactly (Chan et al.), so the manifest's
# statistics never need a whole split in memory.

def state_moments(agent_state, agent_valid, frame_scale) -> dict:
  """Moments of the rows `normalization_stats` pools (valid agents, both tokens)."""
  return _moments(_state_rows(agent_state, agent_valid, frame_scale))


def offset_moments(agent_state, agent_valid, frame_scale) -> dict:
  """Moments of the rows `offset_stats` pools."""
  return _moments(_offset_rows(agent_state, agent_valid, frame_scale))


def _moments(x: np.ndarray) -> dict:
  mean = x.mean(0) if len(x) else np.zeros(x.shape[-1])
  return {"count": int(len(x)), "mean": mean.tolist(), "m2": ((x - mean) ** 2).sum(0).tolist()}


def merge_moments(parts: list[dict]) -> dict:
  """The moments of the union of the parts' rows."""
  count, mean, m2 = 0, None, None
  for p in parts:
    n, mu, q = p["count"], np.asarray(p["mean"], np.float64), np.asarray(p["m2"], np.float64)
    if n == 0:
      continue
    if count == 0:
      count, mean, m2 = n, mu, q
      continue
    delta, total = mu - mean, count + n
    mean = mean + delta * n / total
    m2 = m2 + q + delta ** 2 * count * n / total
    count = total
  if count == 0:
    return {"count": 0, "mean": [], "m2": []}
  return {"count": count, "mean": mean.tolist(), "m2": m2.tolist()}


def stats_from_moments(moments: dict, what: str) -> dict[str, list[float]]:
  """Mean and std (as `_mean_std`: std 1 for a constant feature) and the count, from merged moments."""
  if moments["count"] == 0:
    raise ValueError(f"no valid agents to compute {what} statistics from")
  std = np.sqrt(np.asarray(moments["m2"]) / moments["count"])
  return {"mean": list(moments["mean"]), "std": np.where(std < 1e-6, 1.0, std).tolist(), "count": moments["count"]}


@struct.dataclass
class NormStats:
  """z-normalisation of the model state `[x/scale, y/scale, speed/15 - 1]`: mean, std `[3]`; with goal
  offsets also the offsets' mean and std `[2]` (scene units; None: absolute goals, the paper's)."""

  mean: jax.Array
  std: jax.Array
  offset_mean: jax.Array | None = None
  offset_std: jax.Array | None = None
  heading: bool = struct.field(pytree_node=False, default=False)  # the state also holds (cos, sin) of the heading

  @property
  def goal_offset(self) -> bool:
    return self.offset_std is not None

  @property
  def state_dim(self) -> int:
    """Features per token of the model state: x, y, speed and, with headings, cos and sin."""
    return 5 if self.heading else 3

  def with_heading(self, heading: bool = True) -> "NormStats":
    return dataclasses.replace(self, heading=bool(heading))

  @classmethod
  def from_manifest(cls, manifest: dict) -> "NormStats":
    norm = manifest.get("normalization")
    if not norm:
      raise ValueError("the dataset manifest has no normalisation statistics (empty training split?)")
    return cls(jnp.asarray(norm["mean"], jnp.float32), jnp.asarray(norm["std"], jnp.float32))

  def with_offsets(self, stats: dict) -> "NormStats":
    """These statistics with goal offsets (`offset_stats`)."""
    return dataclasses.replace(self, offset_mean=jnp.asarray(stats["mean"], jnp.float32),
                               offset_std=jnp.asarray(stats["std"], jnp.float32))

  def to_json(self) -> dict:
    out = {"mean": [float(v) for v in self.mean], "std": [float(v) for v in self.std]}
    if self.goal_offset:
      out["goal_offset"] = {"mean": [float(v) for v in self.offset_mean], "std": [float(v) for v in self.offset_std]}
    if self.heading:
      out["heading"] = True
    return out

  @classmethod
  def from_json(cls, d: dict) -> "NormStats":
    norm = cls(jnp.asarray(d["mean"], jnp.float32), jnp.asarray(d["std"], jnp.float32), heading=bool(d.get("heading")))
    offsets = d.get("goal_offset")
    if offsets and offsets.get("kinematic"):
      raise ValueError("kinematic goal offsets (model.goal_kinematic, measured and not adopted) are no longer "
                       "supported")
    return norm.with_offsets(offsets) if offsets else norm



def _scale(frame_scale, ndim: int) -> jax.Array:
  return jnp.asarray(frame_scale).reshape((-1,) + (1,) * (ndim - 1))


def positions_to_metres(xy: jax.Array, frame_scale: jax.Array, norm: NormStats) -> jax.Array:
  """Model-state positions `[B, A, 2, 2]` (initial, goal) -> metres in the scene frame."""
  init = xy[..., 0, :] * norm.std[:2] + norm.mean[:2]
  if norm.goal_offset:
    goal = init + xy[..., 1, :] * norm.offset_std + norm.offset_mean
  else:
    goal = xy[..., 1, :] * norm.std[:2] + norm.mean[:2]
  return jnp.stack([init, goal], -2) * _scale(frame_scale, xy.ndim)


def positions_from_metres(xy_m: jax.Array, frame_scale: jax.Array, norm: NormStats) -> jax.Array:
  """Inverse of `positions_to_metres`."""
  xy = xy_m / _scale(frame_scale, xy_m.ndim)
  init = (xy[..., 0, :] - norm.mean[:2]) / norm.std[:2]
  if norm.goal_offset:
    goal = (xy[..., 1, :] - xy[..., 0, :] - norm.offset_mean) / norm.offset_std
  else:
    goal = (xy[..., 1, :] - norm.mean[:2]) / norm.std[:2]
  return jnp.stack([init, goal], -2)


def absolute_goals(x: jax.Array, norm: NormStats, frame_scale: jax.Array) -> jax.Array:
  """Model states `[B, A, 2, F]` with the goal position as it would be without goal offsets: z-normalised
  with the position statistics like the initial one (the identity without goal offsets). Guidance steps
  are taken in this parameterisation, so a goal moves as far as an initial state for the same gradient.
  `frame_scale` `[B]`: metres per scene unit."""
  if not norm.goal_offset:
    return x
  absolute = dataclasses.replace(norm, offset_mean=None, offset_std=None)
  metres = positions_to_metres(x[..., :2], frame_scale, norm)
  return x.at[..., :2].set(positions_from_metres(metres, frame_scale, absolute))


def offset_goals(x: jax.Array, norm: NormStats, frame_scale: jax.Array) -> jax.Array:
  """Inverse of `absolute_goals`."""
  if not norm.goal_offset:
    return x
  absolute = dataclasses.replace(norm, offset_mean=None, offset_std=None)
  metres = positions_to_metres(x[..., :2], frame_scale, absolute)
  return x.at[..., :2].set(positions_from_metres(metres, frame_scale, norm))


def normalized_state(scene, norm: NormStats) -> jax.Array:
  """`[B, A, 2, F]` z-normalised model state of a `datatypes.Scene`'s agents (zeros for padding); F =
  `norm.state_dim` (x, y, speed and, with headings, cos and sin of `agent_state[..., 3]`)."""
  xy = positions_from_metres(scene.agent_state[..., :2], scene.frame_scale, norm)
  s = (scene.agent_state[..., 2:3] / SPEED_SCALE - 1.0 - norm.mean[2]) / norm.std[2]
  parts = [xy, s]
  if norm.heading:
    heading = scene.agent_state[..., 3]
    parts.append(jnp.stack([jnp.cos(heading), jnp.sin(heading)], -1))
  x = jnp.concatenate(parts, -1)
  return jnp.where(scene.agent_valid[..., None, None], x, 0.0)


def denormalize_state(x: jax.Array, frame_scale: jax.Array, norm: NormStats) -> jax.Array:
  """Inverse of `normalized_state` for position and speed: `[B, A, 2, F]` -> `[B, A, 2, 3]` x, y (m,
  scene frame) and speed (m/s). The heading, where the state has one, is `denormalize_heading`'s."""
  speed = denormalize_speed(x[..., 2:3], norm)
  return jnp.concatenate([positions_to_metres(x[..., :2], frame_scale, norm), speed], -1)


def denormalize_speed(speed: jax.Array, norm: NormStats) -> jax.Array:
  """Speeds (m/s) of model-state speed features (z-normalised speed / 15 - 1), any shape."""
  return (speed * norm.std[2] + norm.mean[2] + 1.0) * SPEED_SCALE


def denormalize_heading(x: jax.Array) -> jax.Array:
  """`[B, A, 2]` headings (rad) of model states `[B, A, 2, 5]` with headings: the angle of (cos, sin)."""
  return jnp.arctan2(x[..., 4], x[..., 3])
