"""One AV2 scenario folder -> one `datatypes.Scene` of numpy arrays.

Agent selection (DESIGN.md, after the official code's TargetBuilder):
* the track's type is in `config.agent_types` (av2 `object_type`; static objects never qualify);
* it has a state at both AV2 step 50 (initial token) and step 109 (goal token);
* for types in `config.near_lane_types`, its step-50 position lies within `near_boundary_m` of a raw
  lane/crosswalk boundary vertex or within `near_centerline_m` of a centreline point.
Kept agents are ordered by distance to the scene origin at step 50 (closest first; the official code
sorts by x, which is not a canonical order on a rotated map) and capped at `max_agents`, dropping the
farthest; the count dropped is reported. Pedestrians are exempt from the in-lane test by default:
they walk on sidewalks and crosswalks. Agents outside physical ranges (`implausible_agents`: faster than
`MAX_SPEED_MPS`, or farther than `MAX_OFF_MAP_M` outside the map's bounding box, as when map and tracks
sit in different city frames) are left out with a warning, so that they never reach a scene or the
dataset's normalisation statistics.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import ml_collections
import numpy as np

from tdiff_jax import datatypes
from tdiff_jax.data import av2_io
from tdiff_jax.data import config as config_lib
from tdiff_jax.data import map_features


MAX_SPEED_MPS = 70.0   # faster than any road user of AV2: a broken velocity
MAX_OFF_MAP_M = 100.0  # an agent this far outside every map element is not on this map
MAX_HEADING_RAD = 2 * np.pi + 1e-3   # a heading is an angle (AV2: -pi to pi; some tools: 0 to 2 pi)


def implausible_agents(states: np.ndarray, futures: np.ndarray, future_valid: np.ndarray,
                       bounds: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, list[str]]:
  """`[C]` whether each candidate's raw states `[C, 2, 4]` (x, y, speed, heading) or valid future positions
  `[C, H, 2]` are outside physical ranges, and why (a reason per such agent)."""
  lo, hi = bounds[0] - MAX_OFF_MAP_M, bounds[1] + MAX_OFF_MAP_M
  speed = np.abs(states[..., 2]).max(-1) if len(states) else np.zeros(0)
  heading = np.abs(states[..., 3]).max(-1) if len(states) else np.zeros(0)
  outside = lambda xy: ((xy < lo) | (xy > hi)).any(-1)  # noqa: E731
  off_map = outside(states[..., :2]).any(-1) | (outside(futures) & future_valid).any(-1)
  reasons = [f"speed {v:.1f} m/s above {MAX_SPEED_MPS:g}" if v > MAX_SPEED_MPS else
             f"heading {h:.3g} rad is not an angle (|heading| above 2 pi)" if h > MAX_HEADING_RAD else
             f"more than {MAX_OFF_MAP_M:g} m outside the map (map and tracks in different city frames?)"
             for v, h, far in zip(speed, heading, off_map) if v > MAX_SPEED_MPS or h > MAX_HEADING_RAD or far]
  return (speed > MAX_SPEED_MPS) | (heading > MAX_HEADING_RAD) | off_map, reasons


@dataclasses.dataclass
class SceneInfo:
  """What a scene's arrays do not hold: ids and what the caps dropped."""

  scenario_id: str
  city: str
  track_ids: list[str]          # kept agents, in row order
  polygon_ids: list[int]        # AV2 lane or crosswalk id of each kept polygon, in row order
  num_candidates: int           # agents passing the selection before the cap
  agents_dropped: int
  polygons_dropped: int
  drivable_areas_dropped: int
  drivable_areas_resampled: int
  polygons_degenerate: int = 0        # lanes/crosswalks dropped for a zero-length boundary or centreline
  drivable_areas_degenerate: int = 0  # drivable areas dropped for fewer than three distinct vertices
  agents_implausible: int = 0         # agents left out for states outside physical ranges
  warnings: list[str] = dataclasses.field(default_factory=list)  # what was ignored or left out


