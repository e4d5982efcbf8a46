"""Issue 13 probe (thirty-ninth session): does the observed clearance along a returned path tell
a colliding path from a free one?

For every returned path of one or more ``eval_paths`` runs (``--out`` folders with pairs.jsonl
and scenes/<pair>/<method>_path.npy), the path is interpolated at ``--resolution`` (planner
metric) and, at every state, the observed clearance is measured: the smallest distance from the
posed observed object cloud (a fixed 512-point subsample, as ``planner.clear_path`` measures it)
to the observed support cloud. Per path it reports the smallest clearance in rings of distance
from the goal (``--rings``, planner metric), and whether the path collided (the run's
``collision_free``). A path-level refusal "return no path when the clearance beyond r from the
goal is below g" can then be scored exactly from the same runs (a refused path becomes a pair
without a path): ``summarise`` does that over a grid of (r, g), per support family too.

    python scripts/probe_path_gaps.py measure --runs out/s36/paths80_rule_seed1 ... --out F.json
    python scripts/probe_path_gaps.py summarise --gaps F.json [--family pegboard_hook] --out G.json

The runs' pairs are the held-out planning pairs, so a rule read off them is optimistic; this
probe says whether such a test can work, not which threshold to adopt.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

RINGS = (0.0, 0.02, 0.045, 0.08, 0.12)  # m, planner metric: distance-from-goal lower bounds


def measure(args) -> dict:
    from scipy.spatial import cKDTree

    from experiments import eval_paths
    from omnihang_jax import planner
    from omnihang_jax.collision import posed_points, subsample_cloud

    runs = {run: eval_paths.read_rows(Path(run, "pairs.jsonl"), args.method) for run in args.runs}
    names = {p for rows in runs.values() for p, r in rows.items() if r["returned"]}
    cases = eval_paths.load_pairs(
        args.data, args.pairs, records=eval_paths.read_answers(args.pairs_from), names=names
    )
    out = []
    for case in cases:
        tree = cKDTree(case.support_points)
        obj = subsample_cloud(case.object_points, 512, seed=0)
        weight = planner.object_radius(case.scene)
        for run, rows in runs.items():
            row = rows.get(case.name)
            if row is None or not row["returned"]:
                continue
            path_file = Path(run, "scenes", case.name, f"{args.method}_path.npy")
            if not path_file.exists():
                print(f"note: {path_file} missing; skipped")
                continue
            dense = planner.interpolate_path(np.load(path_file), args.resolution, weight)
            from_goal = planner.goal_distances(dense, case.goal, weight)
            moved = posed_points(dense, obj)  # [K, N, 3]
            gap = tree.query(moved.reshape(-1, 3), k=1)[0].reshape(len(dense), -1).min(axis=1)
            rings = {}
            for r in args.rings:
                m = from_goal > r
                rings[f"{r:g}"] = round(float(gap[m].min()), 5) if m.any() else None
            out.append(dict(
                run=run, pair=case.name, support_family=case.meta["support_family"],
                object_category=case.meta["object_category"],
                collision_free=bool(row["collision_free"]), min_gap_beyond=rings,
                approach_used=(row.get("approach") or {}).get("first_tried") is not None,
            ))  # fmt: skip
    result = dict(runs=args.runs, method=args.method, resolution=args.resolution,
                  rings=list(args.rings), paths=out)  # fmt: skip
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(f"{len(out)} returned paths measured -> {args.out}")
    return result


def score(paths: list[dict], pairs_per_run: dict, refuse) -> dict:
    """Precision / recall / F1 over runs (mean over runs) when ``refuse(path)`` drops a path."""
    per_run = defaultdict(lambda: dict(returned=0, free=0, refused_free=0, refused_colliding=0))
    for p in paths:
        s = per_run[p["run"]]
        if refuse(p):
            s["refused_free" if p["collision_free"] else "refused_colliding"] += 1
            continue
        s["returned"] += 1
        s["free"] += p["collision_free"]
    f1s, precs, recs = [], [], []
    for run, s in per_run.items():
        prec = s["free"] / max(s["returned"], 1)
        rec = s["free"] / pairs_per_run[run]
        f1s.append(2 * prec * rec / max(prec + rec, 1e-9))
        precs.append(prec)
        recs.append(rec)
    return dict(
        precision=round(100 * float(np.mean(precs)), 1), recall=round(100 * float(np.mean(recs)), 1),
        f1=round(100 * float(np.mean(f1s)), 1),
        refused_free=sum(s["refused_free"] for s in per_run.values()),
        refused_colliding=sum(s["refused_colliding"] for s in per_run.values()),
    )  # fmt: skip


def summarise(args) -> dict:
    data = json.loads(Path(args.gaps).read_text())
    paths = data["paths"]
    from experiments import eval_paths

    pairs_per_run = {}
    for run in data["runs"]:
        rows = eval_paths.read_rows(Path(run, "pairs.jsonl"), data["method"])
        pairs_per_run[run] = len(rows)  # recall = free paths / all pairs, as eval_paths.summarise
    base = score(paths, pairs_per_run, lambda p: False)
    grid = []
    for ring in data["rings"]:
        key = f"{ring:g}"
        for g in args.gaps_mm:

            def refuse(p, key=key, g=g):
                if args.family and p["support_family"] not in args.family:
                    return False
                v = p["min_gap_beyond"].get(key)
                return v is not None and v * 1e3 < g

            grid.append(dict(ring_m=ring, gap_mm=g, **score(paths, pairs_per_run, refuse)))
    fam = defaultdict(lambda: dict(free=0, colliding=0))
    for p in paths:
        fam[p["support_family"]]["free" if p["collision_free"] else "colliding"] += 1
    result = dict(gaps=args.gaps, family=args.family, baseline=base, by_family=dict(fam), grid=grid)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print("baseline", base)
    for g in sorted(grid, key=lambda r: -r["f1"])[:12]:
        print(g)
    return result


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("measure", help="the observed clearance along every returned path")
    m.add_argument("--runs", nargs="+", required=True, help="eval_paths --out folders")
    m.add_argument("--pairs-from", default="out/paths_records.jsonl.gz")
    m.add_argument("--pairs", type=int, default=80)
    m.add_argument("--data", default="datasets/paper")
    m.add_argument("--method", default="nce_geometric")
    m.add_argument("--resolution", type=float, default=0.005, help="m, planner metric")
    m.add_argument("--rings", type=float, nargs="+", default=list(RINGS))
    m.add_argument("--out", required=True)
    s = sub.add_parser("summarise", help="score path refusals by clearance from the measures")
    s.add_argument("--gaps", required=True, help="measure's JSON")
    s.add_argument("--gaps-mm", type=float, nargs="+", default=[1, 2, 3, 4, 5, 6, 8, 10, 15])
    s.add_argument("--family", nargs="*", default=None, help="refuse only on these families")
    s.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    return measure(args) if args.cmd == "measure" else summarise(args)


if __name__ == "__main__":
    main()
