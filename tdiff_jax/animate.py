"""Animated GIFs of AV2 scenario folders: ground truth, or scenarios `sample.py` wrote.

  python -m tdiff_jax.animate --out=DIR SCENARIO_FOLDER [SCENARIO_FOLDER ...]

Each folder becomes `<DIR>/<scenario_id>.gif` (`<scenario_id>-2.gif` for a second folder of that id or where
that file exists already: nothing is overwritten): the
scene's kept agents (`data.scene.load_scene`)
moving as boxes of their type's size along their observed positions from AV2 step 50 to 109 (the 6 s
the HL model and the infiller generate), over the map. Point it at a real scenario and at the
scenarios `sample.py --animate` generated on the same map to compare them side by side.
"""

from __future__ import annotations

import sys
from pathlib import Path

from absl import app, flags

from tdiff_jax import cli, files, viz
from tdiff_jax.data import av2_io, scene_builder



def animate_folder(folder: Path, out_dir: Path, frame_stride: int = 2, used: set[str] | None = None) -> Path:
  """One scenario folder -> `<out_dir>/<scenario_id>.gif` (the id made a safe file name, `files.safe_name`;
  `<scenario_id>-2.gif`, ... when the name is in `used`, the names taken already, or a file of that name
  exists: nothing is overwritten). Raises `av2_io.BadScenarioError`."""
  scene, info = scene_builder.load_scene(folder)
  used = used if used is not None else set()
  used.update(p.stem for p in out_dir.glob("*.gif"))   # never replace a file already there
  path = out_dir / f"{files.unique_name(files.safe_name(info.scenario_id), used)}.gif"
  viz.animate_scenario(scene, scene.agent_future, scene.agent_future_valid, scene.agent_valid, scene.agent_type,
                       scene.agent_state[:, 0, 3], path, f"{info.scenario_id} (AV2 steps 50 to 109)",
                       frame_stride=frame_stride)
  return path


def define_flags(values: flags.FlagValues) -> None:
  flags.DEFINE_string("out", ".", "output folder", flag_values=values)
  flags.DEFINE_integer("frame_stride", 2, "draw every n-th 0.1 s step", lower_bound=1, flag_values=values)


def run(f: flags.FlagValues, args: list[str]) -> None:
  folders = [files.user_path(a) for a in args]
  if not folders:
    raise app.UsageError("give one or more scenario folders")
  out = files.user_path(f.out)
  out.mkdir(parents=True, exist_ok=True)
  failed, used = 0, set()
  for folder in folders:
    try:
      print(animate_folder(folder, out, f.frame_stride, used))
    except av2_io.BadScenarioError as e:
      failed += 1
      print(f"animate: skipped {folder}: {e}", file=sys.stderr)
    except OSError as e:
      raise SystemExit(f"animate: {e}") from None
  if failed == len(folders):
    raise SystemExit(f"animate: none of the {len(folders)} folder(s) could be animated")


main = cli.entry_point(define_flags, run)


if __name__ == "__main__":
  main()
