"""Profile a training step of Stages 1 / 2a / 2b and its parts (FPS, ball query, forward).

    python -m experiments.profile_where --presets small,original --batches 32,128 --out results/profile_where.json

Every figure is measured in this run, side by side, on random clouds of the preset's shapes
(4096 points per cloud, 50 stable poses: the derived dataset's shapes): median of ``--repeat``
timed calls after a compiled warm-up, ``jax.block_until_ready`` around each. Prints a table
and writes JSON with the device and versions. Stage 2's 2a / 2b steps see object + support
clouds (8192 points).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import _cli
from omnihang_jax import data, pointnet2, train


def _time(fn, *args, repeat: int) -> float:
    jax.block_until_ready(fn(*args))  # compile + warm-up
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def profile(preset: str, batch: int, stages, repeat: int, n_points: int = 4096) -> list[dict]:
    config = train.PRESETS[preset]
    config = dataclasses.replace(config, train=dataclasses.replace(config.train, batch_size=batch))
    sample = data.synthetic_batch(jax.random.key(0), batch, n_points, max_poses=50, max_contacts=4)
    sample = data.HangSample(*(jnp.asarray(x) for x in sample))
    rows = []
    for stage in stages:
        state = jax.jit(train.make_init_state(stage, config))(jax.random.key(1))
        for method in pointnet2.BALL_QUERY_METHODS:  # the same step with each ball query
            step = _with_ball_query(method, jax.jit(train.make_train_step(stage, config)))
            s = _time(lambda st, b, step=step: step(st, b, jax.random.key(2))[1]["loss"],
                      state, sample, repeat=repeat)  # fmt: skip
            rows.append(dict(preset=preset, batch=batch, part=f"train step {stage} ({method})",
                             ms=1e3 * s, samples_per_s=batch / s))  # fmt: skip
    # parts of the encoder on one cloud batch (Stage 1's object cloud; Stage 2 sees twice N)
    enc = config.stage1.encoder
    lvl = enc.sa_levels[0]
    pts = sample.object_points
    fps = jax.jit(lambda p: pointnet2.farthest_point_sample(p, lvl.npoint))
    s = _time(fps, pts, repeat=repeat)
    rows.append(dict(preset=preset, batch=batch, part=f"FPS level 1 ({n_points} -> {lvl.npoint})",
                     ms=1e3 * s))  # fmt: skip
    idx = fps(pts)
    cent = pointnet2.gather_points(pts, idx)
    for method in pointnet2.BALL_QUERY_METHODS:
        bq = jax.jit(lambda p, c, m=method: pointnet2.ball_query(p, c, lvl.radius, lvl.nsample, m))
        s = _time(bq, pts, cent, repeat=repeat)
        rows.append(dict(preset=preset, batch=batch, part=f"ball query L1 {lvl.npoint}x{lvl.nsample} ({method})",
                         ms=1e3 * s))  # fmt: skip
    return rows


def _with_ball_query(method: str, fn):
    """``fn`` (a fresh ``jax.jit``) run with ``pointnet2.ball_query`` using ``method``: it is
    traced on its first call, inside the patch, so the compiled step uses that method."""
    original = pointnet2.ball_query

    def patched(*args, **kwargs):
        kwargs["method"] = method
        return original(*args, **kwargs)

    def run(*args):
        pointnet2.ball_query = patched
        try:
            return fn(*args)
        finally:
            pointnet2.ball_query = original

    return run


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--presets", default="small,original")
    parser.add_argument("--batches", default="32,128")
    parser.add_argument("--stages", default="1,2a,2b")
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--out", default="results/profile_where.json")
    args = parser.parse_args(argv)
    stages = [s for s in args.stages.split(",") if s]
    unknown = set(stages) - set(train.STAGES)
    if unknown:
        parser.error(f"unknown stages {sorted(unknown)}")
    rows = []
    result = {
        "device": str(jax.devices()[0].device_kind),
        "backend": jax.default_backend(),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "repeat": args.repeat,
        "rows": rows,
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    for preset in args.presets.split(","):
        if preset not in train.PRESETS:
            parser.error(f"unknown preset {preset!r}")
        for b in (int(x) for x in args.batches.split(",")):
            for row in profile(preset, b, stages, args.repeat):
                rows.append(row)
                extra = f"{row['samples_per_s']:9.0f} samples/s" if "samples_per_s" in row else ""
                print(f"{preset:9s} batch {b:4d}  {row['part']:38s} {row['ms']:9.2f} ms {extra}",
                      flush=True)  # fmt: skip
            with open(args.out, "w") as f:  # after every setting: a cut-short run keeps its rows
                json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    _cli.run(main)
