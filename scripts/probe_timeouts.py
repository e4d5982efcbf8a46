"""Issue 13 diagnostic (thirtieth session): why does the best hybrid time out?

The mesh planner (the ground truth's checker) finds a path in ~95 % of pairs in a median of
0.04 s, so the true passage is rarely narrow. For every pair a run timed out on, this plans
``--mesh-paths`` paths with the mesh checker (OMPL's stream goes on between plans, so they
differ), interpolates each at the planner's resolution and asks the hybrid's parts what they
call every state: the observed-cloud penetration test, the NCE (with its goal-ball threshold)
and the hybrid (the test OR the NCE). Per pair: is some true path free for the hybrid (then the
time-out is the search's), and otherwise where (distance to the goal, planner metric) and by
which part each true path is first blocked, and at what NCE probability.

    python scripts/probe_timeouts.py --run out/paths80_s24_keep45 --out results/paths80_s30_timeout_probe.json

The estimator settings default to the best hybrid's (docs/paths.md, twenty-fourth session).
CPU, ~1 min a pair. The true paths graze the meshes (shallower than 1 mm is free). Keeping a
clearance through MuJoCo's geom margin did not work on these meshes (contacts were reported
from about 2 mm only), so the probe has no clearance option.
"""

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np
from probe_nce_paths import scores_of  # scripts/ (this script's folder) is on sys.path

from experiments import eval_paths
from omnihang_jax import collision, planner

BANDS = (0.005, 0.01, 0.02, 0.045, 0.10, np.inf)  # m from the goal (planner metric)


