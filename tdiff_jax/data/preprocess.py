"""Preprocessing: AV2 scenario folders (real or synthetic) -> fixed-shape shards + a manifest.

  python -m tdiff_jax.data.preprocess --data_dir ROOT --out CACHE [--workers 0] [--shard_size 256]
      [--force] [--config.max_agents=64 ...]

ROOT holds split folders (`train/`, `val/`, `test/`, each of scenario folders, as AV2 ships them) or
scenario folders directly (then they form the split named by `--split`). The cache gets
`CACHE/<split>/shard_<k>.array_record`, one record per scene (its `datatypes.Scene` arrays and scenario
id, `data/records.py`), read by index without loading a split into memory, beside `shard_<k>.json`
(the shard's metadata: sources, ids, per-scene agent and polygon counts, skipped scenarios, the moments
of the normalisation statistics), and `CACHE/manifest.json`: caps, feature layout, normalisation statistics of the training split, the av2
version, the preprocessing-config hash, counts, what the caps dropped, and every skipped scenario
with its reason.

* All cores: scenarios are read in a process pool; progress is shown per scenario.
* Resumable: shard k always covers the same sorted scenario folders, and a rerun keeps every shard
  whose format, config hash, folder list and sources still match. A source is fingerprinted by the
  name, size and modification time of each file of its scenario folder, recorded per scenario, so a
  replaced, fixed or corrupted file rebuilds its shard. `--force` rebuilds every shard.
* Atomic: shards and the manifest are written to a temporary file and renamed, so a kill never
  leaves a half-written file under a final name; a shard counts as finished when its metadata, written
  last, holds the checksum of its record file and of itself, and both match (`shard_problem`): an edited,
  swapped, cut or corrupted shard is rebuilt by a rerun and refused, named, by a reader.
* Bounded memory: one shard at a time; the manifest's statistics are merged from per-shard moments.
* Bad scenarios are skipped and recorded (unreadable parquet, missing or broken map JSON, no goal
  step, no agents kept, NaN), never abort the run.
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import importlib.metadata
import itertools
import json
import multiprocessing
import os
import sys
from concurrent import futures
from pathlib import Path
from typing import Any, Iterable, Iterator

import ml_collections
import numpy as np

import tdiff_jax
from tdiff_jax import cli, datatypes, files
from tdiff_jax.data import av2_io, normalize, records
from tdiff_jax.data import config as config_lib
from tdiff_jax.data import scene_builder

# 2: ground-truth trajectories (agent_future); 3: degenerate map elements dropped; 4: ArrayRecord shards;
# 5: checksums in the shard metadata, implausible agents left out.
FORMAT_VERSION = 5
MANIFEST = "manifest.json"
SPLITS = av2_io.SPLITS
_SCENE_FIELDS = list(datatypes.SCENE_FIELDS)
_TRUNCATION = ("agents_dropped", "polygons_dropped", "drivable_areas_dropped", "drivable_areas_resampled")
_DEGENERATE = ("polygons_degenerate", "drivable_areas_degenerate")
_IMPLAUSIBLE = ("agents_implausible",)
_COUNTS = _TRUNCATION + _DEGENERATE + _IMPLAUSIBLE


# The scene fields the shard metadata is computed from; the worker returns only these besides the record.
_SUMMARY_FIELDS = ("agent_state", "agent_valid", "agent_type", "pl_valid", "frame_scale")


def _process_folder(args) -> dict[str, Any]:
  """Worker: one scenario folder -> its encoded record (compressed here, so little crosses between
  processes) and the few arrays the shard metadata needs, or a skip record. Never raises."""
  folder, config_dict = args
  config = ml_collections.ConfigDict(config_dict)
  try:
    scene, info = scene_builder.load_scene(folder, config)
    arrays = scene.to_dict()
    record = records.encode({**arrays, "scenario_id": np.array(info.scenario_id)})
    return {"ok": True, "record": record, "scene": {k: arrays[k] for k in _SUMMARY_FIELDS},
            "info": dataclasses.asdict(info)}
  except av2_io.BadScenarioError as e:
    return {"ok": False, "scenario": Path(folder).name, "file": e.path, "reason": e.reason}
  except Exception as e:  # an unforeseen problem in one file must not stop the batch
    return {"ok": False, "scenario": Path(folder).name, "file": str(folder),
            "reason": f"unexpected error ({type(e).__name__}: {e})"}


def _empty_scene(config) -> dict[str, np.ndarray]:
  """Zero-scene arrays with the right trailing shapes (a split without scenes)."""
  specs = datatypes.field_specs(config.max_agents, config.max_polygons, 3 * config.points_per_polyline,
                            config.max_drivable_areas, config.max_drivable_area_vertices)
  return {name: np.zeros((0,) + shape, dtype) for name, (shape, dtype) in specs.items()}


def shard_files(split_dir: Path, k: int) -> tuple[Path, Path]:
  """The record file and the metadata file of shard k."""
  name = f"shard_{k:05d}"
  return split_dir / (name + records.SUFFIX), split_dir / (name + ".json")


def source_fingerprint(folder: Path) -> str:
  """Name, size and modification time (ns) of each scenario file of `folder`: changes when one is
  replaced, edited, added or removed."""
  parts = []
  for f in sorted([*folder.glob("scenario_*.parquet"), *folder.glob("log_map_archive_*.json")]):
    try:
      st = f.stat()
      parts.append(f"{f.name}:{st.st_size}:{st.st_mtime_ns}")
    except OSError:
      parts.append(f"{f.name}:unreadable")
  return "|".join(parts)


def write_shard(path: Path, results: list[dict], folders: list[Path], config, chash: str,
                sources: list[str]) -> dict:
  """Writes one shard's records, then its metadata (each atomically). Returns the metadata."""
  scenes = [r for r in results if r["ok"]]
  state = (np.stack([r["scene"]["agent_state"] for r in scenes]) if scenes
           else np.zeros((0, config.max_agents, 2, len(datatypes.AGENT_FEATURES)), np.float32))
  valid = (np.stack([r["scene"]["agent_valid"] for r in scenes]) if scenes
           else np.zeros((0, config.max_agents), bool))
  scale = np.array([r["scene"]["frame_scale"] for r in scenes], np.float32)
  types_ = [r["scene"]["agent_type"][r["scene"]["agent_valid"]] for r in scenes]
  meta = {
      "format_version": FORMAT_VERSION,
      "config_hash": chash,
      "folders": [f.name for f in folders],
      "sources": sources,
      "scenario_ids": [r["info"]["scenario_id"] for r in scenes],
      "skipped": [{k: r[k] for k in ("scenario", "file", "reason")} for r in results if not r["ok"]],
      "warnings": [{"scenario": r["info"]["scenario_id"], "warning": w} for r in scenes for w in r["info"]["warnings"]],
      "counts": {c: int(sum(r["info"].get(c, 0) for r in scenes)) for c in _COUNTS},
      "scenes_truncated": {c: int(sum(r["info"].get(c, 0) > 0 for r in scenes)) for c in _COUNTS},
      "max_candidates": max((r["info"]["num_candidates"] for r in scenes), default=0),
      "max_polygons_seen": max((int(r["info"]["polygons_dropped"] + r["scene"]["pl_valid"].sum())
                                for r in scenes), default=0),
      # What batching and the trainer need without reading a record.
      "num_agents": [int(r["scene"]["agent_valid"].sum()) for r in scenes],
      "num_polygons": [int(r["scene"]["pl_valid"].sum()) for r in scenes],
      "agent_type_counts": np.bincount(np.concatenate(types_) if types_ else np.zeros(0, int),
                                       minlength=len(datatypes.AGENT_TYPES)).tolist(),
      "state_moments": normalize.state_moments(state, valid, scale),
      "offset_moments": normalize.offset_moments(state, valid, scale),
  }
  records.write(path, [r["record"] for r in scenes])
  meta["records_sha256"] = files.sha256(path)
  meta["meta_sha256"] = _meta_checksum(meta)
  files.atomic_write_text(path.with_suffix(".json"), json.dumps(meta))
  return meta


