"""Generate traffic scenarios from trained checkpoints.

  python sample.py                        # latest checkpoint of workdirs/hl, the synthetic validation maps
  python sample.py --hl_workdir=DIR --maps=AV2_FOLDER --num_per_map=4 --guidance=clearance,lane --out=DIR
  python sample.py --spec=specs/unprotected_left_turn.yaml   # every sample an unprotected left turn

The HL model samples initial and goal states; every sample is then infilled (--infill_mode) and also
written as an AV2 scenario folder under <out>/scenarios; with --animate, also as an animated GIF (agents
moving along their trajectories; `python -m tdiff_jax.animate` does the same for ground-truth folders). Writes
samples.npz, one picture per sample and summary.json to --out (default <workdir>/samples).

A workdir at its default location (workdirs/hl, workdirs/infill) without a checkpoint: the pretrained
model of the default recipe shipped with the package is used, so this runs before any training.
--infill_workdir='' writes the high-level scenarios only. With a stochastic infiller
(--config=configs/infill.py:stochastic), --trajectories_per_sample=K draws K trajectory sets per scenario.
"""

from absl import app, flags

from tdiff_jax import checkpoint, cli, files, generate, infilling, sampler_flags
from tdiff_jax import spec as spec_lib

_HL_WORKDIR = flags.DEFINE_string("hl_workdir", "workdirs/hl", "HL training workdir whose latest checkpoint is used "
                                  "(or an exported model); the pretrained model when workdirs/hl has none")
_MAPS = flags.DEFINE_string("maps", None, "folder of AV2 scenario folders (default: <hl_workdir>/synthetic/val)")
_OUT = flags.DEFINE_string("out", None, "output folder (default: <hl_workdir>/samples)")
_NUM_PER_MAP = flags.DEFINE_integer("num_per_map", 1, "scenarios per map", lower_bound=1)
_NUM_AGENTS = flags.DEFINE_integer("num_agents", 0, "agents per scenario; 0: from training statistics; "
                                   "-1: ground truth", lower_bound=-1)
sampler_flags.define_sampler_flags(flags.FLAGS)  # --method, --steps, --guidance, ...
cli.define_seed_flag(flags.FLAGS)
cli.define_compilation_cache_flag(flags.FLAGS)
_BATCH = flags.DEFINE_integer("batch_size", 8, "scenarios per sampler call", lower_bound=1)
_OVERWRITE = flags.DEFINE_boolean("overwrite", False, "replace the results of an earlier run in --out (without it, "
                                  "an --out that holds them is refused)")
_INFILL_WORKDIR = flags.DEFINE_string("infill_workdir", "workdirs/infill",
                                      "infiller training workdir (or an exported model); the pretrained infiller "
                                      "when workdirs/infill has none; '': HL only")
_ANIMATE = flags.DEFINE_boolean("animate", False, "also write <id>_<k>.gif per sample: its infilled trajectories "
                                 "animated over the 6 s (needs an infiller checkpoint)")
_SPEC = flags.DEFINE_string("spec", None, "a scenario spec (YAML or JSON, e.g. specs/unprotected_left_turn.yaml): "
                            "every sample places its agents, is guided and redrawn towards it, and is checked "
                            "against it (docs/specs.md)")
_INFILL_MODE = flags.DEFINE_enum("infill_mode", "both", list(infilling.MODES),
                                 "hard constraints of the infiller: both ends, initial only, goal only, none")
_DRAWS = flags.DEFINE_integer("trajectories_per_sample", 1, "trajectory draws per high-level scenario (> 1 needs "
                              "a stochastic infiller, --config=configs/infill.py:stochastic; at most "
                              f"{generate.MAX_TRAJECTORIES_PER_SAMPLE})", lower_bound=1,
                              upper_bound=generate.MAX_TRAJECTORIES_PER_SAMPLE)


def main(argv):
  if len(argv) > 1:
    raise app.UsageError(f"unexpected arguments: {argv[1:]}")
  checkpoint.quiet_orbax_logging()
  cli.use_compilation_cache(flags.FLAGS.compilation_cache)
  if not _HL_WORKDIR.value:
    raise app.UsageError("--hl_workdir must name a workdir")
  if _ANIMATE.value and not _INFILL_WORKDIR.value:
    raise SystemExit("sample.py: --animate needs infilled trajectories: give --infill_workdir")
  workdir = files.user_path(_HL_WORKDIR.value)   # where outputs and default maps go
  out = files.user_path(_OUT.value) if _OUT.value else workdir / "samples"
  try:
    spec = spec_lib.load(files.user_path(_SPEC.value)) if _SPEC.value else None   # a bad spec stops here
    # Models: the workdirs', else (at the default locations) the pretrained ones shipped with the package.
    hl_model = sampler_flags.model_dir(flags.FLAGS, "hl_workdir", "hl")
    infill_model = sampler_flags.model_dir(flags.FLAGS, "infill_workdir", "infill")
    maps = files.user_path(_MAPS.value) if _MAPS.value else checkpoint.validation_maps(workdir, hl_model)
    summary = generate.generate(hl_model, maps, out, _NUM_PER_MAP.value, _NUM_AGENTS.value,
                                sampler_flags.sampler_options(flags.FLAGS,
                                                              num_steps=sampler_flags.diffusion_steps(hl_model)),
                                sampler_flags.guidance_params(flags.FLAGS), flags.FLAGS.seed, _BATCH.value,
                                infill_workdir=infill_model, infill_mode=_INFILL_MODE.value, animate=_ANIMATE.value,
                                lane_pull_m=flags.FLAGS.lane_pull_m, trajectories_per_sample=_DRAWS.value,
                                overwrite=_OVERWRITE.value, repair_rounds=flags.FLAGS.repair_rounds, spec=spec)
  except (OSError, ValueError) as e:  # OSError: missing files, a full disk, a read-only folder
    raise SystemExit(f"sample.py: {e}") from None
  print(files.json_text(summary))


if __name__ == "__main__":
  app.run(main)
