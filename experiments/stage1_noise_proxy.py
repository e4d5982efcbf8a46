"""Stage 1's first proposal with z = 0 (the noise mode) against a random z, by pose error
(no simulation): a cheap proxy for whether the mode is a better single answer.

    python -m experiments.stage1_noise_proxy --derived DATA/derived/test \
        --model weights/where_small_paper --out results/stage1_noise_proxy.json

Per pair: K = 5 noise draws, draw 1 replaced by z = 0; errors (``evaluate.pose_errors``) of
draw 0 (random, what the evaluation's first proposal is), of z = 0, and the best of the 4
random draws (what a perfect ranker could pick).
"""

from __future__ import annotations

import argparse
import glob
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from experiments import _cli


def main(argv=None) -> dict:
    from omnihang_jax import dataset_bridge, evaluate, predict
    from omnihang_jax.poses import pose6_to_pose7
    from omnihang_jax.stage1 import make_stage1

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--derived", required=True, help="folder of derived pair .npz files")
    parser.add_argument("--model", default="weights/where_small_paper")
    parser.add_argument("--limit", type=int, default=None, help="first N pairs")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    files = sorted(glob.glob(os.path.join(args.derived, "*.npz")))[: args.limit]
    if not files:
        raise FileNotFoundError(f"no .npz pairs under {args.derived}")
    where = predict.load_predictor(args.model)
    apply = jax.jit(make_stage1(where.stage1_config).apply)
    rows: dict[str, list] = {"random_first": [], "zero": [], "best_of_4_random": []}
    key = jax.random.key(args.seed)
    for f in tqdm(files, desc="pairs"):
        s, _ = dataset_bridge.load_pair_file(f)
        key, k = jax.random.split(key)
        z = jax.random.normal(k, (1, 5, where.stage1_config.noise_dim)).at[:, 1].set(0.0)
        obj, sup = jnp.asarray(s.object_points)[None], jnp.asarray(s.support_points)[None]
        e = evaluate.pose_errors(
            np.asarray(pose6_to_pose7(apply(where.stage1_params, obj, sup, z)))[0], s
        )
        t, r = e["translation_error_m"], e["min_rotation_error_deg"]
        rows["random_first"].append((t[0], r[0]))
        rows["zero"].append((t[1], r[1]))
        rows["best_of_4_random"].append((t[[0, 2, 3, 4]].min(), r[[0, 2, 3, 4]].min()))
    result = {"model": args.model, "derived": args.derived, "pairs": len(files)}
    for name, v in rows.items():
        t, r = np.asarray(v).T
        result[name] = {
            "median_translation_cm": float(np.median(t) * 100),
            "median_min_rotation_deg": float(np.median(r)),
            "within_1cm_and_10deg": float(np.mean((t < 0.01) & (r < 10))),
        }
    print(json.dumps(result, indent=1))
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(result, fh, indent=1)
    return result


if __name__ == "__main__":
    _cli.run(main)
