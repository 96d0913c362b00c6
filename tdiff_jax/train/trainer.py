"""The training loop: `train_and_evaluate(config, workdir)` for both models.

`config.task` picks the model and its loss: "hl" (the high-level diffusion model, `configs/hl.py`) or
"infill" (the trajectory infiller, `configs/infill.py`). Everything else (data, optimiser, EMA,
checkpoints, resume, logging, NaN guard, data parallelism) is shared.

Functional core: the model is split once (`nnx.split`) into a static graph and a pure-dict parameter
pytree; the train step is a pure function of (state, batch, constants) under `jax.jit` with the state
donated. Data parallel over all devices of all processes: a 1-D mesh over the batch axis, batches
sharded, the state replicated, so the same command scales from a CPU to a multi-GPU machine and, with
`train/distributed.py`, to several hosts (each process reads its share of every global batch; process
0 prepares the data, logs and writes metrics).

The training data streams from the preprocessing cache through a Grain pipeline
(`batches.BatchIterator`), so memory does not grow with the dataset.

Each run writes to its workdir: `config.json`, `metrics.jsonl` (one JSON line per log interval and per
validation), and `checkpoints/` (orbax; params, optimiser state, EMA, step, data position, config and
normalisation statistics). Rerunning the same command resumes from the latest checkpoint with the same
data order. A step whose loss or gradient is not finite changes nothing; training then stops with an
error naming the step, and the last checkpoint (all saved before that step) stays the latest.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import optax
from absl import logging
from flax import nnx, struct
from jax.sharding import NamedSharding, PartitionSpec

from tdiff_jax import checkpoint, cli, cpu_products, datatypes, diffusion, files, hl_objective, infilling, models
from tdiff_jax.lane_pull import LanePull
from tdiff_jax.data import batches, config as data_config, normalize, stats as data_stats
from tdiff_jax.models import map_encoder, model_config
from tdiff_jax.models.paper_denoiser import PaperConfig
from tdiff_jax.train import data_setup, distributed, map_input_cache, optim


@struct.dataclass
class TrainState:
  """What a checkpoint holds. `key` is the raw data of a `jax.random.key` (uint32 `[2]`), which
  orbax stores as a plain array; `opt_state` is `optim.make_optimizer`'s (an `optax.ApplyIfFiniteState`).
  The training loop holds it flat (`optim.flatten_state`: params, EMA and Adam's moments as vectors)."""

  step: jax.Array
  params: Any
  opt_state: Any
  ema: Any
  key: jax.Array


# Checkpoints before format 2 hold the optimiser state without the `apply_if_finite` wrapper.
TRAIN_STATE_FORMAT = 2


@struct.dataclass
class Constants:
  """Traced, non-trainable inputs of the step: normalisation statistics and the noise schedule
  (None for the infiller)."""

  norm: normalize.NormStats
  sched: diffusion.Schedule


def task_loss(config: ml_collections.ConfigDict, train: bool) -> Callable:
  """`(model, batch, consts, key, packed=None, map_inputs=None) -> (loss, metrics)` of the config's task
  (`packed`: the batch's packed polygons or None, see `packed_polygons`; `map_inputs`: the HL map encoder's
  input side of the batch computed apart, `map_input_cache.MapInputCache`, or None)."""
  tc = config.train
  if config.task == "infill":
    weight = float(tc.smoothness_weight)
    return lambda model, batch, consts, key, packed=None, map_inputs=None: infilling.infill_loss(
        model, batch, key, weight, train=train, packed=packed)
  entropy_weight = float(tc.entropy_weight)
  self_only_prob = float(tc.self_only_prob) if train else 0.0
  spec = models.model_spec(config)   # the denoiser's loss weighting and noise-level draws
  noise_draws = int(tc.get("noise_draws", 1)) if train else 1  # validation: one draw, comparable across runs
  lane_pull = LanePull.from_config(config)
  return lambda model, batch, consts, key, packed=None, map_inputs=None: hl_objective.hl_loss(
      model, batch, consts.norm, consts.sched, key, entropy_weight, self_only_prob, train=train,
      loss_weighting=spec.loss_weighting, t_sampling=spec.t_sampling, noise_draws=noise_draws, packed=packed,
      map_inputs=map_inputs, lane_pull=lane_pull)


def packed_polygons(config: ml_collections.ConfigDict, batch: datatypes.Scene,
                    sharding: NamedSharding | None = None) -> map_encoder.PackedPolygons | None:
  """The packed polygons of a host batch for the step (`map_encoder.pack_polygons`), when the config's
  map encoder attends over all pairs (`model.pl2pl_neighbors = 0`): the encoder then computes the
  batch's valid points, polygons and polygon pairs, not its padded `[B, P, K]` and `[B, P, P]` grids
  (the same losses). On several devices of one process each device's slice of the batch is packed apart
  (`shards`), and placed on its device by `sharding` (the batch's); across processes the slices' list
  lengths would differ from host to host, so the dense grids are kept there (None)."""
  if jax.process_count() > 1:
    return None
  # The HL config leaves the radius at the model's default (the paper's 150 m); the infiller's sets it.
  radius = float(config.model.get("pl2pl_radius_m", PaperConfig.pl2pl_radius_m))
  packed = map_encoder.packing_for(batch, radius, int(config.model.pl2pl_neighbors),
                                   shards=jax.device_count())
  if packed is None or sharding is None or packed.shards == 1:
    return packed
  return jax.device_put(packed, sharding)


# The host memory the frozen map input side of the training scenes may take (else each step computes it).
MAP_INPUT_CACHE_MB = 1024.0


def map_inputs_cache(config: ml_collections.ConfigDict, graphdef: nnx.GraphDef, params, norm: normalize.NormStats,
                     source) -> map_input_cache.MapInputCache | None:
  """The frozen map encoder input side of every scene of the training split `source`, computed once from
  `params` (`map_input_cache`), when the HL model's input side is frozen (`train.freeze_map_inputs`) and a
  constant of each polygon (`MapEncoder.input_side_is_constant`), and
  its rows fit `MAP_INPUT_CACHE_MB`; otherwise None (the step computes it). Says which, and why.
  With the polygon -> polygon relation embedding frozen with it (exact embeddings, the k nearest polygons),
  the cache holds each polygon's pairs as well (`MapEncoder.pl2pl_relations`)."""
  tc = config.train
  if config.task != "hl" or "map_encoder/pt2pl" not in optim.frozen_modules(tc):
    return None
  encoder = nnx.merge(graphdef, params).map_encoder
  if not encoder.input_side_is_constant:
    logging.info("The map encoder's input side is frozen but not a constant of each polygon (more than one map "
                 "layer, dropout or Fourier tables): each step computes it")
    return None
  limit_mb = MAP_INPUT_CACHE_MB
  num_polygons = int(np.asarray(source.num_polygons).sum())
  # The frozen relations of an encoder that keeps each polygon's k nearest: cached with the input side.
  k = int(config.model.pl2pl_neighbors)
  relations = encoder.r_pl2pl.table_size == 0 and 0 < k < int(config.data.scene.max_polygons)
  size_mb = map_input_cache.cache_bytes(num_polygons, int(config.model.dim), k if relations else 0) / 2**20
  if size_mb > limit_mb:
    logging.info("The frozen map encoder input side of the %d training polygons would take %.0f MB > "
                 "%s MB: each step computes it", num_polygons, size_mb, limit_mb)
    return None
  start = time.perf_counter()
  mean, std = norm.mean[:2], norm.std[:2]
  # Parameters as an argument: closed over, XLA would fold them into the program as constants.
  input_side = jax.jit(lambda p, rows: nnx.merge(graphdef, p).map_encoder.input_side(rows, mean, std))
  pl2pl = jax.jit(lambda p, graph: nnx.merge(graphdef, p).map_encoder.pl2pl_relations(graph))
  cache = map_input_cache.MapInputCache.build(
      lambda rows: input_side(params, rows), source,
      pl2pl_relations=(lambda graph: pl2pl(params, graph)) if relations else None, min_polygons=k + 1)
  logging.info("The frozen map encoder input side%s computed once for the %d polygons of %d training scenes "
               "(%.1f MB, %.1f s)", " and polygon -> polygon relations" if relations else "", num_polygons,
               len(source), cache.nbytes / 2**20, time.perf_counter() - start)
  return cache


def init_state(config: ml_collections.ConfigDict, params: dict, tx: optax.GradientTransformation) -> TrainState:
  return TrainState(step=jnp.zeros((), jnp.int32), params=params, opt_state=tx.init(params),
                    ema=jax.tree_util.tree_map(jnp.copy, params),
                    key=jax.random.key_data(jax.random.key(config.seed)))


def init_flat_state(config: ml_collections.ConfigDict, params: dict
                    ) -> tuple[optim.FlatParams, optax.GradientTransformation, TrainState]:
  """What training runs: the parameters' flat layout, its optimiser and the flat initial state, for
  `jit_train_step(..., flat=flat)` (benchmarks and tests use it to time and check the real step)."""
  flat = optim.FlatParams.of(params, optim.frozen_modules(config.train))
  state = optim.flatten_state(init_state(config, params, optim.make_optimizer(config.train)), flat)
  return flat, optim.make_optimizer(config.train, flat=flat), state


def _as_tree(flat: optim.FlatParams | None) -> Callable:
  """The model's parameter pytree from what the step holds (the vector of `flat`, or the pytree itself)."""
  return flat.unravel if flat is not None else (lambda params: params)


def make_train_step(graphdef: nnx.GraphDef, tx: optax.GradientTransformation,
                    config: ml_collections.ConfigDict, flat: optim.FlatParams | None = None) -> Callable:
  """The pure train step `(state, batch, consts, packed=None, map_inputs=None) -> (state, metrics)`; jit it
  (donating the state). `packed`: `packed_polygons(config, batch)`; `map_inputs`: the batch's rows of a
  `map_input_cache.MapInputCache` (the frozen input side of the map encoder, computed once per scene).

  With `flat`, the state is flat (`optim.flatten_state`) and `tx` is `optim.make_optimizer(c, flat=flat)`:
  the same step, with one array per update instead of one per parameter (what training runs).

  With `train.freeze_map_inputs`, the map encoder's input side
  (`optim.MAP_INPUT_MODULES`, and its relations) keeps its initial weights: its gradient is stopped, so the
  step skips its backward pass, and its parameters are not updated."""
  as_tree = _as_tree(flat)
  tc = config.train
  frozen = optim.frozen_modules(tc)
  ema_decay = float(tc.ema_decay)
  schedule = optim.learning_rate_schedule(tc)
  task_loss_fn = task_loss(config, train=True)

  def train_step(state: TrainState, batch: datatypes.Scene, consts: Constants,
                 packed: map_encoder.PackedPolygons | None = None, map_inputs: map_encoder.MapInputs | None = None):
    key, step_key = jax.random.split(jax.random.wrap_key_data(state.key))

    def loss_fn(params):
      return task_loss_fn(nnx.merge(graphdef, optim.frozen_params(as_tree(params), frozen)), batch, consts,
                          step_key, packed, map_inputs)

    (loss, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(state.params)
    grad_norm = optax.tree.norm(grads)
    # A non-finite loss rejects the step as a non-finite gradient does (`optax.apply_if_finite`).
    checked = jax.tree_util.tree_map(lambda g: jnp.where(jnp.isfinite(loss), g, jnp.nan), grads)
    updates, opt_state = tx.update(checked, state.opt_state, state.params)
    params = optax.apply_updates(state.params, updates)   # zero updates when rejected
    params = optim.keep_frozen(params, state.params, frozen, flat)
    ok = opt_state.last_finite
    ema = optim.keep_frozen(optax.incremental_update(params, state.ema, 1.0 - ema_decay), state.ema, frozen, flat)
    ema = jax.tree_util.tree_map(lambda new, old: jnp.where(ok, new, old), ema, state.ema)
    new = TrainState(state.step + 1, params, opt_state, ema, jax.random.key_data(key))
    metrics = dict(metrics, grad_norm=grad_norm, lr=schedule(state.step), nonfinite=(~ok).astype(jnp.int32))
    return new, metrics

  return train_step


def jit_train_step(graphdef: nnx.GraphDef, tx: optax.GradientTransformation, config: ml_collections.ConfigDict,
                   replicated: NamedSharding | None = None, flat: optim.FlatParams | None = None) -> Callable:
  """The compiled step `train_and_evaluate` runs: `make_train_step` under `jax.jit`, the state donated
  and, given the mesh's `replicated` sharding, the outputs replicated, its matrix products on the CPU
  kernels of `training_compiler_options`. One compile per size bucket."""
  out_shardings = (replicated, replicated) if replicated is not None else None
  return jax.jit(make_train_step(graphdef, tx, config, flat), donate_argnums=0, out_shardings=out_shardings,
                 compiler_options=training_compiler_options(config))


# The jitted train and validation steps of recent runs in this process, by what they are built from (the
# model, diffusion and training config, the mesh and the flat layout; not the data's folders): another run
# of one config in a process (a test, a notebook) reuses their compiled programs instead of compiling again.
_RECENT_STEPS: "collections.OrderedDict[str, tuple[Callable, Callable]]" = collections.OrderedDict()


def compiled_steps(graphdef: nnx.GraphDef, config: ml_collections.ConfigDict, replicated: NamedSharding,
                   flat: optim.FlatParams) -> tuple[Callable, Callable]:
  """`(jit_train_step(...), the jitted make_eval_step(...))` for a run, those of an earlier run in this
  process when they are built from the same things."""
  key = json.dumps({"task": config.task, "model": config.model.to_dict(), "train": config.train.to_dict(),
                    "diffusion": config.diffusion.to_dict() if "diffusion" in config else None,
                    "lane_pull": config.lane_pull.to_dict() if "lane_pull" in config else None,
                    "max_polygons": int(config.data.scene.max_polygons),
                    "mesh": [repr(replicated.mesh), repr(replicated.spec)],
                    "flat": [flat.leaf_ends.tolist(), flat.leaf_frozen.tolist(), flat.leaf_decayed.tolist()]},
                   sort_keys=True, default=str)
  if key not in _RECENT_STEPS:
    train_step = jit_train_step(graphdef, optim.make_optimizer(config.train, flat=flat), config, replicated, flat)
    eval_step = jax.jit(make_eval_step(graphdef, config, flat), out_shardings=replicated,
                        compiler_options=training_compiler_options(config))
    _RECENT_STEPS[key] = (train_step, eval_step)
    while len(_RECENT_STEPS) > 4:
      _RECENT_STEPS.popitem(last=False)
  _RECENT_STEPS.move_to_end(key)
  return _RECENT_STEPS[key]


def training_compiler_options(config: ml_collections.ConfigDict) -> dict[str, str] | None:
  """XLA compiler options of the train and validation steps: the HL model's matrix products on XLA's own
  CPU kernels (`tdiff_jax.cpu_products`, docs/benchmarks.md), the infiller's on XLA's default (YNNPACK's).
  Only XLA's CPU compiler reads them."""
  return cpu_products.COMPILER_OPTIONS if config.task == "hl" else None


def _restore_train_state(ckpt: checkpoint.Checkpointer, template: TrainState, record: dict) -> tuple[TrainState, dict]:
  """The newest restorable state; a checkpoint of format 1 (optimiser state without the
  `apply_if_finite` wrapper) is restored as such and wrapped, so older runs resume."""
  if record.get("train_state_format", 1) >= TRAIN_STATE_FORMAT:
    return ckpt.restore(template)
  inner = template.opt_state.inner_state
  state, record = ckpt.restore(template.replace(opt_state=inner))
  wrapped = optax.ApplyIfFiniteState(notfinite_count=jnp.zeros((), jnp.int32), last_finite=jnp.array(True),
                                     total_notfinite=jnp.zeros((), jnp.int32), inner_state=state.opt_state)
  logging.info("%s: a format-1 checkpoint; its optimiser state is wrapped for skipping non-finite steps",
               ckpt.directory)
  wrapped = jax.device_put(wrapped, jax.tree_util.tree_leaves(template.opt_state)[0].sharding)
  return state.replace(opt_state=wrapped), record


def make_eval_step(graphdef: nnx.GraphDef, config: ml_collections.ConfigDict,
                   flat: optim.FlatParams | None = None) -> Callable:
  """`(params, batch, key, consts, packed=None) -> metrics` without dropout or interaction dropout; with
  `flat`, `params` is the parameter vector; `packed`: `packed_polygons(config, batch)`."""
  loss = task_loss(config, train=False)
  as_tree = _as_tree(flat)

  def eval_step(params, batch, key, consts: Constants, packed: map_encoder.PackedPolygons | None = None):
    _, metrics = loss(nnx.merge(graphdef, as_tree(params)), batch, consts, key, packed)
    return metrics
  return eval_step


def data_mesh() -> jax.sharding.Mesh:
  """A 1-D mesh over all devices; XLA propagates the batch sharding (auto axes)."""
  return jax.make_mesh((jax.device_count(),), ("data",), axis_types=(jax.sharding.AxisType.Auto,))


class MetricWriter:
  """Appends one JSON object per line to `<workdir>/metrics.jsonl` (`python -m tdiff_jax.plot_metrics
  WORKDIR` draws them).

  `resume_step`: the step training resumes from. Rows logged after it by an earlier run (steps that
  were logged but not checkpointed before a kill) are dropped, so a resumed run never repeats a step.
  """

  def __init__(self, path: Path, resume_step: int = 0):
    self.path = path
    if path.exists():
      rows = [line for line in path.read_text().splitlines() if line.strip()]
      keep = [line for line in rows if _logged_step(line) <= resume_step]
      if len(keep) < len(rows):
        logging.info("%s: dropping %d row(s) logged after step %d, which is resumed", path, len(rows) - len(keep),
                     resume_step)
        files.atomic_write_text(path, "".join(line + "\n" for line in keep))

  def write(self, record: dict) -> None:
    line = files.json_text(record) + "\n"   # strict JSON: a NaN loss is null, listed under non_finite_as_null
    try:
      with open(self.path, "a") as f:
        f.write(line)
    except OSError as e:
      raise files.named_os_error(e, self.path) from e


def _logged_step(line: str) -> int:
  try:
    return int(json.loads(line).get("step", 0))
  except (ValueError, AttributeError):  # a line cut by a kill mid-write
    return 1 << 62


# config.train fields that must lie in a range: (low, high, whether the low end is allowed).
_TRAIN_RANGES = {"lr": (0.0, None, False), "warmup_steps": (0, None, True), "min_lr_ratio": (0.0, 1.0, True),
                 "weight_decay": (0.0, None, True), "grad_clip": (0.0, None, False), "ema_decay": (0.0, 1.0, True),
                 "entropy_weight": (0.0, None, True), "self_only_prob": (0.0, 1.0, True)}


def changed_fields(saved: dict, config: ml_collections.ConfigDict, sections: Sequence[str] = ("train", "diffusion")
                   ) -> list[str]:
  """`section.field: saved -> now` for each field of `sections` whose value differs between a checkpoint's
  saved config (a dict) and `config`; a field the saved config lacks (added since) is not reported."""
  changes = []
  for section in sections:
    old, new = saved.get(section, {}), config.get(section, ml_collections.ConfigDict()).to_dict()
    for key in sorted(set(old) & set(new)):
      if json.dumps(old[key], sort_keys=True) != json.dumps(new[key], sort_keys=True, default=list):
        changes.append(f"{section}.{key}: {old[key]!r} -> {new[key]!r}")
  return changes


# Training options of earlier versions (measured and not adopted, docs/research_log.md; or since fixed by the
# denoiser, `loss_weighting` and `t_sampling`, or part of `freeze_map_inputs`): a checkpoint whose config names
# one resumes only with the version that wrote it (`model_config.older_options_error`).
OLDER_TRAIN_OPTIONS = ("max_t", "position_jitter_m", "freeze_map_encoder", "loss_weighting", "t_sampling",
                       "freeze_map_relations")

# The `data` fields that say which scenes a run trains on; a resumed run must keep them.
_DATA_SOURCE_FIELDS = ("dir", "cache_dir", "synthetic_num", "scene")


def resume_record(config: ml_collections.ConfigDict, workdir: Path | str) -> dict | None:
  """The record of the checkpoint a run of `config` in `workdir` resumes from (the newest that restores),
  or None for a fresh run. Raises ValueError when that checkpoint cannot be resumed with `config`: it
  holds the other task's model, another model, or was trained on other data. Writes nothing."""
  ckpt_dir = Path(workdir) / "checkpoints"
  if not ckpt_dir.is_dir():
    return None
  ckpt = checkpoint.Checkpointer(ckpt_dir, create=False)
  try:
    if ckpt.latest_step() is None:
      return None
    record = ckpt.restore_record()
  finally:
    ckpt.close()
  saved = record["config"]
  if saved.get("task", "hl") != config.task:
    raise ValueError(f"{ckpt_dir}: the checkpoint is a {saved.get('task', 'hl')!r} model, the config trains "
                     f"{config.task!r}; use another --workdir")
  # Compared as model dataclasses: a field added since the checkpoint was written takes its default.
  try:
    old_spec = models.model_spec(ml_collections.ConfigDict(saved))
  except ValueError as e:   # e.g. an option since removed, on
    raise ValueError(f"{ckpt_dir}: the checkpoint's {e}; use another --workdir") from None
  new_spec = models.model_spec(config)
  if old_spec != new_spec:
    old_fields, new_fields = dataclasses.asdict(old_spec), dataclasses.asdict(new_spec)
    changed = [f"{k}: {old_fields.get(k)!r} -> {new_fields.get(k)!r}" for k in sorted(old_fields.keys() | new_fields.keys())
               if old_fields.get(k) != new_fields.get(k)]
    if type(old_spec) is not type(new_spec):
      changed.insert(0, f"{type(old_spec).__name__} -> {type(new_spec).__name__}")
    raise ValueError(f"{ckpt_dir}: the checkpoint was trained with another model ({'; '.join(changed)}; its model "
                     f"config: {saved['model']}); use another --workdir")
  used = [f"train.{k}" for k in OLDER_TRAIN_OPTIONS if k in saved.get("train", {})]
  if used:
    raise model_config.older_options_error(used, f"{ckpt_dir}: the checkpoint's ")
  old, new = dict(saved.get("data", {})), config.data.to_dict()
  if isinstance(old.get("scene"), dict):  # compared as full data configs (the fixed fields filled in)
    old["scene"] = data_config.scene_config(old["scene"]).to_dict()
    new["scene"] = data_config.scene_config(new["scene"]).to_dict()
  changed = [f"data.{k}: {old[k]!r} -> {new[k]!r}" for k in _DATA_SOURCE_FIELDS
             if k in old and k in new and _canonical(k, old[k]) != _canonical(k, new[k])]
  if changed:
    raise ValueError(f"{ckpt_dir}: the checkpoint was trained on other data ({'; '.join(changed)}); resume with "
                     "the data it was trained on, or use another --workdir")
  return record


def _canonical(field: str, value) -> str:
  """A data field's value for comparison: paths resolved, the rest as sorted JSON."""
  if field in ("dir", "cache_dir"):
    return str(files.user_path(value).resolve()) if value else ""
  return json.dumps(value, sort_keys=True, default=list)


def check_config(config: ml_collections.ConfigDict) -> None:
  """Raises ValueError naming the field, its value and what is allowed; called before any data work."""
  if config.task not in models.TASKS:
    raise ValueError(f"config.task={config.task!r}: choose one of {models.TASKS}")
  cli.check_seed(int(config.seed), "config.seed")
  data_config.validate_data_config(config.data.scene)
  t = config.train
  for name in ("batch_size", "num_steps", "log_every", "eval_every", "noise_draws"):
    if name in t and int(t[name]) < 1:
      raise ValueError(f"config.train.{name} must be >= 1, got {t[name]}")
  for name, (low, high, closed) in _TRAIN_RANGES.items():
    if name in t:
      v = float(t[name])
      if v < low or (v == low and not closed) or (high is not None and v > high):
        allowed = f"{'>=' if closed else '>'} {low}" + (f" and <= {high}" if high is not None else "")
        raise ValueError(f"config.train.{name}={t[name]}: must be {allowed}")
  if int(config.model.dim) % int(config.model.heads):
    raise ValueError(f"config.model.dim={config.model.dim}: must be a multiple of config.model.heads={config.model.heads}")
  spec = models.model_spec(config)  # the model block (typos, bad values) before any data is generated or preprocessed
  if config.task == "hl":
    pull = LanePull.from_config(config)
    if pull is not None:
      pull.check(spec)
  if int(t.get("cpu_devices", 1)) < 0:
    raise ValueError(f"config.train.cpu_devices must be >= 0 (0: one per core), got {t.cpu_devices}")
  n = jax.device_count()
  if t.batch_size % n:
    raise ValueError(f"config.train.batch_size={t.batch_size} must be a multiple of the {n} devices")


MIN_BUCKET_STEPS = 50
EVAL_BATCHES = 50      # validation: at most this many batches of the validation split
KEEP_CHECKPOINTS = 3


def batch_iterator(source, batch_size: int, config: ml_collections.ConfigDict, train: bool,
                   buckets: tuple[Sequence[int], Sequence[int]] | None = None) -> batches.BatchIterator:
  """This process's share of the global batches of `source`: shuffled and grouped by size for
  training, in order for validation; cropped to the config's size buckets (or `buckets`, (agent
  buckets, polygon buckets)). In training, a bucket the run's `num_steps` batches meet fewer than
  `MIN_BUCKET_STEPS` times is padded to a larger, frequent one (`batches.merge_rare_buckets`): one
  compile fewer (a compile of the train step costs 50 to 100 CPU steps)."""
  c = config.data
  return batches.BatchIterator(
      source, batch_size, seed=config.seed, shuffle=train, drop_remainder=True,
      group_by_size=train, buckets=buckets or (c.agent_buckets, c.polygon_buckets),
      process_index=jax.process_index(), process_count=jax.process_count(),
      min_bucket_batches=MIN_BUCKET_STEPS if train else 0, planned_batches=int(config.train.num_steps))


def validate(eval_fn, params, consts, val_ds, batch_size: int, num_batches: int, config, batch_sharding) -> dict:
  """Validation losses: `eval_fn` averaged over the first `num_batches` batches of `val_ds`, each padded
  to the largest of their size buckets: one compile of `eval_fn` instead of one per bucket (padding is
  masked; the losses are the same up to float rounding)."""
  c = config.data
  n = min(num_batches, len(val_ds) // batch_size)
  if n == 0:
    return {}
  shapes = [batches.batch_bucket(val_ds, np.arange(i * batch_size, (i + 1) * batch_size),
                                 (c.agent_buckets, c.polygon_buckets)) for i in range(n)]
  largest = ((max(a for a, _ in shapes),), (max(p for _, p in shapes),))
  it = batch_iterator(val_ds, batch_size, config, train=False, buckets=largest)
  totals: dict[str, float] = {}
  for i in range(n):
    host = next(it)
    batch = distributed.local_to_global(host, batch_sharding)
    m = jax.device_get(eval_fn(params, batch, jax.random.key(1000 + i), consts,
                                 packed_polygons(config, host, batch_sharding)))
    for k, v in m.items():
      totals[k] = totals.get(k, 0.0) + float(v) / n
  return totals


def norm_stats(config: ml_collections.ConfigDict, manifest: dict) -> normalize.NormStats:
  """The model state's normalisation for `config` from a dataset manifest: the state's statistics and,
  as the HL denoiser's state asks, the goal offsets' and headings."""
  norm = normalize.NormStats.from_manifest(manifest)
  spec = models.model_spec(config) if config.task == "hl" else None
  if spec is not None and spec.goal_offset:
    norm = norm.with_offsets(manifest["goal_offset_normalization"])
  if spec is not None and spec.heading_state:
    norm = norm.with_heading()
  return norm


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: Path | str) -> dict:
  """Trains the config's model (`config.task`) in `workdir`; returns the last logged metrics. One run per
  workdir at a time: a second one is refused (ValueError) while the first holds the workdir's lock."""
  check_config(config)
  workdir = Path(workdir)
  if not distributed.is_primary():   # the primary process holds the lock for all of them
    return _train_and_evaluate(config, workdir)
  resume_record(config, workdir)   # a run refused here leaves the workdir untouched, the lock file too
  data_setup.check_source(config.data, workdir)
  with files.exclusive_lock(workdir, "training run"):
    return _train_and_evaluate(config, workdir)   # checked again, under the lock


def _train_and_evaluate(config: ml_collections.ConfigDict, workdir: Path) -> dict:
  from tqdm import tqdm

  # Every check that can refuse, before anything is written: a refused run leaves the workdir as it was.
  resume = resume_record(config, workdir)
  data_setup.check_source(config.data, workdir)
  primary = distributed.is_primary()
  if primary:
    logging.info("jax %s, process %d of %d, devices %s", jax.__version__, jax.process_index(), jax.process_count(),
                 jax.devices())
    data_setup.prepare_cache(config.data, workdir)  # the others wait: the workdir is shared
  distributed.barrier("data ready")

  cache = data_setup.cache_path(config.data, workdir)
  manifest = batches.read_manifest(cache)
  train_ds = batches.open_split(cache, "train", config.data.scene)   # checksums: a damaged shard is refused here
  has_val = manifest["splits"].get("val", {}).get("scenes", 0) > 0
  val_ds = batches.open_split(cache, "val", config.data.scene) if has_val else None
  if not has_val and primary:   # said, and kept in metrics.jsonl's first row
    logging.warning("%s holds no validation scenes (no usable val/ split in the data): training runs without "
                    "validation, and no val_loss is logged", cache)
  if primary:   # once the data is known to be usable
    workdir.mkdir(parents=True, exist_ok=True)
    files.atomic_write_text(workdir / "config.json", config.to_json(indent=1))
  norm = norm_stats(config, manifest)
  consts = Constants(norm, diffusion.schedule_from_config(config.diffusion) if config.task == "hl" else None)

  mesh = data_mesh()
  replicated = NamedSharding(mesh, PartitionSpec())
  batch_sharding = NamedSharding(mesh, PartitionSpec("data"))
  tc = config.train
  graphdef, params = models.split_model(models.create_model(config))
  logging.info("%s model: %d parameters", config.task, sum(x.size for x in jax.tree_util.tree_leaves(params)))
  tx = optim.make_optimizer(tc)
  state = init_state(config, params, tx)
  it = batch_iterator(train_ds, tc.batch_size, config, train=True)
  if it.merged:
    logging.info("Size buckets met in fewer than %d steps, padded to a frequent one: %s", MIN_BUCKET_STEPS,
                 ", ".join(f"{a}x{p} -> {b}x{q}" for (a, p), (b, q) in sorted(it.merged.items())))
  state = jax.device_put(jax.device_get(state), replicated)  # global arrays (also the restore template)

  ckpt = checkpoint.Checkpointer(workdir / "checkpoints", keep=KEEP_CHECKPOINTS)
  if resume is not None:
    # Training fields may change on purpose (more steps); said aloud, so a new default recipe (or a
    # mistyped flag) does not silently continue a run trained another way.
    if primary and (changes := changed_fields(resume["config"], config)):
      logging.warning("Resuming %s with training settings changed since its checkpoints were written (the "
                      "steps already taken keep the old ones): %s", workdir, "; ".join(changes))
    state, record = _restore_train_state(ckpt, state, resume)
    if primary:
      ckpt.set_aside_skipped()  # damaged newer steps: training redoes them
    distributed.barrier("checkpoints checked")
    ckpt.manager.reload()
    it.set_state(record["data_position"])
    logging.info("Resuming from step %d (%s)", int(state.step), ckpt.directory)

  consts = jax.device_put(consts, replicated)
  map_cache = map_inputs_cache(config, graphdef, state.params, norm, train_ds)
  # The loop holds the state flat (one vector per parameter-shaped pytree); checkpoints hold pytrees.
  flat = optim.FlatParams.of(params, optim.frozen_modules(tc))
  template = jax.eval_shape(lambda: state)
  to_tree = jax.jit(lambda s: optim.unflatten_state(s, template, flat), out_shardings=replicated)
  state = jax.jit(lambda s: optim.flatten_state(s, flat), out_shardings=replicated)(state)
  train_step, eval_step = compiled_steps(graphdef, config, replicated, flat)
  writer = MetricWriter(workdir / "metrics.jsonl", int(state.step)) if primary else None
  eval_batch = min(tc.batch_size, len(val_ds) // jax.device_count() * jax.device_count()) if val_ds else 0

  agent_stats = data_stats.training_agent_stats(train_ds)

  def record_for(step: int) -> dict:
    return {"step": step, "data_position": it.get_state(), "config": config.to_dict(),
            "normalization": norm.to_json(), "data_manifest_config_hash": manifest["config_hash"],
            "agent_stats": agent_stats, "train_state_format": TRAIN_STATE_FORMAT}

  start = int(state.step)
  if start >= tc.num_steps:
    logging.info("Already trained to step %d (train.num_steps=%d); raise num_steps to continue", start, tc.num_steps)
    ckpt.close()
    return {"step": start, "already_done": True}
  last: dict = {}
  pending: list = []
  saved_step = ckpt.latest_step()
  bar = tqdm(total=tc.num_steps, initial=start, desc=f"train {config.task}", unit="step",
             disable=None if primary else True, dynamic_ncols=True)
  t0, steps0 = time.perf_counter(), start

  def flush(step: int) -> None:
    nonlocal pending, t0, steps0, last
    if not pending:
      return
    host = jax.device_get(pending)
    pending = []
    elapsed = time.perf_counter() - t0
    mean = {k: float(np.mean([h[k] for h in host])) for k in host[0]}
    bad = int(sum(h["nonfinite"] for h in host))
    rate = (step - steps0) / max(elapsed, 1e-9)
    last = {"step": step, **{k: v for k, v in mean.items() if k != "nonfinite"},
            "steps_per_s": rate, "scenes_per_s": rate * tc.batch_size}
    if writer:
      writer.write(last)
    bar.set_postfix(loss=f"{mean['loss']:.4f}", steps_s=f"{rate:.2f}")
    if bar.disable and primary:  # no terminal (a log file, a batch job): a plain line instead of the bar
      logging.info("step %d/%d: loss %.4f, %.2f steps/s", step, tc.num_steps, mean["loss"], rate)
    t0, steps0 = time.perf_counter(), step
    if bad:
      if writer:
        writer.write({"step": step, "error": "non-finite loss or gradient", "count": bad})
      raise FloatingPointError(
          f"loss or gradient became NaN/inf ({bad} step(s) up to step {step}); those steps were not applied. "
          f"The last good checkpoint is step {saved_step} in {ckpt.directory}.")

  try:
    for step in range(start, tc.num_steps):
      map_inputs = None
      if map_cache is not None:
        indices, host = it.next_with_indices()
        map_inputs = distributed.local_to_global(map_cache.take(indices, host.num_polygons), batch_sharding)
      else:
        host = next(it)
      state, metrics = train_step(state, distributed.local_to_global(host, batch_sharding), consts,
                                  packed_polygons(config, host, batch_sharding), map_inputs)
      pending.append(metrics)
      s = step + 1
      if s % tc.log_every == 0 or s == tc.num_steps:
        flush(s)
        bar.update(s - bar.n)
      if s % tc.eval_every and s != tc.num_steps:
        continue
      if val_ds is not None and eval_batch > 0:
        val = validate(eval_step, state.params, consts, val_ds, eval_batch, EVAL_BATCHES, config, batch_sharding)
        val_ema = validate(eval_step, state.ema, consts, val_ds, eval_batch, EVAL_BATCHES, config, batch_sharding)
        if writer:
          writer.write({"step": s, **{f"val_{k}": v for k, v in val.items()},
                        **{f"val_ema_{k}": v for k, v in val_ema.items()}})
        last.update({f"val_{k}": v for k, v in val.items()})
      flush(s)  # never save after a non-finite step
      ckpt.save(s, to_tree(state), record_for(s))
      saved_step = s
      t0 = time.perf_counter()  # keep validation and saving out of the next interval's steps/s
  finally:
    bar.close()
    ckpt.close()
  return last
