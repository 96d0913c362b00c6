"""Checkpoints: the one module that talks to orbax.

A checkpoint holds the train state pytree (params, optimiser state, EMA, step, PRNG key) and a JSON
record (step, data-iterator position, the full config, normalisation statistics), so a checkpoint alone
is enough to resume training or to sample. Orbax writes each step into a temporary folder and renames
it when complete, so a run killed mid-save leaves the previous checkpoint as the latest usable one.

Training saves and restores the whole state (`Checkpointer`); sampling and evaluation call
`load_checkpoint`, which restores only the parameters they use (the EMA by default) against an
abstract model from `nnx.eval_shape`: no optimiser is built and no trainer code is imported.

An exported model (`export_model`) is a folder of the parameters sampling uses (`params.npz`) and the
record without the training position (`record.json`, `config.json`): what the package ships as its
pretrained default (`PRETRAINED`, `pretrained_dir`). `load_checkpoint` reads either kind of folder.
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Any, Callable

import jax
import ml_collections
import numpy as np
import orbax.checkpoint as ocp
from absl import logging as absl_logging
from flax import nnx

from tdiff_jax import diffusion, files, models
from tdiff_jax.data.normalize import NormStats
from tdiff_jax.lane_pull import LanePull


class _QuietOrbax(logging.Filter):
  """Orbax logs every save step by step at INFO; keep its warnings only."""

  def filter(self, record):
    return record.levelno >= logging.WARNING or "orbax" not in record.pathname


def quiet_orbax_logging() -> None:
  """For command-line entry points: hide orbax's INFO chatter from the absl log."""
  absl_logging.get_absl_handler().addFilter(_QuietOrbax())


class Checkpointer:

  def __init__(self, directory: Path | str, keep: int = 3, create: bool = True):
    self.directory = Path(directory).absolute()
    self.skipped: list[int] = []  # damaged steps the last `restore()` passed over
    self.manager = ocp.CheckpointManager(
        self.directory,
        options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=create, enable_async_checkpointing=False))

  def latest_step(self) -> int | None:
    return self.manager.latest_step()

  def save(self, step: int, state: Any, record: dict) -> None:
    try:
      self.manager.save(step, args=ocp.args.Composite(state=ocp.args.StandardSave(state),
                                                      record=ocp.args.JsonSave(record)), force=True)
      self.manager.wait_until_finished()
    except OSError as e:  # orbax's own message may not say where (a full disk, a read-only folder)
      raise files.named_os_error(e, self.directory / str(step)) from e

  def restore(self, template: Any, step: int | None = None) -> tuple[Any, dict]:
    """The state (with the template's structure, dtypes and shardings) and the JSON record.

    Without `step`, the newest step that restores: a damaged newer step (a file lost or cut) is
    skipped with a warning naming it and the error, and `skipped` lists such steps afterwards.
    """
    return self._newest(lambda s: self._restore(template, s), step)

  def restore_subtree(self, name: str, abstract: Any, step: int | None = None) -> tuple[Any, dict]:
    """Only the state's field `name` (e.g. "ema"), restored into `abstract` (shapes and dtypes, e.g.
    from `nnx.eval_shape`) on the default device, and the record; damaged steps skipped as `restore`.
    Use a Checkpointer for either this or `restore`, not both (orbax keeps one handler per item)."""
    device = jax.sharding.SingleDeviceSharding(jax.devices()[0])
    restore_args = jax.tree_util.tree_map(lambda _: ocp.ArrayRestoreArgs(restore_type=jax.Array, sharding=device),
                                          abstract)

    def one(s: int):
      out = self.manager.restore(s, args=ocp.args.Composite(
          state=ocp.args.PyTreeRestore({name: abstract}, restore_args={name: restore_args}, partial_restore=True),
          record=ocp.args.JsonRestore()))
      return out["state"][name], out["record"]
    return self._newest(one, step)

  def _newest(self, restore_step: Callable[[int], Any], step: int | None) -> Any:
    if step is not None:
      try:
        return restore_step(step)
      except Exception as e:  # orbax and tensorstore raise many kinds for a damaged step
        raise ValueError(f"{self.directory}: checkpoint step {step} does not restore: {_first_line(e)}") from e
    steps = sorted(self.manager.all_steps(), reverse=True)
    if not steps:
      raise FileNotFoundError(f"{self.directory}: no checkpoint to restore")
    errors = []
    for s in steps:
      try:
        out = restore_step(s)
      except Exception as e:  # orbax and tensorstore raise many kinds for a damaged step
        reason = _first_line(e)
        absl_logging.warning("%s: checkpoint step %d does not restore, skipped: %s", self.directory, s, reason)
        errors.append((s, reason))
        continue
      self.skipped = [s for s, _ in errors]
      return out
    raise ValueError(f"{self.directory}: no checkpoint step restores ("
                     + "; ".join(f"step {s}: {r}" for s, r in errors) + ")")

  def set_aside_skipped(self) -> None:
    """Renames the damaged steps the last `restore()` skipped to `<step>.damaged`, kept for inspection,
    so that training can save those step numbers again."""
    for s in self.skipped:
      src = self.directory / str(s)
      if src.exists():
        src.rename(self.directory / f"{s}.damaged")
        absl_logging.warning("%s: damaged step %d set aside as %s", self.directory, s, f"{s}.damaged")
    self.skipped = []
    self.manager.reload()

  def _restore(self, template: Any, step: int) -> tuple[Any, dict]:
    out = self.manager.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(template),
                                                             record=ocp.args.JsonRestore()))
    return out["state"], out["record"]

  def restore_record(self, step: int | None = None) -> dict:
    """The JSON record of `step`, or without it of the newest step whose record restores (damaged newer
    steps skipped with a warning, as `restore`)."""
    return self._newest(lambda s: self.manager.restore(s, args=ocp.args.Composite(
        record=ocp.args.JsonRestore()))["record"], step)

  def close(self) -> None:
    self.manager.close()


