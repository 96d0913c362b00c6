"""Reading and writing AV2 scenario folders with av2's own API; read errors name the file and the problem.

A scenario folder holds `scenario_<id>.parquet` and `log_map_archive_<id>.json`, as in the Argoverse 2
Motion Forecasting release. Both real and synthetic scenarios go through these functions.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
from av2.datasets.motion_forecasting import scenario_serialization
from av2.datasets.motion_forecasting.data_schema import ArgoverseScenario
from av2.map.map_api import ArgoverseStaticMap

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
class RawScenario:
  """What av2 reads from one scenario folder.

  Attributes:
    scenario: av2's `ArgoverseScenario` (tracks with per-step states); None when only the map was
      asked for and the parquet is missing or unreadable (`problem` says why).
    static_map: av2's `ArgoverseStaticMap` (vector lanes, crosswalks, drivable areas).
    centerlines: lane id -> `[N, 2]` centreline from the JSON `centerline` field (what AV2's release
      ships and QCNet-style pipelines read); lanes without the field are absent here.
  """

  files: ScenarioFiles
  scenario: ArgoverseScenario | None
  static_map: ArgoverseStaticMap
  centerlines: dict[int, Any]
  problem: str | None = None


def find_map_file(folder: Path | str) -> Path:
  """The `log_map_archive_<id>.json` of a scenario folder; raises BadScenarioError if absent or ambiguous."""
  folder = Path(folder)
  maps = sorted(folder.glob("log_map_archive_*.json"))
  if not maps:
    raise BadScenarioError(folder, "missing map log_map_archive_<id>.json")
  if len(maps) > 1:
    raise BadScenarioError(folder, f"{len(maps)} map JSON files, expected one")
  return maps[0]


def find_scenario_files(folder: Path | str) -> ScenarioFiles:
  """Locates the parquet and map JSON of a scenario folder; raises BadScenarioError if absent."""
  folder = Path(folder)
  if not folder.is_dir():
    raise BadScenarioError(folder, "not a directory")
  parquets = sorted(folder.glob("scenario_*.parquet"))
  if not parquets:
    raise BadScenarioError(folder, "missing scenario_<id>.parquet")
  if len(parquets) > 1:
    raise BadScenarioError(folder, f"{len(parquets)} scenario parquet files, expected one")
  map_json = find_map_file(folder)
  scenario_id = parquets[0].stem[len("scenario_"):]
  return ScenarioFiles(scenario_id, folder, parquets[0], map_json)


def load_scenario(files: ScenarioFiles) -> ArgoverseScenario:
  try:
    import pyarrow.parquet as pq
    rows = pq.ParquetFile(files.parquet).metadata.num_rows
  except Exception as e:
    raise BadScenarioError(files.parquet, f"unreadable scenario parquet ({type(e).__name__}: {e})") from e
  if rows == 0:  # av2's loader would fail with a bare KeyError on the first row
    raise BadScenarioError(files.parquet, "scenario parquet has no rows")
  try:
    return scenario_serialization.load_argoverse_scenario_parquet(files.parquet)
  except Exception as e:  # pyarrow, pandas and av2 each raise their own types on bad files
    raise BadScenarioError(files.parquet, f"unreadable scenario parquet ({type(e).__name__}: {e})") from e


def load_map(files: ScenarioFiles) -> tuple[ArgoverseStaticMap, dict[int, Any]]:
  """Loads the map with av2 and the raw JSON centrelines. Raises BadScenarioError."""
  try:
    with open(files.map_json) as f:
      raw = json.load(f)
  except Exception as e:
    raise BadScenarioError(files.map_json, f"broken map JSON ({type(e).__name__}: {e})") from e
  if not isinstance(raw, dict) or "lane_segments" not in raw:
    raise BadScenarioError(files.map_json, "map JSON has no 'lane_segments'")
  try:
    # av2 logs an error for maps without crosswalks; that is legal AV2, so keep it quiet.
    av2_logger = logging.getLogger("av2.map.map_api")
    level = av2_logger.level
    av2_logger.setLevel(logging.CRITICAL)
    try:
      static_map = ArgoverseStaticMap.from_json(files.map_json)
    finally:
      av2_logger.setLevel(level)
  except Exception as e:
    raise BadScenarioError(files.map_json, f"av2 cannot read the map ({type(e).__name__}: {e})") from e
  centerlines = {}
  try:
    for lane in raw["lane_segments"].values():
      if "centerline" in lane:
        centerlines[int(lane["id"])] = np.array([[p["x"], p["y"]] for p in lane["centerline"]], np.float64)
  except Exception as e:
    raise BadScenarioError(files.map_json, f"bad lane centerline ({type(e).__name__}: {e})") from e
  return static_map, centerlines


def read_scenario_folder(folder: Path | str, map_only: bool = False) -> RawScenario:
  """Reads one AV2 scenario folder with av2's loaders. Raises BadScenarioError on bad input.

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
  static_map, centerlines = load_map(files)
  scenario = None
  if files.parquet is not None:
    try:
      scenario = load_scenario(files)
    except BadScenarioError as e:
      if not map_only:
        raise
      problem = e.reason
  return RawScenario(files, scenario, static_map, centerlines, problem)


