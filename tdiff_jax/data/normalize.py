"""The model's agent state and its z-normalisation statistics.

The paper's per-token state is `[x, y, s]` with x, y in scene units (metres / frame scale) and
s = speed / 15 - 1. It is z-normalised with a mean and std computed on the training split's valid
agents, pooled over the initial and goal tokens (reference notes §1.6). The statistics live in the
dataset manifest and, later, in every checkpoint.
"""

from __future__ import annotations

import numpy as np

SPEED_SCALE = 15.0
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
  feats = model_features(np.asarray(agent_state, np.float64), np.asarray(frame_scale, np.float64))
  x = feats[np.asarray(agent_valid)].reshape(-1, feats.shape[-1])
  if len(x) == 0:
    raise ValueError("no valid agents to compute normalisation statistics from")
  std = x.std(0)
  std = np.where(std < 1e-6, 1.0, std)  # a constant feature must not divide by zero
  return {"mean": x.mean(0).tolist(), "std": std.tolist(), "count": int(len(x))}
