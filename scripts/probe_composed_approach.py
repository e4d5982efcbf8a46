"""Issue 13 probe (thirty-ninth session): does the approach network, asked twice, give a route
off the support? No new network and no planning.

The network (``approach.ApproachPredictor``) ranks 26 straight 4.5-cm moves from a pose by the
probability that the move is free; it was trained at stable goals. Here, for each goal: the
first move is the adopted rule's (best usable direction at ``--threshold``, open side), and at
its end (the pre-goal) the network is asked again for a second move (``--second-threshold``).
Each route is checked on the full meshes: free, and off the support (``MeshChecker.clearance``
>= ``--clear`` at its end); beside it the oracle's kinds (``probe_dogleg.py``).

    python scripts/probe_composed_approach.py --out results/paths_s39/composed_approach_heldout.json
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import numpy as np

from experiments import eval_paths
from omnihang_jax import approach, collision, planner


def best(net, case, pose, t: float):
    """(the best usable direction at ``t`` from ``pose``, open side, or None; its probability)."""
    dirs, probs = net.order(case.object_points, case.support_points, pose)
    keep = approach.usable(dirs, probs, t, case.wall_y is not None, True)
    return (dirs[keep][0], float(probs[keep][0])) if keep.any() else (None, float(probs[0]))


def segment(mesh, bounds, a, d, length: float):
    """(the straight move's end, whether the meshes call it free and it stays in ``bounds``)."""
    end, states = planner._retreat_states(a, d, length, 0.002, bounds)
    return end, states is not None and not planner.any_colliding(mesh, states)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs-from", default="out/paths_records.jsonl.gz")
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--approach", default="weights/approach_s37_8k")
    ap.add_argument("--threshold", type=float, default=0.8)
    ap.add_argument("--second-thresholds", type=float, nargs="+", default=[0.5, 0.7, 0.8, 0.9])
    ap.add_argument("--length", type=float, default=0.045)
    ap.add_argument("--clear", type=float, default=0.01)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    cases = eval_paths.load_pairs(
        args.data, args.pairs, records=eval_paths.read_answers(args.pairs_from)
    )
    net = approach.load_predictor([args.approach], args.threshold, 1)
    rows = []
    for case in cases:
        mesh = collision.MeshChecker(case.scene, 1e-3)
        lo, hi = planner.default_bounds(case.scene)
        bounds = (np.asarray(lo, float), np.asarray(hi, float))
        goal = np.asarray(case.goal, float)

        row = dict(pair=case.name, support_family=case.meta["support_family"])
        d1, p1 = best(net, case, goal, args.threshold)
        if d1 is None:
            row["first"] = None
            rows.append(row)
            continue
        pre, free1 = segment(mesh, bounds, goal, d1, args.length)
        row |= dict(first=d1.round(3).tolist(), p1=round(p1, 3), first_free=free1,
                    first_off=free1 and float(mesh.clearance(pre)[0]) >= args.clear)  # fmt: skip
        for t2 in args.second_thresholds:
            d2, p2 = best(net, case, pre, t2)
            if d2 is None:
                row[f"second@{t2:g}"] = None
                continue
            end, free2 = segment(mesh, bounds, pre, d2, args.length)
            row[f"second@{t2:g}"] = dict(
                direction=d2.round(3).tolist(), p=round(p2, 3), free=free1 and free2,
                off=free1 and free2 and float(mesh.clearance(end)[0]) >= args.clear,
            )  # fmt: skip
        rows.append(row)
    used = [r for r in rows if r.get("first") is not None]
    summary = dict(goals=len(rows), first_used=len(used),
                   first_free=sum(r["first_free"] for r in used),
                   first_off=sum(r["first_off"] for r in used))  # fmt: skip
    for t2 in args.second_thresholds:
        k = f"second@{t2:g}"
        two = [r for r in used if r.get(k)]
        summary[k] = dict(
            used=len(two), free=sum(r[k]["free"] for r in two), off=sum(r[k]["off"] for r in two),
            off_where_first_not=sum(r[k]["off"] and not r["first_off"] for r in two),
            first_off_lost=sum(r["first_off"] and not r[k]["off"] for r in two),
            by_family=dict(Counter(r["support_family"] for r in two if r[k]["off"] and not r["first_off"])),
        )  # fmt: skip
    result = dict(settings=vars(args), summary=summary, pairs=rows)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    return result


if __name__ == "__main__":
    main()
