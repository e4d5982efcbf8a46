"""Issue 13 diagnostic (twenty-ninth session): how many of the hybrid's returned paths collide
with the wall behind the support, and would a test on the observed object cloud against the
known wall plane have caught them?

For every returned path of the eval_paths runs given (``--out`` folders: pairs.jsonl +
scenes/<pair>/nce_geometric_path.npy), the dense 2-mm states are checked contact by contact in
MuJoCo against the wall geom alone (penetration > 1 mm: the path collides with the wall), and
the observed object cloud (512 points, the planner's subsample) is posed at each state: its
smallest distance in front of the wall plane ``y = wall_y`` (negative: observed points behind
the wall). Per goal ball B (states within B of the goal exempt, planner metric) and margin M:
the wall-colliding paths a test "some observed point closer than M to the wall" flags, the free
paths it would block and the other colliding paths it flags. CPU, a few minutes.

    python scripts/probe_wall.py --runs out/paths80_s24_keep45,out/paths80_s24_keep45_seed2,out/paths80_s24_clear \
        --out results/paths80_s29_wall_probe.json
"""

import argparse
import json
from pathlib import Path

import mujoco
import numpy as np

from omnihang_jax import collision, dataset_bridge, planner
from sim.library import build_library
from sim.scene import build_scene

ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
ap.add_argument("--runs", required=True, help="eval_paths --out folders, comma-separated")
ap.add_argument("--data", default="datasets/paper")
ap.add_argument("--split", default="test", choices=("test", "train"), help="the runs' pairs")
ap.add_argument("--out", required=True)
args = ap.parse_args()
data = args.data
config = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(data))
lib = build_library(config.library, progress=False)
MARGINS = (0.0, 0.003, 0.005, 0.01, 0.02, 0.03, 0.04, 0.05)
BALLS = (0.0, 0.02, 0.045)
out = []
for run in args.runs.split(","):
    rows = [json.loads(x) for x in Path(run, "pairs.jsonl").read_text().splitlines() if x.strip()]
    rows = [r for r in rows if r["method"] == "nce_geometric" and r["returned"]]
    for r in rows:
        f = np.load(Path(data, "derived", "collision", args.split, f"{r['pair']}.npz"))
        wall_y = float(f["wall_y"])
        obj = collision.subsample_cloud(f["object_points"], 512, 0).astype(float)
        scene = build_scene(lib.objects[r["object_name"]], lib.supports[r["support_name"]])
        w, goal = planner.object_radius(scene), np.asarray(r["goal"], float)
        path = np.load(Path(run, "scenes", r["pair"], "nce_geometric_path.npy"))
        dense = planner.interpolate_path(path, 0.002, w)
        m, d = scene.model, mujoco.MjData(scene.model)
        objg = {int(g) for g in scene.object_geoms}
        wall_depth = np.zeros(len(dense))
        for i, pose in enumerate(dense):
            d.qpos[:7] = pose
            mujoco.mj_kinematics(m, d)
            mujoco.mj_collision(m, d)
            for j in range(d.ncon):
                c = d.contact[j]
                g1, g2 = int(c.geom1), int(c.geom2)
                if (g1 in objg and g2 == scene.wall_geom) or (g2 in objg and g1 == scene.wall_geom):
                    wall_depth[i] = max(wall_depth[i], -float(c.dist))
        gap = (collision.posed_points(dense, obj)[..., 1] - wall_y).min(axis=1)
        gd = planner.goal_distances(dense, goal, w)
        goal_gap = float((collision.posed_points(goal[None], obj)[..., 1] - wall_y).min())
        row = dict(
            run=Path(run).name,
            pair=r["pair"],
            free=bool(r["collision_free"]),
            wall_colliding=bool((wall_depth > 1e-3).any()),
            wall_depth=float(wall_depth.max()),
            goal_gap=goal_gap,
            min_gap={str(b): float(gap[gd > b].min()) if (gd > b).any() else None for b in BALLS},
        )
        out.append(row)
res = {"runs": args.runs.split(","), "rows": out, "table": {}}
for b in BALLS:
    for mg in MARGINS:

        def flag(x, b=b, mg=mg):
            return x["min_gap"][str(b)] is not None and x["min_gap"][str(b)] < mg

        res["table"][f"ball {b} margin {mg}"] = dict(
            wall_paths_caught=sum(flag(x) for x in out if x["wall_colliding"]),
            wall_paths=sum(x["wall_colliding"] for x in out),
            free_blocked=sum(flag(x) for x in out if x["free"]),
            free=sum(x["free"] for x in out),
            other_colliding_flagged=sum(
                flag(x) for x in out if not x["free"] and not x["wall_colliding"]
            ),
        )
Path(args.out).write_text(json.dumps(res, indent=1))
for k, v in res["table"].items():
    print(k, v)
print("goal gaps < 5 mm:", sum(x["goal_gap"] < 0.005 for x in out), "of", len(out))
print(
    [
        (
            x["pair"],
            round(x["wall_depth"], 4),
            round(x["goal_gap"], 4),
            {k: round(v, 4) if v is not None else None for k, v in x["min_gap"].items()},
        )
        for x in out
        if x["wall_colliding"]
    ]
)
