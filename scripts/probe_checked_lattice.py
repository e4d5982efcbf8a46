"""Issue 13 probe (forty-third session): a lattice route off the support searched with the
planner's own checker, against the truth on the full meshes.

The thirty-ninth session's lattice oracle (``planner.lattice_retreat`` on the meshes) made 15 of
its 19 threaded goals free; the learned routes (fortieth-forty-second sessions) cover one- and
two-move routes only. This asks whether the same breadth-first search over translations from
the goal, with **the best planner's checker** (the hybrid: the observed-cloud test, then the
contact NCE, lenient within 2 cm of the goal) as its edge test and **an observed end gap**
(``collision.cloud_gap`` between the posed observed object cloud and the observed support cloud
>= ``--end-gap``) as its end, finds routes that are truly good: every state free on the full
meshes (penetration <= 1 mm, at 2 mm) and the end >= 1 cm off the support and the wall
(``MeshChecker.clearance``), the label of the route networks and of the oracle.

Per goal: its kind (``results/paths_s39/dogleg_heldout.json``), what the adopted rule decides
(a checked route, a straight approach, or nothing: ``eval_paths.learned_route`` /
``learned_approach`` with the adopted flags), and per lattice step the checker's route (found,
nodes, length, seconds) and its truth. A fallback rule would take the lattice route where the
adopted rule gives no route: the summary counts found / truly good by kind and decision.

    python scripts/probe_checked_lattice.py --shard 0/4 --out out/s43/lattice_0.json   # per shard
    python scripts/probe_checked_lattice.py --summarise out/s43/lattice_*.json --out results/paths_s43/checked_lattice.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import types
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from tqdm.auto import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
import probe_route_check  # noqa: E402
import probe_route_rule  # noqa: E402

from experiments import eval_paths  # noqa: E402
from omnihang_jax import approach, collision, planner  # noqa: E402

CLEAR = 0.01  # m: the truth's "off the support" (the route label's and the oracle's)


def route_truth(mesh, goal, found, resolution: float = 0.002) -> dict:
    """Is the route (goal -> via ... -> end) free on the meshes, and is its end off?"""
    points = [np.asarray(goal, float)] + [np.asarray(v, float) for v in found.via[::-1]]
    points.append(np.asarray(found.pregoal, float))
    states = np.concatenate([
        planner.interpolate_segment(a, b, max(1, int(np.ceil(np.linalg.norm(b[:3] - a[:3]) / resolution))))
        for a, b in zip(points[:-1], points[1:], strict=True)
    ])  # fmt: skip
    deepest = float(mesh.penetration(states).max())
    end_clear = float(mesh.clearance(found.pregoal[None])[0])
    return dict(free=deepest <= 1e-3, deepest_m=round(deepest, 5), end_clear_m=round(end_clear, 4),
                good=deepest <= 1e-3 and end_clear >= CLEAR)  # fmt: skip


def summarise(rows: list[dict], steps) -> dict:
    """Found / truly good per step, by goal kind and by the adopted rule's decision."""
    out = {}
    for step in steps:
        key = f"{step:g}"
        table = defaultdict(Counter)
        for r in rows:
            lat = r["lattice"].get(key)
            if lat is None:
                continue
            for group in ("all", f"kind:{r['kind']}", f"decision:{r['decision']}",
                          f"kind:{r['kind']}|decision:{r['decision']}"):  # fmt: skip
                c = table[group]
                c["goals"] += 1
                c["found"] += bool(lat["found"])
                c["good"] += bool(lat["found"] and lat["truth"]["good"])
                c["free"] += bool(lat["found"] and lat["truth"]["free"])
        out[key] = {
            g: dict(c, good_of_found=round(c["good"] / c["found"], 3) if c["found"] else None)
            for g, c in sorted(table.items())
        }
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--routes", default="weights/approach_routes_s40_8k")
    ap.add_argument("--routes-threshold", type=float, default=0.3)
    ap.add_argument("--end-gap", type=float, default=0.01, help="observed end gap (m)")
    probe_route_check.add_planner_args(ap)
    ap.add_argument("--steps", type=float, nargs="+", default=[0.015, 0.0075])
    ap.add_argument("--max-nodes", type=int, default=3000)
    ap.add_argument("--kinds", default="results/paths_s39/dogleg_heldout.json")
    ap.add_argument("--pairs-from", default="out/paths_records.jsonl.gz")
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--goals", choices=("all", "no-route"), default="no-route",
                    help="search every goal, or only where the adopted rule gives no route")  # fmt: skip
    ap.add_argument("--shard", default="0/1", metavar="I/N")
    ap.add_argument("--summarise", nargs="+", default=None, metavar="JSON",
                    help="merge shard outputs (no search)")  # fmt: skip
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    if args.summarise:
        rows, settings = [], None
        for f in args.summarise:
            part = json.loads(Path(f).read_text())
            rows += part["rows"]
            settings = settings or part["settings"]
        steps = settings["steps"]
        result = dict(settings=settings, goals=len(rows), summary=summarise(rows, steps), rows=rows)
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
        print(json.dumps(result["summary"], indent=1))
        return result

    i, n = (int(v) for v in args.shard.split("/"))
    kinds = probe_route_rule.goal_kinds(args.kinds)
    cases = eval_paths.load_pairs(
        args.data, args.pairs, records=eval_paths.read_answers(args.pairs_from)
    )[i::n]
    est = types.SimpleNamespace(
        approach=approach.load_predictor(args.approach, args.approach_threshold),
        approach_open_side=True, approach_check="none",
        routes=approach.load_predictor(args.routes, args.routes_threshold),
        routes_check="checker", routes_end_gap=args.end_gap, routes_tries=10,
    )  # fmt: skip
    nce_cfg, nce_params, _ = collision.load_estimator(Path(args.weights, "nce"))
    settings = probe_route_check.hybrid_settings(
        args.geometric, args.nce_threshold, args.nce_far_threshold, args.nce_goal_ball
    )
    rows, t0 = [], time.perf_counter()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)

    def write():  # after every goal: a killed shard keeps what it searched
        result = dict(settings=vars(args), seconds=round(time.perf_counter() - t0, 1), rows=rows)
        out.write_text(json.dumps(result, indent=1) + "\n")
        return result

    for case in tqdm(cases, desc=f"goals {args.shard}", disable=args.no_progress):
        weight = planner.object_radius(case.scene)
        bounds = planner.default_bounds(case.scene)
        check = planner.hybrid_checker(
            nce_cfg, nce_params, case.object_points, case.support_points, case.support_normals,
            settings, case.goal, weight, pow2=True,
        )  # fmt: skip
        directions, _, _ = eval_paths.learned_approach(case, est)
        found, record = eval_paths.learned_route(case, est, check, args.resolution)
        decision = "route" if found is not None else "straight" if len(directions) else "none"
        row = dict(pair=case.name, family=case.meta["support_family"],
                   kind=kinds.get(case.name, "unknown"), decision=decision, lattice={})  # fmt: skip
        if args.goals == "no-route" and decision == "route":
            rows.append(row)
            write()
            continue
        mesh = collision.MeshChecker(case.scene, 1e-3)
        tree = cKDTree(np.asarray(case.support_points, float))

        def off(pose, tree=tree, case=case):
            gap = collision.cloud_gap(case.object_points, tree, pose[None], upper=args.end_gap)
            return bool(gap[0] >= args.end_gap)

        for step in args.steps:
            t = time.perf_counter()
            lat, expanded = planner.lattice_retreat(
                check, case.goal, step, off, args.max_nodes, bounds, args.resolution
            )
            entry = dict(found=lat is not None, nodes=expanded,
                         seconds=round(time.perf_counter() - t, 2))  # fmt: skip
            if lat is not None:
                entry |= dict(waypoints=len(lat.via) + 1,
                              length_m=round(float(np.linalg.norm(lat.pregoal[:3] - case.goal[:3])), 4),
                              truth=route_truth(mesh, case.goal, lat))  # fmt: skip
            row["lattice"][f"{step:g}"] = entry
        rows.append(row)
        write()
    result = write()
    print(json.dumps(summarise(rows, args.steps)[f"{args.steps[0]:g}"].get("all"), indent=1))
    return result


if __name__ == "__main__":
    main()
