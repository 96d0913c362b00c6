"""Synthetic AV2 worlds: seeded procedural scenarios written in the real AV2 file format.

A world is a road network (`tdiff_jax.data.road_network`: one junction of 3 to 5 arms at irregular
angles, a corridor of 2 or 3 junctions, or a junction-free road; curved and straight roads with 1 to 3
lanes each way, turn pockets, merges and splits, bike lanes, parking strips and lots, crosswalks) with
110 steps at 10 Hz of collision-free traffic on it (`tdiff_jax.data.traffic`), rotated and translated
into a random "city" frame. The traffic part also runs on real AV2 maps (`--maps`): scenarios for maps
that come without logs, written with the map's own JSON.

Scenarios go through av2's own serializer and the map JSON carries every field av2's loader needs
(centrelines included), so the code that reads real AV2 reads these.

Commands:
  python -m tdiff_jax.data.synthetic --out DIR --num N --seed S [--val_fraction 0.1]
  python -m tdiff_jax.data.synthetic --out DIR --num N --maps FOLDER   # traffic on FOLDER's AV2 maps
write DIR/train/<id>/ and DIR/val/<id>/ folders. Reruns skip scenarios already written; each scenario
folder appears atomically. With --maps, scenario i uses the i-th map folder (cycling through them); a
map av2 cannot read is skipped and counted.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import shutil
import uuid
from concurrent import futures
from pathlib import Path

import numpy as np
from absl import flags
from av2.datasets.motion_forecasting.data_schema import (
    ArgoverseScenario, ObjectState, ObjectType, Track, TrackCategory)

from tdiff_jax import cli, files
from tdiff_jax.data import av2_io, road_network, traffic
from tdiff_jax.data.traffic import NUM_STEPS

OBSERVED_STEPS = 50
# Recorded in each dataset's synthetic.json: a folder of worlds from another version of the generator is
# refused rather than mixed with new ones (2: road networks of several parts, `road_network`).
GENERATOR_VERSION = 2


# ------------------------------------------------------------------------------------------------
# AV2 files
# ------------------------------------------------------------------------------------------------

@dataclasses.dataclass
class SyntheticScenario:
  """A generated world as av2 objects: the scenario and the map JSON dict."""

  scenario: ArgoverseScenario
  map_json: dict
  kind: str


def _pts(xy: np.ndarray, z: np.ndarray | float) -> list[dict]:
  z = np.broadcast_to(np.asarray(z, np.float64), (len(xy),))
  return [{"x": round(x, 2), "y": round(y, 2), "z": round(zz, 2)}
          for (x, y), zz in zip(np.asarray(xy, np.float64).tolist(), z.tolist())]


def scenario_id_for(seed: int, index: int) -> str:
  """The scenario id of (seed, index), known before generating it (so reruns can skip it)."""
  return str(uuid.UUID(bytes=np.random.default_rng([seed, index, 1]).bytes(16), version=4))


def _tracks(agents: list[traffic.Agent], rng, to_city, angle: float) -> tuple[list[Track], str]:
  """av2 tracks of the agents (the AV's id "AV"; a full-length track promoted to focal if no focal vehicle
  could be placed), sorted by id as av2's loader groups them, and the focal track's id."""
  base = int(rng.integers(10_000, 900_000))
  tracks = []
  focal_id = None
  for k, agent in enumerate(agents):
    track_id = "AV" if agent.role == "AV" else str(base + k)
    if agent.role == "AV":
      category = TrackCategory.UNSCORED_TRACK
    elif agent.role == "focal":
      category, focal_id = TrackCategory.FOCAL_TRACK, track_id
    elif agent.present.all() and agent.role not in ("static", "parked"):
      category = TrackCategory.SCORED_TRACK if rng.random() < 0.3 else TrackCategory.UNSCORED_TRACK
    else:
      category = TrackCategory.TRACK_FRAGMENT
    xy = to_city(agent.xy)
    heading = np.arctan2(np.sin(agent.heading + angle), np.cos(agent.heading + angle))
    vel = agent.speed[:, None] * np.stack([np.cos(heading), np.sin(heading)], -1)
    steps = np.flatnonzero(agent.present)
    states = [ObjectState(observed=t < OBSERVED_STEPS, timestep=t, position=(x, y), heading=h, velocity=(vx, vy))
              for t, (x, y), h, (vx, vy) in zip(steps.tolist(), xy[steps].tolist(), heading[steps].tolist(),
                                                vel[steps].tolist())]
    tracks.append(Track(track_id, states, ObjectType(agent.object_type), category))
  if focal_id is None:  # no focal vehicle could be placed: promote a full-length track
    full = [t for t in tracks if t.track_id != "AV" and len(t.object_states) == NUM_STEPS]
    focal = (full or tracks)[0]
    focal.category = TrackCategory.FOCAL_TRACK
    focal_id = focal.track_id
  tracks.sort(key=lambda t: t.track_id)
  return tracks, focal_id


def _scenario(scenario_id: str, tracks: list[Track], focal_id: str, rng, city: str) -> ArgoverseScenario:
  start = float(int(rng.integers(315_000_000_000_000_000, 320_000_000_000_000_000)))
  timestamps = np.linspace(start, start + (NUM_STEPS - 1) * 1e8, NUM_STEPS)
  return ArgoverseScenario(scenario_id=scenario_id, timestamps_ns=timestamps, tracks=tracks,
                           focal_track_id=focal_id, city_name=city, map_id=None, slice_id=None)


def generate_scenario(seed: int, index: int) -> SyntheticScenario:
  """A generated world with traffic. Deterministic in (seed, index)."""
  rng = np.random.default_rng([seed, index])
  world = road_network.build_world(rng)
  agents = traffic.populate(world, rng)

  # Place the local world in a random city frame.
  angle = float(rng.uniform(-np.pi, np.pi))
  rot = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
  shift = rng.uniform(-1500, 4500, 2).round(2)
  to_city = lambda xy: np.asarray(xy) @ rot.T + shift  # noqa: E731
  ground = float(rng.uniform(-20, 30))

  lanes = {}
  for lane in world.lanes:
    left, right = lane.boundaries()
    z_left = ground + 0.01 * np.arange(len(left))
    z_right = ground + 0.01 * np.arange(len(right))
    lanes[str(lane.id)] = {
        "centerline": _pts(to_city(lane.center), 0.0),
        "id": lane.id,
        "is_intersection": bool(lane.is_intersection),
        "lane_type": lane.lane_type,
        "left_lane_boundary": _pts(to_city(left), z_left),
        "left_lane_mark_type": lane.left_mark,
        "left_neighbor_id": lane.left_neighbor,
        "predecessors": list(lane.predecessors),
        "right_lane_boundary": _pts(to_city(right), z_right),
        "right_lane_mark_type": lane.right_mark,
        "right_neighbor_id": lane.right_neighbor,
        "successors": list(lane.successors),
    }
  crossings = {str(i): {"edge1": _pts(to_city(e1), ground), "edge2": _pts(to_city(e2), ground), "id": i}
               for i, e1, e2 in world.crosswalks}
  areas = {str(i): {"area_boundary": _pts(to_city(ring), ground), "id": i} for i, ring in world.drivable_areas}
  map_json = {"drivable_areas": areas, "lane_segments": lanes, "pedestrian_crossings": crossings}
  tracks, focal_id = _tracks(agents, rng, to_city, angle)
  scenario = _scenario(scenario_id_for(seed, index), tracks, focal_id, rng, "synthetic")
  return SyntheticScenario(scenario, map_json, world.kind)


def generate_on_map(map_folder: Path | str, seed: int, index: int) -> SyntheticScenario:
  """Traffic on the AV2 map of `map_folder` (its scenario parquet, if any, is not read), written with the
  map's own JSON. Deterministic in (map, seed, index). Raises `av2_io.BadScenarioError` for a map av2's
  rules refuse or one without a vehicle lane."""
  raw = av2_io.read_scenario_folder(map_folder, map_only=True)
  rng = np.random.default_rng([seed, index])
  agents = traffic.populate(traffic.world_from_map(raw), rng)
  if not any(a.role == "AV" for a in agents):
    raise av2_io.BadScenarioError(raw.files.map_json, "no vehicle lane to drive the AV on")
  city = raw.tracks.city_name if raw.tracks is not None else "unknown"
  tracks, focal_id = _tracks(agents, rng, lambda xy: np.asarray(xy), 0.0)
  scenario = _scenario(scenario_id_for(seed, index), tracks, focal_id, rng, city)
  return SyntheticScenario(scenario, raw.map_data, "map")


def write_scenario(sc: SyntheticScenario, split_dir: Path) -> Path:
  """Writes `<split_dir>/<id>/` atomically: a folder appears complete or not at all."""
  return av2_io.write_scenario_folder(sc.scenario, sc.map_json, split_dir)


def _generate_one(args) -> str | None:
  """Writes scenario `index`; returns its id, or None for a map that was skipped (with a warning)."""
  seed, index, split_dir, map_folder = args
  if (Path(split_dir) / scenario_id_for(seed, index)).is_dir():
    return scenario_id_for(seed, index)  # written by an earlier run
  if map_folder is None:
    sc = generate_scenario(seed, index)
  else:
    try:
      sc = generate_on_map(map_folder, seed, index)
    except av2_io.BadScenarioError as e:
      logging.warning("synthetic: map skipped: %s", e)
      return None
  write_scenario(sc, Path(split_dir))
  return sc.scenario.scenario_id


def split_of(index: int, num: int, val_fraction: float) -> str:
  num_val = int(math.ceil(num * val_fraction)) if val_fraction > 0 else 0
  return "val" if index >= num - num_val else "train"


def generate_dataset(out: Path | str, num: int, seed: int = 0, val_fraction: float = 0.1,
                     workers: int | None = None, progress: bool = True,
                     splits: tuple[str, ...] = ("train", "val"), maps: Path | str | None = None) -> dict[str, int]:
  """Writes `num` scenarios under out/train and out/val. Resumable: existing scenarios are kept.
  `splits=("val",)` writes the validation scenarios only (a later call with both splits adds the rest).
  `maps`: a folder of AV2 scenario folders (or an AV2 root, its val split) whose maps get the traffic,
  scenario i on the i-th map (cycling); None: generated worlds. Maps av2 cannot read are skipped and
  counted (`skipped` in the result).

  `out/synthetic.json` records what the folder holds (written before the first scenario, with the
  counts once all are written). A folder made with other settings, or holding scenario folders this
  generator did not record, is refused: reusing it would mix two datasets and leak scenarios between
  the splits. Returns the number of scenarios per split.
  """
  from tqdm import tqdm

  out = Path(out)
  done_file = out / "synthetic.json"
  asked = {"num": num, "seed": seed, "val_fraction": val_fraction, "generator": GENERATOR_VERSION}
  map_list = None
  if maps is not None:
    map_list = av2_io.map_folders(maps)
    asked["maps"] = str(Path(maps).resolve())
  if done_file.exists():
    meta = json.loads(done_file.read_text())
    made = {k: meta.get(k) for k in asked}
    if made != asked:
      raise ValueError(f"{out} holds synthetic scenarios made with {made}, not the {asked} asked for; "
                       "use another folder (or delete this one)")
    if meta.get("counts"):
      return meta["counts"]
  elif any(p.is_dir() and any(p.iterdir()) for p in (out / "train", out / "val")):
    raise ValueError(f"{out} already holds scenario folders that this generator did not record; "
                     "use another folder (or delete this one)")
  out.mkdir(parents=True, exist_ok=True)
  files.atomic_write_text(done_file, json.dumps(asked))   # what this folder is being filled with
  jobs, counts = [], {"train": 0, "val": 0}
  for i in range(num):
    split = split_of(i, num, val_fraction)
    counts[split] += 1
    if split in splits:
      (out / split).mkdir(parents=True, exist_ok=True)
      jobs.append((seed, i, str(out / split), str(map_list[i % len(map_list)]) if map_list else None))
  for split in counts:  # leftovers of a killed run
    for tmp in (out / split).glob(".tmp-*") if (out / split).exists() else []:
      shutil.rmtree(tmp, ignore_errors=True)
  workers = workers or os.cpu_count() or 1
  bar = tqdm(total=len(jobs), desc="synthetic scenarios", disable=not progress, unit="scn")
  skipped = {"train": 0, "val": 0}
  if workers == 1:
    written = map(_generate_one, jobs)
  else:
    import multiprocessing
    pool = futures.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
    written = pool.map(_generate_one, jobs, chunksize=8)
  for job, sid in zip(jobs, written):
    if sid is None:
      skipped[Path(job[2]).name] += 1
    bar.update()
  if workers != 1:
    pool.shutdown()
  bar.close()
  counts = {split: counts[split] - skipped[split] for split in counts}
  if any(skipped.values()):
    counts["skipped"] = sum(skipped.values())
  if set(splits) >= {"train", "val"}:
    files.atomic_write_text(done_file, json.dumps({**asked, "counts": counts}))
  return counts


def define_flags(values: flags.FlagValues) -> None:
  flags.DEFINE_string("out", None, "output directory (gets train/ and val/)", required=True, flag_values=values)
  flags.DEFINE_integer("num", 1000, "number of scenarios in all", lower_bound=1, flag_values=values)
  cli.define_seed_flag(values)
  flags.DEFINE_float("val_fraction", 0.1, "share of the scenarios in val/, in [0, 1)", lower_bound=0.0,
                     upper_bound=0.999999, flag_values=values)
  flags.DEFINE_integer("workers", 0, "processes (0: all cores)", lower_bound=0, flag_values=values)
  flags.DEFINE_string("maps", None, "traffic on the AV2 maps of this folder of scenario folders (or an AV2 root's "
                      "val split) instead of generated worlds", flag_values=values)


def run(f: flags.FlagValues, args: list[str]) -> None:
  cli.no_arguments(args)
  try:
    counts = generate_dataset(files.user_path(f.out), f.num, f.seed, f.val_fraction, f.workers or None,
                              maps=files.user_path(f.maps) if f.maps else None)
  except (OSError, ValueError) as e:
    raise SystemExit(f"synthetic: {e}") from None
  print(json.dumps({"out": str(f.out), **counts}))


main = cli.entry_point(define_flags, run)  # `python -m tdiff_jax.data.synthetic --out=DIR`, `main(["--out=DIR"])`


if __name__ == "__main__":
  main()
