"""Issue 13 probe (thirty-ninth session): is the take-off traced along the observed wire
(below) free on the full meshes, and does it end off the support?

Per held-out goal of the path benchmark (the pairs' first stable poses): the traced take-off,
its length along the wire and straight on, the deepest mesh penetration along it (interpolated
at 2 mm, planner metric) and the true clearance at its end (``mj_geomDistance``).

    python scripts/probe_wire_takeoff.py --out results/paths_s39/wire_takeoff_pegboards.json   # ~2 min

The tracing (no meshes, the observed clouds alone):

1. the contact point: the centroid of the observed support points within ``touch`` of the
   posed observed object cloud at the goal;
2. the wire's tangent there: the principal axis of the support points within ``radius``
   (signed away from the wall, or upward for a free-standing support);
3. a step of ``step`` along the tangent, re-centred on the local centroid (so the point rides
   the wire through bends), the tangent re-estimated and kept on the same side, until fewer than
   ``min_points`` support points are near: past the wire's free end;
4. the object carried rigidly with the wire's local frame: each step's pose is the goal pose
   turned by the smallest rotation taking the first tangent to the current one, about the
   current contact point;
5. then straight on along the last tangent until the posed observed object cloud is ``clear``
   away from the observed support (at most ``beyond``).

The approach is that take-off reversed. Pure NumPy / SciPy on the host, like the planner.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from experiments import eval_paths
from omnihang_jax import collision, planner
from omnihang_jax.collision import posed_points


@dataclasses.dataclass(frozen=True)
class WireConfig:
    touch: float = 0.012  # m: support points this near the posed object cloud are the contact
    radius: float = 0.012  # m: support points this near the current point give the tangent
    step: float = 0.004  # m along the wire per step
    min_points: int = 4  # fewer support points near the next point: past the wire's end
    max_length: float = 0.30  # m along the wire at most
    wall_margin: float = 0.015  # m: support points this near the wall plane are the panel
    clear: float = 0.015  # m of observed clearance that ends the take-off
    beyond: float = 0.12  # m straight on past the wire's end at most
    object_points: int = 512  # the posed object cloud's subsample (planner.clear_path's)
    rotate: bool = True  # carry the object with the wire's turning (False: translate only)
    lift: float = 0.0  # m: the object first lifted this much (+z) off the wire, then carried


class TakeOff(NamedTuple):
    poses: np.ndarray  # [K, 7] goal first, then the take-off's waypoints (the last: off)
    wire: np.ndarray  # [W, 3] the traced contact points along the wire
    along_wire: float  # m traced along the wire
    straight: float  # m straight on past its end
    clearance: float  # m: observed clearance at the last pose


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ])  # fmt: skip


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a to unit vector b, as a quaternion (w, x, y, z)."""
    c = float(np.clip(np.dot(a, b), -1.0, 1.0))
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    if s < 1e-9:
        if c > 0:
            return np.array([1.0, 0, 0, 0])
        perp = np.cross(a, [1.0, 0, 0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0, 1.0, 0])
        return np.concatenate([[0.0], perp / np.linalg.norm(perp)])
    half = np.arctan2(s, c) / 2
    return np.concatenate([[np.cos(half)], np.sin(half) * axis / s])


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    r = np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip
    return r @ v


def _tangent(points: np.ndarray) -> np.ndarray:
    centred = points - points.mean(axis=0)
    return np.linalg.svd(centred, full_matrices=False)[2][0]


