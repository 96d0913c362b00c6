"""How XLA compiles the samplers' and the infiller's matrix products on a CPU: its own kernels, not YNNPACK's.

XLA's CPU compiler (jaxlib 0.10) hands each matrix product to the YNNPACK library by default
(`xla_cpu_experimental_ynn_fusion_type`, "individual dot" fusions). A sampler's products are small (a
denoiser step of an 8-agent scene multiplies 16 x 128 activations by 128 x 512 weights) and their
weights are arguments of the call, not constants, so the library repacks every weight matrix on every
call: one profiled DDIM step of the paper's denoiser (8 agents, 96 polygons, AMD EPYC) spent 4.3 ms in
its operations with the library and 2.0 ms with XLA's own kernels. `COMPILER_OPTIONS` turns the
library's fusions off for the functions compiled with it, `jax.jit(..., compiler_options=COMPILER_OPTIONS)`:
`sampling.sample` (every sampler, guided or not) and `infill.infill` / `infill.infill_errors`. The
map encodings and the train steps, whose products are large (thousands of map points or pairs), keep
XLA's default, which measured as fast or faster for them (README, Benchmarks). Called inside a caller's
`jax.jit`, these functions are compiled with the caller's options. The option only changes CPU
compilation.

`TDIFF_JAX_YNN_PRODUCTS=1` in the environment, read at import, keeps XLA's default everywhere: for
measuring the difference (`benchmarks/*.py`), or should a later jaxlib's library be the faster. Results
differ from the default's by float rounding only (products summed in another order; tested), which a
sampler amplifies as it amplifies any rounding (README, Benchmarks).
"""

from __future__ import annotations

import os

SWITCH = "TDIFF_JAX_YNN_PRODUCTS"   # "1": XLA's default (YNNPACK's products)

# No library fusion types: products and elementwise operations through XLA's own emitters (a `jax.jit`
# option is parsed as XLA parses the flag of the same name).
COMPILER_OPTIONS: dict[str, str] | None = (
    None if os.environ.get(SWITCH, "0") == "1" else {"xla_cpu_experimental_ynn_fusion_type": ""})
