"""Compile and run times of the value state with near points on this machine's accelerator
(twenty-first session: the first GPU attempt did not compile in 380 s)."""

import dataclasses
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from omnihang_jax import stage3

B = int(sys.argv[1]) if len(sys.argv) > 1 else 512
base = stage3.ValueConfig()
for name, c in [("plain", base), ("snear", dataclasses.replace(base, support_near=256)),
                ("bnear", dataclasses.replace(base, support_near=256, object_near=256))]:  # fmt: skip
    rng = np.random.default_rng(0)
    full = stage3.PairClouds(*(jnp.asarray(rng.normal(size=(B, 4096, 3)).astype(np.float32) * 0.1)
                               for _ in range(4)))  # fmt: skip
    small = stage3.subsample_clouds(full, c)
    net = stage3.make_value(c)
    params = net.init(jax.random.key(0))
    poses = jnp.tile(jnp.asarray([0, 0, 0, 1, 0, 0, 0.0], jnp.float32), (B, 1))
    t = time.time()
    f = jax.jit(net.logits).lower(params, small, poses).compile()
    tc = time.time() - t
    t = time.time()
    jax.block_until_ready(f(params, small, poses))
    print(f"{name}: compile {tc:.1f} s, run {time.time() - t:.3f} s (batch {B})", flush=True)
