"""The paper's tables for any checkpoint and dataset split: `python -m tdiff_jax.evaluate`.

  python -m tdiff_jax.evaluate                                   # workdirs/hl (+ workdirs/infill) on its training data's val split
  python -m tdiff_jax.evaluate --data=/path/to/av2/val --max_scenes=2000 --out=eval_av2

A workdir at its default location (workdirs/hl, workdirs/infill) without a checkpoint: the pretrained
model of the default recipe shipped with the package, on its synthetic validation worlds (generated
into workdirs/hl/synthetic when missing).

Table I (high-level scenarios): for every scenario of the split with ground-truth agents, the HL model
samples a scenario on its map with the ground truth's agent count and types (unguided, as the paper's
table; `--guidance` for guided sampling; `--method=auto`, the default, samples with DPM-Solver++(2M) in
11 calls (from noise 12) and 4 restarts unguided and DDIM-50 guided, `--method=ddim` as the paper); both are scored with `tdiff_jax.metrics` for the initial and the goal states separately, under
the official and the strict conventions. The GT row is computed from the data itself.
Table II (infilling, with an infiller checkpoint): ADE, FDE and miss rate (FDE > 2 m) per
hard-constraint mode, given the ground-truth initial pose and goal.
The realism of complete scenarios (with both models; `--realism_rollouts`, default 16 per map): the
sim-agents meta-metric (`tdiff_jax.realism`) of the logged 6-second scenario of each map under
generated ones (`REALISM_ROWS`: the logged trajectories themselves, constant velocity, the infiller
between the logged states, HL samples then the infiller; `--stochastic_infill_workdir` adds a generative
infiller's two rows, its Table II and the diversity of its draws).

Every Table I row also has `goal_reachable_pct` (`metrics.goal_reachability`: road users whose goal lies
on a lane reachable from their initial lane along the directed lane graph within a 6 s path; the same
value in the initial and goal rows). The shuffled-map control scores the model's samples on the map
of the next scene of the batch: a model that uses its map is much more off-road there than on its own.

`--guided_row=boxes,lane,offroad` also samples every scene with those guidance costs and adds a
"guided" row (DDIM-50 unless `--method` says otherwise).

Scenarios that cannot be loaded are skipped and counted. Writes to --out (default <hl workdir>/eval; a
folder of an earlier run's results only with --overwrite, and then replaced whole) and prints the Markdown:
  table.md, table.json   the tables (table.json also holds every histogram and the checkpoint's config);
  grid.png               ground truth next to samples on the first maps (`--grid`);
  dist_<metric>_<endpoint>.png, rates.png   the distributions and common-sense metrics (`viz`);
  realism.png            each realism feature's histograms, logged and generated (`viz`);
  report.html            all of it on one self-contained page (`report`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from absl import flags

from tdiff_jax import (audit, checkpoint, cli, datatypes, files, geometry, host, infilling, metrics, realism,
                       repair, sampler_flags, sampling)
from tdiff_jax.data import av2_export, av2_io, batches, scene_builder

ENDPOINTS = ("initial", "goal")
SORT_WINDOW = 8   # batches of scenes loaded and ordered by size together
# The paper's Table I (official convention; JSDs are JS distances).
PAPER_TABLE_I = {
    "initial": {"GT": (0.50, 1.70, 1.58, None, None, None, None), "Ours": (9.80, 5.10, 1.81, 0.068, 0.200, 0.201, 0.101)},
    "goal": {"GT": (0.50, 2.80, 1.86, None, None, None, None), "Ours": (10.6, 7.21, 2.02, 0.08, 0.198, 0.206, 0.103)},
}


@jax.jit
def batch_metrics(gen_state: jax.Array, gen_heading: jax.Array, scene: datatypes.Scene) -> dict:
  """Accumulators for GT and model, per endpoint: {"gt"|"model": {"initial"|"goal": {...}}}."""
  out = {"gt": {}, "model": {}}
  for tok, name in enumerate(ENDPOINTS):
    gt = scene.agent_state[..., tok, :]
    out["gt"][name] = metrics.state_accumulators(gt[..., :2], gt[..., 2], gt[..., 3], scene)
    out["model"][name] = metrics.state_accumulators(gen_state[..., tok, :2], gen_state[..., tok, 2],
                                                    gen_heading[..., tok], scene)
  return out


# The map's fields of the scene contract: polygons, points, topology and drivable areas.
MAP_FIELDS = tuple(f.name for f in dataclasses.fields(datatypes.Scene) if f.name.startswith(("pl_", "pt_", "da_")))


def with_next_map(batch: datatypes.Scene) -> datatypes.Scene:
  """The batch with scene i's agents on scene (i + 1) mod B's map (the shuffled-map control)."""
  return batch.replace(**{f: jnp.roll(getattr(batch, f), -1, axis=0) for f in MAP_FIELDS})


# The realism score's rows (`realism`): trajectories of the logged agents, scored against the logged scenario.
REALISM_ROWS = {"logged": "the logged trajectories themselves (the best possible score)",
                "constant_velocity": "constant velocity from the logged initial states",
                "infiller": "infiller between the logged initial and goal states",
                "hl_infiller": "HL samples, then the infiller",
                "stochastic_infiller": "stochastic infiller between the logged initial and goal states",
                "hl_stochastic_infiller": "HL samples, then the stochastic infiller"}
# Keys: fold_in(key(seed), stream), then one per scene and rollout (or draw).
REALISM_STREAM, INFILL_STREAM, DIVERSITY_STREAM = 1, 2, 3
DIVERSITY_DRAWS = 8   # trajectory draws per high-level scenario for the stochastic infiller's diversity
MAX_REALISM_ROLLOUTS = 64   # generated scenarios per map (the challenge uses 32); more is refused, not run out of memory


def realism_batch(hl: checkpoint.LoadedModel, infillers: dict, batch: datatypes.Scene, indices: list[int],
                  seed: int, rollouts: int, options: sampling.SamplerOptions,
                  guidance_params: sampling.GuidanceParams | None, repair_rounds: int = 0) -> dict:
  """For each of `REALISM_ROWS` that `infillers` ({"infiller": model, "stochastic_infiller": model}, either
  may be missing) allow, the maps' logged scenarios scored under the row's trajectories
  (`realism.log_likelihoods`: per map `[M]` sums and counts) and the row's pooled histograms
  ("logged": the logged trajectories score themselves), and "score_seconds", the time the scoring took
  (the trajectories made). The HL rows draw `rollouts` scenarios per map (the
  logged agent count and types) and a stochastic infiller `rollouts` trajectory sets; rollout r of scene i
  is keyed by its own index. A deterministic row's one trajectory set counts as `rollouts` identical ones.
  With a stochastic infiller also "diversity": `realism.draw_diversity` of `DIVERSITY_DRAWS` draws for each
  map's first HL scenario. `batch` `[M, ...]` (`batches.sampler_batches`): its first `len(indices)` scenes are
  the maps scored, the rest padding (keyed by the first's index)."""
  m, num_maps = batch.agent_valid.shape[0], len(indices)
  indices = list(indices) + [indices[0]] * (m - num_maps)
  geom = geometry.map_geometry(batch, *geometry.compact_sizes(batch))
  heading0 = batch.agent_state[..., 0, 3]
  both = infilling.mode_id("both")
  repeat = lambda tree, n: jax.tree_util.tree_map(lambda x: jnp.repeat(x, n, axis=0), tree)  # noqa: E731
  keys = lambda stream, n: sampling.keys_at(jax.random.fold_in(jax.random.key(seed), stream),  # noqa: E731
                                            [i * n + r for i in indices for r in range(n)])
  scenes = repeat(batch, rollouts)
  # The HL scenarios as a user gets them (`repair.sample_complete`), repaired with the deterministic infiller
  # when there is one, else the stochastic one: one set of states for both infillers' rows.
  repairer = infillers.get("infiller") or infillers["stochastic_infiller"]
  completed = repair.sample_complete(hl, repairer, scenes.replace(agent_state=jnp.zeros_like(scenes.agent_state)),
                                     keys(REALISM_STREAM, rollouts), options, guidance_params, mode=both,
                                     repair_rounds=repair_rounds, infill_key=keys(INFILL_STREAM, rollouts))
  out = completed.hl
  sampled = scenes.replace(agent_state=jnp.concatenate([out.state, out.heading[..., None]], -1))
  rows = {"logged": (batch.agent_future, heading0, 1),
          "constant_velocity": (realism.constant_velocity(batch.agent_state[..., 0, :]), heading0, 1)}
  result = {}
  for name, inf in infillers.items():
    infill = functools.partial(infilling.infill_batch, inf.graphdef, inf.params,
                               polygon_buckets=inf.config.data.polygon_buckets)
    if inf.stochastic:   # draws: one per rollout, from the logged and the sampled states
      rows[name] = (infill(scenes, repeat(heading0, rollouts), both, keys(INFILL_STREAM, rollouts)),
                    repeat(heading0, rollouts), rollouts)
      one = jax.tree_util.tree_map(lambda x: x[::rollouts], sampled)   # each map's first HL scenario
      draws = jnp.stack([infill(one, one.agent_state[..., 0, 3], both, keys(DIVERSITY_STREAM + 10 * d, 1))
                         for d in range(DIVERSITY_DRAWS)])
      result["diversity"] = jax.device_get(realism.draw_diversity(draws, one))
    else:
      rows[name] = (infill(batch, heading0, both), heading0, 1)
    trajectory = completed.trajectory if inf is repairer else infill(sampled, out.heading[..., 0], both,
                                                                      keys(INFILL_STREAM, rollouts))
    rows["hl_" + name] = (trajectory, out.heading[..., 0], rollouts)
  jax.block_until_ready(rows)
  t_score = time.perf_counter()
  logged_valid = batch.agent_future_valid & batch.agent_valid[..., None]
  logged = realism.trajectory_features(batch.agent_future, logged_valid, heading0, batch.agent_type, geom)
  for name, (xy, h0, n) in rows.items():
    valid = logged_valid if name == "logged" else jnp.broadcast_to(repeat(batch.agent_valid, n)[..., None],
                                                                  xy.shape[:-1])
    counts = realism.scenario_histograms(xy, valid, h0, repeat(batch.agent_type, n), repeat(geom, n))
    counts = {k: v.reshape(m, n, -1).sum(1)[:num_maps] * (rollouts // n) for k, v in counts.items()}
    ll = realism.log_likelihoods(counts, jax.tree_util.tree_map(lambda x: x[:num_maps], logged))  # noqa: B023
    result[name] = jax.device_get((ll, {k: v.sum(0) for k, v in counts.items()}))
  result["score_seconds"] = time.perf_counter() - t_score
  return result


def evaluate(hl_workdir: Path | str | None, data: Path | str, infill_workdir: Path | str | None = None,
             batch_size: int = 8, seed: int = 0, max_scenes: int = 0,
             options: sampling.SamplerOptions = sampling.DEFAULT, progress: bool = True,
             grid_path: Path | str | None = None, grid_scenes: int = 4,
             guided_options: sampling.SamplerOptions | None = None,
             guidance_params: sampling.GuidanceParams | None = None,
             lane_pull_m: float | None = None, realism_rollouts: int = 16,
             stochastic_infill_workdir: Path | str | None = None, scenarios_dir: Path | str | None = None,
             repair_rounds: int = repair.DEFAULT_REPAIR_ROUNDS) -> dict:
  """Computes Table I (when `hl_workdir` is given), Table II (for each infiller given: `infill_workdir`,
  and a generative one, `stochastic_infill_workdir`) and, with an HL model, an infiller and
  `realism_rollouts` > 0, the realism score of complete scenarios (`realism_batch`).
  `guidance_params` (scale and weights) apply to whichever options are guided.

  With `grid_path`, the first `grid_scenes` scenes' ground truth and samples are drawn side by side there.
  With `guided_options`, every scene is also sampled with them (same keys) for Table I's "guided" rows.
  `lane_pull_m`: the lane pull's reach (`checkpoint.with_lane_pull`; None: the checkpoint's, 0: off).
  With an HL model and the (deterministic) infiller, Table I's samples are the states of complete scenarios
  as `sample.py` makes them: infilled (both ends pinned) and the faulty agents resampled for up to
  `repair_rounds` rounds (`repair.sample_complete`; the realism rows' too). With `scenarios_dir` as well,
  each scene's complete sample is written there as an AV2 scenario folder, and "complete_scenarios" is
  their audit beside the logged scenarios' (`audit.audit_generated`: overlaps and leaving the road, read
  back with av2's loader).
  """
  from tqdm import tqdm

  if hl_workdir is None and infill_workdir is None and stochastic_infill_workdir is None:
    raise ValueError("nothing to evaluate: give an HL and/or an infiller checkpoint")
  if batch_size < 1 or max_scenes < 0:
    raise ValueError(f"batch_size must be >= 1 and max_scenes >= 0, got {batch_size} and {max_scenes}")
  if not 0 <= realism_rollouts <= MAX_REALISM_ROLLOUTS:
    raise ValueError(f"realism_rollouts={realism_rollouts}: must be between 0 and {MAX_REALISM_ROLLOUTS}")
  if repair_rounds < 0:
    raise ValueError(f"repair_rounds must be >= 0, got {repair_rounds}")
  cli.check_seed(seed)
  hl = checkpoint.load_checkpoint(hl_workdir, task="hl") if hl_workdir is not None else None
  if hl is not None:
    hl = checkpoint.with_lane_pull(hl, lane_pull_m)
  elif lane_pull_m is not None:
    raise ValueError("a lane pull is set, but there is no HL checkpoint to sample")
  inf = checkpoint.load_checkpoint(infill_workdir, task="infill") if infill_workdir is not None else None
  sto = None
  if stochastic_infill_workdir is not None:
    sto = checkpoint.load_checkpoint(stochastic_infill_workdir, task="infill")
    if not sto.stochastic:
      raise ValueError(f"{stochastic_infill_workdir}: not a stochastic infiller (train one with "
                       "--config=configs/infill.py:stochastic)")
  infillers = {name: m for name, m in (("infiller", inf), ("stochastic_infiller", sto)) if m is not None}
  data_config = (hl or inf or sto).config.data
  folders = av2_io.map_folders(data)
  if max_scenes:
    folders = folders[:max_scenes]
  skipped: list[dict] = []
  warned: list[dict] = []   # what loading left out of a scene (agents beyond the cap, degenerate map elements)
  cities: dict[int, str] = {}
  written: list[tuple[int, Path]] = []   # (scene index, the AV2 folder of its complete sample)
  write_scenarios = scenarios_dir is not None and hl is not None and "infiller" in infillers
  num_scenes = num_agents = 0

  sizes = (batches.sampler_agent_buckets(data_config), data_config.polygon_buckets)

  def scene_batches():
    """`(indices, batch)`: the split loaded `SORT_WINDOW` batches at a time (a whole AV2 split does not fit in
    memory), bad scenarios skipped, each window cut into batches of one size (`batches.sampler_batches`:
    its first len(indices) scenes are the scenes `indices`, the rest padding). A scene's samples depend on
    its index only."""
    window = []
    for index, folder in enumerate(folders):
      try:
        scene, info = scene_builder.load_scene(folder, data_config.scene)
        window.append((index, scene))
        cities[index] = info.city
        warned.extend({"scenario": folder.name, "warning": w} for w in info.warnings)
      except av2_io.BadScenarioError as e:
        skipped.append({"scenario": folder.name, "file": e.path, "reason": e.reason})
      if len(window) == batch_size * SORT_WINDOW or (index == len(folders) - 1 and window):
        for positions, batch in batches.sampler_batches([s for _, s in window], batch_size, *sizes):
          yield [window[p][0] for p in positions], batch
        window = []

  acc = {"gt": {e: None for e in ENDPOINTS}, "model": {e: None for e in ENDPOINTS}, "guided": {e: None for e in ENDPOINTS}}
  other_map = {"gt": {e: None for e in ENDPOINTS}, "model": {e: None for e in ENDPOINTS}}
  reach = {who: dict.fromkeys(metrics.REACHABILITY_COUNTS, 0) for who in acc}
  negative_speed = {who: {"negative": 0, "tokens": 0} for who in ("model", "guided")}   # returned as 0 by `sample`
  grid_rows: list = []
  errors = {name: {"ade": [], "fde": []} for name in infillers}
  rollouts = realism_rollouts if hl is not None and infillers else 0
  realism_parts: list[dict] = []
  realism_seconds = 0.0
  t0 = time.perf_counter()
  for indices, batch in tqdm(scene_batches(), desc="evaluate", unit="batch", disable=not progress):
    host.drop_compiled_near_map_limit()  # each batch's shapes compile; their programs hold memory maps
    n = len(indices)
    padded = indices + [indices[0]] * (batch.agent_valid.shape[0] - n)   # a key for each scene of the batch
    keys = sampling.keys_at(jax.random.key(seed), padded)
    num_scenes += n
    num_agents += int(batch.agent_valid.sum())
    batch = jax.tree_util.tree_map(jnp.asarray, batch)
    if hl is not None:  # the ground truth's agent count and types; states zeroed
      conditioning = batch.replace(agent_state=jnp.zeros_like(batch.agent_state))
      repairer = infillers.get("infiller")
      maps = repair.encode_batch(hl, conditioning)   # once for every sampler call on the batch
      if repairer is not None:   # the states a user gets: sampled, infilled, the faulty agents resampled
        completed = repair.sample_complete(hl, repairer, conditioning, keys, options, guidance_params,
                                           mode=infilling.mode_id("both"), repair_rounds=repair_rounds, maps=maps)
        out = completed.hl
      else:
        out = repair.sample_states(hl, conditioning, keys, options, guidance_params, maps)
      res = jax.device_get(batch_metrics(out.state, out.heading, batch))
      negative_speed["model"]["negative"] += int(out.negative_speed.sum())
      negative_speed["model"]["tokens"] += 2 * int(out.valid.sum())
      for who in ("gt", "model"):
        for e in ENDPOINTS:
          acc[who][e] = metrics.add(acc[who][e], res[who][e])
      if guided_options is not None:
        guided = repair.sample_states(hl, conditioning, keys, guided_options, guidance_params, maps)
        res = jax.device_get(batch_metrics(guided.state, guided.heading, batch))
        negative_speed["guided"]["negative"] += int(guided.negative_speed.sum())
        negative_speed["guided"]["tokens"] += 2 * int(guided.valid.sum())
        for e in ENDPOINTS:
          acc["guided"][e] = metrics.add(acc["guided"][e], res["model"][e])
      host_batch, host_state = jax.device_get(batch), jax.device_get(out.state)
      host_guided = jax.device_get(guided.state) if guided_options is not None else None
      for i in range(n):
        one = jax.tree_util.tree_map(lambda x: x[i], host_batch)  # noqa: B023
        states = [("gt", one.agent_state), ("model", host_state[i])]
        if host_guided is not None:
          states.append(("guided", host_guided[i]))
        for who, st in states:
          for k, v in metrics.goal_reachability(st, one).items():
            reach[who][k] += v
        if grid_path is not None and indices[i] < grid_scenes:   # the split's first scenes
          grid_rows.append((indices[i], (one, np.stack([one.agent_state[..., :3], host_state[i]]),
                                         f"scene {indices[i]}")))
      if write_scenarios:   # the complete scenarios as a user receives them: AV2 folders
        written += write_complete(batch, completed, [folders[i] for i in indices], [cities[i] for i in indices],
                                  list(indices), Path(scenarios_dir), seed)
      if n > 1:  # the control: every scene's states on the next scene's map
        res = jax.device_get(batch_metrics(out.state, out.heading, with_next_map(batch)))
        for who in other_map:
          for e in ENDPOINTS:
            other_map[who][e] = metrics.add(other_map[who][e], res[who][e])
    draw_keys = sampling.keys_at(jax.random.fold_in(jax.random.key(seed), INFILL_STREAM), padded)
    for name, model in infillers.items():   # a stochastic infiller: one draw per scene and mode
      infill_maps = infilling.encode_maps(model.graphdef, model.params, batch, model.config.data.polygon_buckets)
      err = jax.device_get(infilling.infill_errors(model.graphdef, model.params, batch, infill_maps, draw_keys))
      valid = err["valid"].reshape(-1)
      errors[name]["ade"].append(err["ade"].reshape(len(infilling.MODES), -1)[:, valid])
      errors[name]["fde"].append(err["fde"].reshape(len(infilling.MODES), -1)[:, valid])
    if rollouts:
      t_realism = time.perf_counter()
      realism_parts.append(realism_batch(hl, infillers, batch, indices, seed, rollouts, options, guidance_params,
                                         repair_rounds))
      realism_seconds += time.perf_counter() - t_realism
  if not num_scenes:
    reasons = "; ".join(f"{s['scenario']}: {s['reason']}" for s in skipped[:MAX_SKIPPED_SHOWN])
    raise ValueError(f"{data}: no usable scenario with ground-truth agents ({len(skipped)} skipped: {reasons})")
  if grid_rows:
    from tdiff_jax import viz  # matplotlib only when a picture is asked for
    grid_rows.sort(key=lambda r: r[0])
    viz.plot_comparison_grid([row for _, row in grid_rows], grid_path,
                             ("ground truth", "generated (guided)" if options.costs else "generated (unguided)"))
  result = {"data": str(data), "scenes": num_scenes, "skipped": skipped, "scene_warnings": warned,
            "seconds": round(time.perf_counter() - t0, 1), "agents": num_agents}
  if hl is not None:
    rounds = repair_rounds if "infiller" in infillers else 0
    result["hl_checkpoint"] = {"workdir": str(hl_workdir), "step": hl.record["step"],
                               "sampler": {"method": options.method, "stride": options.stride,
                                           "solver_steps": options.solver_steps,
                                           "solver_max_noise": options.solver_max_noise,
                                           "restarts": options.restarts, "final_cost_steps": options.final_cost_steps,
                                           "repair_rounds": rounds,
                                           "network_calls": options.network_calls(hl.sched.num_steps),
                                           "description": options.describe() + (
                                               f", guided by {'+'.join(options.costs)}" if options.costs else "") + (
                                               f", {rounds} repair rounds" if rounds else ""),
                                           "guidance": list(options.costs),
                                           "lane_pull": dataclasses.asdict(hl.lane_pull) if hl.lane_pull else None},
                               "config": hl.record["config"]}
    rows = {"GT": "gt", "model": "model", **({"guided": "guided"} if guided_options is not None else {})}
    result["table_i"] = {
        conv: {e: {row: metrics.summarize(acc[who][e], None if row == "GT" else acc["gt"][e], conv)
                   for row, who in rows.items()} for e in ENDPOINTS}
        for conv in metrics.CONVENTIONS}
    # Every histogram behind the JSDs (counts on `metrics.HISTOGRAMS` bins), for plots and reuse.
    result["histograms"] = {
        conv: {e: {row: {name: acc[who][e][f"{conv}/hist_{name}"].tolist() for name in metrics.HISTOGRAMS}
                   for row, who in rows.items()} for e in ENDPOINTS}
        for conv in metrics.CONVENTIONS}
    result["histogram_bins"] = {name: {"bins": b, "upper_edge": top} for name, (b, top) in metrics.HISTOGRAMS.items()}
    if guided_options is not None:
      result["hl_checkpoint"]["guided_sampler"] = {
          "description": guided_options.describe(), "guidance": list(guided_options.costs),
          "network_calls": guided_options.network_calls(hl.sched.num_steps)}
    for conv in metrics.CONVENTIONS:
      for e in ENDPOINTS:
        for row, who in rows.items():
          result["table_i"][conv][e][row]["goal_reachable_pct"] = metrics.reachability_pct(reach[who])
    result["goal_reachability"] = {who: reach[who] for who in rows.values()}
    # Sampled speeds below zero (a stopped agent's speed is a magnitude): `sample` returns them as 0.
    result["negative_speeds"] = {who: dict(negative_speed[who], pct=100.0 * negative_speed[who]["negative"]
                                           / max(negative_speed[who]["tokens"], 1))
                                 for who in rows.values() if who != "gt"}
    if other_map["model"]["initial"] is not None:
      result["shuffled_map_control"] = {
          e: {who: {"own_map_offroad_pct": metrics.summarize(acc[who][e], None, "official")["offroad_rate_pct"],
                    "other_map_offroad_pct": metrics.summarize(other_map[who][e], None, "official")["offroad_rate_pct"]}
              for who in ("gt", "model")} for e in ENDPOINTS}
  for name, workdir, suffix in (("infiller", infill_workdir, ""), ("stochastic_infiller", stochastic_infill_workdir,
                                                                   "_stochastic")):
    if name in infillers:
      result["infill_checkpoint" + suffix] = {"workdir": str(workdir), "step": infillers[name].record["step"]}
      ade, fde = np.concatenate(errors[name]["ade"], 1), np.concatenate(errors[name]["fde"], 1)
      result["table_ii" + suffix] = metrics.summarize_displacement_errors(ade, fde, np.ones(ade.shape[1], bool),
                                                                          infilling.MODES)
  if realism_parts:
    result["realism"] = summarize_realism(realism_parts, rollouts, realism_seconds)
  if written:
    t_audit = time.perf_counter()
    result["complete_scenarios"] = audit.audit_generated([f for _, f in written], [folders[i] for i, _ in written],
                                                         data_config.scene)
    result["complete_scenarios"]["seconds"] = round(time.perf_counter() - t_audit, 1)
  return result


def write_complete(batch: datatypes.Scene, completed: repair.CompleteSample, map_folders: list[Path],
                   cities: list[str], indices: list[int], scenarios_dir: Path, seed: int) -> list[tuple[int, Path]]:
  """Each scene's complete sample (`repair.sample_complete`) written as an AV2 scenario folder under
  `scenarios_dir` (`av2_export`, on the map of `map_folders`); returns (scene index, folder) pairs."""
  host_batch = jax.device_get(batch)
  city_xy = datatypes.to_city(host_batch, np.asarray(completed.trajectory, np.float64))
  heading0, valid = np.asarray(completed.hl.heading[..., 0]), np.asarray(completed.hl.valid)
  done = []
  for j, (folder, city, index) in enumerate(zip(map_folders, cities, indices)):
    gen_id = av2_export.generated_scenario_id(folder.name, 0, seed)
    done.append((index, av2_export.write_generated_scenario(scenarios_dir, gen_id, city, av2_io.find_map_file(folder),
                                                            city_xy[j], heading0[j], host_batch.agent_type[j], valid[j])))
  return done


def summarize_realism(parts: list[dict], rollouts: int, seconds: float) -> dict:
  """The realism table from `realism_batch` outputs: per row each feature's and the meta-metric's mean
  over the maps, and every row's and the logged scenarios' pooled histograms (counts on `realism.FEATURES`'
  bins)."""
  rows, histograms = {}, {}
  for row in (r for r in REALISM_ROWS if r in parts[0]):
    ll = {name: tuple(np.concatenate([p[row][0][name][i] for p in parts]) for i in (0, 1))
          for name in realism.FEATURES}
    rows[row] = realism.summarize(realism.scores(ll))
    histograms[row] = {name: np.sum([p[row][1][name] for p in parts], 0).tolist() for name in realism.FEATURES}
  out = {"rollouts_per_map": rollouts, "rows": rows, "histograms": histograms, "seconds": round(seconds, 1),
         "score_seconds": round(float(np.sum([p["score_seconds"] for p in parts])), 1),
         "features": {name: f._asdict() for name, f in realism.FEATURES.items()}}
  if "diversity" in parts[0]:
    total = {k: float(np.sum([p["diversity"][k] for p in parts])) for k in parts[0]["diversity"]}
    out["diversity"] = {"draws": DIVERSITY_DRAWS, "agents": int(total["agents"]),
                        "pairwise_ade_m": total["pairwise_ade_sum"] / max(total["agents"], 1),
                        "fork_agents": int(total["fork_agents"]),
                        "fork_multi_lane_pct": 100.0 * total["fork_multi_lane"] / max(total["fork_agents"], 1),
                        "pinned_goal_error_max_m": float(np.max([p["diversity"]["pinned_goal_error_max"] for p in parts]))}
  return out


def _fmt(x, digits: int = 3) -> str:
  if x is None:
    return "-"
  if isinstance(x, float) and math.isnan(x):
    return "n/a"
  return f"{x:.{digits}f}"


MAX_SKIPPED_SHOWN = 20  # skipped scenarios listed with their reasons in table.md (all of them in table.json)


def to_markdown(result: dict) -> str:
  lines = [f"Evaluation on `{result['data']}`: {result['scenes']} scenes, {result['agents']} ground-truth agents"
           f" ({len(result['skipped'])} scenario(s) skipped)."]
  shown = result["skipped"][:MAX_SKIPPED_SHOWN]
  lines += [f"- skipped `{s['scenario']}`: {s['reason']}" for s in shown]
  if len(result["skipped"]) > len(shown):
    lines += [f"- and {len(result['skipped']) - len(shown)} more (all in table.json)"]
  warned = result.get("scene_warnings", [])
  lines += [f"- `{w['scenario']}`: {w['warning']}" for w in warned[:MAX_SKIPPED_SHOWN]]
  if len(warned) > MAX_SKIPPED_SHOWN:
    lines += [f"- and {len(warned) - MAX_SKIPPED_SHOWN} more warnings (all in table.json)"]
  if "table_i" in result:
    ck = result["hl_checkpoint"]
    lines += ["", f"Table I: high-level scenarios (HL checkpoint step {ck['step']}, {ck['sampler']['description']}, "
              f"{ck['sampler']['network_calls']} network calls, guidance {ck['sampler']['guidance'] or 'none'})."]
    if ck["sampler"].get("lane_pull"):
      lines.append("Lane pull: " + ", ".join(f"{k} {v:g}" for k, v in ck["sampler"]["lane_pull"].items()) + ".")
    if "guided_sampler" in ck:
      g = ck["guided_sampler"]
      lines.append(f"Rows \"guided\": {g['description']}, {g['network_calls']} network calls, guidance "
                   f"{', '.join(g['guidance'])}.")
    for conv in metrics.CONVENTIONS:
      js = "JS distance" if conv == "official" else "JS divergence"
      lines += ["", f"**{conv} convention** ({js}; see `tdiff_jax/metrics.py`)", "",
                "| states | row | Collision (%) | Off-road (%) | Near. edge (m) | Speed | Lat. dev. | Local density | "
                "Near. dist. | Goal reachable (%) |",
                "|---|---|---|---|---|---|---|---|---|---|"]
      for e in ENDPOINTS:
        for who in result["table_i"][conv][e]:
          r = result["table_i"][conv][e][who]
          lines.append(f"| {e} | {who} | {_fmt(r['collision_rate_pct'], 2)} | {_fmt(r['offroad_rate_pct'], 2)} | "
                       f"{_fmt(r['near_edge_m'], 2)} | {_fmt(r['jsd_speed'])} | {_fmt(r['jsd_lateral_deviation'])} | "
                       f"{_fmt(r['jsd_local_density'])} | {_fmt(r['jsd_nearest_distance'])} | "
                       f"{_fmt(r.get('goal_reachable_pct'), 1)} |")
      if conv == "strict":
        outside = {e: result["table_i"][conv][e]["model"]["outside_map"] for e in ENDPOINTS}
        lines.append(f"\nModel road users outside the map crop (excluded from strict off-road): {outside}.")
    reach = result["goal_reachability"]
    lines.append(f"\nGoal reachability over road users ({reach['gt']['pedestrians']} pedestrians excluded): endpoints "
                 f"off every lane: GT {reach['gt']['off_lane']}, model {reach['model']['off_lane']} of "
                 f"{reach['model']['road_users']}.")
    lines += ["", "Road users whose goal is not reachable, by reason (`metrics.goal_reachability`):", "",
              "| row | " + " | ".join(metrics.REACHABILITY_FAILURES) + " | reachable | road users |",
              "|---" * (len(metrics.REACHABILITY_FAILURES) + 3) + "|"]
    for who, counts in reach.items():
      lines.append(f"| {who} | " + " | ".join(str(counts.get(k, 0)) for k in metrics.REACHABILITY_FAILURES)
                   + f" | {counts['reachable']} | {counts['road_users']} |")
    neg = result["negative_speeds"]
    lines.append("\nSampled speeds below zero, returned as 0 (share of sampled states): " + ", ".join(
        f"{who} {n['negative']} of {n['tokens']} ({n['pct']:.1f} %)" for who, n in neg.items()) + ".")
    if "shuffled_map_control" in result:
      c = result["shuffled_map_control"]
      lines += ["", "Shuffled-map control (official off-road %, states scored on their own map / on the next "
                "scene's map):", "", "| states | GT own | GT other | model own | model other |", "|---|---|---|---|---|"]
      for e in ENDPOINTS:
        lines.append(f"| {e} | {_fmt(c[e]['gt']['own_map_offroad_pct'], 1)} | {_fmt(c[e]['gt']['other_map_offroad_pct'], 1)} | "
                     f"{_fmt(c[e]['model']['own_map_offroad_pct'], 1)} | "
                     f"{_fmt(c[e]['model']['other_map_offroad_pct'], 1)} |")
  for suffix, kind in (("", "infiller"), ("_stochastic", "stochastic infiller, one draw")):
    if "table_ii" + suffix in result:
      lines += ["", f"Table II: trajectory infilling ({kind}, checkpoint step "
                f"{result['infill_checkpoint' + suffix]['step']}, ground-truth initial pose and goal given).", "",
                "| hard constraints | ADE (m) | FDE (m) | MR (%) |", "|---|---|---|---|"]
      names = {"both": "initial and goal", "initial": "initial", "goal": "goal", "none": "none"}
      for mode, r in result["table_ii" + suffix].items():
        lines.append(f"| {names[mode]} | {_fmt(r['ade_m'], 2)} | {_fmt(r['fde_m'], 2)} | {_fmt(r['miss_rate_pct'], 2)} |")
  if "realism" in result:
    lines += realism_markdown(result["realism"])
  if "complete_scenarios" in result:
    c = result["complete_scenarios"]
    lines += ["", "Complete scenarios as written (each scene's sample infilled with both ends pinned, `scenarios/` read "
              "back with av2's loader, `tdiff_jax.audit`): agents whose box overlaps another's at some step of the 6 s, "
              "road users whose centre leaves the drivable area at some step.", "",
              "| scenarios | agents | overlap (%) | road users | off-road (%) |", "|---|---|---|---|---|"]
    for who in ("generated", "logged"):
      r = c[who]
      lines.append(f"| {who} ({r['scenarios']}) | {r['agents']} | {_fmt(r['overlap_pct'], 1)} | {r['road_users']} | "
                   f"{_fmt(r['offroad_pct'], 1)} |")
  return "\n".join(lines) + "\n"


REALISM_COLUMNS = {"linear_speed": "Speed", "linear_acceleration": "Accel.", "angular_speed": "Ang. speed",
                   "angular_acceleration": "Ang. accel.", "distance_to_nearest_object": "Nearest obj.",
                   "collision": "Collision", "time_to_collision": "TTC", "distance_to_road_edge": "Road edge",
                   "offroad": "Off-road"}


def realism_markdown(r: dict) -> list[str]:
  """The realism table's Markdown lines."""
  lines = ["", f"Realism of complete scenarios (sim-agents meta-metric, `tdiff_jax/realism.py`): the logged "
           f"scenario of each map scored under {r['rollouts_per_map']} generated scenarios' feature histograms; "
           "means over the maps (higher is better, 1 at most).", "",
           "| row | meta | " + " | ".join(REALISM_COLUMNS.values()) + " |", "|---" * (len(REALISM_COLUMNS) + 2) + "|"]
  for row, v in r["rows"].items():
    label = REALISM_ROWS[row]
    lines.append(f"| {label} | **{_fmt(v['meta'])}** | " + " | ".join(_fmt(v[k]) for k in REALISM_COLUMNS) + " |")
  lines.append("\nAV2 has no traffic-light states: the traffic-light violation term (weight 0.05) is left out and the "
               "other weights renormalised; boxes are per-type sizes (AV2 has none). The constant-velocity and infiller "
               "rows have one trajectory set per map, counted as many times as the rollouts.")
  if "diversity" in r:
    d = r["diversity"]
    lines.append(f"\nStochastic infiller, {d['draws']} draws for each map's first HL scenario ({d['agents']} agents): "
                 f"mean pairwise ADE {d['pairwise_ade_m']:.2f} m; agents at a fork (two or more successor lanes) whose "
                 f"draws take more than one lane at the midpoint: {d['fork_multi_lane_pct']:.1f} % of "
                 f"{d['fork_agents']}; largest distance of a draw's end from its pinned goal "
                 f"{d['pinned_goal_error_max_m']:.1e} m.")
  return lines


def write_pictures_and_report(result: dict, markdown: str, out: Path, grid: Path | None) -> Path:
  """The distribution plots and rates.png (with Table I) and report.html in `out`; returns the report."""
  from tdiff_jax import report, viz  # matplotlib only when pictures are asked for

  rates, dists = None, []
  if "table_i" in result:
    rates = viz.rate_figure(result, out / "rates.png")
    dists = viz.distribution_figures(result, out)
  realism_png = None
  if "realism" in result:
    realism_png = viz.realism_figure(result["realism"], out / "realism.png")
  return report.write_report(out / "report.html", result, markdown, rates, dists,
                             grid if grid is not None and grid.exists() else None, realism_png)


RESULT = "table.json"


def define_flags(values: flags.FlagValues) -> None:
  flags.DEFINE_string("hl_workdir", "workdirs/hl", "HL training workdir or exported model; the pretrained model "
                      "when workdirs/hl has no checkpoint ('' to skip Table I)", flag_values=values)
  flags.DEFINE_string("infill_workdir", "workdirs/infill", "infiller training workdir or exported model; the "
                      "pretrained infiller when workdirs/infill has no checkpoint ('' to skip Table II)",
                      flag_values=values)
  flags.DEFINE_string("stochastic_infill_workdir", "", "a generative infiller's workdir "
                      "(--config=configs/infill.py:stochastic): its Table II, realism rows and diversity",
                      flag_values=values)
  flags.DEFINE_string("data", None, "folder of AV2 scenario folders, or an AV2 root (its val split); default: the "
                      "validation split of the HL workdir's training data (its synthetic worlds, its data.dir, or "
                      "the source of its data.cache_dir)", flag_values=values)
  flags.DEFINE_string("out", None, "output folder (default <hl or infill workdir>/eval)", flag_values=values)
  flags.DEFINE_integer("batch_size", 8, "scenarios per sampler call", lower_bound=1, flag_values=values)
  flags.DEFINE_integer("max_scenes", 0, "use at most this many scenarios (0: all)", lower_bound=0, flag_values=values)
  cli.define_seed_flag(values)
  sampler_flags.define_sampler_flags(values)
  cli.define_compilation_cache_flag(values)
  flags.DEFINE_integer("grid", 4, "draw this many scenes' ground truth and samples side by side to <out>/grid.png "
                       "(0: none)", lower_bound=0, flag_values=values)
  flags.DEFINE_list("guided_row", [], "also sample with these guidance costs (e.g. boxes,lane,offroad) and add a "
                    "'guided' row to Table I and the charts", flag_values=values)
  flags.DEFINE_integer("realism_rollouts", 16, "generated scenarios per map for the realism score of complete "
                       f"scenarios (needs an HL model and an infiller; 0: none; at most {MAX_REALISM_ROLLOUTS})",
                       lower_bound=0, upper_bound=MAX_REALISM_ROLLOUTS, flag_values=values)
  flags.DEFINE_boolean("overwrite", False, "replace the results of an earlier run in --out (without it, an --out "
                       "that holds them is refused)", flag_values=values)
  flags.DEFINE_boolean("report", True, "write the distribution plots, rates.png and report.html (--noreport: only "
                       "the tables)", flag_values=values)


def run(f: flags.FlagValues, args: list[str]) -> None:
  cli.no_arguments(args)
  checkpoint.quiet_orbax_logging()
  cli.use_compilation_cache(f.compilation_cache)
  base = files.user_path(f.hl_workdir or f.infill_workdir or ".")   # where outputs and default data go
  out = files.user_path(f.out) if f.out else base / "eval"
  try:
    stochastic = files.user_path(f.stochastic_infill_workdir) if f.stochastic_infill_workdir else None
    inputs = [files.user_path(f.data) if f.data else None, f.hl_workdir or None, f.infill_workdir or None, stochastic]
    files.check_output_folder(out, f.overwrite, inputs)   # before any work
    # Models: the workdirs', else (at the default locations) the pretrained ones shipped with the package.
    hl_workdir = sampler_flags.model_dir(f, "hl_workdir", "hl")
    infill_workdir = sampler_flags.model_dir(f, "infill_workdir", "infill")
    data = files.user_path(f.data) if f.data else checkpoint.validation_maps(base, hl_workdir or infill_workdir)
    inputs[0] = data
    num_steps = sampler_flags.diffusion_steps(hl_workdir) if hl_workdir else 500
    options = sampler_flags.sampler_options(f, num_steps=num_steps)
    guided = sampler_flags.sampler_options(f, costs=f.guided_row, num_steps=num_steps) if f.guided_row else None
    with files.output_folder(out, f.overwrite, "evaluate", inputs) as staging:   # the folder whole, or not at all
      grid = staging / "grid.png" if f.grid and hl_workdir else None
      result = evaluate(hl_workdir, data, infill_workdir, f.batch_size, f.seed, f.max_scenes, options,
                        grid_path=grid, grid_scenes=f.grid, guided_options=guided,
                        guidance_params=sampler_flags.guidance_params(f),
                        lane_pull_m=f.lane_pull_m, realism_rollouts=f.realism_rollouts,
                        stochastic_infill_workdir=stochastic, scenarios_dir=staging / "scenarios",
                        repair_rounds=f.repair_rounds)
      md = to_markdown(result)
      if f.report:
        write_pictures_and_report(result, md, staging, grid)
      files.atomic_write_text(staging / "table.md", md)
      files.atomic_write_text(staging / RESULT, files.json_text(result, indent=1))
  except (OSError, ValueError) as e:  # OSError: missing files, a full disk, a read-only folder
    raise SystemExit(f"evaluate: {e}") from None
  sys.stdout.write(md)


main = cli.entry_point(define_flags, run)


if __name__ == "__main__":
  main()
