"""Issue 13 diagnostic (twenty-fifth session): do completed clouds see the hybrid's far collisions?

For every returned path of eval_paths runs (the paths as saved: cleared where the run cleared
them), the dense states (2 mm) are checked with the meshes (``MeshChecker``, 1 mm). Beyond R of
the goal (the planner's metric), the smallest gap between the posed object cloud and the
support cloud is measured twice: with the observed clouds, and with the completed clouds
(observed + ``omnihang_jax.completion``'s predicted points, object and support). Printed per
margin M: the colliding paths with a far penetrating state whose gap is below M (caught), and
the free paths with any far state below M (which a planner would have to route around).
CPU, about a minute a run.

    python scripts/probe_completion.py --runs out/paths80_s24_keep45,out/paths80_s24_keep45_seed2 \\
        --completion weights/completion_s25 --out results/paths80_s25_completion_probe.json
"""

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from omnihang_jax import collision, completion, dataset_bridge, planner
from sim.library import build_library
from sim.scene import build_scene

MARGINS = (0.003, 0.005, 0.008, 0.012)


def far_gaps(dense, far, obj, tree, chunk=64):
    """Smallest cloud gap per dense state (inf where not far)."""
    gap = np.full(len(dense), np.inf)
    idx = np.flatnonzero(far)
    for a in range(0, len(idx), chunk):
        sel = idx[a : a + chunk]
        gap[sel] = collision.cloud_gap(obj, tree, dense[sel], 0.05)
    return gap


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", required=True, help="eval_paths --out folders, comma-separated")
    ap.add_argument("--completion", default="weights/completion_s25")
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--radius", type=float, default=0.045, help="m: the goal ball left out")
    ap.add_argument("--object-points", type=int, default=1024, help="observed object points kept")
    ap.add_argument(
        "--carve",
        action="store_true",
        help="drop predicted points the cameras would have seen (completion.carve)",
    )
    ap.add_argument("--out", default=None, help="JSON")
    args = ap.parse_args(argv)
    nets = completion.load_nets(args.completion)
    config = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(args.data))
    lib = build_library(config.library, progress=False)
    rows_out, cache = [], {}
    recs = {}
    if args.carve:
        from sim import dataset

        recs = {int(r["pair_index"]): r for r in dataset.load_records(args.data)}
    kept_share = []
    for run in [Path(r) for r in args.runs.split(",") if r]:
        rows = [json.loads(x) for x in (run / "pairs.jsonl").read_text().splitlines() if x.strip()]
        latest = {(r["pair"], r["method"]): r for r in rows}
        for r in latest.values():
            p = run / "scenes" / r["pair"] / f"{r['method']}_path.npy"
            if not r["returned"] or not p.exists():
                continue
            if r["pair"] not in cache:
                f = np.load(Path(args.data, "derived", "collision", "test", f"{r['pair']}.npz"))
                obs_o, obs_s = f["object_points"], f["support_points"]
                eyes = None
                if args.carve:
                    rec = recs[int(r["pair_index"])]
                    eyes = (rec["object_eye"], rec["support_eye"])
                po, ps = completion.predict_points(nets, obs_o, obs_s, eyes)
                if args.carve:
                    n = nets["object"][0].n_output, nets["support"][0].n_output
                    kept_share.append((len(po) / n[0], len(ps) / n[1]))
                obs_o_sub = collision.subsample_cloud(obs_o, args.object_points, 0)
                cache[r["pair"]] = dict(
                    observed=(obs_o_sub, cKDTree(obs_s)),
                    completed=(
                        np.concatenate([obs_o_sub, po]),
                        cKDTree(np.concatenate([obs_s, ps])),
                    ),
                )
            clouds = cache[r["pair"]]
            scene = build_scene(lib.objects[r["object_name"]], lib.supports[r["support_name"]])
            w, goal = planner.object_radius(scene), np.asarray(r["goal"], float)
            dense = planner.interpolate_path(np.load(p), 0.002, w)
            pen = planner.MeshChecker(scene, 1e-3).penetration(dense) > 1e-3
            far = planner.goal_distances(dense, goal, w) > args.radius
            row = dict(run=run.name, pair=r["pair"], family=r["support_family"],
                       free=bool(r["collision_free"]), far_penetrating=int((pen & far).sum()))  # fmt: skip
            for name, (obj, tree) in clouds.items():
                gap = far_gaps(dense, far, obj, tree)
                row[f"{name}_min_far_gap_mm"] = (
                    round(1e3 * float(gap.min()), 2) if far.any() else None
                )
                pg = gap[pen & far]
                row[f"{name}_min_gap_at_penetration_mm"] = (
                    round(1e3 * float(pg.min()), 2) if len(pg) else None
                )
            rows_out.append(row)
    col = [o for o in rows_out if not o["free"] and o["far_penetrating"] > 0]
    free = [o for o in rows_out if o["free"]]
    table = {}
    for name in ("observed", "completed"):
        for m in MARGINS:
            mm = 1e3 * m
            table[f"{name}_{mm:g}mm"] = dict(
                colliding_far_caught=sum(o[f"{name}_min_gap_at_penetration_mm"] < mm for o in col),
                free_blocked=sum((o[f"{name}_min_far_gap_mm"] or np.inf) < mm for o in free),
            )
    summary = dict(
        runs=args.runs, completion=args.completion, radius_m=args.radius, carve=args.carve,
        kept_share=np.mean(kept_share, axis=0).round(3).tolist() if kept_share else None,
        returned=len(rows_out), colliding=sum(not o["free"] for o in rows_out),
        colliding_with_far_penetration=len(col), free=len(free), by_margin=table, rows=rows_out,
    )  # fmt: skip
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
