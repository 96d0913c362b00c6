"""Do complete scenarios, as written, stay apart and on the road? Read back from AV2 scenario folders.

  python -m tdiff_jax.audit workdirs/hl/samples          # a sample.py output folder: generated and logged
  python -m tdiff_jax.audit --out=audit.json DIR [DIR ...]   # any AV2 scenario folders (or folders of them)

Each scenario folder is read as a user reads it: the tracks with av2's own loader
(`load_argoverse_scenario_parquet`), the map's drivable areas from its map JSON. Over AV2 steps 50 to 109
(the 6 s that sample.py generates):
* an agent **overlaps** when its box (its type's size, `datatypes.AGENT_BOX_SIZE_M`, turned by the heading
  the file gives) and another agent's box intersect at some step both exist (a separating-axis test at each
  step);
* a road user (not a pedestrian) **leaves the road** when its centre lies outside every drivable area of
  the map at some step (maps without a drivable area are not judged).

For a sample.py output folder, the logged scenarios of the same maps are read too, with the agents the
scene builder keeps (`scene_builder.load_scene`: types, both states present, near a lane), so that the
generated shares have the logged ones beside them. `sample.py` writes this audit into its summary
(`complete_scenarios`).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from absl import flags

from tdiff_jax import cli, datatypes, files
from tdiff_jax.data import av2_io, road_network, scene_builder

FIRST_STEP, LAST_STEP = datatypes.INITIAL_STEP, datatypes.INITIAL_STEP + datatypes.HORIZON - 1   # 50, 109
_SIZES = np.array([datatypes.AGENT_BOX_SIZE_M[t] for t in datatypes.AGENT_TYPES])   # [types, 2] length, width


def box_corners(xy: np.ndarray, heading: np.ndarray, size: np.ndarray) -> np.ndarray:
  """`[..., 4, 2]` corners of boxes centred at `xy` `[..., 2]`, turned by `heading` `[...]`, of `size`
  `[..., 2]` (length along the heading, width)."""
  c, s = np.cos(heading)[..., None], np.sin(heading)[..., None]
  half_l, half_w = size[..., :1] / 2, size[..., 1:] / 2
  signs = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], np.float64)
  along, across = signs[:, 0] * half_l, signs[:, 1] * half_w                 # [..., 4]
  return np.stack([xy[..., None, 0] + c * along - s * across, xy[..., None, 1] + s * along + c * across], -1)


def overlapping_agents(xy: np.ndarray, heading: np.ndarray, size: np.ndarray, valid: np.ndarray) -> np.ndarray:
  """`[A]` whether each agent's box intersects another's at some step both are valid (separating axes:
  two convex boxes are apart exactly when their projections on one of the four edge normals are apart).

  Args: xy `[A, T, 2]` (m), heading `[A, T]` (rad), size `[A, 2]` (m), valid `[A, T]`.
  """
  num = xy.shape[0]
  if num < 2:
    return np.zeros(num, bool)
  i, j = np.triu_indices(num, 1)
  both = valid[i] & valid[j]                                                  # [P, T]
  corners = box_corners(xy, heading, np.broadcast_to(size[:, None], xy.shape))   # [A, T, 4, 2]
  axes = np.stack([np.cos(heading), np.sin(heading), -np.sin(heading), np.cos(heading)], -1).reshape(
      *heading.shape, 2, 2)                                                   # [A, T, 2 axes, 2]
  apart = np.zeros(both.shape, bool)
  for owner in (i, j):   # each box's two edge normals
    for k in range(2):
      axis = axes[owner, :, k]                                                # [P, T, 2]
      pi = np.einsum("ptcd,ptd->ptc", corners[i], axis)                       # [P, T, 4]
      pj = np.einsum("ptcd,ptd->ptc", corners[j], axis)
      apart |= (pi.max(-1) < pj.min(-1)) | (pj.max(-1) < pi.min(-1))
  hit = (both & ~apart).any(-1)                                               # [P]
  out = np.zeros(num, bool)
  out[i[hit]] = True
  out[j[hit]] = True
  return out


def outside_areas(points: np.ndarray, areas: list[np.ndarray]) -> np.ndarray:
  """`[N]` whether each point `[N, 2]` lies outside every polygon of `areas` (rings `[V, 2]`; even-odd rule)."""
  return ~road_network.inside_rings(points, areas)


def read_tracks(folder: Path, track_ids: list[str] | None = None):
  """The tracks of a scenario folder over steps 50 to 109, read with av2's loader: `(xy [A, T, 2],
  heading [A, T], valid [A, T], type [A])` for `track_ids` (in that order) or every track of a known
  agent type. Raises `av2_io.BadScenarioError` when av2 cannot read the folder."""
  from av2.datasets.motion_forecasting.scenario_serialization import load_argoverse_scenario_parquet
  parquet = av2_io.find_scenario_files(folder).parquet
  av2_io.check_regular_file(parquet)
  try:
    scenario = load_argoverse_scenario_parquet(parquet)
  except Exception as e:   # av2 raises many kinds on a bad file
    raise av2_io.BadScenarioError(parquet, f"av2 cannot read it ({type(e).__name__}: {e})") from None
  by_id = {t.track_id: t for t in scenario.tracks if t.object_type.value in datatypes.AGENT_TYPES}
  tracks = [by_id[i] for i in track_ids if i in by_id] if track_ids is not None else list(by_id.values())
  steps = datatypes.HORIZON
  xy, heading = np.zeros((len(tracks), steps, 2)), np.zeros((len(tracks), steps))
  valid = np.zeros((len(tracks), steps), bool)
  for a, track in enumerate(tracks):
    for state in track.object_states:
      if FIRST_STEP <= state.timestep <= LAST_STEP:
        h = state.timestep - FIRST_STEP
        xy[a, h], heading[a, h], valid[a, h] = state.position, state.heading, True
  kinds = np.array([datatypes.AGENT_TYPES.index(t.object_type.value) for t in tracks], np.int32)
  return xy, heading, valid & np.isfinite(xy).all(-1) & np.isfinite(heading), kinds


def drivable_areas(folder: Path) -> list[np.ndarray]:
  """The map's drivable-area rings `[V, 2]` (city metres) of a scenario folder."""
  files_ = av2_io.ScenarioFiles("", folder, None, av2_io.find_map_file(folder))
  _, polylines, _ = av2_io.load_map(files_)
  return [ring for ring in polylines.drivable_areas.values() if len(ring) >= 3]


def check_scenario(folder: Path, track_ids: list[str] | None = None) -> dict:
  """One folder's counts: agents, those overlapping another, road users judged, those leaving the road."""
  xy, heading, valid, kinds = read_tracks(folder, track_ids)
  overlap = overlapping_agents(xy, heading, _SIZES[kinds], valid)
  areas = drivable_areas(folder)
  road = (kinds != datatypes.PEDESTRIAN) & valid.any(-1) & bool(areas)
  off = np.zeros(len(kinds), bool)
  if road.any():
    outside = outside_areas(xy[road].reshape(-1, 2), areas).reshape(int(road.sum()), -1)
    off[road] = (outside & valid[road]).any(-1)
  exists = valid.any(-1)
  return {"agents": int(exists.sum()), "overlap": int((overlap & exists).sum()),
          "road_users": int(road.sum()), "offroad": int(off.sum())}


def summarize(counts: list[dict], skipped: list[dict]) -> dict:
  """Shares (%) of agents that overlap another and of road users that leave the road, over scenarios."""
  total = {k: sum(c[k] for c in counts) for k in ("agents", "overlap", "road_users", "offroad")}
  return {"scenarios": len(counts), **total,
          "overlap_pct": 100.0 * total["overlap"] / max(total["agents"], 1),
          "offroad_pct": 100.0 * total["offroad"] / max(total["road_users"], 1),
          "skipped": skipped}


def audit_folders(folders: list[Path], logged: bool = False, scene_config=None) -> dict:
  """`summarize` over scenario folders; with `logged`, each folder's agents are the ones the scene builder
  keeps (the logged scenario as the model saw it). Folders that cannot be read are skipped and listed."""
  counts, skipped = [], []
  for folder in folders:
    try:
      ids = scene_builder.load_scene(folder, scene_config)[1].track_ids if logged else None
      counts.append(check_scenario(folder, ids))
    except av2_io.BadScenarioError as e:
      skipped.append({"scenario": folder.name, "file": e.path, "reason": e.reason})
  return summarize(counts, skipped)


def audit_run(samples_dir: Path | str, maps: Path | str | None = None, scene_config=None) -> dict:
  """The audit of a sample.py output folder: its generated scenarios (`scenarios/`) and the logged
  scenarios of the maps they were generated on (`maps`, default the summary's), each map once."""
  samples_dir = Path(samples_dir)
  summary = json.loads((samples_dir / "summary.json").read_text())
  if "scenarios" not in summary:
    raise ValueError(f"{samples_dir}: holds high-level scenarios only (sample.py --infill_workdir=''): no "
                     "complete scenarios to audit")
  generated = [samples_dir / "scenarios" / s["scenario_id"] for s in summary["scenarios"]]
  map_folders = {f.name: f for f in av2_io.map_folders(maps or summary["maps"])}
  used = sorted({s["map_folder"] for s in summary["scenarios"]})
  return audit_generated(generated, [map_folders[name] for name in used if name in map_folders], scene_config)


def audit_generated(generated: list[Path], map_folders: list[Path], scene_config=None) -> dict:
  """{"generated": ..., "logged": ...}: `audit_folders` of generated scenario folders and of the logged
  scenarios of the maps they were generated on."""
  return {"generated": audit_folders(generated), "logged": audit_folders(map_folders, True, scene_config)}


def define_flags(values: flags.FlagValues) -> None:
  flags.DEFINE_string("maps", None, "with a sample.py output folder: the maps it sampled (default: the summary's)",
                      flag_values=values)
  flags.DEFINE_string("out", None, "also write the audit as JSON to this file", flag_values=values)


def run(f: flags.FlagValues, args: list[str]) -> None:
  if not args:
    raise SystemExit("audit: give a sample.py output folder, or AV2 scenario folders")
  paths = [files.user_path(a) for a in args]
  try:
    if len(paths) == 1 and (paths[0] / "summary.json").is_file():
      result = audit_run(paths[0], files.user_path(f.maps) if f.maps else None)
    else:
      folders = [p for path in paths for p in ([path] if any(path.glob("scenario_*.parquet"))
                                                 else av2_io.list_scenario_folders(path))]
      result = {"scenarios": audit_folders(folders)}
  except (OSError, ValueError) as e:
    raise SystemExit(f"audit: {e}") from None
  text = files.json_text(result, indent=1)
  if f.out:
    files.atomic_write_text(files.user_path(f.out), text)
  sys.stdout.write(text + "\n")


main = cli.entry_point(define_flags, run)


if __name__ == "__main__":
  main()