def _track_arrays(tracks: av2_io.TrackTable | None, wanted_types: set[str]):
  """Per candidate track (in track-id order, as av2's loader groups them): id, type index, [2, 4] raw
  state (x, y, speed, heading) at 50/109, and [H, 2] positions at steps 50..109 with their [H] validity.
  Vectorised over the parquet's rows; a (track, step) given twice takes its last row."""
  h = datatypes.HORIZON
  if tracks is None or not len(tracks.track_id):
    return [], np.zeros(0, np.int32), np.zeros((0, 2, 4)), np.zeros((0, h, 2)), np.zeros((0, h), bool)
  ids, track = np.unique(tracks.track_id, return_inverse=True)           # sorted ids, row -> track
  first = np.zeros(len(ids), np.int64)
  first[track[::-1]] = np.arange(len(track))[::-1]                       # each track's first row
  kinds = tracks.object_type[first]                                      # a track's type: its first row's
  steps = tracks.timestep
  # Each track's row at the initial and goal steps (-1: absent) and its positions over the horizon.
  row_at = np.full((len(ids), 2), -1, np.int64)
  for tok, step in enumerate((datatypes.INITIAL_STEP, datatypes.GOAL_STEP)):
    rows = np.flatnonzero(steps == step)
    row_at[track[rows], tok] = rows                                      # duplicates: the last row wins
  in_horizon = np.flatnonzero((steps >= datatypes.INITIAL_STEP) & (steps < datatypes.INITIAL_STEP + h))
  fut = np.zeros((len(ids), h, 2), np.float64)
  fut_valid = np.zeros((len(ids), h), bool)
  fut[track[in_horizon], steps[in_horizon] - datatypes.INITIAL_STEP] = tracks.position[in_horizon]
  fut_valid[track[in_horizon], steps[in_horizon] - datatypes.INITIAL_STEP] = True
  cand = np.flatnonzero(np.isin(kinds, list(wanted_types)) & (row_at >= 0).all(-1))
  r = row_at[cand]                                                       # [C, 2]
  states = np.concatenate([tracks.position[r], np.hypot(*np.moveaxis(tracks.velocity[r], -1, 0))[..., None],
                           tracks.heading[r][..., None]], -1)            # [C, 2, 4]
  type_idx = np.array([datatypes.AGENT_TYPES.index(k) for k in kinds[cand]], np.int32)
  return [str(i) for i in ids[cand]], type_idx, states.reshape(len(cand), 2, 4), fut[cand], fut_valid[cand]


def _min_dist(query: np.ndarray, points: np.ndarray) -> np.ndarray:
  """[N, 2], [M, 2] -> [N] distance to the nearest point."""
  if len(points) == 0:
    return np.full(len(query), np.inf)
  # x and y apart: the same sums as over a trailing axis of 2, without the [N, M, 2] intermediate.
  d2 = (query[:, None, 0] - points[None, :, 0]) ** 2 + (query[:, None, 1] - points[None, :, 1]) ** 2
  return np.sqrt(d2.min(-1))


