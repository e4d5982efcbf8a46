"""Issue 13 probe (thirty-eighth session): where do the colliding paths touch, and did the
observed clouds show it?

For every colliding path of one or more ``eval_paths`` runs (``--out`` folders with pairs.jsonl
and scenes/<pair>/<method>_path.npy), the path is interpolated at 2 mm (planner metric) and
checked with MuJoCo's contacts on the full meshes; the deepest object-support contact deeper
than ``--tolerance`` is reported with its distance from the goal (planner metric), its height
in front of the wall plane (support frame y minus ``wall_y``; None for free-standing supports)
and the distance from the contact point to the nearest observed object point (the pair's
partial cloud posed at that state) and observed support point. A contact far from every
observed object point is made by the object's unobserved side; near both clouds, the estimators
passed a state the observed clouds nearly show.

    python scripts/probe_contacts.py --runs out/s36/paths80_rule_seed1 out/s36/paths80_rule_seed2 \\
        --out results/paths_s38/contacts_s36_seeds12.json          # ~3 min, CPU
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from experiments import eval_paths
from omnihang_jax import collision, planner


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, help="eval_paths --out folders")
    ap.add_argument("--pairs-from", default="out/paths_records.jsonl.gz")
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--method", default="nce_geometric")
    ap.add_argument("--tolerance", type=float, default=1e-3, help="m of penetration")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    from scipy.spatial import cKDTree

    runs = {}
    for run in args.runs:
        rows = [json.loads(x) for x in Path(run, "pairs.jsonl").read_text().splitlines()]
        runs[run] = {r["pair"]: r for r in rows if r["method"] == args.method}
    names = {p for rows in runs.values() for p, r in rows.items()
             if r["returned"] and not r["collision_free"]}  # fmt: skip
    cases = eval_paths.load_pairs(args.data, args.pairs, records=eval_paths.read_answers(args.pairs_from), names=names)  # fmt: skip
    out = []
    for case in cases:
        support_tree = cKDTree(case.support_points)
        checker = collision.MeshChecker(case.scene, args.tolerance)
        weight = planner.object_radius(case.scene)
        for run, rows in runs.items():
            row = rows.get(case.name)
            if row is None or not row["returned"] or row["collision_free"]:
                continue
            path = np.load(Path(run, "scenes", case.name, f"{args.method}_path.npy"))
            dense = planner.interpolate_path(path, 0.002, weight)
            depths, points = checker.deepest_contacts(dense)
            i = int(np.argmax(depths))
            if depths[i] <= args.tolerance:
                print(f"note: {case.name} in {run}: no contact deeper than the tolerance")
                continue
            depth, pos = float(depths[i]), points[i]
            posed = collision.posed_points(dense[i], case.object_points)[0]
            rec = dict(
                run=run, pair=case.name, support_family=case.meta["support_family"],
                object_category=case.meta["object_category"], depth_mm=round(depth * 1e3, 1),
                from_goal_cm=round(float(planner.goal_distances(dense[i : i + 1], case.goal, weight)[0]) * 100, 1),
                in_front_of_wall_cm=None if case.wall_y is None else round((pos[1] - case.wall_y) * 100, 1),
                to_observed_object_mm=round(float(np.min(np.linalg.norm(posed - pos, axis=1))) * 1e3, 1),
                to_observed_support_mm=round(float(support_tree.query(pos)[0]) * 1e3, 1),
                approach_used=(row.get("approach") or {}).get("first_tried") is not None,
            )  # fmt: skip
            out.append(rec)
            print(rec, flush=True)
    by_family = defaultdict(lambda: dict(paths=0, object_unobserved=0, both_observed=0))
    for r in out:
        f = by_family[r["support_family"]]
        f["paths"] += 1
        f["object_unobserved"] += r["to_observed_object_mm"] > 20
        f["both_observed"] += r["to_observed_object_mm"] <= 10 and r["to_observed_support_mm"] <= 10
    summary = dict(runs=args.runs, tolerance_m=args.tolerance, colliding_paths=len(out),
                   by_family=dict(by_family), paths=out)  # fmt: skip
    Path(args.out).write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(dict(by_family), indent=1))
    return summary


if __name__ == "__main__":
    main()
