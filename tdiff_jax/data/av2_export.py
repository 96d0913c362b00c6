"""Generated scenarios as AV2 scenario folders, readable by av2's loader and by `load_scene`.

One folder per generated scenario: `scenario_<id>.parquet` written with av2's serializer and
`log_map_archive_<id>.json`, a copy of the source map. Tracks hold AV2 steps 50..109 (the initial
state is step 50 and the goal step 109, as in the training data); `timestamps_ns` spans the usual
110 steps at 10 Hz. Positions are city-frame metres. Velocities are finite differences of the
trajectory; headings follow the direction of motion and keep the last heading while an agent is
(nearly) stopped, starting from its initial heading. Track ids are "0", "1", ... in row order; track
"0" is the focal track, the others are scored tracks.
"""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import numpy as np
from av2.datasets.motion_forecasting.data_schema import (
    ArgoverseScenario, ObjectState, ObjectType, Track, TrackCategory)

from tdiff_jax import datatypes
from tdiff_jax.data import av2_io

DT_S = 0.1


def generated_scenario_id(source_id: str, sample_index: int, seed: int) -> str:
  """A deterministic UUID for sample `sample_index` of map `source_id` under `seed`."""
  return str(uuid.uuid5(uuid.NAMESPACE_URL, f"tdiff_jax/{source_id}/{sample_index}/{seed}"))


def kinematics(xy: np.ndarray, initial_heading: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """Velocity `[A, H, 2]` (m/s) and heading `[A, H]` (rad) of trajectories `[A, H, 2]`."""
  vel = np.gradient(xy, DT_S, axis=1) if xy.shape[1] > 1 else np.zeros_like(xy)
  step = np.diff(xy, axis=1, prepend=xy[:, :1])
  moving = np.linalg.norm(step, axis=-1) > datatypes.STOPPED_STEP_M
  heading = np.empty(xy.shape[:2])
  current = np.asarray(initial_heading, np.float64).copy()
  for h in range(xy.shape[1]):  # forward fill over the 60 steps, vectorised over agents
    current = np.where(moving[:, h], np.arctan2(step[:, h, 1], step[:, h, 0]), current)
    heading[:, h] = current
  return vel, heading


def build_scenario(scenario_id: str, city: str, city_xy: np.ndarray, initial_heading: np.ndarray,
                   agent_type: np.ndarray, valid: np.ndarray) -> ArgoverseScenario:
  """An av2 `ArgoverseScenario` from trajectories `[A, H, 2]` (city metres) of the valid agents."""
  rows = np.flatnonzero(valid)
  vel, heading = kinematics(np.asarray(city_xy, np.float64)[rows], np.asarray(initial_heading)[rows])
  tracks = []
  for k, a in enumerate(rows):
    states = [ObjectState(observed=False, timestep=datatypes.INITIAL_STEP + h,
                          position=(float(city_xy[a, h, 0]), float(city_xy[a, h, 1])),
                          heading=float(heading[k, h]), velocity=(float(vel[k, h, 0]), float(vel[k, h, 1])))
              for h in range(city_xy.shape[1])]
    category = TrackCategory.FOCAL_TRACK if k == 0 else TrackCategory.SCORED_TRACK
    tracks.append(Track(str(k), states, ObjectType(datatypes.AGENT_TYPES[int(agent_type[a])]), category))
  tracks.sort(key=lambda t: t.track_id)  # av2's loader groups tracks by string id
  steps = datatypes.GOAL_STEP + 1
  timestamps = np.arange(steps, dtype=np.float64) * DT_S * 1e9
  return ArgoverseScenario(scenario_id=scenario_id, timestamps_ns=timestamps, tracks=tracks,
                           focal_track_id="0" if len(rows) else "", city_name=city, map_id=None, slice_id=None)


def write_generated_scenario(out_dir: Path | str, scenario_id: str, city: str, source_map_json: Path | str,
                             city_xy: np.ndarray, initial_heading: np.ndarray, agent_type: np.ndarray,
                             valid: np.ndarray) -> Path:
  """Writes `<out_dir>/<scenario_id>/` atomically and returns it."""
  scenario = build_scenario(scenario_id, city, city_xy, initial_heading, agent_type, valid)
  map_json = json.loads(Path(source_map_json).read_text())
  return av2_io.write_scenario_folder(scenario, map_json, out_dir)