def take_off(
    goal: np.ndarray,
    object_points: np.ndarray,
    support_points: np.ndarray,
    wall_y: float | None,
    config: WireConfig = WireConfig(),
) -> TakeOff | None:
    """The take-off along the wire from ``goal`` [7] (support frame, xyz + wxyz) traced on the
    observed clouds (object frame [N, 3], support frame [M, 3]); None when no support point
    touches the posed object cloud, or the wire cannot be followed (too few points near)."""
    from scipy.spatial import cKDTree

    from omnihang_jax.collision import subsample_cloud

    goal = np.asarray(goal, float)
    sup = np.asarray(support_points, float)
    if wall_y is not None:  # the panel is not the wire
        sup = sup[sup[:, 1] > wall_y + config.wall_margin]
    if len(sup) < config.min_points:
        return None
    tree = cKDTree(sup)
    obj = subsample_cloud(np.asarray(object_points, float), config.object_points, seed=0)
    posed = posed_points(goal[None], obj)[0]
    near = tree.query_ball_point(posed, config.touch)
    touching = np.unique(np.concatenate([np.asarray(n, int) for n in near]))
    if len(touching) < config.min_points:
        return None
    p = sup[touching].mean(axis=0)
    local = tree.query_ball_point(p, config.radius)
    if len(local) < config.min_points:
        return None
    t = _tangent(sup[local])
    away = np.array([0.0, 1.0, 0.0]) if wall_y is not None else np.array([0.0, 0.0, 1.0])
    if np.dot(t, away) < 0:
        t = -t
    t0, p0 = t.copy(), p.copy()
    wire, poses = [p.copy()], [goal.copy()]

    lift = np.array([0.0, 0.0, config.lift])
    if config.lift > 0:
        first = goal.copy()
        first[:3] += lift
        poses.append(first)

    def pose_at(point, tangent):
        q = _rotation_between(t0, tangent) if config.rotate else np.array([1.0, 0, 0, 0])
        out = np.empty(7)
        out[:3] = point + _rotate(q, goal[:3] - p0) + lift
        out[3:] = _quat_mul(q, goal[3:])
        return out / np.r_[1, 1, 1, np.linalg.norm(out[3:]) * np.ones(4)]

    def clearance(pose):
        return float(tree.query(posed_points(pose[None], obj)[0], k=1)[0].min())

    travelled = 0.0
    for _ in range(int(np.ceil(config.max_length / config.step))):
        ahead = p + config.step * t
        local = tree.query_ball_point(ahead, config.radius)
        if len(local) < config.min_points:
            break
        pts = sup[local]
        new_p = pts.mean(axis=0)
        # keep moving forward: only the points ahead of the current one re-centre it
        fwd = pts[(pts - p) @ t > 0]
        if len(fwd) >= config.min_points:
            new_p = (
                p
                + config.step * t
                + ((fwd.mean(axis=0) - ahead) - np.dot(fwd.mean(axis=0) - ahead, t) * t)
            )
        new_t = _tangent(pts)
        if np.dot(new_t, t) < 0:
            new_t = -new_t
        if np.dot(new_t, t) < np.cos(np.radians(35)):  # a kink, not a bend of this wire
            break
        if np.dot(new_p - p, t) < 0.25 * config.step:  # re-centring undid the step: stuck
            break
        travelled += float(np.linalg.norm(new_p - p))
        p, t = new_p, new_t / np.linalg.norm(new_t)
        wire.append(p.copy())
        poses.append(pose_at(p, t))
    along = travelled
    straight = 0.0
    last = poses[-1]
    while straight < config.beyond and clearance(last) < config.clear:
        straight += config.step * 2
        last = last.copy()
        last[:3] = last[:3] + config.step * 2 * t
    if straight > 0:
        poses.append(last)
    return TakeOff(np.array(poses), np.array(wire), along, straight, clearance(poses[-1]))


def approach_path(off: TakeOff, keep_every: int = 3) -> np.ndarray:
    """[K, 7] the take-off reversed (pre-goal first, goal last), thinned to every
    ``keep_every``-th traced pose (the first and last kept)."""
    poses = off.poses
    idx = sorted(set(range(0, len(poses), keep_every)) | {0, len(poses) - 1})
    return poses[idx][::-1].copy()


VARIANTS = {  # name -> WireConfig overrides, as measured in the thirty-ninth session
    "base": {},
    "no_rotation": dict(rotate=False),
    "lift2mm": dict(lift=0.002),
    "lift4mm": dict(lift=0.004),
    "no_rotation_lift3mm": dict(rotate=False, lift=0.003),
    "radius8mm": dict(radius=0.008, touch=0.008),
    "radius20mm": dict(radius=0.02),
}


def measure(case, config: WireConfig) -> dict:
    """One goal's traced take-off checked on the full meshes."""
    t0 = time.perf_counter()
    off = take_off(case.goal, case.object_points, case.support_points, case.wall_y, config)
    row = dict(pair=case.name, support_family=case.meta["support_family"], traced=off is not None,
               seconds=round(time.perf_counter() - t0, 3))  # fmt: skip
    if off is None:
        return row
    dense = planner.interpolate_path(off.poses, 0.002, planner.object_radius(case.scene))
    mesh = collision.MeshChecker(case.scene, 1e-3)
    depth = mesh.penetration(dense)
    hit = np.flatnonzero(depth > 1e-3)
    return row | dict(
        along_wire_cm=round(off.along_wire * 100, 1), straight_cm=round(off.straight * 100, 1),
        observed_clear_mm=round(off.clearance * 1e3, 1), deepest_mm=round(float(depth.max()) * 1e3, 1),
        first_hit_of=[int(hit[0]) if len(hit) else None, len(dense)], free=not len(hit),
        true_clear_mm=round(float(mesh.clearance(off.poses[-1])[0]) * 1e3, 1),
    )  # fmt: skip


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs-from", default="out/paths_records.jsonl.gz")
    ap.add_argument("--pairs", type=int, default=80)
    ap.add_argument("--data", default="datasets/paper")
    ap.add_argument("--families", nargs="*", default=["pegboard_hook"])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    cases = eval_paths.load_pairs(
        args.data, args.pairs, records=eval_paths.read_answers(args.pairs_from)
    )
    cases = [c for c in cases if not args.families or c.meta["support_family"] in args.families]
    result = dict(settings=vars(args), goals=len(cases), variants={})
    for name in args.variants:
        config = dataclasses.replace(WireConfig(), **VARIANTS[name])
        rows = [measure(case, config) for case in cases]
        summary = dict(traced=sum(r["traced"] for r in rows), free=sum(r.get("free", False) for r in rows),
                       free_and_off=sum(r.get("free", False) and r["true_clear_mm"] >= 10 for r in rows),
                       median_deepest_mm=float(np.median([r["deepest_mm"] for r in rows if r["traced"]] or [0])))  # fmt: skip
        result["variants"][name] = dict(config=config.__dict__, summary=summary, pairs=rows)
        print(name, summary, flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
