"""Data parallelism (``omnihang_jax.sharding``): on 4 CPU devices
(``--xla_force_host_platform_device_count=4``, in a subprocess: the flag must precede JAX's start)
a Stage-1 training step and the where-to-hang answer give the numbers one device gives."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from omnihang_jax import sharding

ROOT = Path(__file__).resolve().parents[1]


def run_on_devices(code: str, devices: int, tmp_path: Path) -> dict:
    """``code`` in a fresh Python with ``devices`` CPU devices; it writes JSON to OUT."""
    out = tmp_path / f"out_{devices}.json"
    env = dict(os.environ, JAX_PLATFORMS="cpu", OUT=str(out))
    env["XLA_FLAGS"] = (
        f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={devices}"
    )
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=600)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(out.read_text())


def test_one_device_is_left_as_it_is():
    mesh = sharding.data_mesh()
    tree = {"a": np.ones((3, 2))}
    assert sharding.replicate(tree, mesh) is tree and sharding.shard_batch(tree, mesh) is tree
    assert sharding.padded_size(3, mesh) == 3


TRAIN_STEP = """
    import json, os
    import jax, numpy as np
    from omnihang_jax import data, sharding, train
    assert len(jax.devices()) == 4
    config = train.WHERE_TINY
    batch = data.synthetic_batch(jax.random.key(1), 8, n_points=config.num_object_points)
    state = jax.jit(train.make_init_state("1", config))(jax.random.key(0))
    step = jax.jit(train.make_train_step("1", config))
    key = jax.random.key(2)
    one_state, one = step(state, jax.tree.map(jax.numpy.asarray, batch), key)  # device 0
    mesh = sharding.data_mesh()
    shard = sharding.shard_batch(batch, mesh)
    assert len(shard.object_points.sharding.device_set) == 4
    four_state, four = step(sharding.replicate(state, mesh), shard, key)
    diff = max(float(np.abs(np.asarray(a) - np.asarray(b)).max())
               for a, b in zip(jax.tree.leaves(one_state.params), jax.tree.leaves(four_state.params)))
    try:
        sharding.shard_batch(data.synthetic_batch(jax.random.key(1), 6, n_points=16), mesh)
        uneven = "accepted"
    except ValueError as err:
        uneven = str(err)
    json.dump(dict(loss_one=float(one["loss"]), loss_four=float(four["loss"]), params_diff=diff,
                   uneven=uneven), open(os.environ["OUT"], "w"))
"""


@pytest.mark.slow  # a fresh JAX and two compiles of the tiny Stage-1 step (~35 s on 2 cores)
def test_a_training_step_on_four_devices_equals_one_device(tmp_path):
    out = run_on_devices(TRAIN_STEP, 4, tmp_path)
    assert np.isfinite(out["loss_one"])
    np.testing.assert_allclose(out["loss_four"], out["loss_one"], rtol=1e-4)
    assert out["params_diff"] < 1e-5
    assert "multiple of 4" in out["uneven"]


ANSWER = """
    import json, os, sys
    sys.path.insert(0, "tests")
    import jax, numpy as np
    from pathlib import Path
    from test_where import pairs, save_tiny_stage12, random_params
    import dataclasses
    from omnihang_jax import pipeline, refine, stage3, where
    root = Path(os.environ["OUT"]).parent / f"w{len(jax.devices())}"
    save_tiny_stage12(root / "stage12")
    for name, seed in (("value", 0), ("ranker", 1)):
        net = stage3.make_value(stage3.VALUE_TINY)
        refine.save_value(root / name, stage3.VALUE_TINY, random_params(net.init, seed))
    pipe = dataclasses.replace(pipeline.ANSWER_PIPELINE, num_proposals=3, views=((0, 1),),
                               cem=stage3.CEMConfig(population=8, iterations=2, elites=3))
    w = where.load_where(where.WhereConfig(stage12=str(root / "stage12"),
                                           value=str(root / "value"),
                                           rankers=(str(root / "ranker"),),
                                           pipeline=pipe, check=0))
    out = w.answer(pairs(3), [4, 5, 6], seed=0)  # 3 pairs: padded to 4 on four devices
    json.dump(dict(devices=len(jax.devices()), ranked=out.ranked.tolist(),
                   stage1=out.stage1.tolist()), open(os.environ["OUT"], "w"))
"""


@pytest.mark.slow  # compiles the tiny answer twice, in two processes (~2 min on 2 cores)
def test_the_answer_on_four_devices_equals_one_device(tmp_path):
    one = run_on_devices(ANSWER, 1, tmp_path)
    four = run_on_devices(ANSWER, 4, tmp_path)
    assert (one["devices"], four["devices"]) == (1, 4)
    np.testing.assert_allclose(four["stage1"], one["stage1"], atol=1e-5)
    np.testing.assert_allclose(four["ranked"], one["ranked"], atol=1e-4)
