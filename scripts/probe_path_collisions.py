"""Issue 13 diagnostic: where along the hybrid's returned paths the meshes collide, and what
the contact NCE said there; and the NCE's probability at the goals it calls colliding.

Reads an eval_paths run's per-pair records and saved paths (``--out`` folder: pairs.jsonl +
scenes/<pair>/<method>_path.npy), rebuilds the same 80 cases (same sample, same clouds), and
for every returned path checks it densely with the meshes (2 mm, planner metric), recording
for each penetrating state its depth, its distance to the goal (planner metric) and the NCE's
probability (the same subsampled clouds as the planner's checker). Prints a table and writes
JSON. CPU, ~4 min for 80 pairs on 2 cores.

    python scripts/probe_path_collisions.py --run out/paths80_s19_fast \
        --weights weights/collision_s18_contact \
        --pairs-from results/hanging_success_stage3_s14_cemv.pairs.jsonl.gz --pairs 80 \
        --out results/paths80_s19_fast_collisions.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import numpy as np
from scipy.spatial import cKDTree

from experiments import eval_paths
from omnihang_jax import collision, planner


def clearance(tree: cKDTree, object_points: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Smallest distance from the posed object cloud to the support cloud (``tree``), a pose:
    the quantity ``planner.ClearanceFarFromGoal`` thresholds."""
    return collision.cloud_gap(object_points, tree, poses)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", required=True, help="an eval_paths --out folder")
    ap.add_argument("--weights", required=True)
    ap.add_argument("--pairs-from", required=True)
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--method", default="nce_geometric")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    rows = {
        r["pair"]: r
        for r in map(json.loads, Path(args.run, "pairs.jsonl").read_text().splitlines())
        if r["method"] == args.method
    }
    cases = eval_paths.load_pairs(
        args.data, args.pairs, records=eval_paths.read_answers(args.pairs_from)
    )
    cfg, params, _ = collision.load_estimator(Path(args.weights, "nce"))
    prob = jax.jit(collision.nce_probability(cfg))
    sub = collision.subsample_cloud
    out = []
    for case in cases:
        row = rows.get(case.name)
        if row is None:
            continue
        weight = planner.object_radius(case.scene)
        oc = sub(case.object_points, cfg.object_input, eval_paths.SUBSET_SEED_OBJECT)
        sc = sub(case.support_points, cfg.support_input, eval_paths.SUBSET_SEED_SUPPORT)

        def p_of(poses, oc=oc, sc=sc):
            return np.concatenate([
                np.asarray(prob(params, oc, sc, np.asarray(poses[i : i + 64], np.float32)))
                for i in range(0, len(poses), 64)
            ])  # fmt: skip

        rec = dict(pair=case.name, category=case.meta["object_category"],
                   family=case.meta["support_family"], returned=row["returned"],
                   collision_free=row["collision_free"],
                   goal_called_colliding=row["goal_called_colliding"],
                   goal_p=float(p_of(case.goal[None])[0]))  # fmt: skip
        path_file = Path(args.run, "scenes", case.name, f"{args.method}_path.npy")
        if row["returned"] and path_file.exists():
            path = np.load(path_file)
            dense = planner.interpolate_path(path, 0.002, weight)
            mesh = collision.MeshChecker(case.scene, 1e-3)
            depth = mesh.penetration(dense)
            bad = depth > 1e-3
            dist = planner.goal_distances(dense, case.goal, weight)
            p = p_of(dense)
            tree = cKDTree(case.support_points)
            # the same object subsample as the checker (eval_paths --far-clearance)
            obj = sub(
                case.object_points, eval_paths.FAR_CLEARANCE_POINTS, eval_paths.SUBSET_SEED_OBJECT
            )
            clear = clearance(tree, obj, dense)
            rec |= dict(dense_states=len(dense), penetrating_states=int(bad.sum()))
            if bad.any():
                rec |= dict(
                    deepest_m=float(depth.max()),
                    goal_distance_m=dict(
                        min=float(dist[bad].min()),
                        max=float(dist[bad].max()),
                        at_deepest=float(dist[np.argmax(depth)]),
                    ),  # fmt: skip
                    nce_p=dict(
                        max=float(p[bad].max()),
                        median=float(np.median(p[bad])),
                        at_deepest=float(p[np.argmax(depth)]),
                    ),  # fmt: skip
                    # observed clouds' clearance at the penetrating states (m)
                    clearance_m=dict(min=float(clear[bad].min()), max=float(clear[bad].max())),
                )
            # the smallest observed clearance of the path's states beyond 5 / 10 cm of the goal
            for r in (0.05, 0.10):
                far = dist > r
                rec[f"min_clearance_beyond_{int(r * 100)}cm"] = (
                    float(clear[far].min()) if far.any() else None
                )
            # the NCE on the free path's states, for the threshold's other side
            rec["free_states_p_max_beyond_2cm"] = float(
                p[(~bad) & (dist > 0.02)].max() if ((~bad) & (dist > 0.02)).any() else 0.0
            )
        out.append(rec)
        print(json.dumps({k: v for k, v in rec.items() if k not in ("pair",)})[:300])
    summary = dict(
        run=args.run, weights=args.weights, method=args.method, threshold=cfg.threshold,
        pairs=out,
    )  # fmt: skip
    Path(args.out).write_text(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
