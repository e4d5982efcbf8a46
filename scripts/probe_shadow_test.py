"""Issue 13 diagnostic (twenty-fourth session): would a camera-shadow test have caught the
hybrid's far collisions?

The support's shadow: a depth map of the observed support cloud seen from its camera (the
dataset record's ``support_eye``), cells of 1.5 x the cloud's median angular spacing, each the
nearest support depth within one cell; a point is in the shadow when it lies more than 2 mm and
at most THICKNESS behind that depth along its camera ray (the support's unobserved back). The
object side: the planner's 256-point subsample of the observed object cloud, optionally
"thickened" by copies moved away from the object camera (``object_eye``) by each of DEPTHS
(its unobserved back). For every returned path of an eval_paths run, the dense states (2 mm)
farther than R from the goal are tested; printed: the colliding paths whose far penetrating
states the test flags, and the free paths it flags anywhere far (which the planner would have
to route around). CPU, about a minute.

    python scripts/probe_shadow_test.py --run out/paths80_s24_clear --radius 0.045 \\
        --thickness 0.015 --object-depths 0.004,0.008,0.012
"""

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from omnihang_jax import collision, dataset_bridge, planner
from sim import dataset
from sim.library import build_library
from sim.scene import build_scene


class Shadow:
    """Depth map of the support cloud from its camera; counts posed points in its shadow."""

    def __init__(self, support_points, eye, thickness=0.015, behind=0.002, cell=None):
        sup = np.asarray(support_points, float)
        self.eye = np.asarray(eye, float).reshape(3)
        self.thickness, self.behind = thickness, behind
        v = sup - self.eye
        fwd = v.mean(axis=0)
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        self.axes = np.stack([right, np.cross(right, fwd), fwd])
        ab, depth = self.project(sup)
        if cell is None:
            cell = 1.5 * float(np.median(cKDTree(ab).query(ab, k=2)[0][:, 1]))
        self.cell = cell
        ij = np.floor(ab / cell).astype(np.int64)
        self.lo = ij.min(axis=0) - 2
        shape = ij.max(axis=0) - self.lo + 3
        grid = np.full(tuple(shape), np.inf)
        np.minimum.at(grid, tuple((ij - self.lo).T), depth)
        near = grid.copy()
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                near = np.minimum(near, np.roll(np.roll(grid, di, 0), dj, 1))
        self.depth = near

    def project(self, points):
        v = (np.asarray(points, float) - self.eye) @ self.axes.T
        ahead = np.maximum(v[..., 2], 1e-9)
        return v[..., :2] / ahead[..., None], np.linalg.norm(v, axis=-1)

    def count(self, moved):
        """moved [B, N, 3] support frame -> [B] points in the shadow."""
        ab, depth = self.project(moved)
        ij = np.floor(ab / self.cell).astype(np.int64) - self.lo
        ok = np.all((ij >= 0) & (ij < np.array(self.depth.shape)), axis=-1)
        ok &= ((moved - self.eye) @ self.axes[2]) > 0
        ij = np.where(ok[..., None], ij, 0)
        front = np.where(ok, self.depth[ij[..., 0], ij[..., 1]], np.inf)
        return ((depth > front + self.behind) & (depth < front + self.thickness)).sum(-1)


def thicken(points, eye, depths):
    """Observed points plus copies moved away from their camera by each depth (object frame)."""
    points = np.asarray(points, float)
    u = points - np.asarray(eye, float)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return np.concatenate([points] + [points + dd * u for dd in depths])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--run", required=True, help="an eval_paths --out folder")
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--radius", type=float, default=0.045, help="m: the goal ball left out")
    ap.add_argument("--thickness", type=float, default=0.015, help="m: the support's back")
    ap.add_argument("--object-depths", default="", help="m,m,...: the object's back")
    ap.add_argument("--min-points", type=int, default=0)
    ap.add_argument("--out", default=None, help="JSON")
    args = ap.parse_args(argv)
    run = Path(args.run)
    depths = [float(x) for x in args.object_depths.split(",") if x]
    rows = [json.loads(x) for x in (run / "pairs.jsonl").read_text().splitlines() if x.strip()]
    want = {int(r["pair_index"]) for r in rows}
    recs = {int(r["pair_index"]): r for r in dataset.load_records(args.data)
            if int(r["pair_index"]) in want}  # fmt: skip
    config = dataset_bridge.dataset_config_from_recipe(dataset_bridge.read_recipe(args.data))
    lib = build_library(config.library, progress=False)
    out = []
    for r in rows:
        p = run / "scenes" / r["pair"] / f"{r['method']}_path.npy"
        if not r["returned"] or not p.exists():
            continue
        f = np.load(Path(args.data, "derived", "collision", "test", f"{r['pair']}.npz"))
        rec = recs[int(r["pair_index"])]
        scene = build_scene(lib.objects[r["object_name"]], lib.supports[r["support_name"]])
        w, goal = planner.object_radius(scene), np.asarray(r["goal"], float)
        obj = thicken(
            collision.subsample_cloud(f["object_points"], 256, 0), rec["object_eye"], depths
        )
        shadow = Shadow(f["support_points"], rec["support_eye"], thickness=args.thickness)
        dense = planner.interpolate_path(np.load(p), 0.002, w)
        pen = planner.MeshChecker(scene, 1e-3).penetration(dense)
        far = planner.goal_distances(dense, goal, w) > args.radius
        counts = np.concatenate([shadow.count(planner.posed_points(dense[a : a + 64], obj))
                                 for a in range(0, len(dense), 64)])  # fmt: skip
        flag, bad = counts > args.min_points, pen > 1e-3
        out.append(dict(pair=r["pair"], free=bool(r["collision_free"]),
                        far_flagged=int((far & flag).sum()), far_penetrating=int((bad & far).sum()),
                        far_penetrating_flagged=int((bad & far & flag).sum())))  # fmt: skip
    col = [o for o in out if not o["free"]]
    free = [o for o in out if o["free"]]
    summary = dict(
        run=args.run, radius_m=args.radius, thickness_m=args.thickness, object_depths_m=depths,
        colliding_paths=len(col),
        colliding_with_far_penetration=sum(o["far_penetrating"] > 0 for o in col),
        flagged_at_a_far_penetrating_state=sum(o["far_penetrating_flagged"] > 0 for o in col),
        free_paths=len(free), free_flagged_far=sum(o["far_flagged"] > 0 for o in free), rows=out,
    )  # fmt: skip
    print({k: v for k, v in summary.items() if k != "rows"})
    if args.out:
        Path(args.out).write_text(json.dumps(summary, indent=1))
    return summary


if __name__ == "__main__":
    main()
