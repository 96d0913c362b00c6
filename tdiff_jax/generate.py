"""Generating scenarios from trained checkpoints on a folder of maps (`python sample.py`).

End to end (paper §V-D): the HL model samples every agent's initial and goal state; then, when an
infiller checkpoint is given, the infiller connects them with 60-step trajectories in the chosen
hard-constraint mode, and each generated scenario is also written as an AV2 scenario folder.

* The checkpoint alone defines the model: its JSON record holds the config, the normalisation
  statistics and the training data's agent statistics; the EMA parameters are used by default.
* Maps are AV2 scenario folders (real or synthetic); only the map is needed, so test-split scenarios
  work too. A map that fails to load is reported and skipped.
* Agents per sample: `num_agents > 0` places that many; `0` (default) draws the count from training
  scenes with a similar number of polygons and the types from the training type frequencies; `-1`
  uses the ground-truth agents' count and types of the scenario.
* Outputs in `out_dir`: `samples.npz` (per sample: scenario id, sample index, state, heading, city
  positions, validity, `negative_speed` (where a sampled speed below zero was returned as 0),
  agent types; with the infiller also `trajectory` `[N, A, H, 2]` in the scene
  frame and `trajectory_city`), one PNG per sample, `summary.json`, and with the infiller
  `scenarios/<generated id>/` AV2 folders (see `data.av2_export`).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from pathlib import Path

import jax
import ml_collections
import numpy as np
from absl import logging

from tdiff_jax import (audit, checkpoint, cli, datatypes, files, guidance, host, infilling, repair,
                       sampling)
from tdiff_jax import spec as spec_lib
from tdiff_jax.data import av2_export, av2_io, batches, scene_builder
from tdiff_jax.data import stats as data_stats

SUMMARY = "summary.json"
MAX_TRAJECTORIES_PER_SAMPLE = 64   # draws per scenario; more is refused rather than run out of memory


def plan_agents(scene: datatypes.Scene, num_agents: int, stats: dict, rng: np.random.Generator,
                neighbours: int = 20, spec: spec_lib.Spec | None = None) -> datatypes.Scene:
  """Sets `agent_type`/`agent_valid` of one unbatched scene for sampling (states zeroed). With a `spec`, its
  constrained agents take the first slots with their types, and `spec.others` agents (None: `num_agents`'s
  count less the constrained ones) follow."""
  a_cap = scene.num_agents
  if spec is not None:
    fixed = np.array([a.type for a in spec.agents], np.int32)
    others = plan_agents(scene, num_agents if spec.others is None else spec.others, stats, rng, neighbours) \
        if spec.others != 0 else None
    n_others = 0 if others is None else int(others.agent_valid.sum())
    if spec.others is None:
      n_others = max(0, n_others - len(fixed))
    n_others = min(n_others, a_cap - len(fixed))
    agent_type = np.zeros(a_cap, np.int32)
    agent_type[:len(fixed)] = fixed
    if n_others:
      agent_type[len(fixed):len(fixed) + n_others] = others.agent_type[:n_others]
    valid = np.arange(a_cap) < len(fixed) + n_others
    return scene.replace(agent_type=agent_type, agent_valid=valid, agent_state=np.zeros_like(scene.agent_state),
                         agent_future=np.zeros_like(scene.agent_future),
                         agent_future_valid=np.zeros_like(scene.agent_future_valid))
  if num_agents == -1:
    agent_type, valid = scene.agent_type.copy(), scene.agent_valid.copy()
  else:
    if num_agents == 0:
      pairs = np.asarray(stats["polygons_agents"])
      near = np.argsort(np.abs(pairs[:, 0] - int(scene.pl_valid.sum())), kind="stable")[:neighbours]
      num_agents = int(pairs[rng.choice(near), 1])
    n = max(1, min(num_agents, a_cap))
    freq = np.asarray(stats["type_frequency"], np.float64)
    agent_type = np.zeros(a_cap, np.int32)
    agent_type[:n] = rng.choice(len(freq), size=n, p=freq / freq.sum())
    valid = np.arange(a_cap) < n
  return scene.replace(agent_type=agent_type.astype(np.int32), agent_valid=valid,
                       agent_state=np.zeros_like(scene.agent_state),
                       agent_future=np.zeros_like(scene.agent_future),
                       agent_future_valid=np.zeros_like(scene.agent_future_valid))


def _stats_from_cache(workdir: Path | str, config: ml_collections.ConfigDict) -> dict:
  """Agent statistics of the training split, for checkpoints that do not carry them."""
  cache = Path(config.data.cache_dir) if config.data.cache_dir else Path(workdir) / "cache"
  try:
    return data_stats.training_agent_stats(batches.open_split(cache, "train", config.data.scene))
  except (FileNotFoundError, KeyError, ValueError) as e:
    raise FileNotFoundError(f"the checkpoint has no agent statistics and its training cache is unusable ({e}); "
                            "pass --num_agents=N or --num_agents=-1") from e


def generate(workdir: Path | str, maps: Path | str, out_dir: Path | str, num_per_map: int = 1, num_agents: int = 0,
             options: sampling.SamplerOptions = sampling.DEFAULT,
             guidance_params: sampling.GuidanceParams | None = None, seed: int = 0, batch_size: int = 8,
             max_maps: int = 0, pictures: bool = True, progress: bool = True,
             infill_workdir: Path | str | None = None, infill_mode: str = "both", animate: bool = False,
             lane_pull_m: float | None = None, trajectories_per_sample: int = 1,
             overwrite: bool = False, repair_rounds: int = repair.DEFAULT_REPAIR_ROUNDS,
             spec: spec_lib.Spec | None = None) -> dict:
  """Samples `num_per_map` scenarios per map and writes them to `out_dir`; returns the summary.

  With `infill_workdir` (an infiller training workdir), every sample is also infilled in
  `infill_mode` (see `infilling.MODES`) and written as an AV2 scenario folder, and with `animate` as
  an animated GIF `<id>_<k>.gif` (`viz.animate_scenario`). `lane_pull_m`: the lane pull's reach (`checkpoint.with_lane_pull`; None: the checkpoint's, 0: off).
  With an infiller, the agents whose trajectories overlap another's or leave the road are resampled for up
  to `repair_rounds` rounds, the others held (`repair.sample_complete`; 0: the sampler alone).
  `trajectories_per_sample` > 1 (a stochastic infiller): that many trajectory draws per high-level scenario,
  `trajectory` `[N, K, A, H, 2]` in samples.npz and one AV2 folder per draw (`draw` in the summary's
  scenarios); pictures and animations show draw 0.

  `spec` (`spec.load`; needs an infiller): every sample places the spec's constrained agents first (the
  first is each AV2 folder's focal track), is guided by the spec's cost, and the agents that miss their
  predicates are redrawn with the faulty ones for up to `repair_rounds` rounds; maps that cannot hold the
  spec (`spec.feasibility`) are skipped and listed; samples.npz gains `spec_agent` `[N, A]` (the expanded spec
  entry of each agent, -1 for the others) and `spec_satisfied` `[N]`, the summary a `spec` section (the
  satisfaction per predicate, the unsatisfied samples, the infeasible maps).

  `out_dir` must be new or empty, or with `overwrite` hold an earlier run's results (its summary.json),
  which are then replaced whole; the outputs appear there complete or not at all (`files.output_folder`).
  Maps whose scenario ids repeat get distinct output names (`<id>-2`, ...).
  """
  from tqdm import tqdm

  if num_per_map < 1 or batch_size < 1 or num_agents < -1 or max_maps < 0:
    raise ValueError("num_per_map and batch_size must be >= 1, num_agents >= -1, max_maps >= 0")
  cli.check_seed(seed)
  if animate and infill_workdir is None:
    raise ValueError("animate needs infilled trajectories: give an infiller checkpoint (infill_workdir)")
  if spec is not None and infill_workdir is None:
    raise ValueError(f"{spec.source}: a spec needs an infiller checkpoint (infill_workdir): its samples are redrawn "
                     "with the agents whose trajectories collide or leave the road")
  mode = infilling.mode_id(infill_mode)
  if repair_rounds < 0:
    raise ValueError(f"repair_rounds must be >= 0, got {repair_rounds}")
  if not 1 <= trajectories_per_sample <= MAX_TRAJECTORIES_PER_SAMPLE:
    raise ValueError(f"trajectories_per_sample must be between 1 and {MAX_TRAJECTORIES_PER_SAMPLE}, got "
                     f"{trajectories_per_sample}")
  final_dir = Path(out_dir)
  inputs = (maps, workdir, infill_workdir)   # never inside an output folder that may be replaced
  files.check_output_folder(final_dir, overwrite, inputs)  # refused before anything is loaded or written
  model = checkpoint.with_lane_pull(checkpoint.load_checkpoint(workdir, task="hl"), lane_pull_m)
  infiller = checkpoint.load_checkpoint(infill_workdir, task="infill") if infill_workdir is not None else None
  if trajectories_per_sample > 1 and (infiller is None or not infiller.stochastic):
    raise ValueError(f"trajectories_per_sample={trajectories_per_sample} needs a stochastic infiller "
                     "(--config=configs/infill.py:stochastic); a deterministic one draws one trajectory per scenario")
  if pictures or animate:
    from tdiff_jax import viz  # matplotlib only when pictures are asked for
  config = model.config
  if num_agents > config.data.scene.max_agents:  # refused rather than silently capped
    raise ValueError(f"num_agents={num_agents} is more than this model places: at most "
                     f"{config.data.scene.max_agents} (its data.scene.max_agents)")
  if spec is not None:
    spec_lib.check_cap(spec, config.data.scene.max_agents)
    if "spec" not in options.costs:
      options = dataclasses.replace(options, costs=options.costs + ("spec",))
  folders = av2_io.map_folders(maps)
  if max_maps:
    folders = folders[:max_maps]
  rng = np.random.default_rng(seed)
  stats = model.record.get("agent_stats") or (_stats_from_cache(workdir, config) if num_agents == 0 else None)
  items, failed, warned, keys, infeasible = [], [], [], set(), []
  first_placement = {}   # with a spec: item position -> its first placement (`spec.propose`)
  for folder in folders:
    try:
      scene, info = scene_builder.load_scene(folder, config.data.scene, require_agents=num_agents == -1)
    except av2_io.BadScenarioError as e:
      failed.append({"map": folder.name, "file": e.path, "reason": e.reason})
      logging.warning("skipping map %s: %s", folder.name, e.reason)
      continue
    reasons = spec_lib.feasibility(spec, scene) if spec is not None else []
    if reasons:
      infeasible.append({"map": folder.name, "reasons": reasons})
      logging.warning("map %s cannot hold spec %s: %s", folder.name, spec.name, "; ".join(reasons))
      continue
    for w in info.warnings:
      warned.append({"map": folder.name, "warning": w})
      logging.warning("map %s: %s", folder.name, w)
    safe = files.safe_name(info.scenario_id)   # the id is file content: never a path of its own
    key = files.unique_name(safe, keys)
    if key != info.scenario_id:
      note = (f"scenario id {info.scenario_id!r} is not a safe file name: its outputs are named {key}"
              if safe != info.scenario_id else f"scenario id {info.scenario_id} repeats: its outputs are named {key}")
      warned.append({"map": folder.name, "warning": note})
      logging.warning("map %s: %s", folder.name, note)
    planned = [plan_agents(scene, num_agents, stats, rng, spec=spec) for _ in range(num_per_map)]
    placements = [spec_lib.propose(spec, scene, _placement_rng(seed, len(items) + k, 0))   # each sample's first
                  for k in range(num_per_map)] if spec is not None else [None] * num_per_map
    if spec is not None and any(p is None for p in placements):
      reason = "no placement of the constrained agents holds the spec's initial states"
      infeasible.append({"map": folder.name, "reasons": [reason]})
      logging.warning("map %s cannot hold spec %s: %s", folder.name, spec.name, reason)
      continue
    for k in range(num_per_map):
      first_placement[len(items)] = placements[k]
      items.append((key, info, folder, k, planned[k]))
  if not items:  # nothing to write: an empty samples.npz would look like success
    reasons = "; ".join([f"{f['file']}: {f['reason']}" for f in failed]
                        + [f"{f['map']}: {'; '.join(f['reasons'])}" for f in infeasible])
    raise ValueError(f"{maps}: none of the {len(folders)} map(s) could be sampled: {reasons}")

  with files.output_folder(final_dir, overwrite, "sample.py", inputs) as out_dir:  # whole, or not at all
    names = ("state", "heading", "city_xy", "valid", "negative_speed", "agent_type")
    if infiller is not None:
      names += ("trajectory", "trajectory_city")
    satisfied = {}   # with a spec: item position -> its predicates (`spec.check`)
    results = {name: [] for name in names}
    a_cap = config.data.scene.max_agents

    def pad(x):  # back from the batch's agent bucket to the cap, so every batch stacks
      return np.pad(x, [(0, 0), (0, a_cap - x.shape[1])] + [(0, 0)] * (x.ndim - 2))

    generated, done = {}, []   # by item position; the item positions in the order sampled
    t0 = time.perf_counter()
    cost_sums, total_agents = {}, 0
    resampled = faulty = 0   # agents resampled by the repair; agents still at fault after it
    # Batches of scenes of one size (`batches.sampler_batches`); item p's samples depend on p only, and the
    # outputs are written in the items' order.
    buckets = (batches.sampler_agent_buckets(config.data), config.data.polygon_buckets)
    batched = list(batches.sampler_batches([s for *_, s in items], batch_size, *buckets))
    for positions, batch in tqdm(batched, desc="sample", unit="batch", disable=not progress):
      chunk = [items[p] for p in positions]
      host.drop_compiled_near_map_limit()  # each batch's shapes compile; their programs hold memory maps
      padded = np.pad(positions, (0, batch.agent_valid.shape[0] - len(positions)), mode="edge")  # a key per scene
      batch_dev = jax.tree_util.tree_map(jax.numpy.asarray, batch)
      keys = sampling.keys_at(jax.random.key(seed), padded)
      infill_keys = [sampling.keys_at(jax.random.fold_in(jax.random.key(seed), 1 + d), padded)   # per scene and draw
                     for d in range(trajectories_per_sample)]
      traj = None
      if infiller is not None and spec is not None:   # towards the spec, and apart and on the road
        complete = sample_spec(model, infiller, batch, keys, options, guidance_params, spec, mode=mode,
                               repair_rounds=repair_rounds, infill_key=infill_keys[0],
                               placement=lambda b, attempt: first_placement[padded[b]] if not attempt  # noqa: B023
                               else spec_lib.propose(spec, jax.tree_util.tree_map(lambda x: x[b], batch),  # noqa: B023
                                                     _placement_rng(seed, padded[b], attempt)))  # noqa: B023
      elif infiller is not None:   # sampled, infilled and the faulty agents resampled (`repair`)
        complete = repair.sample_complete(model, infiller, batch_dev, keys, options, guidance_params, mode=mode,
                                          repair_rounds=repair_rounds, infill_key=infill_keys[0])
      if infiller is not None:
        out = complete.hl
        resampled += int((np.asarray(complete.resampled) > 0).sum())
        faulty += int(np.asarray(complete.overlap | complete.offroad).sum())
        hl_scene = batch_dev.replace(agent_state=jax.numpy.concatenate([out.state, out.heading[..., None]], -1))
        draws = [np.asarray(complete.trajectory)] + [np.asarray(infilling.infill_batch(
            infiller.graphdef, infiller.params, hl_scene, out.heading[..., 0], mode, infill_keys[d],
            polygon_buckets=infiller.config.data.polygon_buckets)) for d in range(1, trajectories_per_sample)]
        traj = draws[0]
      else:
        out = repair.sample_states(model, batch_dev, keys, options, guidance_params)
      n_agents = int(batch.agent_valid.sum())
      for name, value in _costs(out.state, batch_dev).items():  # on the cropped batch, while it is on device
        cost_sums[name] = cost_sums.get(name, 0.0) + value * n_agents
      total_agents += n_agents
      real = lambda tree: jax.tree_util.tree_map(lambda x: x[:len(positions)], tree)  # noqa: E731,B023  no padding
      out, batch = real(jax.device_get(out)), real(batch)
      if traj is not None:
        draws = [d[:len(positions)] for d in draws]
        traj = draws[0]
      _check_finite(out.state, out.heading, out.valid, workdir)
      if spec is not None:
        for j, p in enumerate(positions):
          satisfied[p] = spec_lib.check(spec, np.asarray(out.state[j]), np.asarray(out.heading[j]),
                                        jax.tree_util.tree_map(lambda x: x[j], batch))  # noqa: B023
      city_xy = datatypes.to_city(batch, np.asarray(out.state)[..., :2].astype(np.float64))  # float64: 1e6 m maps
      values = {"state": out.state, "heading": out.heading, "city_xy": city_xy, "valid": out.valid,
                "negative_speed": out.negative_speed,
                "agent_type": batch.agent_type}
      if traj is not None:
        city = [datatypes.to_city(batch, d.astype(np.float64)) for d in draws]
        many = trajectories_per_sample > 1   # [N, K, A, H, 2], else [N, A, H, 2]
        values["trajectory"] = np.stack(draws, 1) if many else traj
        values["trajectory_city"] = np.stack(city, 1) if many else city[0]
      for name, value in values.items():
        value = np.asarray(value)
        results[name].append(pad(value) if value.ndim < 5 else np.stack([pad(v) for v in value.swapaxes(0, 1)], 1))
      done.extend(positions)
      for j, (key, info, folder, k, scene) in enumerate(chunk):
        sid = info.scenario_id
        if pictures:
          title = f"{sid} sample {k} (HL step {model.record['step']}"
          title += f", infilled in mode {infilling.MODES[mode]})" if traj is not None else ")"
          if spec is not None:
            title += f"\nspec {spec.name}: " + ("holds" if all(satisfied[positions[j]].values()) else "missed")
          viz.plot_hl_scenario(scene, np.asarray(out.state[j]), np.asarray(out.valid[j]),
                               np.asarray(batch.agent_type[j]),
                               out_dir / f"{key}_{k}.png", title, trajectories=None if traj is None else traj[j],
                               labels=None if spec is None else {i: spec.label(i) for i in range(len(spec.agents))})
        if animate:
          viz.animate_scenario(scene, traj[j], np.ones(traj[j].shape[:2], bool), np.asarray(out.valid[j]),
                               np.asarray(batch.agent_type[j]), np.asarray(out.heading[j, :, 0]),
                               out_dir / f"{key}_{k}.gif", f"{sid} sample {k}, generated (HL step "
                               f"{model.record['step']}, infilled in mode {infilling.MODES[mode]})")
        for d in range(trajectories_per_sample if traj is not None else 0):
          gen_id = av2_export.generated_scenario_id(key, k, seed) if d == 0 else \
              av2_export.generated_scenario_id(f"{key}/draw{d}", k, seed)
          av2_export.write_generated_scenario(
              out_dir / "scenarios", gen_id, info.city, av2_io.find_map_file(folder),
              city[d][j], np.asarray(out.heading[j, :, 0]), np.asarray(batch.agent_type[j]), np.asarray(out.valid[j]))
          generated.setdefault(positions[j], []).append(
              {"scenario_id": gen_id, "map": sid, "map_folder": folder.name, "sample_index": k,
               **({"draw": d} if trajectories_per_sample > 1 else {})})
    seconds = time.perf_counter() - t0
    back = np.argsort(done)   # the items' order
    arrays = {name: np.concatenate(v)[back] for name, v in results.items()}
    ids = [info.scenario_id for _, info, *_ in items]
    files.atomic_write(out_dir / "samples.npz", lambda f: np.savez(
        f, scenario_id=np.array(ids, dtype=np.str_),
        map_folder=np.array([folder.name for _, _, folder, *_ in items], dtype=np.str_),
        sample_index=np.array([k for *_, k, _ in items], np.int32), **arrays, **_spec_arrays(spec, satisfied, a_cap)))

    summary = {
        "checkpoint": _where(workdir), "step": model.record["step"], "maps": str(maps),
        "maps_sampled": len(folders) - len(failed), "failed_maps": failed, "map_warnings": warned,
        "samples": len(ids), "negative_speeds_set_to_zero": int(arrays["negative_speed"].sum()),
        "options": dataclasses.asdict(options), "lane_pull": dataclasses.asdict(model.lane_pull) if model.lane_pull else None,
        "seed": seed, "seconds": round(seconds, 2),
        "agents_per_sample": float(arrays["valid"].sum(-1).mean()),
    }
    if infiller is not None:
      summary.update({"infiller_checkpoint": _where(infill_workdir),
                      "infiller_step": infiller.record["step"], "infill_mode": infilling.MODES[mode],
                      "scenario_folders": str(final_dir / "scenarios"),
                      "scenarios": [g for p in sorted(generated) for g in generated[p]]})
      if trajectories_per_sample > 1:
        summary["trajectories_per_sample"] = trajectories_per_sample
      summary["repair"] = {"rounds": repair_rounds, "agents_resampled": resampled, "agents_at_fault_after": faulty}
      # What the user takes away, read back as they would: overlaps and off-road over the 6 s, and the
      # logged scenarios of the same maps beside them.
      t_audit = time.perf_counter()
      used = {folder.name: folder for _, _, folder, *_ in items}
      summary["complete_scenarios"] = audit.audit_generated(
          [out_dir / "scenarios" / g["scenario_id"] for g in summary["scenarios"]],
          [used[name] for name in sorted({g["map_folder"] for g in summary["scenarios"]})], config.data.scene)
      summary["complete_scenarios"]["seconds"] = round(time.perf_counter() - t_audit, 2)
    if spec is not None:
      summary["spec"] = _spec_summary(spec, items, satisfied, infeasible, generated)
    if total_agents:  # per-batch means weighted by the batch's agents
      summary["mean_costs_m"] = {k: v / total_agents for k, v in cost_sums.items()}
    files.atomic_write_text(out_dir / SUMMARY, files.json_text(summary, indent=1))
  return summary


# Placements of a spec's constrained agents tried per sample (`sample_spec`).
SPEC_PLACEMENTS = 3


def _placement_rng(seed: int, position: int, attempt: int) -> np.random.Generator:
  """Item `position`'s draws of its spec placement `attempt`: its own, whichever batch it falls in."""
  return np.random.default_rng((seed, int(position), attempt))


