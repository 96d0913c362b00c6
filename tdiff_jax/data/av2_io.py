"""Reading and writing AV2 scenario folders; read errors name the file and the problem.

A scenario folder holds `scenario_<id>.parquet` and `log_map_archive_<id>.json`, as in the Argoverse 2
Motion Forecasting release. Both real and synthetic scenarios go through these functions. The map JSON
is parsed once (orjson) into coordinate arrays (`MapPolylines`) and each lane's attributes as av2's
`LaneSegment` reads them (`LaneAttributes`, their values checked against av2's enums); av2's
`ArgoverseStaticMap`, whose per-vertex objects took as long as the rest of reading a scenario, is built
only when asked for (`RawScenario.static_map`; a test checks both give the same lanes on every real
sample). The tracks are read as columns with pyarrow (`load_tracks`, about 25
times faster than av2's loader, which builds a Python object per row; a test checks that both give the
same tracks and states on every real sample); scenarios are written in av2's serializer's format
(`write_tracks_parquet`: its table built column by column instead of a data frame per track, 7 times
as fast; a test checks the files are byte for byte av2's).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import functools
import json
import logging
import operator
import os
import stat
from pathlib import Path

import numpy as np
import orjson
import pandas as pd
from av2.datasets.motion_forecasting.data_schema import ArgoverseScenario, ObjectType
from av2.map.drivable_area import DrivableArea
from av2.map.lane_segment import LaneMarkType, LaneSegment, LaneType
from av2.map.map_api import ArgoverseStaticMap
from av2.map.pedestrian_crossing import PedestrianCrossing

from tdiff_jax.files import atomic_path


class BadScenarioError(ValueError):
  """A scenario that cannot become a scene. `reason` is short and names the problem."""

  def __init__(self, path: Path | str, reason: str):
    super().__init__(f"{path}: {reason}")
    self.path = str(path)
    self.reason = reason


@dataclasses.dataclass
class ScenarioFiles:
  scenario_id: str
  folder: Path
  parquet: Path | None  # None only when the map alone was asked for and the parquet is missing
  map_json: Path


@dataclasses.dataclass
class TrackTable:
  """The rows of a scenario parquet as columns, one row per (track, timestep), in file order.

  Attributes:
    scenario_id, city_name: of the scenario (its first row, as av2's loader).
    track_id: `[N]` str. object_type: `[N]` str (av2 `ObjectType` values). timestep: `[N]` int64.
    position, velocity: `[N, 2]` float64 (city metres, m/s). heading: `[N]` float64 (rad).
  """

  scenario_id: str
  city_name: str
  track_id: np.ndarray
  object_type: np.ndarray
  timestep: np.ndarray
  position: np.ndarray
  velocity: np.ndarray
  heading: np.ndarray

  @property
  def num_tracks(self) -> int:
    return len(np.unique(self.track_id))

  @property
  def last_step(self) -> int:
    """The largest timestep of any track (-1 without rows)."""
    return int(self.timestep.max()) if len(self.timestep) else -1


_TRACK_COLUMNS = ("scenario_id", "city", "track_id", "object_type", "timestep", "position_x", "position_y",
                  "heading", "velocity_x", "velocity_y")


@dataclasses.dataclass
class MapPolylines:
  """The map's coordinates as `[N, 2]` float64 arrays (city metres, x and y), read from the map JSON once
  (av2's map objects rebuild an array from per-vertex objects at every access).

  Attributes:
    lane_left, lane_right: lane id -> its left / right boundary.
    lane_center: lane id -> the JSON `centerline` field (what AV2's release ships and QCNet-style
      pipelines read); lanes without the field are absent here.
    crosswalk_edges: crosswalk id -> its two edges (`edge1`, `edge2`).
    drivable_areas: drivable-area id -> its boundary ring as the JSON lists it.
  """

  lane_left: dict[int, np.ndarray]
  lane_right: dict[int, np.ndarray]
  lane_center: dict[int, np.ndarray]
  crosswalk_edges: dict[int, tuple[np.ndarray, np.ndarray]]
  drivable_areas: dict[int, np.ndarray]

  @classmethod
  def from_json_data(cls, raw: dict) -> "MapPolylines":
    lanes = list(raw["lane_segments"].values())
    centred = [l for l in lanes if "centerline" in l]
    crossings = list(raw.get("pedestrian_crossings", {}).values())
    areas = list(raw["drivable_areas"].values())
    lines = [*(l["left_lane_boundary"] for l in lanes), *(l["right_lane_boundary"] for l in lanes),
             *(l["centerline"] for l in centred), *(c["edge1"] for c in crossings),
             *(c["edge2"] for c in crossings), *(d["area_boundary"] for d in areas)]
    # Every vertex in one array (one conversion instead of one per polyline), then a view per polyline.
    flat = np.array([_XY(p) for line in lines for p in line]).reshape(-1, 2)
    if flat.dtype.kind not in "fiu":  # numpy would parse numbers written as strings without a word
      raise ValueError(f"coordinates must be numbers, found {flat.dtype} values")
    flat = flat.astype(np.float64)
    bad = ~(np.abs(flat) <= MAX_COORDINATE_M).all(-1)   # NaN too
    if bad.any():
      labels = [*(f"lane {l['id']} left boundary" for l in lanes), *(f"lane {l['id']} right boundary" for l in lanes),
                *(f"lane {l['id']} centerline" for l in centred), *(f"crosswalk {c['id']} edge1" for c in crossings),
                *(f"crosswalk {c['id']} edge2" for c in crossings), *(f"drivable area {d['id']}" for d in areas)]
      first = int(np.argmax(bad))
      line = int(np.searchsorted(np.cumsum([len(line) for line in lines]), first, side="right"))
      raise ValueError(f"{labels[line]}: vertex {flat[first].tolist()} is not a finite coordinate within "
                       f"{MAX_COORDINATE_M:g} m of the city origin")
    arrays = iter(np.split(flat, np.cumsum([len(line) for line in lines])[:-1]))
    take = lambda items: [next(arrays) for _ in items]  # noqa: E731
    left, right, center, edge1, edge2, ring = (take(lanes), take(lanes), take(centred), take(crossings),
                                               take(crossings), take(areas))
    ids = lambda items: [int(x["id"]) for x in items]  # noqa: E731
    return cls(
        lane_left=dict(zip(ids(lanes), left)),
        lane_right=dict(zip(ids(lanes), right)),
        lane_center=dict(zip(ids(centred), center)),
        crosswalk_edges=dict(zip(ids(crossings), zip(edge1, edge2))),
        drivable_areas=dict(zip(ids(areas), ring)))


_XY = operator.itemgetter("x", "y")
MAX_COORDINATE_M = 1e8   # |x|, |y| of a map vertex: beyond the Earth's circumference is no city coordinate
_OBJECT_TYPES = frozenset(t.value for t in ObjectType)
_LANE_TYPES = frozenset(t.value for t in LaneType)
_MARK_TYPES = frozenset(t.value for t in LaneMarkType)


@dataclasses.dataclass(frozen=True)
class LaneAttributes:
  """One lane segment's attributes, the fields of av2's `LaneSegment.from_dict` but its boundaries
  (`MapPolylines` holds those as arrays): type and mark types (av2's `LaneType` and `LaneMarkType`
  values, checked), whether it lies in an intersection, and its lane-graph neighbours by id."""

  lane_type: str
  is_intersection: bool
  left_mark_type: str
  right_mark_type: str
  predecessors: tuple[int, ...]
  successors: tuple[int, ...]
  left_neighbor_id: int | None
  right_neighbor_id: int | None

  @classmethod
  def from_json_data(cls, lane: dict) -> "LaneAttributes":
    """From a `lane_segments` entry of the map JSON; ValueError names a field av2 would not accept."""
    values = (lane["lane_type"], lane["left_lane_mark_type"], lane["right_lane_mark_type"])
    for value, allowed, field in zip(values, (_LANE_TYPES, _MARK_TYPES, _MARK_TYPES),
                                     ("lane_type", "left_lane_mark_type", "right_lane_mark_type")):
      if value not in allowed:
        raise ValueError(f"lane {lane.get('id')}: {field} {value!r} is not one of av2's")
    return cls(lane_type=values[0], is_intersection=bool(lane["is_intersection"]), left_mark_type=values[1],
               right_mark_type=values[2], predecessors=tuple(lane["predecessors"]),
               successors=tuple(lane["successors"]), left_neighbor_id=lane["left_neighbor_id"],
               right_neighbor_id=lane["right_neighbor_id"])


@dataclasses.dataclass
class RawScenario:
  """What is read from one scenario folder.

  Attributes:
    tracks: the scenario's track rows (`TrackTable`); None when only the map was asked for and the
      parquet is missing or unreadable (`problem` says why).
    lanes: lane id -> its attributes (`LaneAttributes`: type, marks, intersection, topology).
    polylines: the map's coordinates as arrays, and the JSON lane centrelines (`MapPolylines`).
    map_data: the parsed map JSON, from which `static_map` is built when asked for.
  """

  files: ScenarioFiles
  tracks: TrackTable | None
  lanes: dict[int, LaneAttributes]
  polylines: MapPolylines
  problem: str | None = None
  map_data: dict | None = dataclasses.field(default=None, repr=False)

  @functools.cached_property
  def static_map(self) -> ArgoverseStaticMap:
    """av2's `ArgoverseStaticMap` of the map (vector lanes, crosswalks, drivable areas), built on first
    use. Raises BadScenarioError (naming the map file) when av2 cannot read the map."""
    if self.map_data is None:
      raise ValueError(f"{self.files.map_json}: no map JSON data kept to build av2's map from")
    try:
      return static_map_from_json_data(self.map_data, self.files.map_json.stem[len("log_map_archive_"):])
    except Exception as e:
      raise BadScenarioError(self.files.map_json, f"av2 cannot read the map ({type(e).__name__}: {e})") from e


# The largest scenario files read (AV2's maps are about 1 MB, its parquets about 0.2 MB): a bigger file, or
# one that is no regular file (a pipe, a device, a link to one), is refused before it is read.
MAX_FILE_BYTES = 256 << 20


def check_regular_file(path: Path) -> None:
  """Raises BadScenarioError unless `path` (links followed) is a regular file of at most `MAX_FILE_BYTES`."""
  try:
    info = path.stat()
  except OSError as e:
    raise BadScenarioError(path, f"cannot be read ({e.strerror or e})") from None
  if not stat.S_ISREG(info.st_mode):
    raise BadScenarioError(path, "not a regular file (a pipe, a device or a folder): not read")
  if info.st_size > MAX_FILE_BYTES:
    raise BadScenarioError(path, f"{info.st_size} bytes, more than the {MAX_FILE_BYTES >> 20} MiB a scenario file "
                           "may hold: not read")


def _read_bounded(path: Path) -> bytes:
  """The bytes of a file `check_regular_file` accepted, never more than `MAX_FILE_BYTES` (it may grow)."""
  with open(path, "rb") as f:
    data = f.read(MAX_FILE_BYTES + 1)
  if len(data) > MAX_FILE_BYTES:
    raise BadScenarioError(path, f"more than the {MAX_FILE_BYTES >> 20} MiB a scenario file may hold: not read")
  return data


def _listing(folder: Path) -> list[str]:
  """The names in a scenario folder; BadScenarioError when it cannot be listed (no permission, a dangling link)."""
  if not folder.is_dir():
    what = "a link to nothing" if folder.is_symlink() and not folder.exists() else "not a directory"
    raise BadScenarioError(folder, what)
  try:
    return os.listdir(folder)
  except OSError as e:
    raise BadScenarioError(folder, f"unreadable folder ({e.strerror or e})") from None


def find_map_file(folder: Path | str) -> Path:
  """The `log_map_archive_<id>.json` of a scenario folder; raises BadScenarioError if absent, ambiguous, or
  not a regular file of bounded size (`check_regular_file`)."""
  folder = Path(folder)
  maps = sorted(folder / n for n in _listing(folder) if fnmatch.fnmatchcase(n, "log_map_archive_*.json"))
  if not maps:
    raise BadScenarioError(folder, "missing map log_map_archive_<id>.json")
  if len(maps) > 1:
    raise BadScenarioError(folder, f"{len(maps)} map JSON files, expected one")
  check_regular_file(maps[0])
  return maps[0]


def find_scenario_files(folder: Path | str) -> ScenarioFiles:
  """Locates the parquet and map JSON of a scenario folder; raises BadScenarioError if absent."""
  folder = Path(folder)
  parquets = sorted(folder / n for n in _listing(folder) if fnmatch.fnmatchcase(n, "scenario_*.parquet"))
  if not parquets:
    raise BadScenarioError(folder, "missing scenario_<id>.parquet")
  if len(parquets) > 1:
    raise BadScenarioError(folder, f"{len(parquets)} scenario parquet files, expected one")
  map_json = find_map_file(folder)
  scenario_id = parquets[0].stem[len("scenario_"):]
  return ScenarioFiles(scenario_id, folder, parquets[0], map_json)


def load_tracks(files: ScenarioFiles) -> TrackTable:
  """Reads the scenario parquet's track columns with pyarrow. Raises BadScenarioError (naming the
  file and the rule) when it is unreadable, has no rows, lacks a column or value the scene needs, has a
  numeric column of another type, or breaks one row per track and timestep (`_check_one_row_per_step`)."""
  import pyarrow as pa
  import pyarrow.parquet as pq
  check_regular_file(files.parquet)   # a pipe would block the reader forever
  try:
    table = pq.ParquetFile(files.parquet).read(columns=list(_TRACK_COLUMNS), use_threads=False)
  except Exception as e:  # pyarrow raises its own types on bad files, KeyError-like ones on missing columns
    raise BadScenarioError(files.parquet, f"unreadable scenario parquet ({type(e).__name__}: {e})") from e
  if table.num_rows == 0:
    raise BadScenarioError(files.parquet, "scenario parquet has no rows")
  cols = {}
  for name in _TRACK_COLUMNS:
    column = table.column(name)
    # A missing float (pandas writes NaN as null) reads as NaN, which the scene builder reports per track.
    if column.null_count and name in _TRACK_COLUMNS[:5]:
      raise BadScenarioError(files.parquet, f"column {name!r} has {column.null_count} missing values")
    if name in ("scenario_id", "city"):  # the scenario's, read from its first row (as av2's loader)
      cols[name] = column[:1].to_pylist()
    elif name in ("track_id", "object_type"):  # a few distinct strings: each converted once, not per row
      coded = column.combine_chunks().dictionary_encode()
      cols[name] = np.asarray(coded.dictionary.to_numpy(zero_copy_only=False), str)[coded.indices.to_numpy()]
    else:
      cols[name] = column.to_numpy(zero_copy_only=False)
  for name in _TRACK_COLUMNS[4:]:  # numpy would parse numbers written as strings without a word
    kind = table.schema.field(name).type
    if not (pa.types.is_integer(kind) or (name != "timestep" and pa.types.is_floating(kind))):
      raise BadScenarioError(files.parquet, f"column {name!r} is of type {kind}, expected "
                             f"{'integers' if name == 'timestep' else 'numbers'}")
  numeric = {k: np.asarray(cols[k], np.float64) for k in _TRACK_COLUMNS[5:]}
  timestep = np.asarray(cols["timestep"], np.int64)
  _check_one_row_per_step(files.parquet, cols["track_id"], cols["object_type"], timestep)
  return TrackTable(
      scenario_id=str(cols["scenario_id"][0]), city_name=str(cols["city"][0]),
      track_id=cols["track_id"], object_type=cols["object_type"],
      timestep=timestep, heading=numeric["heading"],
      position=np.stack([numeric["position_x"], numeric["position_y"]], -1),
      velocity=np.stack([numeric["velocity_x"], numeric["velocity_y"]], -1))


def _check_one_row_per_step(path: Path, track_id: np.ndarray, object_type: np.ndarray, timestep: np.ndarray) -> None:
  """Raises BadScenarioError for an object type av2 does not know, and when a track has two rows at one
  timestep or rows of two object types (two objects sharing an id, whose rows would otherwise be merged
  or replace each other)."""
  unknown = sorted({str(t) for t in np.unique(object_type)} - _OBJECT_TYPES)
  if unknown:
    raise BadScenarioError(path, f"object types {unknown[:5]} are not av2's")
  ids, track = np.unique(track_id, return_inverse=True)
  key = track.astype(np.int64) * (int(timestep.max()) - int(timestep.min()) + 1) + (timestep - timestep.min())
  unique, first, counts = np.unique(key, return_index=True, return_counts=True)
  if len(unique) < len(key):
    row = first[np.argmax(counts > 1)]
    raise BadScenarioError(path, f"track {track_id[row]} has {counts.max()} rows at timestep {timestep[row]}: "
                           "one row per track and timestep")
  types = np.unique(np.stack([track, np.unique(object_type, return_inverse=True)[1]]), axis=1)[0]
  if len(types) > len(ids):
    t = int(types[np.argmax(np.diff(types) == 0)])
    found = sorted({str(k) for k in object_type[track == t]})
    raise BadScenarioError(path, f"track {ids[t]} has rows of object types {found}: one object per track id")


def static_map_from_json_data(raw: dict, log_id: str) -> ArgoverseStaticMap:
  """av2's `ArgoverseStaticMap.from_json` on an already parsed JSON (it would parse the file again)."""
  if "pedestrian_crossings" not in raw:  # legal AV2 (av2 logs an error for it): no crosswalks
    raw = dict(raw, pedestrian_crossings={})
  return ArgoverseStaticMap(
      log_id=log_id,
      vector_drivable_areas={d["id"]: DrivableArea.from_dict(d) for d in raw["drivable_areas"].values()},
      vector_lane_segments={l["id"]: LaneSegment.from_dict(l) for l in raw["lane_segments"].values()},
      vector_pedestrian_crossings={c["id"]: PedestrianCrossing.from_dict(c)
                                   for c in raw["pedestrian_crossings"].values()},
      raster_drivable_area_layer=None, raster_roi_layer=None, raster_ground_height_layer=None)


# Map JSON sections: (name, a field every entry has once, so that counting it in the text finds keys the
# parser folded together).
_MAP_SECTIONS = (("lane_segments", b'"lane_type"'), ("pedestrian_crossings", b'"edge1"'),
                 ("drivable_areas", b'"area_boundary"'))
_INT64 = (-2**63, 2**63)


def _is_id(value) -> bool:
  """An AV2 map id: a JSON integer in int64's range (not a bool, a string or a float)."""
  return type(value) is int and _INT64[0] <= value < _INT64[1]


def check_map_json(raw, text: bytes = b"") -> None:
  """Raises ValueError naming the rule a parsed map JSON breaks: each section an object of entries keyed by
  their integer `id` (unique), lane topology ids integers or null, `is_intersection` a boolean. `text`,
  the file's bytes, finds entries whose keys repeat (a JSON parser keeps only the last)."""
  if not isinstance(raw, dict) or "lane_segments" not in raw or "drivable_areas" not in raw:
    raise ValueError("map JSON needs the objects 'lane_segments' and 'drivable_areas'")
  for section, field in _MAP_SECTIONS:
    entries = raw.get(section, {})
    if not isinstance(entries, dict) or not all(isinstance(e, dict) for e in entries.values()):
      raise ValueError(f"{section} must be an object of objects")
    for key, entry in entries.items():
      if not _is_id(entry.get("id")):
        raise ValueError(f"{section} entry {key!r}: id {entry.get('id')!r} is not an integer id")
      if key != str(entry["id"]):
        raise ValueError(f"{section} entry {key!r} holds id {entry['id']} (each entry is keyed by its own id: "
                         "a repeated or edited id)")
    if text and text.count(field) > len(entries):
      raise ValueError(f"{section}: {text.count(field)} entries in the file but {len(entries)} distinct keys "
                       "(a repeated key: the parser keeps only the last)")
  for key, lane in raw["lane_segments"].items():
    if type(lane.get("is_intersection")) is not bool:
      raise ValueError(f"lane {key}: is_intersection {lane.get('is_intersection')!r} is not a boolean")
    for name in ("predecessors", "successors"):
      if not isinstance(lane.get(name), list) or not all(_is_id(i) for i in lane[name]):
        raise ValueError(f"lane {key}: {name} {lane.get(name)!r} is not a list of integer ids")
    for name in ("left_neighbor_id", "right_neighbor_id"):
      if lane.get(name) is not None and not _is_id(lane[name]):
        raise ValueError(f"lane {key}: {name} {lane[name]!r} is neither an integer id nor null")


def load_map(files: ScenarioFiles) -> tuple[dict[int, LaneAttributes], MapPolylines, dict]:
  """Parses the map JSON once: each lane's attributes, the coordinates as arrays, and the parsed JSON
  (for `RawScenario.static_map`). Raises BadScenarioError naming the rule the file breaks."""
  try:
    text = _read_bounded(files.map_json)
    raw = orjson.loads(text)
  except BadScenarioError:
    raise
  except Exception as e:
    raise BadScenarioError(files.map_json, f"broken map JSON ({type(e).__name__}: {e})") from e
  try:
    check_map_json(raw, text)
  except ValueError as e:
    raise BadScenarioError(files.map_json, str(e)) from e
  try:
    lanes = {int(l["id"]): LaneAttributes.from_json_data(l) for l in raw["lane_segments"].values()}
  except Exception as e:
    raise BadScenarioError(files.map_json, f"bad lane segment ({type(e).__name__}: {e})") from e
  try:
    polylines = MapPolylines.from_json_data(raw)
  except Exception as e:
    raise BadScenarioError(files.map_json, f"bad map coordinates ({type(e).__name__}: {e})") from e
  return lanes, polylines, raw


def read_scenario_folder(folder: Path | str, map_only: bool = False) -> RawScenario:
  """Reads one AV2 scenario folder (map and tracks). Raises BadScenarioError on bad input.

  With `map_only` (a map to sample on; its tracks are optional) a missing or unreadable scenario
  parquet is not an error: the result has `scenario=None` and `problem` says what was wrong.
  """
  folder = Path(folder)
  try:
    files = find_scenario_files(folder)
  except BadScenarioError as e:
    if not (map_only and folder.is_dir() and not any(folder.glob("scenario_*.parquet"))):
      raise
    map_json = find_map_file(folder)
    files, problem = ScenarioFiles(map_json.stem[len("log_map_archive_"):], folder, None, map_json), e.reason
  else:
    problem = None
  lanes, polylines, map_data = load_map(files)
  tracks = None
  if files.parquet is not None:
    try:
      tracks = load_tracks(files)
    except BadScenarioError as e:
      if not map_only:
        raise
      problem = e.reason
  return RawScenario(files, tracks, lanes, polylines, problem, map_data)


def list_scenario_folders(root: Path | str) -> list[Path]:
  """Scenario folders directly under `root` (folders holding a scenario parquet), sorted by name.

  Folders that look like scenarios but lack a file are listed too, and so are folders that cannot be
  listed and links to nothing, so that their readers report them as skipped, with the reason, rather than
  silently miss them. Hidden folders (`.tmp-*` ones of an interrupted write) are never listed.
  """
  root = Path(root)
  if not root.is_dir():
    raise FileNotFoundError(f"{root}: data directory does not exist")
  out = []
  for d in sorted(root.iterdir()):
    if d.name.startswith("."):  # hidden, e.g. `.tmp-*` left by a killed writer: never a scenario
      continue
    if d.is_symlink() and not d.exists():
      out.append(d)   # a dangling link: reported, not ignored
      continue
    if not d.is_dir():
      continue
    try:
      names = os.listdir(d)
    except OSError:
      out.append(d)   # unreadable: reported with its reason by whoever reads it
      continue
    if any(fnmatch.fnmatchcase(n, "scenario_*.parquet") or fnmatch.fnmatchcase(n, "log_map_archive_*.json")
           for n in names):
      out.append(d)
  return out


def scenario_id_of(folder: Path) -> str:
  """The scenario id a folder's file names declare (parquet, else map), without reading them."""
  for pattern, prefix in (("scenario_*.parquet", "scenario_"), ("log_map_archive_*.json", "log_map_archive_")):
    found = sorted(Path(folder).glob(pattern))
    if found:
      return found[0].stem[len(prefix):]
  return Path(folder).name


def write_tracks_parquet(path: Path | str, scenario: ArgoverseScenario) -> None:
  """Writes `scenario`'s tracks as av2's `serialize_argoverse_scenario_parquet` does, the same file byte for
  byte (tested), from one table of columns: av2 builds a data frame per track, column by column, which
  took most of the synthetic worlds' generation time. Raises ValueError for a scenario without tracks."""
  tracks = scenario.tracks
  if not tracks:
    raise ValueError(f"scenario {scenario.scenario_id}: no tracks to write")
  states = [s for t in tracks for s in t.object_states]
  per_track = [len(t.object_states) for t in tracks]
  repeat = lambda values: np.repeat(np.array(values, dtype=object), per_track).tolist()  # noqa: E731
  frame = pd.DataFrame({  # av2's columns, in its order and dtypes
      "observed": np.array([s.observed for s in states], bool),
      "track_id": repeat([t.track_id for t in tracks]),
      "object_type": repeat([t.object_type.value for t in tracks]),
      "object_category": np.repeat(np.array([t.category.value for t in tracks], np.int64), per_track),
      "timestep": np.array([s.timestep for s in states], np.int64),
      "position_x": np.array([s.position[0] for s in states], np.float64),
      "position_y": np.array([s.position[1] for s in states], np.float64),
      "heading": np.array([s.heading for s in states], np.float64),
      "velocity_x": np.array([s.velocity[0] for s in states], np.float64),
      "velocity_y": np.array([s.velocity[1] for s in states], np.float64),
  })
  frame["scenario_id"] = scenario.scenario_id
  frame["start_timestamp"] = scenario.timestamps_ns[0]
  frame["end_timestamp"] = scenario.timestamps_ns[-1]
  frame["num_timestamps"] = len(scenario.timestamps_ns)
  frame["focal_track_id"] = scenario.focal_track_id
  frame["city"] = scenario.city_name
  if scenario.map_id is not None:
    frame["map_id"] = scenario.map_id
  if scenario.slice_id is not None:
    frame["slice_id"] = scenario.slice_id
  frame.to_parquet(path)


def write_scenario_folder(scenario: ArgoverseScenario, map_json: dict, parent: Path | str) -> Path:
  """Writes `<parent>/<scenario id>/` (the tracks in av2's parquet format, `write_tracks_parquet`, and the
  map JSON) atomically: the folder appears complete or not at all."""
  parent = Path(parent)
  sid = scenario.scenario_id
  final = parent / sid
  with atomic_path(final, directory=True) as tmp:
    write_tracks_parquet(tmp / f"scenario_{sid}.parquet", scenario)
    # json.dumps uses the C encoder in one go; json.dump streams chunk by chunk and is several times slower.
    (tmp / f"log_map_archive_{sid}.json").write_text(json.dumps(map_json, sort_keys=True))
  return final


# The layout of an AV2 root: split folders of scenario folders.
SPLITS = ("train", "val", "test")


def discover_splits(data_dir: Path, default_split: str) -> dict[str, list[Path]]:
  """Split name -> scenario folders: the `train/`, `val/`, `test/` folders of `data_dir`, or, when it
  has none, its scenario folders as `default_split`. What looks wrong is logged (`dataset_warnings`)."""
  data_dir = Path(data_dir)
  if not data_dir.is_dir():
    raise FileNotFoundError(f"{data_dir}: data directory does not exist")
  splits = {s: list_scenario_folders(data_dir / s) for s in SPLITS if (data_dir / s).is_dir()}
  if not splits:
    splits = {default_split: list_scenario_folders(data_dir)}
  if not any(splits.values()):
    raise FileNotFoundError(f"{data_dir}: no AV2 scenario folders found (expected <split>/<id>/scenario_<id>.parquet)")
  for w in dataset_warnings(data_dir, splits):
    logging.warning("%s", w)
  return splits


def dataset_warnings(data_dir: Path, splits: dict[str, list[Path]]) -> list[str]:
  """Scenario ids found in several folders or splits (a train/val leak), and scenario folders that
  are ignored because they sit beside the split folders."""
  out = []
  seen: dict[str, list[str]] = {}
  for split, folders in splits.items():
    for f in folders:
      seen.setdefault(scenario_id_of(f), []).append(f"{split}/{f.name}" if split in SPLITS and
                                                            (data_dir / split).is_dir() else f.name)
  for sid, where in sorted(seen.items()):
    if len(where) > 1:
      kinds = {w.split("/")[0] for w in where if "/" in w}
      what = "in two splits" if len(kinds) > 1 else "in several folders"
      listed = ", ".join(where[:5]) + (f" and {len(where) - 5} more" if len(where) > 5 else "")
      out.append(f"{data_dir}: scenario {sid} appears {what}: {listed}")
  if any((data_dir / s).is_dir() for s in SPLITS):
    beside = list_scenario_folders(data_dir)
    if beside:
      names = ", ".join(f.name for f in beside[:5]) + (f" and {len(beside) - 5} more" if len(beside) > 5 else "")
      out.append(f"{data_dir}: {len(beside)} scenario folder(s) beside the split folders are ignored "
                 f"(move them into {'/'.join(SPLITS)}/): {names}")
  return out




def map_folders(maps: Path | str) -> list[Path]:
  """Scenario folders of `maps`, or of its val split when it is an AV2 root. Raises FileNotFoundError for
  a root whose `val/` is missing or holds none: another split is never used in its place unless named."""
  splits = discover_splits(Path(maps), "maps")
  if "maps" in splits:
    return splits["maps"]
  if not splits.get("val"):
    found = ", ".join(f"{s}/" for s in splits if splits[s])
    raise FileNotFoundError(f"{Path(maps) / 'val'}: no AV2 scenario folders (an AV2 root's val split is the one "
                            f"used; this root holds {found}: pass the folder of the split to use, e.g. "
                            f"{Path(maps) / next(s for s in splits if splits[s])})")
  return splits["val"]
