"""How to hang: one planner factory, :func:`make_planner`, and its named configs.

A planner takes the observed clouds of the object and the support (and the scene when the
meshes are known) and a hanging pose, and returns a path of poses from a start pose in front
of the support to the hang (OMPL's RRT-Connect, :mod:`omnihang_jax.planner`). What decides
"colliding" is the config's ``checker``:

- ``"hybrid"`` (:data:`DEFAULT`): the observed-cloud penetration test OR the contact NCE, the
  NCE strict beyond ``goal_ball`` of the goal and lenient within it; the plan ends along a
  route of one or two straight moves (the route network) or a straight approach (the approach
  network) when those networks are sure enough; one replan after a time-out; the returned path
  moved away from the observed support where the checker allows (``planner.clear_path``);
- ``"nce"`` (:data:`PAPER_NCE`): the neural collision estimator alone, as in the paper;
- ``"hce"`` (:data:`PAPER_HCE`): the paper's heuristic collision estimator (predicted support
  normals, a penetration score);
- ``"mesh"`` (:data:`MESH`): MuJoCo on the full meshes, the ground truth (needs a scene).

The ``hang`` command and ``experiments.evaluate paths`` (:mod:`omnihang_jax.paths_eval`) plan
with the same :class:`Planner`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
import tempfile
import time
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

__all__ = [
    "PlannerConfig",
    "DEFAULT",
    "PAPER_NCE",
    "PAPER_HCE",
    "MESH",
    "CONFIGS",
    "Clouds",
    "Planner",
    "make_planner",
    "describe",
    "for_hang",
    "nce_clouds",
    "principal_box",
    "cloud_frame",
    "move_origin",
]

CHECKERS = ("hybrid", "nce", "hce", "mesh")
HCE_OBJECT_POINTS = 256  # object points of the HCE's score (the NCE's global branch's)


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    """How to hang, as one set of numbers. Folders are relative to the working directory."""

    checker: str = "hybrid"  # "hybrid" | "nce" | "hce" | "mesh" (module docstring)
    weights: str = "weights/nce"  # the NCE (<weights>/nce) and HCE normal net (/hce_normals)
    # the hybrid's observed-cloud test (collision.GeometricConfig) and the NCE's thresholds,
    # chosen jointly on 60 training validation pairs: the most precise "free" on near-contact
    # poses at a 95 % goal pass (54.7 % of the stable poses called free)
    test_depth: float = 0.0005  # m: an object point this far behind the observed support ...
    test_radius: float = 0.002  # m: ... within this radius of an observed support point
    test_min_points: int = 0  # colliding when more object points than this are inside
    far_threshold: float = 0.56  # the NCE's threshold beyond goal_ball of the goal
    near_threshold: float = 0.99  # and within it (a hang rests on the support)
    goal_ball: float = 0.02  # m, planner metric (translation + radius x angle)
    # the returned path moved towards this observed clearance (m) where the checker allows,
    # the goal's last clear_keep_ball kept (planner.clear_path); 0: off
    clear_target: float = 0.03
    clear_keep_ball: float = 0.045
    replan: bool = True  # after a time-out, one fresh search with the same checker
    # the straight approach: the last approach_length into the goal along the approach
    # network's best direction when p >= approach_threshold; never towards the wall of a
    # wall-mounted support (open_side); the replan after a time-out plans plainly ("plain") or
    # with the same approach ("same"); None: off
    approach: str | None = "weights/approach"
    approach_threshold: float = 0.8
    approach_length: float = 0.045
    approach_open_side: bool = True
    approach_replan: str = "plain"
    # the route network asked first: its first route at p >= routes_threshold (at most
    # routes_tries, best first) that the checker calls free and whose end the observed clouds
    # show routes_end_gap (m) clear; the plan ends along it; None: off (needs the approach)
    routes: str | None = "weights/approach_routes"
    routes_threshold: float = 0.3
    routes_end_gap: float = 0.01
    routes_tries: int = 10
    plan_time: float = 30.0  # s, OMPL's time limit per plan (the evaluation protocol)
    replan_time: float | None = None  # s for the replan (None: plan_time)
    path_step: float = 0.01  # m: the returned path resampled this finely (drawing, keyframes)
    # when the estimator finds no path and the meshes are known, plan on the meshes (the hang
    # command; never in an evaluation)
    mesh_fallback: bool = True

    def __post_init__(self):
        if self.checker not in CHECKERS:
            raise ValueError(f"checker must be one of {CHECKERS}, got {self.checker!r}")
        if self.checker == "mesh" and (self.approach or self.routes or self.clear_target):
            raise ValueError("the mesh checker plans plainly: no approach, routes or clearing")
        if self.routes and not self.approach:
            raise ValueError("routes need the approach (the straight rule where none is sure)")
        if self.approach_replan not in ("plain", "same"):
            raise ValueError(f"approach_replan must be plain or same, got {self.approach_replan!r}")
        if not self.plan_time > 0 or (self.replan_time is not None and self.replan_time < 0):
            raise ValueError("plan_time must be > 0 and replan_time >= 0")

    @property
    def geometric(self):
        """The hybrid's observed-cloud test as a ``collision.GeometricConfig``."""
        from omnihang_jax import collision

        return dataclasses.replace(collision.GeometricConfig(), depth=self.test_depth,
                                   radius=self.test_radius, min_points=self.test_min_points)  # fmt: skip


