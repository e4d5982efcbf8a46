"""Latency of the whole where-to-hang pipeline (Stages 1-3 incl. CEM) in one jitted call.

    python -m experiments.bench_stage3 --value weights/value_s16_hardneg --out results/bench_stage3.json

Times ``jax.jit(make_hang_pipeline(...))`` on random clouds (the cost does not depend on the
values) at batch 1 and at larger batches after one warm-up call (compilation, timed apart):
median and p10/p90 over ``--repeat`` calls ended by ``block_until_ready``. A batch larger
than ``--chunk`` runs as consecutive jitted calls of ``--chunk`` pairs (CEM's population
holds B x K x 32 states per iteration; the reported pairs/s includes that split).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import platform
import re
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from experiments import _cli
from omnihang_jax import pointnet2, refine, stage3
from omnihang_jax.predict import load_predictor, load_rank_values

# the subsamples of the "viewsN" pipelines (PipelineConfig.views, twenty-sixth session): the
# quarters of the evenly spaced part's stride in bit-reversed order, each set holding the last
# ((1, 2) is subset 2 of 4); views3 is the one evaluated (0, 1/2, 3/4: thirty-first and
# thirty-second sessions; 1/4 in its place before the thirty-third, the same shapes and time)
VIEWS = {
    "views1": ((0, 1),),
    "views2": ((0, 1), (1, 2)),
    "views3": ((0, 1), (1, 2), (3, 4)),
    "views4": ((0, 1), (1, 2), (1, 4), (3, 4)),
}
# An answer is NAME[-seq][-bf16][-fpsU][-bqM][@K]:
# -seq: each view's and start's CEM one after the other (PipelineConfig.fuse = False, the
#   pipeline before the twenty-seventh session);
# -bf16: traced and called inside jax.default_matmul_precision("bfloat16"): the latency a
#   lower-precision V would have, not its answers (thirty-second session);
# -fpsU: traced with U steps per loop iteration of farthest-point sampling
#   (pointnet2.FPS_UNROLL; the same answers, another loop; thirty-second session);
# -bqM: traced with ball-query method M (cumsum, count, top_k: pointnet2.BALL_QUERY_METHOD; the
#   same answers; thirty-third session);
# @K: K proposals (a view each: K x views refined candidates per start), over --proposals.
ANSWER = re.compile(r"^(?P<name>[a-z0-9]+)(?P<seq>-seq)?(?P<bf16>-bf16)?(?:-fps(?P<fps>[1-9][0-9]*))?"
                    r"(?:-bq(?P<bq>cumsum|count|top_k))?(?:@(?P<k>[1-9][0-9]*))?$")  # fmt: skip


class Answer(NamedTuple):
    name: str
    seq: bool
    bf16: bool
    fps_unroll: int | None
    proposals: int | None
    ball_query: str | None = None


def parse_answer(text: str) -> Answer | None:
    """'views3-fps8-bqcount@10' -> Answer('views3', False, False, 8, 10, 'count'); None if
    malformed."""
    m = ANSWER.match(text)
    if m is None:
        return None
    fps, k = m["fps"], m["k"]
    return Answer(
        m["name"], bool(m["seq"]), bool(m["bf16"]), fps and int(fps), k and int(k), m["bq"]
    )


@contextlib.contextmanager
def _context(answer: Answer):
    """What an answer is traced and timed in: its matmul precision, FPS unroll and ball query."""
    before = pointnet2.FPS_UNROLL, pointnet2.BALL_QUERY_METHOD
    bf16 = jax.default_matmul_precision("bfloat16") if answer.bf16 else contextlib.nullcontext()
    with bf16:
        try:
            if answer.fps_unroll is not None:
                pointnet2.FPS_UNROLL = answer.fps_unroll
            if answer.ball_query is not None:
                pointnet2.BALL_QUERY_METHOD = answer.ball_query
            yield
        finally:
            pointnet2.FPS_UNROLL, pointnet2.BALL_QUERY_METHOD = before


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--weights", default="weights/where_small_paper")
    parser.add_argument(
        "--value", default=stage3.CEM_VALUE, help="CEM's V (default stage3.CEM_VALUE)"
    )
    parser.add_argument("--out", required=True)
    parser.add_argument("--batches", default="1,16,256")
    parser.add_argument("--chunk", type=int, default=16)
    parser.add_argument("--repeat", type=int, default=10)
    parser.add_argument(
        "--proposals", type=int, default=None,
        help="K of every timed pipeline (default: each its own, the answer pipeline's "
        f"{stage3.ANSWER_PIPELINE.num_proposals} and the paper's 5)",
    )  # fmt: skip
    parser.add_argument("--points", type=int, default=4096)
    parser.add_argument(
        "--answers", default="chosen,paper",
        help="comma-separated pipelines timed side by side (interleaved, same clouds): chosen "
        "= stage3.ANSWER_PIPELINE (both starts refined, the observed-cloud rule) ranked with "
        "the networks of --rank-value (the default pipeline), single = the same ranked by "
        "CEM's V alone, paper = Stage-2 starts, highest V, views1 / views2 / views3 = chosen "
        "on one / two / three subsamples (PipelineConfig.views); a name + '-seq' (e.g. "
        "views2-seq): each view's and start's CEM in turn (PipelineConfig.fuse = False); "
        "a name + '-bf16' (e.g. views3-bf16@10): bfloat16 matmul precision; a name + '-fpsU' "
        "(e.g. views3-fps8@10): farthest-point sampling unrolled U steps a loop iteration; "
        "a name + '@K' (e.g. views2@10): K proposals; the first is the reference of the ratios",
    )  # fmt: skip
    parser.add_argument(
        "--rank-value", action="append", default=None, metavar="DIR",
        help="value folders ranking beside --value in 'chosen' (default stage3.RANK_VALUES)",
    )  # fmt: skip
    args = parser.parse_args(argv)
    answers = args.answers.split(",")
    known = ("chosen", "single", "paper", *VIEWS)
    parsed = {a: parse_answer(a) for a in answers}
    bad = [a for a, p in parsed.items() if p is None or p.name not in known]
    if bad:
        parser.error(f"unknown --answers {bad}; known: {', '.join(known)}")
    pred = load_predictor(args.weights)
    vcfg, vparams = refine.load_value(args.value)
    rank_dirs = list(stage3.RANK_VALUES if args.rank_value is None else args.rank_value)
    stage1_config, stage1_params = pred.stage1_spec  # a Stage-1 mix ("A+B") too
    rank_configs, rank_params = load_rank_values(rank_dirs)
    params = {"stage1": stage1_params, "stage2": pred.stage2_params, "value": vparams,
              "rank_values": rank_params}  # fmt: skip
    configs, hangs = {}, {}
    for a in answers:
        name, seq, k_of = parsed[a].name, parsed[a].seq, parsed[a].proposals
        base = stage3.PipelineConfig() if name == "paper" else stage3.ANSWER_PIPELINE
        ranks = len(rank_dirs) if name == "chosen" or name in VIEWS else 0
        k = k_of or args.proposals or base.num_proposals
        configs[a] = dataclasses.replace(
            base, num_proposals=k, rank_values=ranks, fuse=not seq,
            views=VIEWS.get(name, base.views),
        )  # fmt: skip
        hangs[a] = jax.jit(
            stage3.make_hang_pipeline(
                stage1_config, pred.stage2_config, vcfg, configs[a], rank_configs
            )
        )
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
        first, times = {}, {a: [] for a in answers}
        for a in answers:
            t = time.perf_counter()
            with _context(parsed[a]):
                jax.block_until_ready(hangs[a](params, jax.random.key(0), clouds))
            first[a] = time.perf_counter() - t
        for r in range(args.repeat):
            for a in answers:  # interleaved: both see the same machine load
                t = time.perf_counter()
                with _context(parsed[a]):
                    for c in range(calls):
                        out = hangs[a](params, jax.random.key(r * 1000 + c), clouds)
                    jax.block_until_ready(out)
                times[a].append(time.perf_counter() - t)
        for a in answers:
            ms = np.asarray(times[a]) * 1000
            rows.append({
                "answer": a, "batch": batch, "jitted_batch": b, "calls": calls,
                "first_call_s": first[a], "median_ms": float(np.median(ms)),
                "p10_ms": float(np.percentile(ms, 10)), "p90_ms": float(np.percentile(ms, 90)),
                "pairs_per_s": float(batch / np.median(ms) * 1000), "repeat": args.repeat,
                "ratio_to_first": float(np.median(ms) / np.median(np.asarray(times[answers[0]]) * 1000)),
            })  # fmt: skip
            print(json.dumps(rows[-1]))
    result = {
        "what": "Stages 1-3 in one jitted call; chosen: CEM from every Stage-1 and Stage-2 "
        "proposal, the answer by selection.CHOSEN (stage3.ANSWER_PIPELINE) on the ranking "
        "networks' mean log V (stage3.RANK_VALUES; with CEM's V when rank_with_value); single: "
        "the same on CEM's V alone; paper: CEM from every Stage-2 proposal, the highest V",
        "answers": {
            a: {
                "starts": list(configs[a].starts),
                "select": dataclasses.asdict(configs[a].select),
                "pool_starts": configs[a].pool_starts,
                "rank_values": rank_dirs if configs[a].rank_values else [],
                "rank_with_value": configs[a].rank_with_value,
                "proposals": configs[a].num_proposals,
                "views": [list(v) for v in configs[a].views],
                "fuse": configs[a].fuse,
                "matmul_precision": "bfloat16" if parsed[a].bf16 else "default",
                "fps_unroll": parsed[a].fps_unroll or pointnet2.fps_unroll(),
                "ball_query": parsed[a].ball_query or pointnet2.BALL_QUERY_METHOD,
            }
            for a in answers
        },  # fmt: skip
        "cem": dataclasses.asdict(configs[answers[0]].cem),
        "proposals": args.proposals,  # None: each pipeline its own (answers[..]["proposals"])
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
