"""`python sample.py` / `generate`: outputs, failed maps reported, agent plans, no-checkpoint message."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from configs import hl as hl_config
from conftest import DATA, REAL_50
from tdiff_jax import generate, sampling
from tdiff_jax.data import synthetic
from tdiff_jax.train import trainer

ROOT = Path(__file__).resolve().parent.parent
FAST = sampling.SamplerOptions(method="ddim", stride=10)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
  workdir = tmp_path_factory.mktemp("hl_tiny")
  config = hl_config.get_config("tiny")
  config.train.num_steps = 3
  trainer.train_and_evaluate(config, workdir)
  return workdir


@pytest.fixture(scope="module")
def maps(trained, tmp_path_factory) -> Path:
  folder = tmp_path_factory.mktemp("maps")
  for sc in sorted((trained / "synthetic" / "val").iterdir())[:2]:
    shutil.copytree(sc, folder / sc.name)
  shutil.copytree(DATA / REAL_50, folder / REAL_50)   # a real test-split map: no goal step, still a map
  broken = synthetic.write_scenario(synthetic.generate_scenario(9, 0), folder)
  next(broken.glob("*.json")).write_text("{")
  return folder


def test_generate_writes_samples_pictures_and_summary(trained, maps, tmp_path):
  summary = generate.generate(trained, maps, tmp_path, num_per_map=2, options=FAST, progress=False)
  assert summary["maps_sampled"] == 3 and summary["samples"] == 6
  assert len(summary["failed_maps"]) == 1 and "broken map JSON" in summary["failed_maps"][0]["reason"]
  z = np.load(tmp_path / "samples.npz")
  assert z["state"].shape[0] == 6 and z["state"].shape[2:] == (2, 3)
  assert (z["valid"].sum(-1) >= 1).all() and np.isfinite(z["state"]).all()
  assert len(list(tmp_path.glob("*.png"))) == 6
  assert json.loads((tmp_path / "summary.json").read_text())["samples"] == 6


def test_agent_count_choices(trained, maps, tmp_path):
  fixed = generate.generate(trained, maps, tmp_path / "a", num_agents=3, options=FAST, pictures=False, progress=False)
  z = np.load(tmp_path / "a" / "samples.npz")
  assert (z["valid"].sum(-1) == 3).all() and fixed["samples"] == 3
  gt = generate.generate(trained, maps, tmp_path / "b", num_agents=-1, options=FAST, pictures=False, progress=False)
  reasons = " ".join(f["reason"] for f in gt["failed_maps"])
  assert gt["samples"] == 2 and "no goal step" in reasons  # ground truth needs agents


def test_missing_checkpoint_says_how_to_train(tmp_path):
  with pytest.raises(FileNotFoundError, match="train one first"):
    generate.generate(tmp_path / "nothing", tmp_path, tmp_path / "out")
  done = subprocess.run([sys.executable, "sample.py", f"--workdir={tmp_path / 'nothing'}"], capture_output=True,
                        text=True, timeout=300, cwd=ROOT)
  assert done.returncode != 0 and "python train.py --config=configs/hl.py" in done.stderr
