"""Re-judge the answers of an ``eval_stage3`` run in MuJoCo and PyBullet (the second judge).

    python -m experiments.judge_stage3 --pairs results/hanging_success_stage3.pairs.jsonl.gz \\
        --per-category 20 --workers 2 --out results/hanging_success_stage3_judges.json

For each pair the chosen pose of every stage (Stage 1, 1+2, 1+3, all stages) is simulated
under the evaluation protocol by ``sim.judges.judge_stability(..., judge="both")``
(PyBullet ``MATCHED`` set-up, docs/judges.md); success per judge = mean over categories.
PyBullet runs ~2 poses/s per core, hence a balanced subset.
"""

from __future__ import annotations

import argparse
import gzip
import json
import sys

import numpy as np

from experiments import _cli
from omnihang_jax import dataset_bridge, refine
from omnihang_jax.eval_pipeline import STAGES

_W: dict = {}


def _init(dataset_dir: str) -> None:
    from sim.library import build_library

    recipe = dataset_bridge.read_recipe(dataset_dir)
    _W["library"] = build_library(
        dataset_bridge.dataset_config_from_recipe(recipe).library, progress=False
    )


def _judge(job):
    from omnihang_jax.evaluate import protocol_stability
    from sim import judges
    from sim.scene import build_scene

    obj, sup, poses = job
    lib = _W["library"]
    scene = build_scene(lib.objects[obj], lib.supports[sup])
    res = judges.judge_stability(scene, np.asarray(poses), protocol_stability(), judge="both")
    return {name: r.stable.tolist() for name, r in res.by_judge.items()}


def _open(path):
    return gzip.open(path, "rt") if str(path).endswith(".gz") else open(path)


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--pairs", required=True, help="per-pair JSONL(.gz) of eval_stage3")
    parser.add_argument("--data", default="datasets/paper")
    parser.add_argument("--per-category", type=int, default=20)
    parser.add_argument("--workers", type=int, default=0)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    try:
        with _open(args.pairs) as f:
            records = [json.loads(x) for x in f if x.strip()]
    except (OSError, json.JSONDecodeError) as err:
        print(f"judge_stage3: error: cannot read {args.pairs}: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    by_cat: dict[str, list] = {}
    for r in records:
        by_cat.setdefault(r["category"], []).append(r)
    chosen = []
    for rs in by_cat.values():  # evenly spaced within each category (deterministic)
        idx = np.linspace(0, len(rs) - 1, min(args.per_category, len(rs))).round().astype(int)
        chosen += [rs[i] for i in sorted(set(idx))]
    jobs = [(r["object"], r["support"], [r[s]["pose"] for s in STAGES]) for r in chosen]
    dataset_dir = dataset_bridge.resolve_dataset_dir(args.data)[0]
    if args.workers > 0:
        from sim.workers import spawn_pool

        with spawn_pool(args.workers, _init, (str(dataset_dir),)) as pool:
            verdicts = pool.map_async(_judge, jobs, chunksize=2).get()
    else:
        _init(str(dataset_dir))
        verdicts = [_judge(j) for j in jobs]
    out = {"pairs": len(chosen), "per_category": args.per_category, "source": args.pairs}
    for judge in ("mujoco", "pybullet", "both"):
        out[judge] = {}
        for i, stage in enumerate(STAGES):
            cats: dict[str, list] = {}
            for r, v in zip(chosen, verdicts, strict=True):
                ok = v["mujoco"][i] and v["pybullet"][i] if judge == "both" else v[judge][i]
                cats.setdefault(r["category"], []).append(bool(ok))
            out[judge][stage] = {
                "mean": float(100 * np.mean([np.mean(x) for x in cats.values()])),
                "per_category": {c: float(100 * np.mean(x)) for c, x in cats.items()},
            }
    agree = [v["mujoco"][i] == v["pybullet"][i] for v in verdicts for i in range(len(STAGES))]
    out["agreement"] = float(np.mean(agree))
    refine.write_json(args.out, out)
    print(json.dumps({j: {s: round(out[j][s]["mean"], 1) for s in STAGES}
                      for j in ("mujoco", "pybullet", "both")} | {"agreement": out["agreement"]}))  # fmt: skip
    return out


if __name__ == "__main__":
    _cli.run(main)