DEFAULT = PlannerConfig()
_BARE = dict(approach=None, routes=None, clear_target=0.0, replan=False, mesh_fallback=False)
PAPER_NCE = PlannerConfig(checker="nce", **_BARE)
PAPER_HCE = PlannerConfig(checker="hce", **_BARE)
MESH = PlannerConfig(checker="mesh", **_BARE)
CONFIGS = {"default": DEFAULT, "paper_nce": PAPER_NCE, "paper_hce": PAPER_HCE, "mesh": MESH}


class Clouds(NamedTuple):
    """A body as a planner sees it: its observed cloud [N, 3] and outward normals [N, 3]
    (object frame / support frame). ``hang.Body`` has the same fields."""

    points: np.ndarray
    normals: np.ndarray


def principal_box(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre [3], extents [3]) of a cloud's box along its principal axes, largest extent
    first: both follow the cloud through any rotation and shift (the centre turns and moves
    with it, the extents stay), unlike an axis-aligned box."""
    pts = np.asarray(points, np.float64)
    mean = pts.mean(0)
    _, _, axes = np.linalg.svd(pts - mean, full_matrices=False)
    proj = (pts - mean) @ axes.T
    lo, hi = proj.min(0), proj.max(0)
    return mean + 0.5 * (lo + hi) @ axes, hi - lo


def move_origin(poses: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Poses [..., 7] of an object frame -> the same placements of the frame whose origin sits
    at ``offset`` [3] in it (points ``p - offset``): t + R(q) offset, q unchanged."""
    from scipy.spatial.transform import Rotation

    poses = np.asarray(poses, np.float64)
    flat = poses.reshape(-1, 7).copy()
    flat[:, :3] += Rotation.from_quat(flat[:, [4, 5, 6, 3]]).apply(np.asarray(offset, float))
    return flat.reshape(poses.shape)


class _CloudGeometry(NamedTuple):
    """What the planner's start, bounds and metric read from a scene, taken from the clouds
    when there is no scene: the object's extents and the support's box."""

    obj: Any
    support_bounds: np.ndarray


def cloud_frame(obj, sup, goal: np.ndarray):
    """The planner's view of a pair known only from its clouds: (object Clouds centred on
    :func:`principal_box`'s centre, the goal [7] of that centred frame, the centre [3],
    the geometry that ``planner.start_pose``, ``default_bounds`` and ``object_radius`` read).
    Nothing in it depends on the frame the object cloud came in: a turned and shifted cloud
    gives the same start, bounds and metric for the same placement."""
    centre, extents = principal_box(obj.points)
    centred = Clouds(np.asarray(obj.points, np.float32) - centre.astype(np.float32),
                     np.asarray(obj.normals, np.float32))  # fmt: skip
    size = type("Extents", (), {"extents": extents})()
    geometry = _CloudGeometry(size, np.stack([sup.points.min(0), sup.points.max(0)]))
    return centred, move_origin(goal, centre), centre, geometry