def sample_spec(hl: checkpoint.LoadedModel, infiller: checkpoint.LoadedModel, batch: datatypes.Scene,
                key: jax.Array, options: sampling.SamplerOptions, guidance_params: sampling.GuidanceParams | None,
                spec: spec_lib.Spec, placement, *, mode: int, repair_rounds: int,
                infill_key: jax.Array | None = None) -> repair.CompleteSample:
  """Complete scenarios of a batch (numpy `[B]` scenes whose first agent slots are the spec's, `plan_agents`)
  that hold `spec`, as far as `SPEC_PLACEMENTS` placements go.

  Each placement holds the constrained agents' initial states `placement(b, attempt)` (`spec.propose`; None:
  none found) and runs `repair.sample_complete` guided by the spec's cost (`options.costs` with "spec"), the
  agents that miss their predicates redrawn with the faulty ones, and a constrained agent whose sampled goal
  misses its maneuver or cut-in held from then on at a goal on its route (`spec.route_goals`); the scenes that still miss the spec or have
  a constrained agent at fault are placed again (keys folded with the attempt), each keeping its sample with
  the fewest agents off the spec, then the fewest at fault.
  """
  b, a = batch.agent_valid.shape
  guidance_params = guidance_params or sampling.GuidanceParams()
  judge = functools.partial(_spec_violations, spec, batch)
  batch_dev = jax.tree_util.tree_map(jax.numpy.asarray, batch)
  maps = repair.encode_batch(hl, batch_dev)
  keys = sampling.scene_keys(key, b)
  placed = [placement(i, 0) for i in range(b)]
  best, best_score = None, None
  for attempt in range(SPEC_PLACEMENTS):
    held = [spec_lib.held_tokens(spec, p, a) for p in placed]
    g = dataclasses.replace(guidance_params, spec=spec_lib.arrays(spec, b, a, placed))
    fold = lambda ks: ks if ks is None or not attempt else jax.vmap(  # noqa: E731
        lambda k: jax.random.fold_in(k, 1000 + attempt))(sampling.scene_keys(ks, b))  # noqa: B023
    out = repair.sample_complete(hl, infiller, batch_dev, fold(keys), options, g, mode=mode,
                                 repair_rounds=repair_rounds, infill_key=fold(infill_key), maps=maps, judge=judge,
                                 hold=functools.partial(_route_goals, spec, batch, placed),
                                 fixed_state=np.stack([h[0] for h in held]), fixed_mask=np.stack([h[1] for h in held]))
    score = out.badness()   # [B] agents off the spec first, then agents at fault
    if best is None:
      best, best_score = out, score
    else:
      better = score < best_score
      pick = lambda n, o: jax.numpy.where(better.reshape((-1,) + (1,) * (n.ndim - 1)), n, o)  # noqa: E731,B023
      best, best_score = jax.tree_util.tree_map(pick, out, best), np.where(better, score, best_score)
    # Placed again where the spec is missed or a constrained agent is at fault (the others' faults are the
    # repair's, as in a plain sample).
    k = len(spec.agents)
    constrained_faults = np.asarray(best.overlap | best.offroad)[:, :k].any(-1)
    again = (best_score > a) | constrained_faults
    if not again.any():
      break
    for i in np.flatnonzero(again):
      placed[i] = placement(i, attempt + 1) or placed[i]
  return best


