"""Latency of the whole where-to-hang pipeline (Stages 1-3 incl. CEM) in one jitted call.

    python -m experiments.bench_stage3 --value weights/value_small_paper --out results/bench_stage3.json

Times ``jax.jit(make_hang_pipeline(...))`` on random clouds (the cost does not depend on the
values) at batch 1 and at larger batches after one warm-up call (compilation, timed apart):
median and p10/p90 over ``--repeat`` calls ended by ``block_until_ready``. A batch larger
than ``--chunk`` runs as consecutive jitted calls of ``--chunk`` pairs (CEM's population
holds B x K x 32 states per iteration; the reported pairs/s includes that split).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import _cli
from omnihang_jax import refine, stage3
from omnihang_jax.predict import load_predictor


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--weights", default="weights/where_small_paper")
    parser.add_argument("--value", default="weights/value_small_paper")
    parser.add_argument("--out", required=True)
    parser.add_argument("--batches", default="1,16,256")
    parser.add_argument("--chunk", type=int, default=16)
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument("--proposals", type=int, default=5)
    parser.add_argument("--points", type=int, default=4096)
    parser.add_argument(
        "--answer", choices=("chosen", "paper"), default="chosen",
        help="chosen: stage3.ANSWER_PIPELINE (both starts refined, observed-cloud rule); "
        "paper: Stage-2 starts, highest V",
    )  # fmt: skip
    args = parser.parse_args(argv)
    pred = load_predictor(args.weights)
    vcfg, vparams = refine.load_value(args.value)
    params = {"stage1": pred.stage1_params, "stage2": pred.stage2_params, "value": vparams}
    base = stage3.ANSWER_PIPELINE if args.answer == "chosen" else stage3.PipelineConfig()
    cfg = dataclasses.replace(base, num_proposals=args.proposals)
    hang = jax.jit(stage3.make_hang_pipeline(pred.stage1_config, pred.stage2_config, vcfg, cfg))
    rows = []
    for batch in (int(b) for b in args.batches.split(",")):
        b = min(batch, args.chunk)
        calls = -(-batch // b)
        rng = np.random.default_rng(batch)

        def cloud(scale, b=b, rng=rng):
            x = rng.normal(scale=scale, size=(b, args.points, 3)).astype(np.float32)
            n = rng.normal(size=(b, args.points, 3)).astype(np.float32)
            return jnp.asarray(x), jnp.asarray(n / np.linalg.norm(n, axis=-1, keepdims=True))

        (op, on), (sp, sn) = cloud(0.05), cloud(0.1)
        clouds = stage3.PairClouds(op, on, sp, sn)
        t = time.perf_counter()
        jax.block_until_ready(hang(params, jax.random.key(0), clouds))
        first = time.perf_counter() - t
        times = []
        for r in range(args.repeat):
            t = time.perf_counter()
            for c in range(calls):
                out = hang(params, jax.random.key(r * 1000 + c), clouds)
            jax.block_until_ready(out)
            times.append(time.perf_counter() - t)
        ms = np.asarray(times) * 1000
        rows.append({
            "batch": batch, "jitted_batch": b, "calls": calls, "first_call_s": first,
            "median_ms": float(np.median(ms)), "p10_ms": float(np.percentile(ms, 10)),
            "p90_ms": float(np.percentile(ms, 90)),
            "pairs_per_s": float(batch / np.median(ms) * 1000), "repeat": args.repeat,
        })  # fmt: skip
        print(json.dumps(rows[-1]))
    result = {
        "what": "Stages 1-3 (K proposals, Stage 2, CEM on V from every Stage-2 proposal"
        + (
            ", and from every Stage-1 proposal, the answer by selection.CHOSEN)"
            if args.answer == "chosen"
            else ", the highest V)"
        ),
        "answer": args.answer,
        "starts": list(cfg.starts),
        "select": dataclasses.asdict(cfg.select),
        "cem": vars(cfg.cem) if hasattr(cfg.cem, "__dict__") else str(cfg.cem),
        "proposals": args.proposals,
        "points": args.points,
        "device": str(jax.devices()[0]),
        "device_kind": jax.devices()[0].device_kind,
        "versions": {"jax": jax.__version__, "python": platform.python_version()},
        "rows": rows,
    }
    refine.write_json(args.out, result)
    return result


if __name__ == "__main__":
    _cli.run(main)