def _meta_checksum(meta: dict, field: str = "meta_sha256") -> str:
  """SHA-256 of the metadata's canonical JSON, its own checksum (`field`) left out."""
  body = json.dumps({k: v for k, v in meta.items() if k != field}, sort_keys=True)
  return hashlib.sha256(body.encode()).hexdigest()


def shard_problem(path: Path) -> tuple[dict | None, str | None]:
  """(metadata, None) for a finished, intact shard (its record file `path`), else (None, what is wrong):
  missing or unreadable, of another format, metadata edited (its checksum), record file changed or
  swapped (the metadata's checksum of it), or fewer records than the metadata lists."""
  meta_path = path.with_suffix(".json")
  try:
    meta = json.loads(meta_path.read_text())
  except (OSError, ValueError) as e:
    return None, f"{meta_path}: unreadable shard metadata ({type(e).__name__})"
  found = meta.get("format_version") if isinstance(meta, dict) else None
  if found != FORMAT_VERSION:
    return None, f"{meta_path}: shard of cache format {found}, this code reads {FORMAT_VERSION}"
  if meta.get("meta_sha256") != _meta_checksum(meta):
    return None, f"{meta_path}: the shard metadata does not match its checksum (edited or damaged)"
  try:
    digest = files.sha256(path)
  except OSError as e:
    return None, f"{path}: unreadable record file ({e.strerror or e})"
  if digest != meta.get("records_sha256"):
    return None, f"{path}: the record file does not match the checksum in its metadata (changed, swapped or damaged)"
  if records.count(path) != len(meta.get("scenario_ids", ())):
    return None, f"{path}: the record file does not hold the {len(meta['scenario_ids'])} scenes its metadata lists"
  return meta, None


