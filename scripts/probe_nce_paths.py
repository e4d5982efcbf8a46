"""Issue 13 diagnostic (twenty-eighth session): would another NCE have stopped the hybrid's
colliding paths, and how many free paths would it have blocked?

For every returned path of eval_paths runs (as saved: cleared where the run cleared them), the
dense states (2 mm, the evaluation's) are checked with the meshes (``MeshChecker``, 1 mm) and
scored by each NCE with the clouds the planner would give it (``eval_paths.nce_clouds``: the
observed ones, or the completed ones for an NCE trained on them). The states are split by
their distance to the goal (planner metric): ``near`` (within ``--near`` of the goal, where the
hybrid's NCE is lenient at 0.99), ``mid`` (to ``--radius``, the goal's neighbourhood the
clearing keeps) and ``far`` (beyond). Per NCE, region and threshold: the colliding paths with a
penetrating state in the region scored above the threshold (caught) and the free paths with any
state in the region above it (blocked: a planner would have to route around them).

The paths were found by a planner whose checker called their states free (the contact NCE at
0.56 beyond 2 cm, at 0.99 within, at 5-mm spacing): the contact NCE is scored on states chosen
to pass it. The question is whether another NCE sees what it missed. CPU, a few minutes per NCE.

    python scripts/probe_nce_paths.py --runs out/paths80_s24_keep45,out/paths80_s24_keep45_seed2 \\
        --weights weights/collision_s18_contact,out/s28/nce2/weights,out/s28/nce2/weights_crop \\
        --out results/paths80_s28_nce_probe.json
"""

import argparse
import json
from pathlib import Path

import jax
import numpy as np

from experiments.eval_paths import SUBSET_SEED_OBJECT, SUBSET_SEED_SUPPORT, PairCase, nce_clouds
from omnihang_jax import collision, completion, dataset_bridge, planner
from sim.library import build_library
from sim.scene import build_scene

THRESHOLDS = (0.3, 0.4, 0.5, 0.56, 0.6, 0.7, 0.8, 0.9, 0.99)
REGIONS = ("near", "mid", "far")


def scores_of(prob, params, oc, sc, states, chunk=64):
    out = []
    for a in range(0, len(states), chunk):
        part = np.asarray(states[a : a + chunk], np.float32)
        n = len(part)
        if n < chunk:
            part = np.concatenate([part, np.repeat(part[-1:], chunk - n, axis=0)])
        out.append(np.asarray(prob(params, oc, sc, part))[:n])
    return np.concatenate(out) if out else np.zeros(0)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", required=True, help="eval_paths --out folders, comma-separated")
    ap.add_argument(
        "--weights", required=True, help="NCE weight folders (FOLDER/nce), comma-separated"
    )
    ap.add_argument("--completion", default="weights/completion_s25",
                    help="for NCEs trained on completed clouds (carved with the records' cameras)")  # fmt: skip
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--near", type=float, default=0.02, help="m: the NCE's lenient goal ball")
    ap.add_argument("--radius", type=float, default=0.045, help="m: the clearing's kept ball")
    ap.add_argument("--out", default=None, help="JSON")
    args = ap.parse_args(argv)
    nces = {}
    for w in [x for x in args.weights.split(",") if x]:
        cfg, params, _ = collision.load_estimator(Path(w, "nce"))
        nces[w] = (cfg, params, jax.jit(collision.nce_probability(cfg)))
    need_completion = any(c.input_clouds == "completed" for c, _, _ in nces.values())
    nets = completion.load_nets(args.completion) if need_completion else None
    recs = {}
    if need_completion:
        from sim import dataset

        recs = {int(r["pair_index"]): r for r in dataset.load_records(args.data)}
    config = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(args.data))
    lib = build_library(config.library, progress=False)
    cases: dict = {}
    rows = []
    for run in [Path(r) for r in args.runs.split(",") if r]:
        lines = (run / "pairs.jsonl").read_text().splitlines()
        latest = {(r["pair"], r["method"]): r for r in map(json.loads, filter(str.strip, lines))}
        for r in latest.values():
            p = run / "scenes" / r["pair"] / f"{r['method']}_path.npy"
            if not r["returned"] or not p.exists():
                continue
            if r["pair"] not in cases:
                f = np.load(Path(args.data, "derived", "collision", "test", f"{r['pair']}.npz"))
                case = PairCase(name=r["pair"], meta={}, scene=None,
                                object_points=f["object_points"], object_normals=f["object_normals"],
                                support_points=f["support_points"],
                                support_normals=f["support_normals"], goal=None)  # fmt: skip
                if nets is not None:
                    rec = recs[int(r["pair_index"])]
                    po, ps = completion.predict_points(
                        nets, case.object_points, case.support_points,
                        (rec["object_eye"], rec["support_eye"]),
                    )  # fmt: skip
                    case = case._replace(predicted_object=po, predicted_support=ps)
                cases[r["pair"]] = case
            case = cases[r["pair"]]
            scene = build_scene(lib.objects[r["object_name"]], lib.supports[r["support_name"]])
            w, goal = planner.object_radius(scene), np.asarray(r["goal"], float)
            dense = planner.interpolate_path(np.load(p), 0.002, w)
            pen = planner.MeshChecker(scene, 1e-3).penetration(dense) > 1e-3
            d = planner.goal_distances(dense, goal, w)
            region = {"near": d <= args.near, "mid": (d > args.near) & (d <= args.radius),
                      "far": d > args.radius}  # fmt: skip
            row = dict(run=run.name, pair=r["pair"], family=r["support_family"],
                       category=r["object_category"], free=bool(r["collision_free"]),
                       penetrating={k: int((pen & m).sum()) for k, m in region.items()})  # fmt: skip
            for w_name, (cfg, params, prob) in nces.items():
                oc, sc = nce_clouds(case, cfg)
                oc = collision.subsample_cloud(oc, cfg.object_input, SUBSET_SEED_OBJECT)
                sc = collision.subsample_cloud(sc, cfg.support_input, SUBSET_SEED_SUPPORT)
                s = scores_of(prob, params, oc, sc, dense)
                row[w_name] = {
                    k: dict(max_all=float(s[m].max()) if m.any() else None,
                            max_penetrating=float(s[m & pen].max()) if (m & pen).any() else None)
                    for k, m in region.items()
                }  # fmt: skip
            rows.append(row)
            print(f"{run.name} {r['pair']} free={row['free']} pen={row['penetrating']}", flush=True)
    table = {}
    for w_name in nces:
        table[w_name] = {}
        for k in REGIONS:
            col = [o for o in rows if not o["free"] and o["penetrating"][k] > 0]
            free = [o for o in rows if o["free"] and o[w_name][k]["max_all"] is not None]
            table[w_name][k] = dict(
                colliding_with_penetration=len(col), free=len(free),
                **{f"{t:g}": dict(caught=sum(o[w_name][k]["max_penetrating"] > t for o in col),
                                  free_blocked=sum(o[w_name][k]["max_all"] > t for o in free))
                   for t in THRESHOLDS},
            )  # fmt: skip
    summary = dict(runs=args.runs, weights=list(nces), near_m=args.near, radius_m=args.radius,
                   returned=len(rows), colliding=sum(not o["free"] for o in rows),
                   by_nce=table, rows=rows)  # fmt: skip
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}, indent=1))
    if args.out:
        Path(args.out).write_text(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