def _first_line(e: Exception) -> str:
  return f"{type(e).__name__}: " + (str(e).strip().splitlines() or [""])[0][:300]


@dataclasses.dataclass
class LoadedModel:
  """A trained model ready to use: `nnx.merge(graphdef, params)`, its statistics and config."""

  graphdef: nnx.GraphDef
  params: dict
  norm: NormStats
  sched: diffusion.Schedule | None  # None for the infiller
  config: ml_collections.ConfigDict
  record: dict
  lane_pull: LanePull | None = None  # HL: the denoiser's lane pull the checkpoint was trained with (`sampling.sample`)

  @property
  def task(self) -> str:
    return self.config.get("task", "hl")

  @property
  def stochastic(self) -> bool:
    """A generative infiller (`flow_noise_m > 0`): its trajectories are draws, keyed."""
    return self.task == "infill" and self.config.model.get("flow_noise_m", 0.0) > 0


# The models of the default recipe, shipped with the package (how they were made: pretrained.json there).
PRETRAINED = Path(__file__).parent / "pretrained"
EXPORTED_PARAMS, EXPORTED_RECORD = "params.npz", "record.json"


def pretrained_dir(task: str) -> Path:
  """The shipped pretrained model of `task` ("hl" or "infill"), a folder `load_checkpoint` reads."""
  if task not in models.TASKS:
    raise ValueError(f"task={task!r}: choose one of {models.TASKS}")
  return PRETRAINED / task


def _has_training_steps(folder: Path) -> bool:
  """Whether `folder/checkpoints` holds a saved step (a folder named by its number), without orbax."""
  ckpt_dir = folder / "checkpoints"
  return ckpt_dir.is_dir() and any(d.name.isdigit() and d.is_dir() for d in ckpt_dir.iterdir())


def is_exported(folder: Path | str) -> bool:
  """Whether `folder` is read as an exported model (`export_model`): it holds `params.npz` and no training
  checkpoint. The rule: a folder with training checkpoints is read from its newest checkpoint, whatever
  else it holds (`load_checkpoint` logs a warning when it also holds an exported model)."""
  folder = Path(folder)
  return (folder / EXPORTED_PARAMS).is_file() and not _has_training_steps(folder)


