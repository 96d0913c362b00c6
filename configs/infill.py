"""Config of the trajectory infiller: `python train.py --config=configs/infill.py[:VARIANT]`.

Same data pipeline, trainer, checkpoints and resume as `configs/hl.py`; writes to workdirs/infill.
Variants:
  default  the embedded synthetic AV2 worlds, a small model that trains on a 2-core CPU in minutes;
  av2      the official settings for a real AV2 root: --config=configs/infill.py:av2 --config.data.dir=/path/to/av2;
  stochastic  the default with the generative infiller (beyond the paper: trajectories drawn from a flow,
           `tdiff_jax/infilling.py`); train it with --workdir=workdirs/infill_stochastic;
  tiny     a very small model and dataset, for tests.
Override any field on the command line, e.g. --config.train.batch_size=8; a misspelt field is an error.
"""

import ml_collections

from configs import hl


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
  variant = arg or "default"
  if variant not in ("default", "av2", "stochastic", "tiny"):
    raise ValueError(f"configs/infill.py: unknown variant {variant!r}; choose default, av2, stochastic or tiny")
  c = hl.get_config("default" if variant == "stochastic" else variant)  # the same data settings and caches
  c.task = "infill"
  del c["diffusion"]

  # The official infiller: 128 wide, 8 heads, 2 attention layers per stage, a 2-layer temporal
  # transformer with FFN width 128, 1 map layer, radii 150 m.
  c.model = ml_collections.ConfigDict(dict(
      dim=128, heads=8, num_layers=2, temporal_layers=2, temporal_ff=128, map_layers=1, num_freq_bands=64,
      dropout=0.1, pl2pl_radius_m=150.0, pl2pl_neighbors=0, pl2a_radius_m=150.0, pl2a_neighbors=0,
      a2a_radius_m=150.0,
      # The relation embeddings interpolated from tables of this many values per input (0: exact; configs/hl.py).
      fourier_tables=2048,
      # > 0: the generative infiller, a flow from noise of this scale (m); 0: the paper's deterministic one.
      flow_noise_m=0.0))

  t = c.train
  del t["entropy_weight"], t["self_only_prob"]
  t.smoothness_weight = 0.5
  t.lr = 1e-4 if variant == "av2" else t.lr  # the official README's infill learning rate
  t.freeze_map_inputs = False

  if variant in ("default", "stochastic"):
    # Coarser buckets than the HL default: fewer shapes to compile on a CPU.
    c.data.agent_buckets = (32, 64)
    c.data.polygon_buckets = (96, 128, 256)
    c.model.update(dict(dim=64, heads=4, num_layers=1, num_freq_bands=8, pl2pl_neighbors=16, pl2a_neighbors=32,
                        fourier_tables=0))
    # One JAX device per core (train.py on a CPU): 0.94 to 1.03 against 0.78 to 0.88 logged steps/s on
    # one device, 200 steps each on a 2-core CPU.
    t.update(dict(batch_size=8, num_steps=500, lr=2e-3, warmup_steps=50, min_lr_ratio=0.05, ema_decay=0.99,
                  log_every=25, eval_every=250))
  if variant == "stochastic":
    c.model.flow_noise_m = 3.0
  elif variant == "tiny":
    c.model.update(dict(dim=32, heads=2, num_layers=1, temporal_layers=1, temporal_ff=32, num_freq_bands=4,
                        dropout=0.0, pl2pl_neighbors=8, pl2a_neighbors=16, fourier_tables=0))
  return c
