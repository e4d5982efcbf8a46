"""Where the answer pipeline's time goes at batch 1 (issue 12's latency), part by part.

Each part is jitted on its own and timed side by side with the others (interleaved, the same
inputs, medians over ``--repeat`` calls): the whole pipeline (``stage3.ANSWER_PIPELINE`` with
``--views`` views and ``--proposals`` K), Stages 1-2 alone, the fused CEM alone, the ranking
alone, and inside one CEM iteration the value network on its population (views x starts x K x
population states): the state (``posed_state``: the contact features' distance maps), the
PointNet++ encoder and head, and the encoder's farthest-point sampling and ball query of its
first level. The parts do not add up exactly (XLA fuses across them in the whole), but they
say where an exact speed-up can come from::

    python -m experiments.profile_stage3 --views 0/1,1/2,3/4 --out results/profile_stage3.json
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import _cli
from omnihang_jax import pointnet2, refine, stage3
from omnihang_jax.predict import load_predictor, load_rank_values, make_predict

PARTS = (
    "pipeline",
    "stages12",
    "cem",
    "ranking",
    "cem_iteration_value",
    "cem_iteration_state",
    "cem_iteration_network",
    "cem_iteration_fps_level0",
    "cem_iteration_ball_query_level0",
)
FPS_UNROLLS = (1, 2, 4, 8, 16, 32, 128)  # fps_unroll_U parts
# ball_query_M parts: the first level's ball query by each method (the same indices)


def _views(text: str) -> tuple[tuple[int, int], ...]:
    return tuple(tuple(int(x) for x in v.split("/")) for v in text.split(","))


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--weights", default="weights/where_small_paper")
    parser.add_argument("--value", default=stage3.CEM_VALUE)
    parser.add_argument("--views", default="0/1,1/2", help="J/T,... (PipelineConfig.views)")
    parser.add_argument("--proposals", type=int, default=stage3.ANSWER_PIPELINE.num_proposals)
    parser.add_argument("--points", type=int, default=4096)
    parser.add_argument("--repeat", type=int, default=20)
    parser.add_argument(
        "--parts", default=None,
        help="comma-separated parts to time (default all); fps_unroll_U (e.g. fps_unroll_1): "
        "the first level's farthest-point sampling with U steps per loop iteration; "
        "ball_query_M (cumsum, count, top_k): its ball query by method M",
    )  # fmt: skip
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    known = (PARTS + tuple(f"fps_unroll_{u}" for u in FPS_UNROLLS)
             + tuple(f"ball_query_{m}" for m in pointnet2.BALL_QUERY_METHODS))  # fmt: skip
    wanted = args.parts.split(",") if args.parts else list(known)
    if unknown := [p for p in wanted if p not in known]:
        parser.error(f"unknown --parts {unknown}; known: {', '.join(known)}")

    pred = load_predictor(args.weights)
    vcfg, vparams = refine.load_value(args.value)
    rank_configs, rank_params = load_rank_values(stage3.RANK_VALUES)
    s1_config, s1_params = pred.stage1_spec
    config = dataclasses.replace(
        stage3.ANSWER_PIPELINE, num_proposals=args.proposals, views=_views(args.views),
        rank_values=len(rank_params),
    )  # fmt: skip
    params = {"stage1": s1_params, "stage2": pred.stage2_params, "value": vparams,
              "rank_values": rank_params}  # fmt: skip
    rng = np.random.default_rng(0)

    def cloud(scale):
        x = rng.normal(scale=scale, size=(1, args.points, 3)).astype(np.float32)
        n = rng.normal(size=(1, args.points, 3)).astype(np.float32)
        return jnp.asarray(x), jnp.asarray(n / np.linalg.norm(n, axis=-1, keepdims=True))

    (op, on), (sp, sn) = cloud(0.05), cloud(0.1)
    clouds = stage3.PairClouds(op, on, sp, sn)
    key = jax.random.key(0)

    hang = stage3.make_hang_pipeline(s1_config, pred.stage2_config, vcfg, config, rank_configs)
    predict = make_predict(s1_config, pred.stage2_config)
    refiner = stage3.make_refiner(vcfg, config.cem)
    rank = stage3.make_ensemble_score(rank_configs, config.rank_with_value, stacked=config.views)
    value = stage3.make_value(vcfg)

    p12 = predict(s1_params, pred.stage2_params, op, sp, key, args.proposals, support_normals=sn)
    starts = jnp.concatenate([p12.stage2_poses, p12.stage1_poses], axis=1)  # [1, 2K, 7]
    nv = len(config.views)
    subs = [stage3.subset_clouds(clouds, vcfg, *v) for v in config.views]
    small = jax.tree.map(lambda *x: jnp.concatenate(x, axis=0), *subs)  # [V, ...]
    vstarts = jnp.concatenate([starts] * nv, axis=0)  # [V, 2K, 7]
    states = nv * starts.shape[1] * config.cem.population
    pop = jnp.repeat(vstarts.reshape(-1, 7), config.cem.population, axis=0)  # [states, 7]
    pop = pop + jnp.concatenate([0.005 * jax.random.normal(key, (states, 3)),
                                 jnp.zeros((states, 4))], axis=1)  # fmt: skip
    pop_clouds = jax.tree.map(lambda x: jnp.repeat(x, states // nv, axis=0), small)
    points, feats = jax.vmap(lambda c, p: stage3.posed_state(c, p, vcfg))(pop_clouds, pop)
    level = vcfg.pointnet.sa_levels[0]
    centroids = pointnet2.gather_points(
        points, pointnet2.farthest_point_sample(points, level.npoint)
    )
    # the ranking scores every view's starts as its candidates ([V, 2K], view-major, as fused)
    cand_scores = jnp.zeros(vstarts.shape[:2])

    parts = {
        "pipeline": (hang, (params, key, clouds)),
        "stages12": (
            lambda p, k, c: predict(
                p["stage1"],
                p["stage2"],
                c.object_points,
                c.support_points,
                k,
                args.proposals,
                support_normals=c.support_normals,
            ),
            (params, key, clouds),
        ),  # fmt: skip
        "cem": (lambda p, c, s: refiner(p["value"], key, c, s), (params, small, vstarts)),
        "ranking": (
            lambda p, c, s, x: rank(s, p["rank_values"], c, x),
            (params, clouds, cand_scores, vstarts),
        ),
        "cem_iteration_value": (
            lambda p, c, x: value.logits(p["value"], c, x),
            (params, pop_clouds, pop),
        ),
        "cem_iteration_state": (
            lambda c, x: jax.vmap(lambda a, b: stage3.posed_state(a, b, vcfg))(c, x),
            (pop_clouds, pop),
        ),
        "cem_iteration_network": (
            lambda p, x, f: stage3.ValueNet(vcfg).apply(p["value"], x, f),
            (params, points, feats),
        ),
        "cem_iteration_fps_level0": (
            lambda x: pointnet2.farthest_point_sample(x, level.npoint),
            (points,),
        ),
        "cem_iteration_ball_query_level0": (
            lambda x, c: pointnet2.ball_query(x, c, level.radius, level.nsample),
            (points, centroids),
        ),
    }
    for u in FPS_UNROLLS:
        parts[f"fps_unroll_{u}"] = (
            lambda x, u=u: pointnet2.farthest_point_sample(x, level.npoint, unroll=u),
            (points,),
        )
    for m in pointnet2.BALL_QUERY_METHODS:
        parts[f"ball_query_{m}"] = (
            lambda x, c, m=m: pointnet2.ball_query(x, c, level.radius, level.nsample, method=m),
            (points, centroids),
        )
    parts = {name: parts[name] for name in wanted}
    jitted = {name: jax.jit(f) for name, (f, _) in parts.items()}
    first, times = {}, {name: [] for name in parts}
    for name, (_, a) in parts.items():
        t = time.perf_counter()
        jax.block_until_ready(jitted[name](*a))
        first[name] = time.perf_counter() - t
    for _ in range(args.repeat):
        for name, (_, a) in parts.items():  # interleaved: every part sees the same load
            t = time.perf_counter()
            jax.block_until_ready(jitted[name](*a))
            times[name].append(time.perf_counter() - t)
    rows = {}
    for name in parts:
        ms = np.asarray(times[name]) * 1000
        rows[name] = {"median_ms": float(np.median(ms)), "p10_ms": float(np.percentile(ms, 10)),
                      "p90_ms": float(np.percentile(ms, 90)), "first_call_s": first[name]}  # fmt: skip
        print(f"{name:34s} {rows[name]['median_ms']:9.2f} ms")
    result = {
        "what": "the answer pipeline at batch 1, part by part, each jitted alone and timed "
        "interleaved (experiments.profile_stage3); cem_iteration_*: one CEM iteration's "
        f"value network on its {states} states (views x starts x K x population)",
        "views": [list(v) for v in config.views],
        "proposals": args.proposals,
        "cem": dataclasses.asdict(config.cem),
        "population_states": states,
        "repeat": args.repeat,
        "device": str(jax.devices()[0]),
        "device_kind": jax.devices()[0].device_kind,
        "versions": {"jax": jax.__version__, "python": platform.python_version()},
        "parts": rows,
    }
    refine.write_json(args.out, result)
    return result


if __name__ == "__main__":
    _cli.run(main)