def build_scene(raw: av2_io.RawScenario, config: ml_collections.ConfigDict,
                require_agents: bool = True) -> tuple[datatypes.Scene, SceneInfo]:
  """Turns what av2 read into padded scene arrays. Raises `BadScenarioError` for unusable scenes.

  With `require_agents=False` (map conditioning for sampling) a scenario without a goal step, without
  kept agents, with non-finite tracks or without a readable parquet still gives a scene; what was
  ignored is listed in `SceneInfo.warnings`.
  """
  files, tracks = raw.files, raw.tracks
  warnings = []
  if tracks is None:
    if require_agents:
      raise av2_io.BadScenarioError(files.folder, raw.problem or "no scenario parquet")
    warnings.append(f"tracks ignored, only the map is used: {raw.problem}")
  last_step = tracks.last_step if tracks is not None else -1
  if last_step < datatypes.GOAL_STEP and require_agents:
    raise av2_io.BadScenarioError(
        files.parquet, f"only {last_step + 1} steps, no goal step {datatypes.GOAL_STEP} "
        "(a test-split scenario has only the 50 observed steps)")

  polygons, polygons_degenerate = map_features.map_polygons(raw)
  if not polygons:
    extra = f" ({polygons_degenerate} degenerate ones dropped)" if polygons_degenerate else ""
    raise av2_io.BadScenarioError(files.map_json, f"map has no lanes or crosswalks{extra}")
  origin = map_features.map_crop_center(raw.polylines)

  # ---- agents ------------------------------------------------------------------------------
  wanted = set(config_lib.parse_types(config.agent_types, "agent_types"))
  near_types = {datatypes.AGENT_TYPES.index(t) for t in config_lib.parse_types(config.near_lane_types, "near_lane_types")}
  ids, type_idx, states, futures, future_valid = _track_arrays(tracks, wanted)
  bad = ~np.isfinite(states).all(axis=(1, 2))
  if bad.any() and require_agents:
    raise av2_io.BadScenarioError(
        files.parquet, f"NaN or inf in the state of track {ids[int(np.argmax(bad))]} at step "
        f"{datatypes.INITIAL_STEP} or {datatypes.GOAL_STEP}")
  bad_future = ~np.isfinite(futures).all(axis=(1, 2))
  if bad_future.any() and require_agents:
    raise av2_io.BadScenarioError(
        files.parquet, f"NaN or inf in a position of track {ids[int(np.argmax(bad_future))]} between steps "
        f"{datatypes.INITIAL_STEP} and {datatypes.GOAL_STEP}")
  if (bad | bad_future).any():  # map only: such tracks are left out, with a word
    warnings.append(f"{int((bad | bad_future).sum())} track(s) with NaN or inf states ignored")
    good = np.flatnonzero(~(bad | bad_future))
    ids = [ids[i] for i in good]
    type_idx, states, futures, future_valid = type_idx[good], states[good], futures[good], future_valid[good]
  implausible, why = implausible_agents(states, futures, future_valid, map_features.map_bounds(raw.polylines))
  if implausible.any():
    example = int(np.argmax(implausible))
    warnings.append(f"{int(implausible.sum())} agent(s) outside physical ranges left out (track {ids[example]}: "
                    f"{why[0]})")
    good = np.flatnonzero(~implausible)
    ids = [ids[i] for i in good]
    type_idx, states, futures, future_valid = type_idx[good], states[good], futures[good], future_valid[good]
  if len(ids):
    boundary, center = map_features.near_lane_points(polygons)
    p0 = states[:, 0, :2]
    near = ((_min_dist(p0, boundary) <= config.near_boundary_m)
            | (_min_dist(p0, center) <= config.near_centerline_m))
    keep = near | ~np.isin(type_idx, list(near_types))
  else:
    keep = np.zeros(0, bool)
  cand = np.flatnonzero(keep)
  if len(cand) == 0 and require_agents:
    left_out = f"; {warnings[-1]}" if implausible.any() else ""
    raise av2_io.BadScenarioError(
        files.parquet, f"no agents kept: none of types {sorted(wanted)} is present at steps "
        f"{datatypes.INITIAL_STEP} and {datatypes.GOAL_STEP} near a lane{left_out}")
  dist = np.linalg.norm(states[cand, 0, :2] - origin, axis=-1)
  rows = cand[np.argsort(dist, kind="stable")][: config.max_agents]

  a_cap = config.max_agents
  agent_state = np.zeros((a_cap, 2, 4), np.float32)
  agent_type = np.zeros((a_cap,), np.int32)
  agent_valid = np.zeros((a_cap,), bool)
  agent_future = np.zeros((a_cap, datatypes.HORIZON, 2), np.float32)
  agent_future_valid = np.zeros((a_cap, datatypes.HORIZON), bool)
  m = len(rows)
  rel = states[rows].copy()
  rel[..., :2] -= origin
  agent_state[:m] = rel
  agent_type[:m] = type_idx[rows]
  agent_valid[:m] = True
  agent_future_valid[:m] = future_valid[rows]
  agent_future[:m] = np.where(future_valid[rows][..., None], futures[rows] - origin, 0.0)

  # ---- map ---------------------------------------------------------------------------------
  pl, order = map_features.encode_polygons(polygons, origin, config.max_polygons, config.points_per_polyline)
  if not np.isfinite(pl["pt_xy"]).all():
    raise av2_io.BadScenarioError(files.map_json, "NaN or inf in a lane or crosswalk")
  pl_edge = map_features.topology([polygons[i].lane_id for i in order], raw.lanes, config.max_polygons)
  da, da_dropped, da_resampled, da_degenerate = map_features.encode_drivable_areas(
      raw.polylines, origin, config.max_drivable_areas, config.max_drivable_area_vertices)
  if not np.isfinite(da["da_xy"]).all():
    raise av2_io.BadScenarioError(files.map_json, "NaN or inf in a drivable area")

  # What the map and the caps left out, said rather than shrunk silently.
  shrunk = [(polygons_degenerate, "lane(s) or crosswalk(s) without length (fewer than two distinct points) dropped"),
            (da_degenerate, "drivable area(s) with fewer than three distinct vertices dropped"),
            (len(cand) - m, f"agent(s) beyond the cap of {a_cap} (the farthest from the map centre) left out"),
            (len(polygons) - len(order), f"lane(s) or crosswalk(s) beyond the cap of {config.max_polygons} "
             "(the farthest) left out"),
            (da_dropped, f"drivable area(s) beyond the cap of {config.max_drivable_areas} left out")]
  warnings += [f"{n} {what}" for n, what in shrunk if n]
  if not da["da_valid"].any():
    warnings.append("no drivable area: off-road is not judged on this map")
  scene = datatypes.Scene(
      agent_state=agent_state, agent_type=agent_type, agent_valid=agent_valid,
      agent_future=agent_future, agent_future_valid=agent_future_valid, pl_edge=pl_edge, frame_origin=origin.astype(np.float64),
      frame_scale=np.float32(config.frame_scale_m), **pl, **da)
  info = SceneInfo(
      scenario_id=tracks.scenario_id if tracks is not None else files.scenario_id,
      city=tracks.city_name if tracks is not None else "unknown",
      track_ids=[ids[i] for i in rows], polygon_ids=[int(polygons[i].source_id) for i in order],
      num_candidates=len(cand),
      agents_dropped=len(cand) - m, polygons_dropped=len(polygons) - len(order),
      drivable_areas_dropped=da_dropped, drivable_areas_resampled=da_resampled,
      polygons_degenerate=polygons_degenerate, drivable_areas_degenerate=da_degenerate,
      agents_implausible=int(implausible.sum()), warnings=warnings)
  return scene, info


def load_scene(folder: Path | str, config: ml_collections.ConfigDict | None = None,
               require_agents: bool = True) -> tuple[datatypes.Scene, SceneInfo]:
  """Reads an AV2 scenario folder and builds its scene. Raises `BadScenarioError`."""
  config = config_lib.scene_config(config)
  return build_scene(av2_io.read_scenario_folder(folder, map_only=not require_agents), config, require_agents)
