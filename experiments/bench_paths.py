"""Benchmark of the path-planning side: collision queries per second of the batched estimators
(NCE, HCE) on this machine's JAX device, the mesh checker's on its CPU, and planning per pair
with the named planner configs (``omnihang_jax.paths``).

    python -m experiments.bench_paths --weights weights/nce --out results/bench_paths.json
    python -m experiments.bench_paths --weights weights/nce --data datasets/paper --batches "" \
        --planner 4 --configs default,paper_nce --key cpu_planner --out results/bench_paths.json

Queries: one jitted ``collides`` per estimator, clouds of the configured sizes, batches of 1
to 4,096 poses, best of ``--repeats`` timed calls after a warm-up (compilation excluded).
``--compare B``: B's NCE timed beside the first. ``--paths``: planning times of an
evaluation summary. Writes JSON with device and versions; merges into an existing file, keyed
by device, so CPU and GPU runs sit side by side.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import time
from pathlib import Path

import jax
import numpy as np

from omnihang_jax import collision


def _time(fn, repeats: int) -> float:
    jax.block_until_ready(fn())
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return best


def estimator_throughput(
    weights: str | None,
    batches=(1, 16, 64, 256, 1024, 4096),
    repeats: int = 3,
    preset="fast",
    on_row=None,
    compare: str | None = None,
) -> dict:
    """Queries per second of NCE and HCE at each batch size (random clouds of the configured
    sizes, random poses: the cost does not depend on the values). ``on_row(result)`` is
    called after each batch size (so that a run cut short keeps what it measured).
    ``compare``: a second weights folder whose NCE is timed in the same run, call for call
    beside the first (``compare_nce_*`` and ``compare_nce_cost_ratio`` = its time / the first's)."""
    if weights:
        nce_cfg, nce_params, _ = collision.load_estimator(Path(weights, "nce"))
        normal_cfg, normal_params, _ = collision.load_estimator(Path(weights, "hce_normals"))
    else:
        nce_cfg, normal_cfg = collision.NCE_PRESETS[preset], collision.NORMAL_PRESETS[preset]
        nce_params = collision.make_nce(nce_cfg).init(jax.random.key(0))
        normal_params = collision.make_normal_net(normal_cfg).init(jax.random.key(1))
    rng = np.random.default_rng(0)
    oc = rng.uniform(-0.1, 0.1, (nce_cfg.object_input, 3)).astype(np.float32)
    sc = rng.uniform(-0.15, 0.15, (nce_cfg.support_input, 3)).astype(np.float32)
    sc_h = rng.uniform(-0.15, 0.15, (normal_cfg.points, 3)).astype(np.float32)
    nce = jax.jit(collision.nce_collides(nce_cfg))
    hce = jax.jit(collision.hce_collides(normal_cfg))
    normals = collision.make_normal_net(normal_cfg).apply(normal_params, sc_h[None])[0]
    heuristic = jax.jit(
        lambda normals, oc, sc, poses: (
            collision.heuristic_score(oc, sc, normals, poses) > normal_cfg.threshold
        )
    )
    out = {"nce_config": nce_cfg.__dict__, "normal_config": normal_cfg.__dict__, "rows": []}
    if compare:
        cmp_cfg, cmp_params, _ = collision.load_estimator(Path(compare, "nce"))
        cmp_oc = rng.uniform(-0.1, 0.1, (cmp_cfg.object_input, 3)).astype(np.float32)
        cmp_sc = rng.uniform(-0.15, 0.15, (cmp_cfg.support_input, 3)).astype(np.float32)
        cmp_nce = jax.jit(collision.nce_collides(cmp_cfg))
        out |= {"compare": compare, "compare_nce_config": cmp_cfg.__dict__}
    for b in batches:
        poses = np.concatenate(
            [rng.uniform(-0.1, 0.1, (b, 3)), rng.normal(size=(b, 4))], axis=1
        ).astype(np.float32)
        row = {"batch": b}
        fns = [
            ("nce", lambda poses=poses: nce(nce_params, oc, sc, poses)),
            ("hce", lambda poses=poses: hce(normal_params, oc, sc_h, poses)),
            ("hce_normals_cached", lambda poses=poses: heuristic(normals, oc, sc_h, poses)),
        ]
        if compare:
            fns.append(
                ("compare_nce", lambda poses=poses: cmp_nce(cmp_params, cmp_oc, cmp_sc, poses))
            )
        seconds = {}
        for name, fn in fns:
            seconds[name] = s = _time(fn, repeats)
            row[f"{name}_ms"] = round(1e3 * s, 3)
            row[f"{name}_queries_per_s"] = round(b / s, 1)
        if compare:
            row["compare_nce_cost_ratio"] = round(seconds["compare_nce"] / seconds["nce"], 3)
        out["rows"].append(row)
        print(json.dumps(row), flush=True)
        if on_row is not None:
            on_row(out)
    return out


def mesh_throughput(data: str, n_poses: int = 2000) -> dict:
    """States per second of the planner's mesh checker (MuJoCo C, this CPU) on one pair."""
    from omnihang_jax import paths_eval, planner

    spec = paths_eval.held_out_pairs(data, 1)[0]
    scene = paths_eval.pair_scene(data, spec)[0]
    rng = np.random.default_rng(0)
    lo, hi = planner.default_bounds(scene)
    poses = np.concatenate(
        [rng.uniform(lo, hi, (n_poses, 3)), rng.normal(size=(n_poses, 4))], axis=1
    )
    poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    checker = planner.MeshChecker(scene)
    checker(poses[:10])
    t0 = time.perf_counter()
    checker(poses)
    s = time.perf_counter() - t0
    return {"pair": spec.name, "states": n_poses, "states_per_s": round(n_poses / s, 1)}


def planner_states(data: str, n_pairs: int, names=("default", "paper_nce")) -> dict:
    """Per named planner config (``omnihang_jax.paths.CONFIGS``, built by ``make_planner``):
    states checked per second of planning and planning seconds on ``n_pairs`` held-out pairs
    (OMPL seeded once per process: the plans' outcomes are not the figure)."""
    from omnihang_jax import paths, paths_eval

    specs = paths_eval.held_out_pairs(data, n_pairs)
    summary, rows = {}, []
    for name in names:
        plan = paths.make_planner(dataclasses.replace(paths.CONFIGS[name], mesh_fallback=False))
        mine = []
        for spec in specs:
            scene, obj, sup = paths_eval.pair_scene(data, spec)
            info = plan(scene, obj, sup, np.asarray(spec.goal)).info
            row = dict(config=name, pair=spec.name, status=info["status"],
                       planning_s=round(info["planning_s"], 3), states=info["states_checked"],
                       states_per_s=round(info["states_checked"] / max(info["planning_s"], 1e-9), 1))  # fmt: skip
            print(json.dumps(row), flush=True)
            mine.append(row)
        rows += mine
        summary[name] = dict(
            median_states_per_s=float(np.median([r["states_per_s"] for r in mine])),
            median_planning_s=float(np.median([r["planning_s"] for r in mine])),
        )
    return dict(pairs=len(specs), summary=summary, rows=rows)


def planning_times(paths_json: str) -> dict:
    """Median / p90 planning time per pair and method from an evaluation summary (per config or method)."""
    res = json.loads(Path(paths_json).read_text())
    out = {}
    for name, entry in res["methods"].items() if "methods" in res else res.items():
        if not isinstance(entry, dict) or "planning_s" not in entry:
            continue
        t = np.asarray(entry["planning_s"], float)
        out[name] = {
            "pairs": len(t),
            "median_s": round(float(np.median(t)), 3),
            "p90_s": round(float(np.quantile(t, 0.9)), 3),
        }
    return out


def versions() -> dict:
    import flax
    import mujoco

    v = {
        "python": platform.python_version(),
        "jax": jax.__version__,
        "flax": flax.__version__,
        "mujoco": mujoco.__version__,
    }
    try:
        from importlib.metadata import version

        v["ompl"] = version("ompl")
    except Exception:  # ompl is not installed on the GPU image
        v["ompl"] = None
    return v


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--weights", default=None, help="train_collision output (default: fresh)")
    parser.add_argument("--preset", default="fast", help="preset when no --weights")
    parser.add_argument("--paths", default=None, help="an evaluation summary JSON: planning times")
    parser.add_argument("--data", default=None, help="dataset: also time the mesh checker")
    parser.add_argument("--batches", default="1,16,64,256,1024,4096")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--compare", default=None, help="a second weights folder: its NCE timed beside the first"
    )
    parser.add_argument(
        "--key", default=None, help="key of this run in --out (default: the device's name)"
    )
    parser.add_argument(
        "--planner", type=int, default=0, metavar="N",
        help="states per second of planning on N held-out pairs (--data), per --configs",
    )  # fmt: skip
    parser.add_argument(
        "--configs", default="default,paper_nce",
        help="--planner: named planner configs (omnihang_jax.paths.CONFIGS), comma-separated",
    )  # fmt: skip
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    if args.planner and not args.data:
        parser.error("--planner needs --data")
    device = jax.devices()[0]
    name = f"{device.platform}:{getattr(device, 'device_kind', device.platform)}"
    key = args.key or name
    out = Path(args.out)
    entry = {
        "device": name,
        "host_cores": os.cpu_count(),
        "versions": versions(),
        "weights": args.weights,
    }

    def save(queries=None):
        if queries is not None:
            entry["queries"] = queries
        merged = json.loads(out.read_text()) if out.exists() else {}
        merged[key] = entry
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(merged, indent=1))

    if args.paths:
        entry["planning"] = planning_times(args.paths)
    if args.planner:
        names = tuple(n for n in args.configs.split(",") if n)
        entry["planner_states"] = planner_states(args.data, args.planner, names)
        save()
    elif args.data:
        entry["mesh_checker_cpu"] = mesh_throughput(args.data)
    batches = tuple(int(b) for b in args.batches.split(",")) if args.batches else ()
    if batches:
        estimator_throughput(
            args.weights, batches, args.repeats, args.preset, on_row=save, compare=args.compare
        )
    save()
    return entry


if __name__ == "__main__":
    main()