def export_model(workdir: Path | str, out: Path | str, step: int | None = None, overwrite: bool = False) -> Path:
  """Writes the EMA parameters and record of `workdir`'s newest (or `step`'s) checkpoint to the folder
  `out` (params.npz, record.json, config.json), which `load_checkpoint` then reads like a workdir. `out`
  must be new or empty, or with `overwrite` an earlier export (`files.output_folder`: replaced whole)."""
  loaded = load_checkpoint(workdir, step=step)
  record = {k: v for k, v in loaded.record.items() if k not in ("data_position", "train_state_format")}
  return write_exported(out, loaded.params, record, overwrite, inputs=(workdir,))


def write_exported(out: Path | str, params, record: dict, overwrite: bool = False, inputs=()) -> Path:
  """An exported model's folder from its parameter pytree and record (whose "config" builds the model),
  written whole (`files.output_folder`)."""
  flat = {jax.tree_util.keystr(path): np.asarray(leaf)
          for path, leaf in jax.tree_util.tree_flatten_with_path(jax.device_get(params))[0]}
  with files.output_folder(out, overwrite, "export_model", inputs) as staging:
    files.atomic_write(staging / EXPORTED_PARAMS, lambda f: np.savez_compressed(f, **flat))
    files.atomic_write_text(staging / EXPORTED_RECORD, files.json_text(record, indent=1))
    files.atomic_write_text(staging / "config.json", files.json_text(record["config"], indent=1))
  return Path(out)


def _load_exported(folder: Path, task: str | None) -> tuple[ml_collections.ConfigDict, Any, Any, dict]:
  """(config, graphdef, params, record) of an exported model; ValueError naming the file when damaged."""
  record_file = folder / EXPORTED_RECORD
  try:
    record = json.loads(record_file.read_text())
    missing = [k for k in RECORD_FIELDS if k not in record] if isinstance(record, dict) else list(RECORD_FIELDS)
    if missing:
      raise ValueError(f"fields {missing} missing")
    config = ml_collections.ConfigDict(record["config"])
  except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
    raise ValueError(f"{record_file}: not an exported model's record ({e})") from None
  found = config.get("task", "hl")
  if task is not None and found != task:
    raise ValueError(f"{folder}: holds the {found!r} model, the {task!r} model is needed here")
  try:
    graphdef, abstract = models.split_model(models.abstract_model(config))
  except (KeyError, AttributeError, IndexError, TypeError, ValueError) as e:
    raise ValueError(f"{record_file}: its config does not build a model ({_first_line(e)})") from None
  params_file = folder / EXPORTED_PARAMS
  try:
    with np.load(params_file, allow_pickle=False) as z:
      stored = {name: z[name] for name in z.files}
  except Exception as e:  # numpy and zipfile raise many kinds for a damaged file
    raise ValueError(f"{params_file}: does not load: {_first_line(e)}") from None

  def leaf(path, spec):
    value = stored.get(jax.tree_util.keystr(path))
    if value is None or value.shape != spec.shape or value.dtype != spec.dtype:
      got = "missing" if value is None else f"{value.dtype}{list(value.shape)}"
      raise ValueError(f"{params_file}: parameter {jax.tree_util.keystr(path)} is {got}, the model needs "
                       f"{spec.dtype}{list(spec.shape)}")
    return jax.numpy.asarray(value)
  return config, graphdef, jax.tree_util.tree_map_with_path(leaf, abstract), record


def has_checkpoint(workdir: Path | str) -> bool:
  """Whether `workdir` holds a checkpoint (or is an exported model)."""
  if is_exported(workdir):
    return True
  ckpt_dir = Path(workdir) / "checkpoints"
  if not ckpt_dir.is_dir():
    return False
  ckpt = Checkpointer(ckpt_dir, create=False)
  try:
    return ckpt.latest_step() is not None
  finally:
    ckpt.close()