def nce_clouds(cfg, object_points: np.ndarray, support_points: np.ndarray):
    """The NCE's fixed cloud subsets, as ``train_collision`` trains with them (seeds 0 / 1):
    ``cfg.object_input`` object points and ``cfg.support_input`` support points."""
    from omnihang_jax import collision

    return (
        collision.subsample_cloud(object_points, cfg.object_input, 0),
        collision.subsample_cloud(support_points, cfg.support_input, 1),
    )


@functools.lru_cache(maxsize=2)
def _nce(folder: str):
    """(config, params, jitted collides) of an NCE folder, once per process."""
    import jax

    from omnihang_jax import collision

    cfg, params, _ = collision.load_estimator(folder)
    return cfg, params, jax.jit(collision.nce_collides(cfg))


@functools.lru_cache(maxsize=2)
def _hce(folder: str):
    """(config, params, jitted normals, jitted score) of an HCE normal-net folder."""
    import jax

    from omnihang_jax import collision

    cfg, params, _ = collision.load_estimator(folder)
    net = collision.make_normal_net(cfg)
    normals = jax.jit(lambda params, pts: net.apply(params, pts[None])[0])
    return cfg, params, normals, jax.jit(collision.heuristic_score)


@functools.lru_cache(maxsize=4)  # the straight approach network and the route network
def _approach(folder: str, threshold: float):
    """The approach network of ``folder`` at ``threshold``, compiled, once per process."""
    from omnihang_jax import approach

    cfg, params, _ = approach.load(folder)
    predictor = approach.ApproachPredictor(dataclasses.replace(cfg, threshold=threshold), params)
    predictor.warm_up()
    return predictor


def describe(config: PlannerConfig) -> str:
    """One line saying what :func:`make_planner` builds from ``config``."""
    if config.checker == "mesh":
        return "OMPL RRT-Connect, full-mesh checker (MuJoCo)"
    if config.checker == "hce":
        text = f"the heuristic collision estimator ({config.weights}/hce_normals)"
    elif config.checker == "nce":
        text = f"the neural collision estimator {config.weights}/nce"
    else:
        text = (
            f"the observed-cloud test (depth {config.test_depth * 1e3:g} mm, radius "
            f"{config.test_radius * 1e3:g} mm) OR the NCE {config.weights}/nce at "
            f"{config.far_threshold:g} ({config.near_threshold:g} within "
            f"{config.goal_ball * 100:g} cm of the goal)"
        )
    if config.routes:
        text += (
            f"; a route of one or two straight moves off the support ({config.routes}, p >= "
            f"{config.routes_threshold:g}, checked by the checker, its end "
            f"{config.routes_end_gap * 100:g} cm clear in the observed clouds)"
        )
    if config.approach:
        text += (
            f"; else a straight {config.approach_length * 100:g}-cm approach ({config.approach}, "
            f"p >= {config.approach_threshold:g})"
        )
    if config.clear_target:
        text += f"; the path cleared towards {config.clear_target * 100:g} cm"
    if config.replan:
        text += "; one replan after a time-out"
    if config.mesh_fallback:
        text += " (the full meshes when it finds no path and meshes are known)"
    return f"OMPL RRT-Connect, {text}"


def missing(config: PlannerConfig) -> str | None:
    """Why :func:`make_planner` cannot build ``config`` here (a weights folder missing), or
    None."""
    folders = []
    if config.checker in ("hybrid", "nce"):
        folders.append(Path(config.weights, "nce"))
    if config.checker == "hce":
        folders.append(Path(config.weights, "hce_normals"))
    folders += [Path(f) for f in (config.approach, config.routes) if f]
    for folder in folders:
        if not (folder / "config.json").exists():
            return f"{folder} missing (no trained network there)"
    try:
        import ompl  # noqa: F401
    except ImportError as exc:
        return f"OMPL not importable ({exc})"
    return None