def _spec_violations(spec: spec_lib.Spec, batch: datatypes.Scene, hl: sampling.HLSample) -> np.ndarray:
  """`[B, A]` the agents of each scene of `batch` (numpy) that miss their spec (`spec.violating_agents`); none
  in the agentless scenes that pad a batch."""
  state, heading = np.asarray(hl.state), np.asarray(hl.heading)
  a = state.shape[1]
  return np.stack([spec_lib.violating_agents(spec, spec_lib.check(
      spec, state[b], heading[b], jax.tree_util.tree_map(lambda x: x[b], batch)), a)  # noqa: B023
      for b in range(state.shape[0])]) & np.asarray(batch.agent_valid, bool)


def _route_goals(spec: spec_lib.Spec, batch: datatypes.Scene, placed: list, hl: sampling.HLSample,
                 judged: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
  """`(state [B, A, 2, 4], mask [B, A, 2])`: goals on their routes (`spec.route_goals`) for the constrained
  agents of each scene whose goal misses its spec, held from the next repair round on."""
  state, heading = np.asarray(hl.state), np.asarray(hl.heading)
  held_state, held_mask = np.zeros(state.shape[:2] + (2, 4), np.float32), np.zeros(state.shape[:2] + (2,), bool)
  k = len(spec.agents)
  for b in np.flatnonzero(judged[:, :k].any(-1)):
    predicates = spec_lib.check(spec, state[b], heading[b], jax.tree_util.tree_map(lambda x: x[b], batch))  # noqa: B023
    goal, held = spec_lib.route_goals(spec, placed[b], state[b], heading[b], predicates)
    held_state[b, :k, 1], held_mask[b, :k, 1] = goal, held
  return held_state, held_mask


def _spec_arrays(spec: spec_lib.Spec | None, satisfied: dict, a_cap: int) -> dict:
  """samples.npz's `spec_agent` `[N, A]` and `spec_satisfied` `[N]` (nothing without a spec)."""
  if spec is None:
    return {}
  k = len(spec.agents)
  entry = np.where(np.arange(a_cap) < k, np.arange(a_cap), -1).astype(np.int32)
  return {"spec_agent": np.tile(entry, (len(satisfied), 1)),
          "spec_satisfied": np.array([all(satisfied[p].values()) for p in sorted(satisfied)], bool)}


def _spec_summary(spec: spec_lib.Spec, items: list, satisfied: dict, infeasible: list, generated: dict) -> dict:
  """summary.json's `spec` section: the satisfaction per spec and per predicate, what misses it, where it cannot hold."""
  ok = [all(satisfied[p].values()) for p in range(len(items))]
  misses = [{"map": items[p][0], "sample_index": items[p][3],
             "scenario_id": generated[p][0]["scenario_id"] if p in generated else None,
             "failed": [name for name, held in satisfied[p].items() if not held]}
            for p in range(len(items)) if not ok[p]]
  return {"name": spec.name, "file": spec.source, "constrained_agents": len(spec.agents),
          "samples": len(items), "satisfied": int(sum(ok)), "satisfied_pct": round(100.0 * sum(ok) / len(items), 2),
          "predicates_pct": {name: round(100.0 * np.mean([satisfied[p][name] for p in range(len(items))]), 2)
                             for name in spec.predicates()},
          "not_satisfied": misses, "infeasible_maps": infeasible}


def _check_finite(state: np.ndarray, heading: np.ndarray, valid: np.ndarray, workdir) -> None:
  """Raises ValueError when a valid agent's sampled state or heading is not finite (a diverged model): never
  written as a result."""
  bad = ~(np.isfinite(state).all((-1, -2)) & np.isfinite(heading).all(-1)) & valid
  if bad.any():
    raise ValueError(f"the model in {workdir} sampled NaN or inf states for {int(bad.sum())} agent(s): its "
                     "parameters or statistics are broken; nothing was written")


def _where(workdir: Path | str) -> str:
  """The checkpoint folder of a workdir, or the folder of an exported model."""
  return str(workdir) if checkpoint.is_exported(workdir) else str(Path(workdir) / "checkpoints")


def _costs(state: jax.Array, scene: datatypes.Scene) -> dict:
  """Mean clearance shortfall below 2 m, distance beyond 2 m from a lane, distance off the drivable area."""
  return {"clearance_2m": float(guidance.clearance(state, scene, 2.0)),
          "lane_beyond_2m": float(guidance.lane_distance(state, scene, 2.0)),
          "offroad": float(guidance.offroad(state, scene))}
