"""Config of the high-level (HL) scenario generator: `python train.py --config=configs/hl.py[:VARIANT]`.

Variants:
  default  the embedded synthetic AV2 worlds, a small model that trains on a 2-core CPU in minutes;
  av2      the paper's settings for a real AV2 root: --config=configs/hl.py:av2 --config.data.dir=/path/to/av2
           (folders train/ and val/ of scenario folders);
  av2_grounded  the paper's model size and training on a real AV2 root, with the grounded denoiser and
           training recipe of the default (docs/training.md);
  paper    the default's size and data with the paper's denoiser and recipe (the ablation baseline);
  tiny     a very small model and dataset, for tests.
Override any field on the command line, e.g. --config.train.batch_size=8; a misspelt field is an error.
"""

import ml_collections



VARIANTS = ("default", "paper", "av2", "av2_grounded", "tiny")
# The denoiser and recipe that learn the map (`models.grounded_denoiser`, docs/training.md); the paper's are
# the fields' defaults.
GROUNDED_MODEL = dict(denoiser="grounded", grounded_neighbors=16)
# The lane pull on the grounded denoiser's estimate (`lane_pull.LanePull`; docs/research_log.md).
GROUNDED_LANE_PULL = dict(across_m=3.5, clearance_m=2.0, end_m=10.0, route_m=9.0, still_m=3.5)


def get_config(arg: str | None = None) -> ml_collections.ConfigDict:
  variant = arg or "default"
  if variant not in VARIANTS:
    raise ValueError(f"configs/hl.py: unknown variant {variant!r}; choose one of {', '.join(VARIANTS)}")
  c = ml_collections.ConfigDict()
  c.task = "hl"
  c.seed = 0

  c.data = ml_collections.ConfigDict()
  # The scene contract's caps (the rest of it: `tdiff_jax.data.config.default_data_config`). A = 64 and
  # P = 256 cover the real AV2 samples (at most 33 kept agents, 150 polygons) with room.
  c.data.scene = ml_collections.ConfigDict(dict(max_agents=64, max_polygons=256))
  c.data.dir = ""        # AV2 root to preprocess; "" and no cache_dir: synthetic worlds
  c.data.cache_dir = ""  # a built cache (default <workdir>/cache)
  c.data.synthetic_num = 600
  # Training batches hold scenes of similar size, padded to the smallest bucket that fits (one compile
  # per bucket pair), so little compute goes to padding.
  c.data.agent_buckets = (8, 16, 32, 64)
  c.data.polygon_buckets = (64, 96, 128, 192, 256)
  # The sampler's batches (`batches.sampler_batches` in sample.py and evaluate): finer agent buckets than
  # training's, since a sampler call compiles in seconds and a train step in a minute; a 33-agent scene
  # samples at 40 agent slots, not 64 (docs/sampling.md).
  c.data.sampler_agent_buckets = (4, 8, 12, 16, 24, 32, 40, 48, 64)

  # The paper's model: its denoiser, 128 wide, 3 layers, 8 heads, 64 Fourier bands, 16 latents (and, fixed,
  # 1 map layer and polygon pairs within 150 m). fourier_tables: the map encoder's slowly varying Fourier
  # embeddings interpolated from this many values per input (0: exact; docs/research_log.md).
  c.model = ml_collections.ConfigDict(dict(
      denoiser="paper", dim=128, heads=8, num_layers=3, num_freq_bands=64, num_latents=16, dropout=0.1,
      pl2pl_neighbors=0, fourier_tables=2048))

  # The lane pull on the grounded denoiser's position estimate, in training and sampling (parameter-free, a
  # setting of the call: `lane_pull.LanePull`): moving road users' estimates at most across_m across a lane
  # their heading agrees with go onto it, not where two agents would end nearer than clearance_m, back onto
  # a lane's end from at most end_m past it, goals onto lanes their initial lane leads to within 6 s from at
  # most route_m across; at sampling only, still road users' estimates to at most still_m from their
  # nearest lane (0: off).
  c.lane_pull = ml_collections.ConfigDict(dict(across_m=0.0, clearance_m=0.0, end_m=0.0, route_m=0.0, still_m=0.0))

  c.diffusion = ml_collections.ConfigDict(dict(num_steps=500))  # the paper's linear betas, 1e-4 to 0.05

  c.train = ml_collections.ConfigDict(dict(
      batch_size=32, num_steps=100_000, lr=1e-3, warmup_steps=1000, min_lr_ratio=1e-4, weight_decay=1e-4,
      grad_clip=1.0, ema_decay=0.999, entropy_weight=0.1, self_only_prob=0.5,
      # noise_draws: each scene's map encoded once per step and its state noised this many times (the
      # denoiser sees batch_size x noise_draws samples); 1 as the paper.
      noise_draws=1,
      # The map encoder's input side keeps its initial weights (the point and polygon input embeddings, the
      # point -> polygon relations and attention, the polygon -> polygon relation embedding: most of its
      # backward pass); its polygon -> polygon attention and map summary train (docs/research_log.md).
      freeze_map_inputs=False,
      # CPU devices of a one-process run (train.py): the CPU split into this many JAX devices, the batch
      # sharded over them, each core running its share of every step; 0: one per core (as many as divide the
      # batch); the default's small step is faster split, the paper-size step on one device
      # (docs/research_log.md). Accelerators ignore it.
      cpu_devices=1,
      # Every eval_every steps and at the end: the validation losses (of the first 50 batches at most) and
      # a checkpoint (the newest three kept).
      log_every=100, eval_every=2000))

  if variant in ("default", "paper"):
    # Exact Fourier embeddings: the small encoder's time goes to its metric point positions, which are not
    # tabulated (periods from 1 m), so tables measured no faster (docs/benchmarks.md).
    c.model.update(dict(dim=64, heads=4, num_layers=2, num_freq_bands=16, pl2pl_neighbors=16, fourier_tables=0))
    c.train.update(dict(batch_size=16, num_steps=700, lr=2e-3, warmup_steps=50, min_lr_ratio=0.05,
                        ema_decay=0.99, log_every=25, eval_every=200))
  if variant in ("default", "av2_grounded"):
    c.model.update(GROUNDED_MODEL)
    c.lane_pull.update(GROUNDED_LANE_PULL)
  if variant == "default":
    # What trains best in about 10 minutes on a 2-core CPU (docs/research_log.md): no dropout, two noise
    # draws per encoded map at batch 8, the map encoder's input side and polygon relations frozen at their
    # initial weights (computed once per scene), one JAX device per CPU core, 2600 steps.
    c.model.dropout = 0.0
    c.train.update(dict(batch_size=8, noise_draws=2, freeze_map_inputs=True, cpu_devices=0, num_steps=2600,
                        eval_every=400))
  elif variant == "tiny":
    c.data.synthetic_num = 40
    c.data.scene.max_agents = 32
    c.data.scene.max_polygons = 128
    c.data.agent_buckets = (32,)
    c.data.sampler_agent_buckets = (32,)
    c.data.polygon_buckets = (128,)
    c.model.update(dict(dim=32, heads=2, num_layers=1, num_freq_bands=4, num_latents=4, dropout=0.0,
                        pl2pl_neighbors=8, fourier_tables=0, **dict(GROUNDED_MODEL, grounded_neighbors=8)))
    c.diffusion.num_steps = 50
    c.train.update(dict(batch_size=4, num_steps=6, lr=3e-3, warmup_steps=2, log_every=2, eval_every=3,
                        ema_decay=0.9))
  return c