def read_shard_meta(path: Path) -> dict | None:
  """The metadata of a finished, intact shard (`shard_problem`), or None."""
  return shard_problem(path)[0]


def manifest_problem(manifest: dict) -> str | None:
  """What is wrong with a manifest of this format (edited: its checksum), or None."""
  if manifest.get("manifest_sha256") != _meta_checksum(manifest, "manifest_sha256"):
    return "the manifest does not match its checksum (edited or damaged)"
  return None


def rebuild_hint(manifest: dict, cache_dir: Path | str) -> str:
  """How to rebuild a cache: the preprocessing command of its source."""
  return (f"rebuild it with: python -m tdiff_jax.data.preprocess --data_dir {manifest.get('source', '<AV2 root>')} "
          f"--out {cache_dir} (a training run rebuilds a cache it made itself)")


def preprocess(data_dir: Path | str, out_dir: Path | str, config: ml_collections.ConfigDict | None = None,
               workers: int | None = None, shard_size: int = 256, default_split: str = "train",
               progress: bool = True, force: bool = False) -> dict:
  """Builds (or completes) the cache; returns the manifest. `force` rebuilds every shard."""
  from tqdm import tqdm

  config = config_lib.scene_config(config)
  config_lib.validate_data_config(config)
  if shard_size < 1:
    raise ValueError(f"shard_size must be >= 1, got {shard_size}")
  chash = config_lib.config_hash(config)
  out_dir = Path(out_dir)
  splits = av2_io.discover_splits(Path(data_dir), default_split)
  workers = workers or os.cpu_count() or 1

  # Plan: which shards are still to do.
  plan = []  # (split, shard index, shard path, folders, source fingerprints)
  shard_meta: dict[str, list[dict]] = {}
  reused, changed = 0, []
  for split, folders in splits.items():
    (out_dir / split).mkdir(parents=True, exist_ok=True)
    for stale in [*(out_dir / split).glob(".tmp-*"), *(out_dir / split).glob("shard_*.npz")]:
      stale.unlink()  # left by a killed run, or shards of an older cache format
    shard_meta[split] = []
    for k in range(0, max(len(folders), 1), shard_size):
      chunk = folders[k:k + shard_size]
      path, _ = shard_files(out_dir / split, k // shard_size)
      sources = [source_fingerprint(f) for f in chunk]
      meta, problem = (None, None) if force else shard_problem(path)
      if problem is not None and path.exists() and progress:
        print(f"preprocess: rebuilding a shard: {problem}", file=sys.stderr)
      same_shard = (meta is not None and meta["config_hash"] == chash
                    and meta["folders"] == [f.name for f in chunk])
      if same_shard and meta.get("sources") == sources:
        shard_meta[split].append(meta)
        reused += 1
        continue
      if same_shard:
        old = dict(zip(meta["folders"], meta.get("sources") or [None] * len(chunk)))
        changed += [f"{split}/{f.name}" for f, src in zip(chunk, sources) if old.get(f.name) != src]
      shard_meta[split].append(None)
      plan.append((split, len(shard_meta[split]) - 1, path, chunk, sources))
    # Shards beyond the current folder count belong to an older listing.
    for path in shard_paths(out_dir / split)[len(shard_meta[split]):]:
      path.unlink()
      path.with_suffix(".json").unlink(missing_ok=True)

  if progress and (reused or changed):
    note = f"preprocess: {reused} finished shard(s) reused, {len(plan)} to build"
    if changed:
      shown = ", ".join(changed[:5]) + (f" and {len(changed) - 5} more" if len(changed) > 5 else "")
      note += f"; sources changed since the last run: {shown}"
    print(note, file=sys.stderr)
  todo = [f for _, _, _, chunk, _ in plan for f in chunk]
  bar = tqdm(total=len(todo), desc="preprocess", unit="scn", disable=not progress)
  cfg = config.to_dict()
  results_iter: Iterable[dict]
  pool = None
  if workers > 1 and len(todo) > 1:
    pool = futures.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
    results_iter = _bounded_map(pool, _process_folder, ((str(f), cfg) for f in todo), window=8 * workers)
  else:
    results_iter = (_process_folder((str(f), cfg)) for f in todo)
  try:
    results_iter = iter(results_iter)
    for split, idx, path, chunk, sources in plan:
      results = []
      for _ in chunk:
        results.append(next(results_iter))
        bar.update()
      shard_meta[split][idx] = write_shard(path, results, chunk, config, chash, sources)
  finally:
    bar.close()
    if pool is not None:
      pool.shutdown(cancel_futures=True)

  manifest = build_manifest(out_dir, config, chash, splits, shard_meta, Path(data_dir))
  scene_warnings = [f"{split}/{w['scenario']}: {w['warning']}" for split, metas in shard_meta.items()
                    for m in metas for w in m["warnings"]]
  manifest["warnings"] = av2_io.dataset_warnings(Path(data_dir), splits) + scene_warnings
  if scene_warnings:
    more = len(scene_warnings) - 5
    shown = "\n  ".join(scene_warnings[:5]) + (f"\n  and {more} more" if more > 0 else "")
    print(f"preprocess: warnings (also in {out_dir / MANIFEST}):\n  {shown}", file=sys.stderr)
  manifest["manifest_sha256"] = _meta_checksum(manifest, "manifest_sha256")
  files.atomic_write(out_dir / MANIFEST, lambda f: f.write(json.dumps(manifest, indent=1).encode()))
  return manifest


def _bounded_map(pool: futures.Executor, fn, items: Iterable, window: int) -> Iterator:
  """`pool.map(fn, items)` in order, with at most `window` items in flight, so finished scenes never
  pile up in memory faster than shards are written (`Executor.map` submits everything at once)."""
  items = iter(items)
  pending = collections.deque(pool.submit(fn, x) for x in itertools.islice(items, window))
  while pending:
    result = pending.popleft().result()
    for x in itertools.islice(items, 1):
      pending.append(pool.submit(fn, x))
    yield result


def build_manifest(out_dir: Path, config, chash: str, splits: dict, shard_meta: dict, data_dir: Path) -> dict:
  stats_split = "train" if "train" in splits else next(iter(splits))
  try:
    stats = normalize.stats_from_moments(
        normalize.merge_moments([m["state_moments"] for m in shard_meta[stats_split]]), "normalisation")
    offsets = normalize.stats_from_moments(
        normalize.merge_moments([m["offset_moments"] for m in shard_meta[stats_split]]), "goal-offset")
  except ValueError:
    stats = offsets = None
  split_info, skipped = {}, []
  totals = {c: 0 for c in _COUNTS}
  truncated = {c: 0 for c in _COUNTS}
  for split, metas in shard_meta.items():
    n = sum(len(m["scenario_ids"]) for m in metas)
    sk = [dict(split=split, **s) for m in metas for s in m["skipped"]]
    skipped += sk
    for m in metas:
      for c in _COUNTS:
        totals[c] += m["counts"][c]
        truncated[c] += m["scenes_truncated"][c]
    split_info[split] = {
        "scenes": n, "scenario_folders": len(splits[split]), "skipped": len(sk),
        "shards": [f"{split}/{shard_files(Path(), i)[0].name}" for i in range(len(metas))],
        "agent_type_counts": np.sum([m["agent_type_counts"] for m in metas], 0, dtype=np.int64).tolist()
        if metas else [0] * len(datatypes.AGENT_TYPES),
        "max_agents_seen": max((m["max_candidates"] for m in metas), default=0),
        "max_polygons_seen": max((m["max_polygons_seen"] for m in metas), default=0),
    }
  return {
      "format_version": FORMAT_VERSION,
      "tdiff_jax_version": tdiff_jax.__version__,
      "av2_version": importlib.metadata.version("av2"),
      "source": str(data_dir),
      "config": config.to_dict(),
      "config_hash": chash,
      "caps": {"agents": config.max_agents, "polygons": config.max_polygons,
               "points_per_polygon": 3 * config.points_per_polyline,
               "drivable_areas": config.max_drivable_areas,
               "drivable_area_vertices": config.max_drivable_area_vertices},
      "feature_layout": {
          "agent_state": list(datatypes.AGENT_FEATURES), "agent_types": list(datatypes.AGENT_TYPES),
          "polygon_types": list(datatypes.POLYGON_TYPES), "point_types": list(datatypes.POINT_TYPES),
          "point_sides": list(datatypes.POINT_SIDES), "edge_types": list(datatypes.EDGE_TYPES),
          "intersection_flags": list(datatypes.INTERSECTION_FLAGS),
          "tokens": {"initial_step": datatypes.INITIAL_STEP, "goal_step": datatypes.GOAL_STEP},
          "agent_future": {"features": ["x", "y"], "first_step": datatypes.INITIAL_STEP, "steps": datatypes.HORIZON},
      },
      "normalization": None if stats is None else {
          **stats, "features": list(normalize.MODEL_FEATURES), "split": stats_split,
          "pooled_over": "valid agents, initial and goal tokens"},
      # For the HL model's goal offsets (`model.goal_offset`): the goal's offset from the initial position.
      "goal_offset_normalization": None if offsets is None else {
          **offsets, "features": ["dx / frame_scale", "dy / frame_scale"], "split": stats_split},
      "splits": split_info,
      "truncation": {"totals": {c: totals[c] for c in _TRUNCATION},
                     "scenes_affected": {c: truncated[c] for c in _TRUNCATION}},
      # Map elements dropped because they have no geometry to encode (see map_features).
      "degenerate_map_elements": {"totals": {c: totals[c] for c in _DEGENERATE},
                                  "scenes_affected": {c: truncated[c] for c in _DEGENERATE}},
      # Agents left out for states outside physical ranges (`scene_builder.implausible_agents`).
      "implausible_agents": {"totals": totals[_IMPLAUSIBLE[0]], "scenes_affected": truncated[_IMPLAUSIBLE[0]]},
      "skipped": skipped,
  }


def shard_paths(split_dir: Path) -> list[Path]:
  """A split's record files, in shard order."""
  return sorted(Path(split_dir).glob("shard_*" + records.SUFFIX))


def load_arrays(split_dir: Path, fields: Iterable[str] | None = None) -> dict[str, np.ndarray]:
  """The named fields (default: all scene fields and scenario ids) of every scene of a split, stacked
  `[N, ...]`, in memory: for tests and small splits (training streams, `batches.open_split`)."""
  from array_record.python import array_record_module

  fields = list(fields) if fields is not None else _SCENE_FIELDS + ["scenario_id"]
  parts: dict[str, list] = {f: [] for f in fields}
  for path in shard_paths(split_dir):
    reader = array_record_module.ArrayRecordReader(str(path))
    for record in reader.read_all():
      scene = records.decode(record)
      for f in fields:
        parts[f].append(scene[f])
    reader.close()
  return {f: np.stack(v) if v else np.zeros((0,)) for f, v in parts.items()}


def run(f, args: list[str]) -> None:
  cli.no_arguments(args)
  try:
    manifest = preprocess(files.user_path(f.data_dir), files.user_path(f.out), f.config, f.workers or None,
                          f.shard_size, f.split, force=f.force)
  except (OSError, ValueError) as e:
    raise SystemExit(f"preprocess: {e}") from None
  print(json.dumps(_summary(manifest)))


def _summary(manifest: dict) -> dict:
  return {"splits": {s: {k: v for k, v in i.items() if k != "shards"} for s, i in manifest["splits"].items()},
          "skipped": manifest["skipped"], "warnings": manifest.get("warnings", []),
          "truncation": manifest["truncation"]["totals"],
          "degenerate_map_elements": manifest["degenerate_map_elements"]["totals"],
          "normalization": manifest["normalization"]}


def define_flags(values) -> None:
  from absl import flags
  from ml_collections import config_flags
  flags.DEFINE_string("data_dir", None, "AV2 root: split folders or scenario folders", required=True,
                      flag_values=values)
  flags.DEFINE_string("out", None, "cache directory", required=True, flag_values=values)
  flags.DEFINE_integer("workers", 0, "processes (0: all cores)", lower_bound=0, flag_values=values)
  flags.DEFINE_integer("shard_size", 256, "scenarios per shard", lower_bound=1, flag_values=values)
  flags.DEFINE_bool("force", False, "rebuild every shard, even those that are up to date", flag_values=values)
  flags.DEFINE_string("split", "train", "split name when data_dir holds scenario folders directly",
                      flag_values=values)
  config_flags.DEFINE_config_dict("config", config_lib.default_data_config(), "data config", lock_config=True,
                                  flag_values=values)


main = cli.entry_point(define_flags, run)


if __name__ == "__main__":
  main()