def with_lane_pull(loaded: LoadedModel, across_m: float | None) -> LoadedModel:
  """`loaded` (an HL checkpoint) sampled with another lane pull (`LoadedModel.lane_pull`): None keeps the
  checkpoint's; 0 turns it off; d > 0 pulls from at most d metres across, the checkpoint's other settings
  kept. Raises ValueError for a negative distance or a model the pull cannot apply to."""
  if across_m is None:
    return loaded
  if loaded.task != "hl":
    raise ValueError(f"the lane pull applies to the HL model, not the {loaded.task!r} model")
  if across_m == 0:
    return dataclasses.replace(loaded, lane_pull=None)
  pull = dataclasses.replace(loaded.lane_pull or LanePull(), across_m=float(across_m))
  pull.check(models.model_spec(loaded.config))
  return dataclasses.replace(loaded, lane_pull=pull)


def load_checkpoint(workdir: Path | str, use_ema: bool = True, task: str | None = None,
                    step: int | None = None) -> LoadedModel:
  """The newest restorable checkpoint of a training workdir, for inference (HL model or infiller;
  `task` checks which): the EMA parameters (or, `use_ema=False`, the raw ones) and nothing else.
  `step`: that checkpoint step instead of the newest. `workdir` may also be an exported model
  (`export_model`, e.g. `pretrained_dir("hl")`), which holds the EMA parameters only.

  Raises FileNotFoundError with how to train one, ValueError if it holds the other task's model.
  """
  if is_exported(workdir):
    if step is not None or not use_ema:
      raise ValueError(f"{workdir}: an exported model holds one set of parameters (the EMA of its step)")
    config, graphdef, params, record = _load_exported(Path(workdir), task)
    absl_logging.info("%s: the exported model (step %s)", workdir, record.get("step"))
    return _loaded(graphdef, params, config, record, Path(workdir) / EXPORTED_PARAMS)
  if (Path(workdir) / EXPORTED_PARAMS).is_file():
    absl_logging.warning("%s holds training checkpoints and an exported model (%s): the newest checkpoint is "
                         "used, the exported model ignored", workdir, EXPORTED_PARAMS)
  ckpt_dir = Path(workdir) / "checkpoints"
  ckpt = Checkpointer(ckpt_dir, create=False) if ckpt_dir.is_dir() else None
  if ckpt is None or ckpt.latest_step() is None:
    if ckpt is not None:
      ckpt.close()
    config_file = f"configs/{task or 'hl'}.py"
    raise FileNotFoundError(
        f"no checkpoint in {ckpt_dir}; train one first: python train.py --config={config_file} --workdir={workdir}")
  if step is not None and step not in ckpt.manager.all_steps():
    steps = sorted(ckpt.manager.all_steps())
    ckpt.close()
    raise FileNotFoundError(f"{ckpt_dir}: no checkpoint step {step} (steps kept: {', '.join(map(str, steps))})")
  try:
    config = ml_collections.ConfigDict(ckpt.restore_record(step)["config"])
    found = config.get("task", "hl")
    if task is not None and found != task:
      raise ValueError(f"{ckpt_dir}: holds the {found!r} model, the {task!r} model is needed here")
    try:
      graphdef, abstract = models.split_model(models.abstract_model(config))
    except ValueError as e:   # e.g. a model option since removed, on
      raise ValueError(f"{ckpt_dir}: the checkpoint's {e}") from None
    params, record = ckpt.restore_subtree("ema" if use_ema else "params", abstract, step)
    config = ml_collections.ConfigDict(record["config"])  # of the step restored (a newer one may be damaged)
  finally:
    ckpt.close()
  absl_logging.info("%s: training checkpoint step %s", ckpt_dir, record.get("step"))
  return _loaded(graphdef, params, config, record, ckpt_dir / str(record.get("step")))


