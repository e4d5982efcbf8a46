"""Issue 13 diagnostic (twenty-fourth session): what the hybrid's colliding paths hit, and
whether the camera saw it.

For every returned path of an eval_paths run that the meshes call colliding (``--out`` folder:
pairs.jsonl + scenes/<pair>/<method>_path.npy), the path is checked densely (2 mm, planner
metric) contact by contact in MuJoCo, and for the deepest object-support contact and the
deepest object-wall contact it records the depth and the distance to the goal. For the deepest
support contact it then asks the support camera (the dataset record's ``support_eye``): how far
is the contact from the nearest observed support point, and where along the camera's ray to
the contact is the first observed support point (within 3 mm of the ray)? A negative offset
means the contact lies that far BEHIND an observed surface: the support's unobserved back.
Also: how many observed object points (512, the planner's subsample) are within 3 mm of the
contact at that state (0: the object's own unobserved side collides). CPU, about a minute.

    python scripts/probe_contact_shadow.py --run out/paths80_s24_clear \\
        --out results/paths80_s24_contact_shadow.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import mujoco
import numpy as np
from scipy.spatial import cKDTree

from omnihang_jax import collision, dataset_bridge, planner
from sim import dataset
from sim.library import build_library
from sim.scene import build_scene


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", required=True, help="an eval_paths --out folder")
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--method", default="nce_geometric")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    run = Path(args.run)
    rows = [json.loads(x) for x in (run / "pairs.jsonl").read_text().splitlines() if x.strip()]
    rows = [r for r in rows if r["method"] == args.method and r["returned"]
            and not r["collision_free"]]  # fmt: skip
    want = {int(r["pair_index"]) for r in rows}
    eyes = {int(r["pair_index"]): np.asarray(r["support_eye"], float)
            for r in dataset.load_records(args.data) if int(r["pair_index"]) in want}  # fmt: skip
    config = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(args.data))
    lib = build_library(config.library, progress=False)
    out = []
    for r in rows:
        f = np.load(Path(args.data, "derived", "collision", "test", f"{r['pair']}.npz"))
        sp = f["support_points"].astype(float)
        obj_cloud = collision.subsample_cloud(f["object_points"], 512, 0).astype(float)
        scene = build_scene(lib.objects[r["object_name"]], lib.supports[r["support_name"]])
        w, goal = planner.object_radius(scene), np.asarray(r["goal"], float)
        path = np.load(run / "scenes" / r["pair"] / f"{args.method}_path.npy")
        dense = planner.interpolate_path(path, 0.002, w)
        m, d = scene.model, mujoco.MjData(scene.model)
        obj = {int(g) for g in scene.object_geoms}
        sup = {int(g) for g in scene.support_geoms}
        deepest = {"support": (0.0, None, None), "wall": (0.0, None, None)}
        for pose in dense:
            d.qpos[:7] = pose
            mujoco.mj_kinematics(m, d)
            mujoco.mj_collision(m, d)
            for j in range(d.ncon):
                c = d.contact[j]
                g1, g2 = int(c.geom1), int(c.geom2)
                other = g2 if g1 in obj else (g1 if g2 in obj else None)
                kind = (
                    "wall"
                    if other == int(scene.wall_geom)
                    else ("support" if other in sup else None)
                )
                if kind and -c.dist > deepest[kind][0]:
                    deepest[kind] = (-float(c.dist), np.array(c.pos), pose.copy())
        row = dict(pair=r["pair"], object_category=r["object_category"],
                   support_family=r["support_family"], deepest_m=r["deepest_m"])  # fmt: skip
        for kind, (depth, _pos, pose) in deepest.items():
            row[f"{kind}_depth_m"] = round(depth, 5)
            row[f"{kind}_goal_distance_m"] = None if pose is None else round(
                float(planner.goal_distances(pose[None], goal, w)[0]), 4)  # fmt: skip
        depth, pos, pose = deepest["support"]
        if pos is not None:
            eye = eyes[int(r["pair_index"])]
            u = (pos - eye) / np.linalg.norm(pos - eye)
            v = sp - eye
            t = v @ u
            on_ray = np.linalg.norm(v - t[:, None] * u, axis=1) < 0.003
            moved = planner.posed_points(pose[None], obj_cloud)[0]
            row |= dict(
                contact_to_observed_support_m=round(float(cKDTree(sp).query(pos)[0]), 5),
                first_observed_on_ray_m=None if not on_ray.any()
                else round(float(t[on_ray].min() - np.linalg.norm(pos - eye)), 5),
                observed_object_points_within_3mm=int(np.sum(np.linalg.norm(moved - pos, axis=1) < 0.003)),
            )  # fmt: skip
        out.append(row)
        print(row, flush=True)
    hit = [o for o in out if o["support_depth_m"] > 1e-3]
    behind = [o for o in hit if (o.get("first_observed_on_ray_m") or 0) < -1e-3]
    summary = dict(
        run=args.run, colliding_paths=len(out),
        support_collisions=len(hit), wall_collisions=sum(o["wall_depth_m"] > 1e-3 for o in out),
        support_contact_behind_an_observed_surface=len(behind),
        behind_depths_m=sorted(-o["first_observed_on_ray_m"] for o in behind),
        without_an_observed_object_point_within_3mm=sum(
            o.get("observed_object_points_within_3mm", 0) == 0 for o in hit),
        rows=out,
    )  # fmt: skip
    Path(args.out).write_text(json.dumps(summary, indent=1))
    print({k: v for k, v in summary.items() if k != "rows"})
    return summary


if __name__ == "__main__":
    main()