def band_of(d: float) -> str:
    lo = 0.0
    for hi in BANDS:
        if d <= hi:
            return f"{lo * 100:g}-{hi * 100:g} cm" if np.isfinite(hi) else f">{lo * 100:g} cm"
        lo = hi
    raise AssertionError


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", required=True, help="an eval_paths --out folder (its pairs.jsonl)")
    ap.add_argument("--method", default="nce_geometric")
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--weights", default="weights/collision_s18_contact")
    ap.add_argument("--geometric", default="results/paths_hybrid_s18_joint95_selection.json")
    ap.add_argument(
        "--pairs-from", default="results/hanging_success_stage3_s14_cemv.pairs.jsonl.gz"
    )
    ap.add_argument("--pairs", type=int, default=80, help="the run's --pairs")
    ap.add_argument("--nce-threshold", type=float, default=0.99)
    ap.add_argument("--nce-far-threshold", type=float, default=0.56)
    ap.add_argument("--nce-goal-ball", type=float, default=0.02)
    ap.add_argument("--mesh-paths", type=int, default=5, help="true paths planned a pair")
    ap.add_argument("--mesh-time", type=float, default=5.0, help="s per mesh plan")
    ap.add_argument("--limit", type=int, default=0, help="only the first N time-out pairs")
    ap.add_argument("--out", default=None, help="JSON")
    args = ap.parse_args(argv)
    rows = [json.loads(x) for x in Path(args.run, "pairs.jsonl").read_text().splitlines() if x]
    latest = {(r["pair"], r["method"]): r for r in rows}
    timeouts = sorted(
        r["pair"] for (p, m), r in latest.items() if m == args.method and not r["returned"]
    )
    if args.limit:
        timeouts = timeouts[: args.limit]
    geo = collision.GeometricConfig()
    chosen = json.loads(Path(args.geometric).read_text())["chosen"]
    geo = dataclasses.replace(geo, **{k: chosen[k] for k in ("depth", "radius", "min_points")})
    est = eval_paths.load_estimators(
        args.weights, args.nce_threshold, args.nce_far_threshold, args.nce_goal_ball, geo
    )
    nce_cfg = est.nce_config
    prob = jax.jit(collision.nce_probability(nce_cfg))
    records = eval_paths.read_answers(args.pairs_from)
    cases = eval_paths.load_pairs(args.data, args.pairs, 1, False, records, False)
    cases = [c for c in cases if c.name in set(timeouts)]
    cfg = planner.PlannerConfig(time_limit=args.mesh_time)
    sub = collision.subsample_cloud
    out_pairs = []
    for case in cases:
        t0 = time.time()
        weight = planner.object_radius(case.scene)
        bounds = planner.default_bounds(case.scene)
        start = planner.start_pose(case.scene, case.goal)
        ch = eval_paths.checkers_for(case, est, cfg.penetration_tolerance, ("nce_geometric",))
        oc, sc = eval_paths.nce_clouds(case, nce_cfg)
        oc = sub(oc, nce_cfg.object_input, eval_paths.SUBSET_SEED_OBJECT)
        sc = sub(sc, nce_cfg.support_input, eval_paths.SUBSET_SEED_SUPPORT)
        mesh = planner.MeshChecker(case.scene, cfg.penetration_tolerance)
        paths = []
        for _ in range(args.mesh_paths):
            res = planner.plan(mesh, start, case.goal, bounds, weight, cfg)
            if res.path is None:
                continue
            dense = planner.interpolate_path(res.path, cfg.resolution, weight)
            d = planner.goal_distances(dense, case.goal, weight)
            keep = d > cfg.goal_radius  # the goal itself is exempt, as in the planner
            dense, d = dense[keep], d[keep]
            geo_flag = np.asarray(ch["geometric"](dense), bool)
            # one NCE pass (padded chunks: one compiled shape): its probability, and the
            # hybrid's NCE verdict from it by the goal-ball rule (collision.goal_ball_collides)
            p = scores_of(prob, est.nce_params, oc, sc, dense)
            near = d <= args.nce_goal_ball
            nce_flag = p > np.where(near, args.nce_threshold, args.nce_far_threshold)
            hyb = geo_flag | nce_flag
            item = dict(states=len(dense), free_for_hybrid=bool(not hyb.any()),
                        geometric_flags=int(geo_flag.sum()), nce_flags=int(nce_flag.sum()),
                        max_p_near=round(float(p[near].max()), 4) if near.any() else 0.0,
                        max_p_far=round(float(p[~near].max()), 4) if (~near).any() else 0.0)  # fmt: skip
            if hyb.any():
                # the blockage nearest the goal: the last flagged state walking from the start
                # (the goal tree must pass it), and the farthest one
                idx = np.flatnonzero(hyb)
                item |= dict(
                    nearest_block_m=round(float(d[idx].min()), 4),
                    farthest_block_m=round(float(d[idx].max()), 4),
                    bands={b: int(n) for b, n in zip(*np.unique([band_of(x) for x in d[idx]],
                                                                return_counts=True))},  # fmt: skip
                    by=("both" if geo_flag.any() and nce_flag.any()
                        else "geometric" if geo_flag.any() else "nce"),  # fmt: skip
                    nce_p_flagged_median=round(float(np.median(p[nce_flag])), 3)
                    if nce_flag.any() else None,
                )  # fmt: skip
            paths.append(item)
        goal_called = bool(ch["nce_geometric"](case.goal[None])[0])
        row = dict(
            pair=case.name, category=case.meta["object_category"],
            family=case.meta["support_family"], goal_called_colliding=goal_called,
            mesh_paths=len(paths), some_true_path_free=any(p["free_for_hybrid"] for p in paths),
            paths=paths, seconds=round(time.time() - t0, 1),
        )  # fmt: skip
        out_pairs.append(row)
        nb = [p.get("nearest_block_m") for p in paths if not p["free_for_hybrid"]]
        print(f"{case.name}: {len(paths)} true paths, free for the hybrid "
              f"{sum(p['free_for_hybrid'] for p in paths)}, blocks by "
              f"{[p.get('by') for p in paths]}, nearest block {nb} m", flush=True)  # fmt: skip
    blocked = [p for r in out_pairs for p in r["paths"] if not p["free_for_hybrid"]]
    summary = dict(
        run=args.run, method=args.method, timeouts=len(timeouts), probed=len(out_pairs),
        pairs_with_a_true_path_free_for_the_hybrid=sum(r["some_true_path_free"] for r in out_pairs),
        goal_called_colliding=sum(r["goal_called_colliding"] for r in out_pairs),
        true_paths=sum(r["mesh_paths"] for r in out_pairs),
        blocked_true_paths=len(blocked),
        blocked_by={k: sum(p["by"] == k for p in blocked) for k in ("geometric", "nce", "both")},
        nearest_block_band={b: sum(band_of(p["nearest_block_m"]) == b for p in blocked)
                            for b in sorted({band_of(p["nearest_block_m"]) for p in blocked})},  # fmt: skip
        # would a laxer NCE beyond the goal ball free some true path (the test and the near
        # threshold as they are)? pairs with such a path, per far threshold
        pairs_free_at_far_threshold={
            str(t): sum(any(p["geometric_flags"] == 0 and p["max_p_near"] <= args.nce_threshold
                            and p["max_p_far"] <= t for p in r["paths"]) for r in out_pairs)
            for t in (0.56, 0.6, 0.7, 0.8, 0.9, 0.95, 0.99, 1.0)
        },  # fmt: skip
        pairs_free_without_the_test_at_far_threshold={
            str(t): sum(any(p["max_p_near"] <= args.nce_threshold and p["max_p_far"] <= t
                            for p in r["paths"]) for r in out_pairs)
            for t in (0.56, 0.7, 0.8, 0.9, 0.99, 1.0)
        },  # fmt: skip
        settings=vars(args),
        pairs=out_pairs,
    )  # fmt: skip
    print(
        json.dumps({k: v for k, v in summary.items() if k not in ("pairs", "settings")}, indent=1)
    )
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