def load_record(workdir: Path | str) -> dict:
  """The JSON record (step, config, statistics) of the model `load_checkpoint(workdir)` loads, without its
  parameters."""
  if is_exported(workdir):
    path = Path(workdir) / EXPORTED_RECORD
    try:
      return json.loads(path.read_text())
    except (OSError, ValueError) as e:
      raise ValueError(f"{path}: not an exported model's record ({e})") from None
  ckpt_dir = Path(workdir) / "checkpoints"
  if not _has_training_steps(Path(workdir)):
    raise FileNotFoundError(f"no checkpoint in {ckpt_dir}")
  ckpt = Checkpointer(ckpt_dir, create=False)
  try:
    return ckpt.restore_record()
  finally:
    ckpt.close()


# What a model's record must hold to sample (`load_checkpoint`).
RECORD_FIELDS = ("step", "config", "normalization")


def _loaded(graphdef: nnx.GraphDef, params: Any, config: ml_collections.ConfigDict, record: dict,
            where: Path) -> LoadedModel:
  """The loaded model; ValueError naming `where` (the parameters' file or checkpoint step) and the field when
  its record lacks a field or a parameter or statistic is not finite (a model that would sample NaN)."""
  hl = config.get("task", "hl") == "hl"
  try:
    norm = NormStats.from_json(record["normalization"])
    sched = diffusion.schedule_from_config(config.diffusion) if hl else None
    pull = LanePull.from_config(config) if hl else None
  except (KeyError, AttributeError, IndexError, TypeError) as e:
    raise ValueError(f"{where}: the model's record lacks or garbles a field ({type(e).__name__}: {e})") from None
  for name, value in norm.to_json().items():
    values = np.asarray(jax.tree_util.tree_leaves(value), np.float64)
    if not np.isfinite(values).all() or (name == "std" and not (values > 0).all()):
      raise ValueError(f"{where}: normalisation statistic {name} is {value}: not finite (and, for std, positive)")
  for path, leaf in jax.tree_util.tree_flatten_with_path(params)[0]:
    if not np.isfinite(np.asarray(leaf)).all():
      raise ValueError(f"{where}: parameter {jax.tree_util.keystr(path)} holds NaN or inf")
  return LoadedModel(graphdef, params, norm, sched, config, record, pull)


def validation_maps(workdir: Path, model: Path | None = None) -> Path:
  """The validation split of the data the model in `model` (default: `workdir`) was trained on.

  `<workdir>/synthetic/val` when it exists or the model was trained on synthetic worlds (no data.dir or
  data.cache_dir; then its recipe's validation worlds are generated there first, seeded as training
  generated them), else the `val` folder of the AV2 root its config.json names (`data.dir`), else of the
  folder its cache was built from (`data.cache_dir`, the `source` of the cache's manifest). Raises
  ValueError when none exists.
  """
  from tdiff_jax.data import batches, synthetic
  own = workdir / "synthetic" / "val"
  if own.is_dir():
    return own
  tried = [str(own)]
  config_file = Path(model or workdir) / "config.json"
  data = json.loads(config_file.read_text()).get("data", {}) if config_file.is_file() else {}
  if data and not data.get("dir") and not data.get("cache_dir") and data.get("synthetic_num"):
    logging.info("generating the validation worlds of %s's synthetic data into %s", model or workdir, own.parent)
    synthetic.generate_dataset(own.parent, data["synthetic_num"], seed=0, splits=("val",))
    return own
  roots = []
  if data.get("dir"):
    roots.append(files.user_path(data["dir"]))
  elif data.get("cache_dir"):
    cache = files.user_path(data["cache_dir"])
    try:
      source = batches.read_manifest(cache).get("source")
    except FileNotFoundError:
      source = None
    if source:
      roots.append(Path(source))
    else:
      tried.append(f"the source of the cache {cache}")
  for root in roots:
    if (root / "val").is_dir():
      return root / "val"
    tried.append(str(root / "val"))
  raise ValueError(f"no validation split of {model or workdir}'s training data found (tried {', '.join(tried)}); "
                   "pass the maps to use (--data, --maps)")
