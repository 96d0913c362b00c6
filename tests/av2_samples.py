"""The real AV2 samples of tests/data (see its NOTICE.md) and a dataset root mixing them with synthetic
and deliberately broken scenarios; imported by the tests as `tests.av2_samples`."""

from __future__ import annotations

from pathlib import Path

DATA = Path(__file__).parent / "data"
# Real AV2 scenarios with all 110 steps, and the test-split one with only the 50 observed steps.
REAL_110 = ["00a0ec58-1fb9-4a2b-bfd7-f4e5da7a9eff", "0a0a2bb7-c4f4-44cd-958a-9ee15cb34aca",
            "0a1e6f0a-1817-4a98-b02e-db8c9327d151"]
REAL_50 = "0a0af725-fbc3-41de-b969-3be718f694e2"


def _copy_scenario(src: Path, dst_root: Path) -> Path:
  import shutil
  dst = dst_root / src.name
  shutil.copytree(src, dst)
  return dst


def make_mixed_dataset(root: Path) -> dict[str, str]:
  """A dataset root with real, synthetic and broken scenarios. Returns {folder name: expected reason}."""
  import math

  from tdiff_jax.data import synthetic

  train, val = root / "train", root / "val"
  train.mkdir(parents=True)
  val.mkdir(parents=True)
  for sid in REAL_110[:2] + [REAL_50]:
    _copy_scenario(DATA / sid, train)
  _copy_scenario(DATA / REAL_110[2], val)
  for i in range(4):
    synthetic.write_scenario(synthetic.generate_scenario(5, i), train)
  for i in range(4, 6):
    synthetic.write_scenario(synthetic.generate_scenario(5, i), val)
  bad = {REAL_50: "no goal step"}

  def broken(index: int) -> Path:
    return synthetic.write_scenario(synthetic.generate_scenario(5, index), train)

  f = broken(10)  # truncated parquet
  pq = next(f.glob("*.parquet"))
  pq.write_bytes(pq.read_bytes()[: pq.stat().st_size // 2])
  bad[f.name] = "unreadable scenario parquet"
  f = broken(11)  # missing map
  next(f.glob("*.json")).unlink()
  bad[f.name] = "missing map"
  f = broken(12)  # broken map JSON
  next(f.glob("*.json")).write_text('{"lane_segments": {')
  bad[f.name] = "broken map JSON"
  sc = synthetic.generate_scenario(5, 13)  # NaN in the AV's state at step 50
  av = next(t for t in sc.scenario.tracks if t.track_id == "AV")
  av.object_states[50].position = (math.nan, av.object_states[50].position[1])
  f = synthetic.write_scenario(sc, train)
  bad[f.name] = "NaN"
  sc = synthetic.generate_scenario(5, 14)  # no agent that could be kept
  sc.scenario.tracks[:] = [t for t in sc.scenario.tracks if t.object_type.value in ("static", "background", "construction")
                           or t.track_id == "AV"]
  for t in sc.scenario.tracks:
    t.object_states[:] = [s for s in t.object_states if s.timestep < 100] if t.track_id == "AV" else t.object_states
  f = synthetic.write_scenario(sc, train)
  bad[f.name] = "no agents kept"
  return bad