def list_scenario_folders(root: Path | str) -> list[Path]:
  """Scenario folders directly under `root` (folders holding a scenario parquet), sorted by name.

  Folders that look like scenarios but lack a file are listed too, so the preprocessing can report
  them as skipped rather than silently miss them. Hidden folders (`.tmp-*` ones of an interrupted
  write) are never listed.
  """
  root = Path(root)
  if not root.is_dir():
    raise FileNotFoundError(f"{root}: data directory does not exist")
  out = []
  for d in sorted(root.iterdir()):
    if d.name.startswith("."):  # hidden, e.g. `.tmp-*` left by a killed writer: never a scenario
      continue
    if d.is_dir() and (any(d.glob("scenario_*.parquet")) or any(d.glob("log_map_archive_*.json"))):
      out.append(d)
  return out


def scenario_id_of(folder: Path) -> str:
  """The scenario id a folder's file names declare (parquet, else map), without reading them."""
  for pattern, prefix in (("scenario_*.parquet", "scenario_"), ("log_map_archive_*.json", "log_map_archive_")):
    found = sorted(Path(folder).glob(pattern))
    if found:
      return found[0].stem[len(prefix):]
  return Path(folder).name


def write_scenario_folder(scenario: ArgoverseScenario, map_json: dict, parent: Path | str) -> Path:
  """Writes `<parent>/<scenario id>/` (parquet through av2's serializer, and the map JSON) atomically:
  the folder appears complete or not at all."""
  parent = Path(parent)
  sid = scenario.scenario_id
  final = parent / sid
  with atomic_path(final, directory=True) as tmp:
    scenario_serialization.serialize_argoverse_scenario_parquet(tmp / f"scenario_{sid}.parquet", scenario)
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
      out.append(f"{data_dir}: scenario {sid} appears {what}: {', '.join(where)}")
  if any((data_dir / s).is_dir() for s in SPLITS):
    beside = list_scenario_folders(data_dir)
    if beside:
      names = ", ".join(f.name for f in beside[:5]) + (f" and {len(beside) - 5} more" if len(beside) > 5 else "")
      out.append(f"{data_dir}: {len(beside)} scenario folder(s) beside the split folders are ignored "
                 f"(move them into {'/'.join(SPLITS)}/): {names}")
  return out




def map_folders(maps: Path | str) -> list[Path]:
  """Scenario folders of `maps`, or of its val (else first) split when it is an AV2 root."""
  splits = discover_splits(Path(maps), "maps")
  return splits.get("val") or next(iter(splits.values()))