def for_hang(checker: str = "auto", plan_time: float = 20.0, replan_time: float | None = None):
    """The config of the ``hang`` command's ``--checker``: "auto" (:data:`DEFAULT`, or
    :data:`MESH` where its weights are missing), "nce" (:data:`PAPER_NCE`), "hce"
    (:data:`PAPER_HCE`) or "mesh" (:data:`MESH`), with its time limits."""
    named = {"auto": DEFAULT, "nce": PAPER_NCE, "hce": PAPER_HCE, "mesh": MESH}
    if checker not in named:
        raise ValueError(f"checker must be one of {sorted(named)}, got {checker!r}")
    config = named[checker]
    if checker == "auto" and missing(config) is not None:
        config = MESH
    return dataclasses.replace(config, plan_time=plan_time, replan_time=replan_time)


class _Captured:
    text = ""


@contextlib.contextmanager
def _captured_stderr():
    """Capture what C/C++ code writes to file descriptor 2 (OMPL's console log) while the
    block runs; ``.text`` holds it afterwards."""
    import sys

    captured = _Captured()
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield captured
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            captured.text = sink.read().decode(errors="replace")


class Planner:
    """``planner(scene, obj, sup, goal) -> PathPlan or None``: a path from the start pose
    (``planner.start_pose``) to ``goal`` [7]. ``obj`` / ``sup``: the observed clouds
    (:class:`Clouds` or ``hang.Body``); ``scene``: ``sim.scene.Scene`` when the meshes are
    known (the start, bounds and metric then come from it, and every returned path is checked
    densely on the meshes: ``info["dense_check_collision_free"]``), else None. None: the mesh
    checker without a scene. No path found: a PathPlan with no poses, the reason in its info.
    ``free_standing``: without a scene, the support stands on the floor (no wall side)."""

    def __init__(self, config: PlannerConfig, seed: int = 1, warm: int = 128):
        from omnihang_jax import planner

        why = missing(config)
        if why is not None:
            raise FileNotFoundError(f"planner {config.checker}: {why}")
        self.config, self.description = config, describe(config)
        self.limits = planner.PlannerConfig(time_limit=config.plan_time, seed=seed)
        self.warm = warm
        self.nce = self.hce = self.approach = self.routes = None
        if config.checker in ("hybrid", "nce"):
            self.nce = _nce(os.path.abspath(Path(config.weights, "nce")))
        if config.checker == "hce":
            self.hce = _hce(os.path.abspath(Path(config.weights, "hce_normals")))
        if config.approach:
            self.approach = _approach(os.path.abspath(config.approach), config.approach_threshold)
        if config.routes:
            self.routes = _approach(os.path.abspath(config.routes), config.routes_threshold)

    def checker(self, obj, sup, goal: np.ndarray, radius: float, scene=None):
        """(checker, name) of one pair: poses [B, 7] -> colliding [B]."""
        from omnihang_jax import collision, planner

        c = self.config
        if c.checker == "mesh":
            return planner.MeshChecker(scene), "the full meshes in MuJoCo"
        if c.checker == "hce":
            cfg, params, normals, score = self.hce
            oc = collision.subsample_cloud(obj.points, HCE_OBJECT_POINTS, 0)
            sc = collision.subsample_cloud(sup.points, cfg.points, 1)
            predicted = np.asarray(normals(params, np.asarray(sc, np.float32)))

            def collides(params, object_cloud, support_cloud, poses):
                return score(object_cloud, support_cloud, params, poses) > cfg.threshold

            check = planner.EstimatorChecker(collides, predicted, oc, sc, pow2=True)
            return check, f"the heuristic collision estimator (threshold {cfg.threshold:.3g})"
        cfg, params, collides = self.nce
        if c.checker == "nce":
            check = planner.EstimatorChecker(
                collides, params, *nce_clouds(cfg, obj.points, sup.points), pow2=True
            )
            return check, f"the neural collision estimator {c.weights}/nce"
        settings = planner.HybridSettings(c.geometric, c.far_threshold, c.near_threshold,
                                          c.goal_ball)  # fmt: skip
        check = planner.hybrid_checker(cfg, params, obj.points, sup.points, sup.normals,
                                       settings, goal, radius, pow2=True)  # fmt: skip
        return check, f"the hybrid checker (the observed-cloud test OR the NCE {c.weights}/nce)"

    def _ending(self, check, obj, sup, goal, scene, free_standing: bool):
        """(approach directions or None, route or None, info or None) of the plan's end."""
        from omnihang_jax import approach, retreats

        c, info, route, directions = self.config, None, None, None
        if self.routes is not None:  # the checked route first
            t0 = time.perf_counter()
            choice = approach.checked_route(
                self.routes, obj.points, sup.points, goal, check, c.routes_end_gap,
                c.routes_tries, self.limits.resolution,
            )  # fmt: skip
            checked = dict(used=choice.route is not None, p=choice.probability, rank=choice.rank,
                           tried=choice.tried, seconds=round(time.perf_counter() - t0, 4))  # fmt: skip
            if choice.route is not None:
                route = retreats.route_retreat(goal, choice.route, self.routes.config.length)
                checked |= dict(
                    waypoints=len(route.via) + 1, last=[float(x) for x in route.direction],
                    corner=[float(x) for x in route.via[-1][:3] - goal[:3]]
                    if len(route.via) else None,
                )  # fmt: skip
            info = dict(route=checked, used=choice.route is not None)
        if self.approach is not None and route is None:
            t0 = time.perf_counter()
            ranked, probs = self.approach.order(obj.points, sup.points, goal)
            wall = (scene.support.wall_y is not None) if scene is not None else not free_standing
            keep = approach.usable(ranked, probs, self.approach.config.threshold, wall,
                                   c.approach_open_side)  # fmt: skip
            info = dict(info or {}, best=[float(x) for x in ranked[0]], best_p=float(probs[0]),
                        used=bool(keep.any()), seconds=round(time.perf_counter() - t0, 4))  # fmt: skip
            if keep.any():
                directions = ranked[keep][:1]
                info["p"] = float(probs[keep][0])
        return directions, route, info

    def _attempt(self, check, name, start, goal, bounds, radius, seconds=None, directions=None,
                 route=None):  # fmt: skip
        from omnihang_jax import approach, planner, retreats

        limits = self.limits if seconds is None else dataclasses.replace(self.limits,
                                                                         time_limit=seconds)  # fmt: skip
        with _captured_stderr() as log:  # OMPL's C++ warnings: kept in info, not shown
            if directions is None and route is None:
                res, retreat = planner.plan(check, start, goal, bounds, radius, limits), None
            else:  # to the pre-goal, then straight in (the network's choice taken as free)
                res, retreat = retreats.plan_with_retreat(
                    check, start, goal, bounds, radius,
                    dataclasses.replace(limits, retreat_lengths=(self.config.approach_length,)),
                    retreat_checker=approach.never_colliding,
                    retreat_directions=approach.DIRECTIONS if directions is None else directions,
                    retreat=route,
                )  # fmt: skip
        info = dict(checker=name, status=res.status, planning_s=res.planning_s,
                    states_checked=res.states_checked,
                    start_xyz_wxyz=[float(x) for x in start])  # fmt: skip
        if retreat is not None:
            info["approach_direction"] = [float(x) for x in retreat.direction]
        if log.text.strip():
            info["ompl_log"] = log.text.strip().splitlines()[:20]
        return res.path, info

    def __call__(self, scene, obj, sup, goal: np.ndarray, free_standing: bool = False,
                 mesh_fallback: bool | None = None):  # fmt: skip
        from omnihang_jax import planner
        from omnihang_jax.hang import PathPlan

        c = self.config
        if c.checker == "mesh" and scene is None:
            return None
        fallback = c.mesh_fallback if mesh_fallback is None else mesh_fallback
        goal = np.asarray(goal, float).reshape(7)
        centre = None
        if scene is not None:
            geometry = scene
        else:  # clouds only: plan the object's box centre, in whatever frame the cloud came
            obj, goal, centre, geometry = cloud_frame(obj, sup, goal)
        start = planner.start_pose(geometry, goal)
        bounds = planner.default_bounds(geometry)
        radius = planner.object_radius(geometry)
        check, name = self.checker(obj, sup, goal, radius, scene)
        if hasattr(check, "warm_up") and self.warm:
            check.warm_up(self.warm)  # compiled outside the planning clock
        directions, route, ending = (None, None, None)
        if c.checker != "mesh":
            directions, route, ending = self._ending(check, obj, sup, goal, scene, free_standing)
        path, info = self._attempt(check, name, start, goal, bounds, radius, None, directions,
                                   route)  # fmt: skip
        if path is None and c.replan and planner.timed_out(info["status"]):
            first = info  # a time-out (not an invalid start or goal): one fresh search
            again = (None, None) if c.approach_replan == "plain" else (directions, route)
            seconds = c.plan_time if c.replan_time is None else c.replan_time
            if seconds > 0:
                path, info = self._attempt(check, name, start, goal, bounds, radius, seconds,
                                           *again)  # fmt: skip
                info = dict(info, replanned_after=first)
        if ending is not None:
            info["approach"] = ending
        if path is not None and c.clear_target and c.checker != "mesh":
            cleared = planner.clear_path(
                path, check, obj.points, sup.points, goal, radius, bounds,
                self.limits.resolution,
                planner.ClearanceConfig(target=c.clear_target, keep_ball=c.clear_keep_ball),
                self.limits.goal_radius,
            )  # fmt: skip
            path = cleared.path
            info["cleared"] = dict(
                gap_before_m=cleared.gap_before, gap_after_m=cleared.gap_after,
                moves=cleared.moves, waypoints_removed=cleared.removed,
                seconds=round(cleared.seconds, 2),
            )  # fmt: skip
        tried = [info]
        if path is None and scene is not None and fallback and c.checker != "mesh":
            # the estimator found no path (it can call the start colliding): the full meshes
            path, info = self._attempt(planner.MeshChecker(scene), "the full meshes in MuJoCo",
                                       start, goal, bounds, radius)  # fmt: skip
            tried.append(info)
        info = dict(info, attempts=tried) if len(tried) > 1 else info
        title = f"RRT-Connect (OMPL) with {info['checker']}"
        if path is None:
            return PathPlan(np.zeros((0, 7)), title, info)
        info["waypoints"] = len(path)
        if centre is not None:  # back to the object frame as given
            info["start_xyz_wxyz"] = [float(x) for x in move_origin(start, -centre)]
            return PathPlan(move_origin(planner.interpolate_path(path, c.path_step, radius),
                                        -centre), title, info)  # fmt: skip
        if scene is not None:
            free, deepest, n = planner.dense_check(
                planner.MeshChecker(scene, self.limits.penetration_tolerance), path,
                self.limits.dense_resolution, radius,
            )  # fmt: skip
            info.update(dense_check_collision_free=free, deepest_penetration_m=deepest,
                        dense_states=n)  # fmt: skip
        return PathPlan(planner.interpolate_path(path, c.path_step, radius), title, info)


def make_planner(config: PlannerConfig = DEFAULT, seed: int = 1, warm: int = 128) -> Planner:
    """The planner of ``config`` (networks loaded and compiled here, once per process).
    ``seed``: OMPL's random seed (OMPL takes one per process: the first plan's). ``warm``:
    each pair's checker compiles its batch sizes up to this many states before planning.
    Raises ``FileNotFoundError`` when a weights folder is missing (:func:`missing`)."""
    return Planner(config, seed, warm)
