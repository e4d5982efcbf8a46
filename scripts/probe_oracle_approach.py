"""Issue 13 probe: what would a right approach over the goal's last centimetres be worth?

For every held-out pair of one or more ``eval_paths`` runs (``--out`` folders with pairs.jsonl
and scenes/<pair>/<method>_path.npy), this script

1. searches an *oracle* straight approach: the first of the planner's 26 retreat directions
   (``planner.RETREAT_DIRECTIONS``, upward first) whose orientation-keeping segment of length
   ``--ball`` from the goal the full meshes call free at every 2-mm state
   (``planner.find_retreat`` with ``collision.MeshChecker``: a checker no estimator matches);
2. checks every returned path densely with the meshes (2 mm, planner metric) and sorts it:
   free, colliding only within ``--ball`` of the goal ("near"), or colliding farther ("far");
3. counts the paths an approach of that kind would make free: the near-only colliding paths
   of pairs that have an oracle approach, if the path's part beyond the ball were joined to
   the approach's far end for nothing. That is an upper bound on the lever "learn the approach
   (e.g. the take-off test's removal direction) and plan to a pre-goal": it ignores the time
   the plan to the pre-goal takes (the twentieth session's retreat lost it there) and the
   junction.

CPU only; ~1 s a path on 2 cores. Writes JSON with every path's class and each run's
precision / recall / F1 as planned and with the bound.

    python scripts/probe_oracle_approach.py --runs out/paths80_s33_replan_seed1 \\
        out/s34/paths80_replan_seed2 --out results/paths80_s34_oracle_approach_probe.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from experiments import eval_paths
from omnihang_jax import collision, planner


def classify(penetration: np.ndarray, distance: np.ndarray, ball: float, tol: float) -> str:
    """'free', 'near' (every penetrating state within ``ball`` of the goal) or 'far'."""
    bad = penetration > tol
    if not bad.any():
        return "free"
    return "near" if float(distance[bad].max()) <= ball else "far"


def prf(returned: int, free: int, pairs: int) -> dict:
    """Precision, recall and F1 (percent, one decimal) as ``eval_paths.summarise`` gives them."""
    p = 100.0 * free / returned if returned else 0.0
    r = 100.0 * free / pairs if pairs else 0.0
    f = 2 * p * r / (p + r) if p + r else 0.0
    return dict(returned=returned, collision_free=free, precision=round(p, 1),
                recall=round(r, 1), f1=round(f, 1))  # fmt: skip


def bound(classes: list[str], has_approach: list[bool], pairs: int) -> dict:
    """The run's figures as planned and with every near-only colliding path of a pair with an
    oracle approach counted free."""
    returned = len(classes)
    free = sum(c == "free" for c in classes)
    fixed = sum(c == "near" and a for c, a in zip(classes, has_approach))
    return dict(as_planned=prf(returned, free, pairs), with_oracle_approach=prf(returned, free + fixed, pairs),
                near_only=sum(c == "near" for c in classes), far=sum(c == "far" for c in classes),
                near_only_with_approach=fixed)  # fmt: skip


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, help="eval_paths --out folders")
    ap.add_argument(
        "--pairs-from", default="results/hanging_success_stage3_s14_cemv.pairs.jsonl.gz"
    )
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--method", default="nce_geometric")
    ap.add_argument("--ball", type=float, default=0.045, help="m, planner metric (default 4.5 cm)")
    ap.add_argument("--tolerance", type=float, default=1e-3, help="m of penetration (evaluation)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    runs = {}
    for run in args.runs:
        rows = [json.loads(x) for x in Path(run, "pairs.jsonl").read_text().splitlines()]
        runs[run] = {r["pair"]: r for r in rows if r["method"] == args.method}  # last row counts
    cases = eval_paths.load_pairs(
        args.data, args.pairs, records=eval_paths.read_answers(args.pairs_from)
    )
    pairs, per_run = [], {run: ([], []) for run in args.runs}
    for case in cases:
        weight = planner.object_radius(case.scene)
        mesh = collision.MeshChecker(case.scene, args.tolerance)
        bounds = planner.default_bounds(case.scene)
        approach = planner.find_retreat(mesh, case.goal, [args.ball], 0.002, bounds)
        rec = dict(pair=case.name, category=case.meta["object_category"],
                   oracle_approach=None if approach is None else approach.direction.tolist(),
                   runs={})  # fmt: skip
        for run, rows in runs.items():
            row = rows.get(case.name)
            path_file = Path(run, "scenes", case.name, f"{args.method}_path.npy")
            if row is None or not row["returned"]:
                continue
            if not path_file.exists():
                raise SystemExit(f"{path_file} missing: the run's paths are needed")
            dense = planner.interpolate_path(np.load(path_file), 0.002, weight)
            depth = mesh.penetration(dense)
            dist = planner.goal_distances(dense, case.goal, weight)
            kind = classify(depth, dist, args.ball, args.tolerance)
            if (kind == "free") != bool(row["collision_free"]):
                print(f"note: {case.name} in {run}: dense check says {kind}, the run said "
                      f"collision_free={row['collision_free']}")  # fmt: skip
            rec["runs"][run] = dict(kind=kind, deepest_m=float(depth.max()))
            per_run[run][0].append(kind)
            per_run[run][1].append(approach is not None)
        pairs.append(rec)
        print(case.name, "approach" if approach is not None else "no approach",
              {Path(r).name: v["kind"] for r, v in rec["runs"].items()})  # fmt: skip
    summary = dict(
        ball_m=args.ball, tolerance_m=args.tolerance, method=args.method, pairs_total=len(cases),
        pairs_with_oracle_approach=sum(p["oracle_approach"] is not None for p in pairs),
        runs={run: bound(k, a, len(cases)) for run, (k, a) in per_run.items()}, pairs=pairs,
    )  # fmt: skip
    Path(args.out).write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps({k: v for k, v in summary.items() if k != "pairs"}, indent=1))
    return summary


if __name__ == "__main__":
    main()
