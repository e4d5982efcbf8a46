"""How to hang: OMPL's RRT-Connect in SE(3) around a batched collision checker (host side).

This module is the host/device boundary of path planning. OMPL (C++, through its 2.x Python
bindings: ``ompl.base`` / ``ompl.geometric``) runs on the host; every collision question goes
to one ``checker(poses [B, 7]) -> colliding [B] bool``:

- :class:`EstimatorChecker` wraps a jitted ``collides(params, object_cloud, support_cloud,
  poses)`` from :mod:`omnihang_jax.collision` (NCE, HCE, HCE with true normals), padding each
  batch to a power of two so that only a handful of shapes is ever compiled;
- :class:`CascadeChecker` ORs a cheap checker and a costly one, asking the costly one only
  where the cheap one says free, and not at all for an edge the cheap one already blocks
  (the hybrid of ``experiments.eval_paths``: the observed-cloud test, then the NCE);
- :class:`MeshChecker` asks MuJoCo (C) for contacts between the full object and support
  meshes (``mj_kinematics`` + ``mj_collision``, as ``sim.kernels.contact_query`` does): the
  paper's "ground truth" planner and the dense check of every returned path.

State validity is the checker on one state; motion validation (:class:`BatchedMotionValidator`)
interpolates the edge at the planner's resolution and checks all its states in batched calls
(an :class:`EstimatorChecker`: 8 evenly spaced states first, the others only if those are
free; same answer, docs/paths.md "The planner's checker"). Settings (:class:`PlannerConfig`, the original code was never released, facts file):

- start: the goal's orientation, in front of the support (+y, away from the wall) at the
  goal's x and height, clear of the support's box by the object's largest extent (its
  centre 1.5 extents beyond the box);
- bounds: the support's box grown by the object's largest extent on every side, and on +y
  up to half an extent beyond the start; rotations unbounded;
- distance: translation + ``r`` x rotation angle, with ``r`` the object's half-extent, so a
  distance is roughly the largest displacement of an object point, in metres;
- resolution 5 mm (no 5-16 mm rod can slip between two checked states of a >= 2 mm part),
  range 10 cm per RRT-Connect extension, time limit per pair (default 20 s);
- goal: only the goal state itself is exempt from the checker (``goal_radius`` 1 um: it is
  given, and a hanging pose rests ON the support, which the dataset's labels call
  colliding); every other state, the last millimetres of the approach included, must be
  called free. ``goal_radius`` > 0 exempts a ball around it (``eval_paths --goal-radius``,
  measured in docs/paths.md: it lets estimator paths dive into the support). The dense check of
  a returned path checks every state at 2 mm with a penetration tolerance of 1 mm (the
  dataset's own ``max_penetration`` for a candidate pose).
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

from omnihang_jax.collision import (  # re-exported: the planner's ground truth and geometry
    MeshChecker,
    cloud_gap,
    default_bounds,
    object_radius,
    posed_points,
    start_pose,
)

__all__ = [
    "object_radius",
    "PlannerConfig",
    "PlanResult",
    "MeshChecker",
    "EstimatorChecker",
    "CascadeChecker",
    "RecordingChecker",
    "WallChecker",
    "HybridSettings",
    "hybrid_checker",
    "ExemptNearGoal",
    "ClearanceFarFromGoal",
    "posed_points",
    "AnalyticChecker",
    "BatchedMotionValidator",
    "default_bounds",
    "start_pose",
    "interpolate_path",
    "plan",
    "dense_check",
    "ClearanceConfig",
    "ClearedPath",
    "clear_path",
    "path_scene_xml",
]


@dataclasses.dataclass(frozen=True)
class PlannerConfig:
    time_limit: float = 20.0  # s per plan (OMPL's solve); the CPU NCE makes ~300 checks/s
    resolution: float = 0.005  # m: states checked along an edge, see module docstring
    range: float = 0.10  # m: longest RRT-Connect extension (<= 20 states per batched call)
    goal_radius: float = 1e-6  # m: states this near the goal are not checked (docstring)
    dense_resolution: float = 0.002  # m: the ground-truth check of a returned path
    penetration_tolerance: float = 1e-3  # m: deeper is colliding (dataset max_penetration)
    seed: int = 1  # OMPL's random seed (0 is not allowed; set once per process)
    # ours (twentieth session): lengths (m) of a straight retreat from the goal tried before
    # planning (plan_with_retreat); () = off, the plain plan
    retreat_lengths: tuple[float, ...] = ()
    # ours (twenty-first session): > 0 makes the retreat a fallback: the plain plan runs for
    # this many seconds first, and only when it finds no path is the retreat searched and
    # planned to with what is left of time_limit (0: the retreat first, as above)
    retreat_after: float = 0.0


_SEEDED: list[int] = []  # the seed OMPL was given in this process (at most one)


class PlanResult(NamedTuple):
    path: np.ndarray | None  # [K, 7] waypoints (start ... goal), None if no exact solution
    status: str  # OMPL's status string
    planning_s: float  # wall time of solve()
    states_checked: int  # states the checker was asked about
    checker_calls: int  # batched calls (one per motion, one per single state)


# ----------------------------------------------------------------------------------------------
# Checkers: poses [B, 7] -> colliding [B]


class EstimatorChecker:
    """A jitted ``collides(params, object_cloud, support_cloud, poses)`` bound to one pair's
    clouds. Batches are padded so that few shapes compile: to the next power of two up to
    8 (>= ``min_batch``), to the next multiple of 8 beyond. ``min_batch`` is 1 by default: a
    single state (OMPL's state validity) costs a batch of 1, not of 8 (the contact NCE on 2
    CPU cores: 4.8 ms against 21 ms). An edge has a median of 36 states (one 30-s plan of a
    pegboard pair): powers of two padded the edges by 43 %, multiples of 8 pad them by 7 %."""

    def __init__(
        self,
        collides_jit: Callable,
        params,
        object_cloud,
        support_cloud,
        min_batch: int = 1,
        pow2: bool = False,
        coarse: int = 8,
    ):
        """``pow2``, ``min_batch=8``, ``coarse=0``: the checker before the nineteenth session
        (every batch padded to a power of two >= 8, an edge in one call), kept for
        ``experiments.bench_paths --planner``."""
        if min_batch < 1 or min_batch > 8 or min_batch & (min_batch - 1):
            raise ValueError(f"min_batch must be a power of two in 1 .. 8, got {min_batch}")
        self.collides = collides_jit
        self.params = params
        self.object_cloud = jax.numpy.asarray(object_cloud, jax.numpy.float32)
        self.support_cloud = jax.numpy.asarray(support_cloud, jax.numpy.float32)
        self.min_batch = min_batch
        self.pow2 = pow2
        self.coarse = coarse

    def padded_size(self, b: int) -> int:
        if b <= 8 or self.pow2:
            return max(self.min_batch, 1 << int(np.ceil(np.log2(max(b, 1)))))
        return -(-b // 8) * 8

    def warm_up(self, largest: int = 144) -> None:
        """Compile every padded size up to ``largest`` (jit caches them for later pairs; the
        longest edge of a 30-s plan had 137 states)."""
        sizes = sorted({self.padded_size(b) for b in range(1, largest + 1)})
        for size in sizes:
            self(np.tile(np.array([0, 0, 10.0, 1, 0, 0, 0], np.float32), (size, 1)))

    def __call__(self, poses: np.ndarray) -> np.ndarray:
        poses = np.asarray(poses, np.float32).reshape(-1, 7)
        b = len(poses)
        if b == 0:
            return np.zeros(0, bool)
        size = self.padded_size(b)
        padded = np.concatenate([poses, np.repeat(poses[:1], size - b, 0)])
        out = self.collides(self.params, self.object_cloud, self.support_cloud, padded)
        return np.asarray(out)[:b]

    def any_colliding(self, poses: np.ndarray) -> bool:
        """Is any state of an edge colliding? ``coarse`` evenly spaced states first (the last
        one the edge's far end), the others only if none of those collides: the same answer as
        ``self(poses).any()``. An edge through the support (colliding over a run of states)
        then costs a batch of ``coarse``, and a free edge the same padded batches as one call
        (OMPL's own motion validator also checks an edge's states out of order). ``coarse``
        0: one call."""
        poses = np.asarray(poses, np.float32).reshape(-1, 7)
        n, coarse = len(poses), self.coarse
        if not coarse or n <= 2 * coarse:
            return bool(self(poses).any())
        first = np.zeros(n, bool)
        first[(np.arange(1, coarse + 1) * n) // coarse - 1] = True
        return bool(self(poses[first]).any() or self(poses[~first]).any())


class CascadeChecker:
    """``first OR second``, asking the (costly) second checker only where the (cheap) first
    says free. Per state it answers exactly what one checker computing both would
    (``collision.nce_geometric_collides``); :meth:`any_colliding` (an edge of the planner)
    stops after the first checker when it flags any state, without asking the second.

    ``states_first`` / ``states_second`` count the states each checker was asked about."""

    def __init__(self, first: Callable, second: Callable):
        self.first, self.second = first, second
        self.states_first = self.states_second = 0

    def warm_up(self, largest: int = 144) -> None:
        for checker in (self.first, self.second):
            if hasattr(checker, "warm_up"):
                checker.warm_up(largest)

    def __call__(self, poses: np.ndarray) -> np.ndarray:
        poses = np.asarray(poses).reshape(-1, 7)
        self.states_first += len(poses)
        hit = np.asarray(self.first(poses), bool).copy()
        rest = np.flatnonzero(~hit)
        if len(rest):
            self.states_second += len(rest)
            hit[rest] = np.asarray(self.second(poses[rest]), bool)
        return hit

    def any_colliding(self, poses: np.ndarray) -> bool:
        poses = np.asarray(poses).reshape(-1, 7)
        self.states_first += len(poses)
        if np.asarray(self.first(poses), bool).any():
            return True
        self.states_second += len(poses)
        return any_colliding(self.second, poses)


class RecordingChecker:
    """``checker``, recording what it was asked and what it answered (twenty-ninth session,
    ``eval_paths --mine``): the states a planner's own checker judges are where its errors
    matter. Per call the poses [B, 7] and verdicts [B] (True = called colliding); an edge
    asked through :meth:`any_colliding` is recorded only when it comes back free (then every
    state was called free; a blocked edge's verdicts per state are unknown). At most
    ``cap`` states are kept, a uniform reservoir over everything asked (seeded: the same
    plan records the same states)."""

    def __init__(self, checker: Callable, cap: int = 200_000, seed: int = 0):
        if cap < 1:
            raise ValueError(f"cap must be >= 1, got {cap}")
        self.checker, self.cap = checker, cap
        self.rng = np.random.default_rng(seed)
        self._poses = np.zeros((cap, 7), np.float32)  # filled in place: no copy per call
        self._called = np.zeros(cap, bool)
        self.seen = 0

    @property
    def poses(self) -> np.ndarray:
        """[K, 7] the states kept (K = min(seen, cap))."""
        return self._poses[: min(self.seen, self.cap)]

    @property
    def called(self) -> np.ndarray:
        """[K] their verdicts (True = called colliding)."""
        return self._called[: min(self.seen, self.cap)]

    def warm_up(self, largest: int = 144) -> None:
        if hasattr(self.checker, "warm_up"):
            self.checker.warm_up(largest)

    def _keep(self, poses: np.ndarray, called: np.ndarray) -> None:
        poses = np.asarray(poses, np.float32).reshape(-1, 7)
        n, filled = len(poses), min(self.seen, self.cap)
        take = min(self.cap - filled, n)
        self._poses[filled : filled + take] = poses[:take]
        self._called[filled : filled + take] = called[:take]
        for i in range(take, n):  # reservoir sampling (Algorithm R) for the rest
            j = int(self.rng.integers(0, self.seen + i + 1))
            if j < self.cap:
                self._poses[j], self._called[j] = poses[i], called[i]
        self.seen += n

    def __call__(self, poses: np.ndarray) -> np.ndarray:
        out = np.asarray(self.checker(poses), bool)
        self._keep(poses, out)
        return out

    def any_colliding(self, poses: np.ndarray) -> bool:
        hit = any_colliding(self.checker, poses)
        if not hit:
            self._keep(poses, np.zeros(len(np.asarray(poses).reshape(-1, 7)), bool))
        return hit


class WallChecker:
    """Colliding where some observed object point, posed, lies behind the wall plane ``y =
    wall_y`` (support frame; the side the support is mounted on) or closer to it than
    ``margin`` (twenty-ninth session). The wall is a known plane that no estimator is told
    about: 6 of 179 returned held-out paths (twenty-fourth session's runs) collide with it, and
    the observed points alone, at margin 0, catch 2 of them and block no free path
    (``scripts/probe_wall.py``). Host NumPy, ~10 us a state for 512 points."""

    def __init__(self, object_points, wall_y: float, margin: float = 0.0):
        if not np.isfinite(wall_y) or margin < 0:
            raise ValueError(f"wall_y must be finite and margin >= 0, got {wall_y}, {margin}")
        self.object_points = np.asarray(object_points, float).reshape(-1, 3)
        self.limit = float(wall_y) + float(margin)

    def __call__(self, poses: np.ndarray) -> np.ndarray:
        poses = np.asarray(poses, float).reshape(-1, 7)
        if not len(poses):
            return np.zeros(0, bool)
        return posed_points(poses, self.object_points)[..., 1].min(axis=1) < self.limit


class AnalyticChecker:
    """Exact checker for tests: a sphere of ``radius`` at the pose's position against
    axis-aligned boxes ``[(low [3], high [3]), ...]`` (rotation does not matter)."""

    def __init__(self, boxes, radius: float = 0.0):
        self.boxes = [(np.asarray(lo, float), np.asarray(hi, float)) for lo, hi in boxes]
        self.radius = radius

    def __call__(self, poses: np.ndarray) -> np.ndarray:
        p = np.asarray(poses, float).reshape(-1, 7)[:, :3]
        hit = np.zeros(len(p), bool)
        for lo, hi in self.boxes:
            nearest = np.clip(p, lo, hi)
            hit |= np.linalg.norm(p - nearest, axis=1) <= self.radius
        return hit


class ExemptNearGoal:
    """``checker``, but every state within ``radius`` (the planner's metric: translation +
    ``weight`` x angle) of ``goal`` is free. As the first checker of a
    :class:`CascadeChecker` it switches that checker off near the goal, so the second decides
    there alone (``eval_paths --test-goal-ball``)."""

    def __init__(self, checker: Callable, goal: np.ndarray, radius: float, weight: float):
        self.checker, self.goal = checker, np.asarray(goal, float)
        self.radius, self.weight = radius, weight

    def warm_up(self, largest: int = 144) -> None:
        if hasattr(self.checker, "warm_up"):
            self.checker.warm_up(largest)

    def __call__(self, poses: np.ndarray) -> np.ndarray:
        poses = np.asarray(poses).reshape(-1, 7)
        far = goal_distances(poses, self.goal, self.weight) > self.radius
        hit = np.zeros(len(poses), bool)
        if far.any():
            hit[far] = np.asarray(self.checker(poses[far]), bool)
        return hit

    def any_colliding(self, poses: np.ndarray) -> bool:
        poses = np.asarray(poses).reshape(-1, 7)
        far = poses[goal_distances(poses, self.goal, self.weight) > self.radius]
        return bool(len(far)) and any_colliding(self.checker, far)


class ClearanceFarFromGoal:
    """Colliding where a state farther than ``radius`` from ``goal`` (the planner's metric)
    brings the observed object cloud within ``margin`` of the observed support cloud.

    Why (twenty-second session, ``scripts/probe_path_collisions.py``): the hybrid's colliding
    paths penetrate the meshes where the observed clouds are still 1-25 mm apart (the object
    meets the support's unobserved side), and 10 of 15 do so more than 4.5 cm from the goal,
    where a hang needs no contact at all. Near the goal (within ``radius``) it says free, and
    the checkers after it in a :class:`CascadeChecker` decide alone. A k-d tree of the support
    cloud on the host (scipy), queried with ``margin`` as the upper bound."""

    def __init__(self, object_points, support_points, goal, radius: float, margin: float,
                 weight: float):  # fmt: skip
        from scipy.spatial import cKDTree

        self.object_points = np.asarray(object_points, float)
        self.tree = cKDTree(np.asarray(support_points, float))
        self.goal, self.radius = np.asarray(goal, float), radius
        self.margin, self.weight = margin, weight

    def __call__(self, poses: np.ndarray) -> np.ndarray:
        poses = np.asarray(poses, float).reshape(-1, 7)
        hit = np.zeros(len(poses), bool)
        far = np.flatnonzero(goal_distances(poses, self.goal, self.weight) > self.radius)
        if len(far):
            gap = cloud_gap(self.object_points, self.tree, poses[far], self.margin)
            hit[far] = np.isfinite(gap)
        return hit


class HybridSettings(NamedTuple):
    """The best planner's checker (docs/paths.md, twenty-second session): the observed-cloud
    penetration test (``geometric``) first, the NCE only where it says free; the NCE's
    threshold is ``near_threshold`` within ``goal_ball`` (planner metric, m) of the goal and
    ``far_threshold`` beyond it (``goal_ball`` 0: ``far_threshold`` everywhere)."""

    geometric: Any  # collision.GeometricConfig
    far_threshold: float
    near_threshold: float
    goal_ball: float

    @classmethod
    def from_selection(cls, path, near_threshold: float, goal_ball: float):
        """From an ``eval_paths --select-geometric`` file (its ``chosen`` row: the test's depth /
        radius / min points and, for a joint selection, the NCE threshold)."""
        import json

        from omnihang_jax import collision

        chosen = json.loads(open(path).read())["chosen"]
        if chosen is None:
            raise ValueError(f"{path}: no setting was chosen (none kept the goal pass)")
        geo = dataclasses.replace(
            collision.GeometricConfig(),
            **{k: chosen[k] for k in ("depth", "radius", "min_points")},
        )
        if "nce_threshold" not in chosen:
            raise ValueError(f"{path}: not a joint selection (no nce_threshold)")
        return cls(geo, float(chosen["nce_threshold"]), float(near_threshold), float(goal_ball))


@functools.lru_cache(maxsize=8)
def _jitted(kind: str, *args):
    from omnihang_jax import collision

    if kind == "goal_ball":
        return jax.jit(collision.goal_ball_collides(*args))
    if kind == "nce":
        return jax.jit(collision.nce_collides(*args))
    return jax.jit(collision.geometric_collides(*args))


def hybrid_checker(
    nce_config,
    nce_params,
    object_points: np.ndarray,
    support_points: np.ndarray,
    support_normals: np.ndarray,
    settings: HybridSettings,
    goal: np.ndarray,
    rotation_weight: float,
    pow2: bool = False,
) -> CascadeChecker:
    """:class:`HybridSettings`' checker for one pair: ``CascadeChecker(test, nce)``, as
    ``experiments.eval_paths`` builds its ``nce_geometric`` method (same cloud subsets, seeds 0
    / 1; the support's lookup table built here, once). Clouds: the observed ones, object frame
    / support frame, with the support's outward normals."""
    from omnihang_jax import collision

    if nce_config.input_clouds != "observed":
        raise ValueError(f"hybrid_checker gives the NCE observed clouds; this one was trained on "
                         f"{nce_config.input_clouds} clouds")  # fmt: skip
    sub = collision.subsample_cloud
    geo = settings.geometric
    grid = collision.support_grid(support_points, support_normals, geo.voxel, geo.max_voxels,
                                  geo.margin)  # fmt: skip
    test = EstimatorChecker(
        _jitted("geometric", geo), grid, sub(object_points, geo.object_points, 0), grid.points,
        pow2=pow2,
    )  # fmt: skip
    clouds = (
        sub(object_points, nce_config.object_input, 0),
        sub(support_points, nce_config.support_input, 1),
    )
    if settings.goal_ball > 0:
        cfg = dataclasses.replace(nce_config, threshold=settings.near_threshold)
        fn = _jitted("goal_ball", cfg, settings.far_threshold, settings.goal_ball)
        params = (nce_params, np.asarray(goal, np.float32), np.float32(rotation_weight))
    else:
        fn = _jitted("nce", dataclasses.replace(nce_config, threshold=settings.far_threshold))
        params = nce_params
    return CascadeChecker(test, EstimatorChecker(fn, params, *clouds, pow2=pow2))


def any_colliding(checker: Callable, poses: np.ndarray) -> bool:
    """Is any of the states colliding? The checker's own ``any_colliding`` when it has one
    (it may stop early), else one call."""
    own = getattr(checker, "any_colliding", None)
    return bool(own(poses)) if own is not None else bool(np.asarray(checker(poses), bool).any())


# ----------------------------------------------------------------------------------------------
# SE(3) helpers (numpy; the same interpolation as OMPL's SE3StateSpace: lerp + slerp)


def _slerp(q0: np.ndarray, q1: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Shortest-arc slerp of unit quaternions (w, x, y, z) at fractions t [K] -> [K, 4]."""
    q0, q1 = q0 / np.linalg.norm(q0), q1 / np.linalg.norm(q1)
    dot = float(np.dot(q0, q1))
    if dot < 0:
        q1, dot = -q1, -dot
    if dot > 0.9995:
        q = q0[None] + t[:, None] * (q1 - q0)[None]
        return q / np.linalg.norm(q, axis=1, keepdims=True)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    s = np.sin(theta)
    return (np.sin((1 - t) * theta)[:, None] * q0 + np.sin(t * theta)[:, None] * q1) / s


def _angle(q0: np.ndarray, q1: np.ndarray) -> float:
    dot = abs(float(np.dot(q0, q1)) / (np.linalg.norm(q0) * np.linalg.norm(q1)))
    return 2.0 * np.arccos(min(1.0, dot))


def pose_distance(a: np.ndarray, b: np.ndarray, rotation_weight: float) -> float:
    """The planner's metric: translation + ``rotation_weight`` x rotation angle."""
    return float(np.linalg.norm(a[:3] - b[:3])) + rotation_weight * _angle(a[3:], b[3:])


def goal_distances(poses: np.ndarray, goal: np.ndarray, rotation_weight: float) -> np.ndarray:
    """:func:`pose_distance` of every pose [B, 7] to ``goal`` [7]: [B]."""
    poses = np.asarray(poses, float).reshape(-1, 7)
    q, g = poses[:, 3:], np.asarray(goal[3:], float)
    dot = np.abs(q @ g) / (np.linalg.norm(q, axis=1) * np.linalg.norm(g))
    angle = 2.0 * np.arccos(np.minimum(1.0, dot))
    return (
        np.linalg.norm(poses[:, :3] - np.asarray(goal[:3], float), axis=1) + rotation_weight * angle
    )


def interpolate_segment(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """States at fractions 1/n ... 1 of the way from a to b: [n, 7] (a itself excluded)."""
    t = np.arange(1, n + 1) / n
    pos = a[None, :3] + t[:, None] * (b[:3] - a[:3])[None]
    return np.concatenate([pos, _slerp(a[3:], b[3:], t)], axis=1)


def interpolate_path(path: np.ndarray, resolution: float, rotation_weight: float) -> np.ndarray:
    """Every waypoint and states at most ``resolution`` apart between them: [K', 7]."""
    out = [np.asarray(path[0], float)[None]]
    for a, b in zip(path[:-1], path[1:]):
        n = max(1, int(np.ceil(pose_distance(a, b, rotation_weight) / resolution)))
        out.append(interpolate_segment(np.asarray(a, float), np.asarray(b, float), n))
    return np.concatenate(out)


# ----------------------------------------------------------------------------------------------
# OMPL


def _state_pose(state) -> np.ndarray:
    rot = state.rotation()
    return np.array([state.getX(), state.getY(), state.getZ(), rot.w, rot.x, rot.y, rot.z])


def _set_state(state, pose: np.ndarray) -> None:
    state.setXYZ(float(pose[0]), float(pose[1]), float(pose[2]))
    q = np.asarray(pose[3:], float) / np.linalg.norm(pose[3:])
    rot = state.rotation()
    rot.w, rot.x, rot.y, rot.z = (float(v) for v in q)


class _Counter:
    """The checker with the goal tolerance and the bookkeeping of a plan."""

    def __init__(self, checker, goal: np.ndarray, goal_radius: float, rotation_weight: float):
        self.checker = checker
        self.goal = goal
        self.goal_radius = goal_radius
        self.weight = rotation_weight
        self.states = 0
        self.calls = 0

    def valid(self, poses: np.ndarray) -> np.ndarray:
        """[B, 7] -> [B] bool, True = free."""
        near = goal_distances(poses, self.goal, self.weight) <= self.goal_radius
        free = np.ones(len(poses), bool)
        ask = np.flatnonzero(~near)
        if len(ask):
            self.states += len(ask)
            self.calls += 1
            free[ask] = ~np.asarray(self.checker(poses[ask]), bool)
        return free

    def any_colliding(self, poses: np.ndarray) -> bool:
        """Is any of the states [B, 7] colliding (one edge)? The checker's own
        ``any_colliding`` when it has one (:class:`CascadeChecker` stops early)."""
        ask = poses[goal_distances(poses, self.goal, self.weight) > self.goal_radius]
        if not len(ask):
            return False
        self.states += len(ask)
        self.calls += 1
        return any_colliding(self.checker, ask)


class BatchedMotionValidator(ob.MotionValidator):
    """OMPL motion validator: the edge's interpolated states (OMPL's segment count at the
    space's resolution), all checked in ONE batched call."""

    def __init__(self, si, counter: _Counter):
        super().__init__(si)
        self.si = si
        self.space = si.getStateSpace()
        self.counter = counter

    def checkMotion(self, s1, s2):  # noqa: N802 (OMPL's name)
        n = max(1, int(self.space.validSegmentCount(s1, s2)))
        states = interpolate_segment(_state_pose(s1), _state_pose(s2), n)
        return not self.counter.any_colliding(states)


def timed_out(status: str) -> bool:
    """Whether OMPL's status string (``PlanResult.status``) is a search that ran out of time
    (no exact path), not an invalid start or goal."""
    return status in ("Timeout", "Approximate solution")


def plan(
    checker: Callable[[np.ndarray], np.ndarray],
    start: np.ndarray,
    goal: np.ndarray,
    bounds: tuple[np.ndarray, np.ndarray],
    rotation_weight: float,
    config: PlannerConfig = PlannerConfig(),
) -> PlanResult:
    """RRT-Connect from ``start`` to ``goal`` (poses [7]) within ``bounds`` (low [3], high
    [3]); ``checker(poses [B, 7]) -> colliding [B]``. Only exact solutions are returned."""
    start, goal = np.asarray(start, float), np.asarray(goal, float)
    lo, hi = np.asarray(bounds[0], float), np.asarray(bounds[1], float)
    if start.shape != (7,) or goal.shape != (7,):
        raise ValueError(f"start and goal must be poses [7], got {start.shape}, {goal.shape}")
    if not (np.all(lo < hi) and np.all(lo <= start[:3]) and np.all(start[:3] <= hi)):
        raise ValueError(f"start {start[:3]} outside the bounds {lo} .. {hi}")
    if not (np.all(lo <= goal[:3]) and np.all(goal[:3] <= hi)):
        raise ValueError(f"goal {goal[:3]} outside the bounds {lo} .. {hi}")
    ou.setLogLevel(ou.LogLevel.LOG_WARN)
    if not _SEEDED:  # OMPL takes its seed once per process, before the first sample
        ou.RNG.setSeed(config.seed)
        _SEEDED.append(config.seed)
    space = ob.SE3StateSpace()
    rb = ob.RealVectorBounds(3)
    for i in range(3):
        rb.setLow(i, float(lo[i]))
        rb.setHigh(i, float(hi[i]))
    space.setBounds(rb)
    space.setSubspaceWeight(1, float(rotation_weight))
    si = ob.SpaceInformation(space)
    counter = _Counter(checker, goal, config.goal_radius, rotation_weight)
    si.setStateValidityChecker(lambda s: bool(counter.valid(_state_pose(s)[None])[0]))
    validator = BatchedMotionValidator(si, counter)
    si.setMotionValidator(validator)
    si.setup()  # computes the maximum extent; the resolution is a fraction of it
    si.setStateValidityCheckingResolution(config.resolution / space.getMaximumExtent())
    ss = og.SimpleSetup(si)
    s, g = space.allocState(), space.allocState()
    _set_state(s, start)
    _set_state(g, goal)
    ss.setStartAndGoalStates(s, g)
    planner = og.RRTConnect(si)
    planner.setRange(config.range)
    ss.setPlanner(planner)
    t0 = time.perf_counter()
    status = ss.solve(config.time_limit)
    seconds = time.perf_counter() - t0
    path = None
    if ss.haveExactSolutionPath():
        path = np.array([_state_pose(x) for x in ss.getSolutionPath().getStates()])
    return PlanResult(path, status.asString(), seconds, counter.states, counter.calls)


# A hang is an insertion; its approach is the reverse of taking the object off. The retreat
# directions (support frame, z up): the 26 of {-1, 0, 1}^3 minus zero, normalised, upward ones
# first (a hung object usually comes off by lifting), then in a fixed order: deterministic.
RETREAT_DIRECTIONS = (
    np.array(
        sorted(
            (d for d in np.ndindex(3, 3, 3) if d != (1, 1, 1)),
            key=lambda d: (-(d[2] - 1), sum(abs(x - 1) for x in d), d),
        ),
        float,
    )
    - 1.0
)
RETREAT_DIRECTIONS /= np.linalg.norm(RETREAT_DIRECTIONS, axis=1, keepdims=True)


class Retreat(NamedTuple):
    pregoal: np.ndarray  # [7] the goal moved back along ``direction`` by ``length``
    direction: np.ndarray  # [3] unit, support frame
    length: float  # m
    states_checked: int
    seconds: float
    # thirty-ninth session: waypoints between the pre-goal and the goal, in approach order
    # (:func:`find_two_move_retreat`: the corner of a two-move retreat); empty: straight in
    via: np.ndarray = np.zeros((0, 7))


def find_retreat(
    checker: Callable[[np.ndarray], np.ndarray],
    goal: np.ndarray,
    lengths,
    resolution: float,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    directions: np.ndarray = RETREAT_DIRECTIONS,
) -> Retreat | None:
    """The first straight, orientation-keeping retreat from ``goal`` that ``checker`` calls
    free on every state at ``resolution`` (the goal itself excluded, as in :func:`plan`):
    lengths in the given order (shortest first is sensible), for each the directions in
    order; within ``bounds`` when given. None when every one is blocked."""
    t0 = time.perf_counter()
    goal = np.asarray(goal, float)
    checked = 0
    for length in lengths:
        for d in directions:
            end, states = _retreat_states(goal, d, float(length), resolution, bounds)
            if states is None:
                continue
            checked += len(states)
            if not any_colliding(checker, states):
                return Retreat(end, np.asarray(d, float), float(length), checked,
                               time.perf_counter() - t0)  # fmt: skip
    return None


def find_two_move_retreat(
    checker: Callable[[np.ndarray], np.ndarray],
    goal: np.ndarray,
    firsts,
    length: float,
    resolution: float,
    bounds: tuple[np.ndarray, np.ndarray] | None,
    off: Callable[[np.ndarray], bool],
    directions: np.ndarray = RETREAT_DIRECTIONS,
) -> Retreat | None:
    """The first retreat of at most two straight, orientation-keeping moves from ``goal`` that
    ``checker`` calls free and whose end ``off(pose [7])`` accepts (e.g. clear of the support):
    the one-move retreats of ``length`` first, then for each first length in ``firsts`` and each
    first direction, a second move of ``length`` in each direction not going back (the
    directions in order). The returned ``Retreat``'s ``direction`` / ``length`` are the second
    move's, ``via`` the corner. None when none exists. Thirty-ninth session
    (``scripts/probe_dogleg.py``): 27 of the 80 benchmark goals are off the support after one
    4.5-cm move, 44 after two."""
    t0 = time.perf_counter()
    goal = np.asarray(goal, float)
    checked = [0]

    def free_end(a, d, L):
        end, states = _retreat_states(a, d, float(L), resolution, bounds)
        if states is None:
            return None
        checked[0] += len(states)
        return None if any_colliding(checker, states) else end

    ends = {}
    for i, d in enumerate(directions):
        end = free_end(goal, d, length)
        if end is None:
            continue
        ends[i] = end
        if off(end):
            return Retreat(end, np.asarray(d, float), float(length), checked[0],
                           time.perf_counter() - t0)  # fmt: skip
    for first in firsts:
        for i, d1 in enumerate(directions):
            same = abs(float(first) - length) < 1e-9
            mid = ends.get(i) if same else free_end(goal, d1, first)
            if mid is None:
                continue
            for d2 in directions:
                if np.dot(d1, d2) < -0.5:  # back the way it came
                    continue
                end = free_end(mid, d2, length)
                if end is not None and off(end):
                    return Retreat(end, np.asarray(d2, float), float(length), checked[0],
                                   time.perf_counter() - t0, via=mid[None])  # fmt: skip
    return None


def move_routes(firsts, directions: np.ndarray = RETREAT_DIRECTIONS) -> np.ndarray:
    """[R, 3] the routes of at most two straight moves a route network scores (fortieth
    session), rows (first direction index or -1, first length m or 0, last direction index):
    the one-move routes first (one per direction), then for each first length in ``firsts``
    every pair of directions that does not go back the way it came (cosine >= -0.5, as
    :func:`find_two_move_retreat` searches them): 26 + 506 routes for one first length."""
    rows = [(-1, 0.0, j) for j in range(len(directions))]
    for first in firsts:
        for i, d1 in enumerate(directions):
            for j, d2 in enumerate(directions):
                if np.dot(d1, d2) >= -0.5:
                    rows.append((i, float(first), j))
    return np.array(rows, float).reshape(-1, 3)


def route_table(
    checker: Callable[[np.ndarray], np.ndarray],
    goal: np.ndarray,
    routes: np.ndarray,
    length: float,
    resolution: float,
    bounds: tuple[np.ndarray, np.ndarray] | None,
    off: Callable[[np.ndarray], bool],
    directions: np.ndarray = RETREAT_DIRECTIONS,
) -> np.ndarray:
    """[R] bool: is each route of :func:`move_routes` free on ``checker`` (every state of both
    moves at ``resolution``, inside ``bounds``) and does ``off`` accept its end? The last move
    is ``length`` long. Each straight segment is checked once (a shared first move, an end's
    ``off``). A route network's labels (``approach.route_labels``)."""
    goal = np.asarray(goal, float)
    segments: dict = {}

    def free_end(start_key, a, j, L):
        key = (start_key, j, round(float(L), 6))
        if key not in segments:
            end, states = _retreat_states(a, directions[j], float(L), resolution, bounds)
            segments[key] = None if states is None or any_colliding(checker, states) else end
        return segments[key]

    ends_off: dict = {}
    out = np.zeros(len(routes), bool)
    for r, (i, first, j) in enumerate(np.asarray(routes, float)):
        i, j = int(i), int(j)
        start_key, start = "goal", goal
        if i >= 0:
            start = free_end("goal", goal, i, first)
            if start is None:
                continue
            start_key = (i, round(float(first), 6))
        end = free_end(start_key, start, j, length)
        if end is None:
            continue
        key = (start_key, j)
        if key not in ends_off:
            ends_off[key] = bool(off(end))
        out[r] = ends_off[key]
    return out


def route_retreat(goal: np.ndarray, route, length: float,
                  directions: np.ndarray = RETREAT_DIRECTIONS) -> Retreat:  # fmt: skip
    """The :class:`Retreat` of one route of :func:`move_routes` (its corner in ``via``), for
    ``plan_with_retreat(retreat=...)``; no check is made (a route network's choice)."""
    goal = np.asarray(goal, float)
    i, first, j = (int(route[0]), float(route[1]), int(route[2]))
    mid = goal.copy()
    via = np.zeros((0, 7))
    if i >= 0:
        mid[:3] += first * directions[i]
        via = mid[None].copy()
    end = mid.copy()
    end[:3] += length * directions[j]
    return Retreat(end, np.asarray(directions[j], float), float(length), 0, 0.0, via=via)


def route_states(goal: np.ndarray, route, length: float, resolution: float,
                 directions: np.ndarray = RETREAT_DIRECTIONS) -> np.ndarray:  # fmt: skip
    """[n, 7] the states of one route of :func:`move_routes` from ``goal`` at ``resolution``
    (the first move, if any, then the last; orientation kept; the goal itself excluded, the
    route's end last): what a planner's own checker is asked before it takes a route network's choice
    (forty-first session)."""
    goal = np.asarray(goal, float)
    i, first, j = (int(route[0]), float(route[1]), int(route[2]))
    parts, start = [], goal
    if i >= 0:
        start, states = _retreat_states(goal, directions[i], first, resolution, None)
        parts.append(states)
    _, states = _retreat_states(start, directions[j], float(length), resolution, None)
    parts.append(states)
    return np.concatenate(parts)


def lattice_retreat(
    checker: Callable[[np.ndarray], np.ndarray],
    goal: np.ndarray,
    step: float,
    off: Callable[[np.ndarray], bool],
    max_nodes: int,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    resolution: float = 0.002,
) -> tuple[Retreat | None, int]:
    """(the shortest retreat from ``goal`` on a lattice of ``step`` translations (26 directions,
    orientation kept) whose every edge ``checker`` calls free at ``resolution`` and whose end
    ``off`` accepts, or None within ``max_nodes`` expanded nodes; the nodes expanded). The
    retreat's ``via`` holds its lattice points between the pre-goal and the goal in approach
    order. Breadth-first: the fewest steps. Thirty-ninth session (``scripts/probe_route_bfs.py``):
    19 of the 36 threaded benchmark goals have one at 7.5-mm steps. A node's new edges are
    checked in one ``checker`` call (forty-third session: a network checker's cost is per call),
    so the route found is the same as edge by edge."""
    from collections import deque

    t0 = time.perf_counter()
    goal = np.asarray(goal, float)
    dirs = np.array([d for d in np.ndindex(3, 3, 3) if d != (1, 1, 1)], int) - 1
    parent = {(0, 0, 0): None}
    queue = deque([(0, 0, 0)])
    expanded = checked = 0

    def pose_of(node):
        pose = goal.copy()
        pose[:3] += step * np.asarray(node, float)
        return pose

    while queue and expanded < max_nodes:
        node = queue.popleft()
        expanded += 1
        here = pose_of(node)
        edges = []  # this node's new neighbours in bounds, checked in one call
        for d in dirs:
            nxt = tuple(int(v) for v in np.asarray(node) + d)
            if nxt in parent:
                continue
            end = pose_of(nxt)
            if bounds is not None and not (
                np.all(bounds[0] <= end[:3]) and np.all(end[:3] <= bounds[1])
            ):
                continue
            n = max(1, int(np.ceil(step * np.linalg.norm(d) / resolution)))
            edges.append((nxt, end, interpolate_segment(here, end, n)))
        if not edges:
            continue
        flat = np.concatenate([states for _, _, states in edges])
        checked += len(flat)
        flags = np.asarray(checker(flat), bool).reshape(-1)
        at = 0
        for nxt, end, states in edges:
            colliding = bool(flags[at : at + len(states)].any())
            at += len(states)
            if colliding:
                continue
            parent[nxt] = node
            if off(end):
                route, k = [], parent[nxt]
                while k is not None and k != (0, 0, 0):
                    route.append(pose_of(k))
                    k = parent[k]
                via = np.array(route) if route else np.zeros((0, 7))  # pre-goal side first
                direction = end[:3] - (via[0][:3] if len(via) else goal[:3])
                length = float(np.linalg.norm(direction))
                return Retreat(end, direction / max(length, 1e-12), length, checked,
                               time.perf_counter() - t0, via=via), expanded  # fmt: skip
            queue.append(nxt)
    return None, expanded


def _retreat_states(goal, direction, length: float, resolution: float, bounds):
    """(far end [7], the straight retreat's states from ``goal`` [n, 7]); states None when
    the far end leaves ``bounds``."""
    end = goal.copy()
    end[:3] = goal[:3] + length * np.asarray(direction, float)
    if bounds is not None and not (np.all(bounds[0] <= end[:3]) and np.all(end[:3] <= bounds[1])):
        return end, None
    return end, interpolate_segment(goal, end, max(1, int(np.ceil(length / resolution))))


def free_retreats(
    checker: Callable[[np.ndarray], np.ndarray],
    goal: np.ndarray,
    length: float,
    resolution: float,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    directions: np.ndarray = RETREAT_DIRECTIONS,
) -> np.ndarray:
    """[D] bool: which straight, orientation-keeping retreats of ``length`` from ``goal``
    ``checker`` calls free (as :func:`find_retreat` judges one; False when leaving ``bounds``).
    The approach network's labels (``approach.approach_labels``)."""
    goal = np.asarray(goal, float)
    out = np.zeros(len(directions), bool)
    for i, d in enumerate(directions):
        _, states = _retreat_states(goal, d, float(length), resolution, bounds)
        out[i] = states is not None and not any_colliding(checker, states)
    return out


def plan_with_retreat(
    checker: Callable[[np.ndarray], np.ndarray],
    start: np.ndarray,
    goal: np.ndarray,
    bounds: tuple[np.ndarray, np.ndarray],
    rotation_weight: float,
    config: PlannerConfig = PlannerConfig(),
    retreat_checker: Callable[[np.ndarray], np.ndarray] | None = None,
    retreat_directions: np.ndarray = RETREAT_DIRECTIONS,
    retreat: Retreat | None = None,
) -> tuple[PlanResult, Retreat | None]:
    """RRT-Connect to a pre-goal, then straight in: :func:`find_retreat` (lengths
    ``config.retreat_lengths``) and, when a retreat is free, :func:`plan` from ``start`` to its
    pre-goal with what is left of the time limit, the path ending pre-goal -> goal. Without a
    free retreat (or with ``retreat_lengths`` empty) the plain plan to the goal. The search's
    time and states count in the result. ``config.retreat_after`` > 0: the plain plan first,
    for that many seconds; the retreat only when it returns no path, with the time left (the
    first plan's time and states count too). ``retreat_checker``: the retreat's checker when
    not ``checker`` (a probe: ``collision.MeshChecker`` gives the oracle approach).
    ``retreat_directions``: those tried, in order (the approach network's ranking; empty: the
    plain plan)."""
    lo, hi = np.asarray(bounds[0], float), np.asarray(bounds[1], float)
    spent_s, spent_states, spent_calls = 0.0, 0, 0
    if config.retreat_lengths and 0 < config.retreat_after < config.time_limit:
        first = plan(checker, start, goal, bounds, rotation_weight,
                     dataclasses.replace(config, time_limit=config.retreat_after))  # fmt: skip
        if first.path is not None:
            return first, None
        spent_s, spent_states, spent_calls = (
            first.planning_s,
            first.states_checked,
            first.checker_calls,
        )
        config = dataclasses.replace(config, time_limit=config.time_limit - first.planning_s)
    found = retreat
    if found is None and config.retreat_lengths:
        found = find_retreat(retreat_checker or checker, goal, config.retreat_lengths,
                             config.resolution, (lo, hi), retreat_directions)  # fmt: skip
    if found is None:
        res = plan(checker, start, goal, bounds, rotation_weight, config)
        return PlanResult(res.path, res.status, res.planning_s + spent_s,
                          res.states_checked + spent_states, res.checker_calls + spent_calls), None  # fmt: skip
    left = dataclasses.replace(config, time_limit=max(config.time_limit - found.seconds, 0.01))
    res = plan(checker, start, found.pregoal, bounds, rotation_weight, left)
    path = None
    if res.path is not None:
        path = np.concatenate([res.path, np.asarray(found.via, float).reshape(-1, 7),
                               np.asarray(goal, float)[None]])  # fmt: skip
    return PlanResult(path, res.status, res.planning_s + found.seconds + spent_s,
                      res.states_checked + found.states_checked + spent_states,
                      res.checker_calls + spent_calls), found  # fmt: skip


# ----------------------------------------------------------------------------------------------
# A returned path moved away from the observed support (twenty-fourth session)


@dataclasses.dataclass(frozen=True)
class ClearanceConfig:
    """Settings of :func:`clear_path`. Why (docs/paths.md, twenty-second session): the
    hybrid's colliding paths meet the support's unobserved side where the observed clouds are
    still 1-25 mm apart (median 6 mm), mostly far from the goal, where a hang needs no contact;
    a hard clearance in the checker blocks routes (time-outs), so here the path the checker
    found is moved away from the observed support afterwards, as far as the checker allows."""

    target: float = 0.03  # m: observed clearance sought at every movable waypoint
    step: float = 0.005  # m: one push of a waypoint's position
    rounds: int = 12  # pushes per waypoint at most
    keep_ball: float = 0.02  # m (planner metric): waypoints this near the goal stay
    spacing: float = 0.02  # m (planner metric): the path subdivided first, waypoints this apart
    shortcut: bool = True  # drop waypoints whose neighbours connect without losing clearance
    band: float = 0.005  # m: object points this near the smallest gap set the push direction
    object_points: int = 512  # observed object points (a fixed subsample, seed 0) measure gaps


class ClearedPath(NamedTuple):
    path: np.ndarray  # [K, 7] start ... goal
    gap_before: float  # m: smallest observed clearance at the movable waypoints, as returned
    gap_after: float  # m: the same after clearing (over the same part of the path)
    moves: int  # accepted pushes
    removed: int  # waypoints the shortcut dropped
    states_checked: int
    seconds: float


def _states_colliding(checker: Callable, states: np.ndarray, chunk: int = 128) -> np.ndarray:
    """``checker`` over many states in chunks of at most ``chunk`` (the shapes a warmed-up
    :class:`EstimatorChecker` has compiled): [B] bool."""
    out = [np.asarray(checker(states[a : a + chunk]), bool) for a in range(0, len(states), chunk)]
    return np.concatenate(out) if out else np.zeros(0, bool)


def clear_path(
    path: np.ndarray,
    checker: Callable[[np.ndarray], np.ndarray],
    object_points: np.ndarray,
    support_points: np.ndarray,
    goal: np.ndarray,
    rotation_weight: float,
    bounds: tuple[np.ndarray, np.ndarray],
    resolution: float,
    config: ClearanceConfig = ClearanceConfig(),
    goal_radius: float = 1e-6,
) -> ClearedPath:
    """``path`` (a plan's waypoints, start ... goal) moved away from the observed support:
    subdivided to ``config.spacing``; then, in rounds, every waypoint farther than
    ``config.keep_ball`` from the goal (start excluded) whose observed clearance (the posed
    observed object cloud [N, 3], object frame, ``config.object_points`` of it, to
    ``support_points`` [M, 3]) is below
    ``config.target`` is pushed ``config.step`` along the direction that opens its smallest
    gap (orientation kept). A push is kept only when it opens the gap, stays in ``bounds`` and
    ``checker`` calls both edges to its neighbours free at ``resolution`` (odd and even
    waypoints in turn, so neighbours stay fixed). Then, with ``config.shortcut``, a waypoint
    is dropped where its neighbours connect through states the checker calls free and no
    nearer the support than the smallest gap of the two edges it replaces (or the target).
    States within ``goal_radius`` of the goal are not checked, as in :func:`plan`."""
    from scipy.spatial import cKDTree

    from omnihang_jax.collision import subsample_cloud

    t0 = time.perf_counter()
    cfg = config
    goal = np.asarray(goal, float)
    lo, hi = np.asarray(bounds[0], float), np.asarray(bounds[1], float)
    obj = subsample_cloud(np.asarray(object_points, float), cfg.object_points, 0)
    sup = np.asarray(support_points, float)
    tree = cKDTree(sup)
    upper = cfg.target + cfg.band + 0.01  # gaps beyond this need no push: inf is enough
    checked = [0]

    def gaps_dirs(poses):
        """(gap [K], unit direction [K, 3] that opens it) of poses [K, 7]."""
        moved = posed_points(poses, obj)  # [K, N, 3]
        d, idx = tree.query(moved.reshape(-1, 3), k=1, distance_upper_bound=upper)
        d, idx = d.reshape(len(poses), -1), idx.reshape(len(poses), -1)
        gap = d.min(axis=1)
        dirs = np.zeros((len(poses), 3))
        for k in np.flatnonzero(np.isfinite(gap)):
            near = np.flatnonzero(d[k] <= gap[k] + cfg.band)
            v = moved[k, near] - sup[idx[k, near]]
            v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
            s = v.mean(axis=0)
            dirs[k] = s / max(np.linalg.norm(s), 1e-9)
        return gap, dirs

    def edge_states(a, b):
        n = max(1, int(np.ceil(pose_distance(a, b, rotation_weight) / resolution)))
        return interpolate_segment(a, b, n)

    def edges_free(pairs):
        """[len(pairs)] bool: every state of each edge (a, b) (a excluded) called free."""
        states = [edge_states(a, b) for a, b in pairs]
        if not states:
            return np.zeros(0, bool)
        owner = np.concatenate([np.full(len(s), i) for i, s in enumerate(states)])
        states = np.concatenate(states)
        ask = goal_distances(states, goal, rotation_weight) > goal_radius
        hit = np.zeros(len(states), bool)
        hit[ask] = _states_colliding(checker, states[ask])
        checked[0] += int(ask.sum())
        return ~np.bincount(owner, weights=hit, minlength=len(pairs)).astype(bool)

    p = interpolate_path(np.asarray(path, float), cfg.spacing, rotation_weight)
    p[-1] = goal
    movable = goal_distances(p, goal, rotation_weight) > cfg.keep_ball
    movable[0] = movable[-1] = False
    gap, dirs = gaps_dirs(p)
    before = float(gap[movable].min()) if movable.any() else float("inf")
    moves = 0
    for _ in range(cfg.rounds):
        moved_any = False
        for parity in (1, 0):
            idx = np.flatnonzero(movable & (np.arange(len(p)) % 2 == parity) & (gap < cfg.target))
            if not len(idx):
                continue
            new = p[idx].copy()
            new[:, :3] += cfg.step * dirs[idx]
            inside = np.all((new[:, :3] >= lo) & (new[:, :3] <= hi), axis=1)
            new_gap, new_dirs = gaps_dirs(new)
            ok = inside & (new_gap > gap[idx])
            cand = np.flatnonzero(ok)
            if not len(cand):
                continue
            pairs = [(p[idx[c] - 1], new[c]) for c in cand] + [
                (new[c], p[idx[c] + 1]) for c in cand
            ]
            free = edges_free(pairs)
            keep = cand[free[: len(cand)] & free[len(cand) :]]
            if len(keep):
                p[idx[keep]] = new[keep]
                gap[idx[keep]], dirs[idx[keep]] = new_gap[keep], new_dirs[keep]
                moves += len(keep)
                moved_any = True
        if not moved_any:
            break
    removed = 0
    if cfg.shortcut:
        keep = np.ones(len(p), bool)
        i = 0
        while i < len(p) - 2:
            j = i + 2  # try to drop i + 1
            if not movable[i + 1]:
                i += 1
                continue
            old = np.concatenate([edge_states(p[i], p[i + 1]), edge_states(p[i + 1], p[j])])
            new = edge_states(p[i], p[j])
            need = min(cfg.target, float(cloud_gap(obj, tree, old, upper).min()))
            if (
                float(cloud_gap(obj, tree, new, upper).min()) >= need
                and edges_free([(p[i], p[j])])[0]
            ):
                keep[i + 1] = False
                p = p[keep]
                movable, gap = movable[keep], gap[keep]
                keep = np.ones(len(p), bool)
                removed += 1
            else:
                i += 1
    after = float(gap[movable].min()) if movable.any() else float("inf")
    return ClearedPath(p, before, after, moves, removed, checked[0], time.perf_counter() - t0)


def dense_check(
    mesh: MeshChecker, path: np.ndarray, resolution: float, rotation_weight: float
) -> tuple[bool, float, int]:
    """The ground truth of a returned path: (collision-free, deepest penetration in m,
    states checked) with the full meshes at ``resolution``."""
    states = interpolate_path(np.asarray(path, float), resolution, rotation_weight)
    pen = mesh.penetration(states)
    return bool(pen.max() <= mesh.tolerance), float(pen.max()), len(states)


def path_scene_xml(scene, path: np.ndarray, max_keys: int = 100) -> str:
    """The pair's MJCF with the path as keyframes (``<key qpos=...>``, at most ``max_keys``,
    first = start, last = goal): open it in MuJoCo's viewer and step through the keys."""
    from sim.scene import scene_xml

    xml, _ = scene_xml(scene.obj, scene.support, scene.physics, pose=path[-1])
    idx = np.unique(np.linspace(0, len(path) - 1, min(max_keys, len(path))).round().astype(int))
    nq = scene.model.nq
    keys = []
    for k, i in enumerate(idx):
        qpos = np.zeros(nq)
        qpos[:7] = path[i]
        keys.append(f'  <key name="path_{k:03d}" qpos="{" ".join(f"{v:.6g}" for v in qpos)}"/>')
    block = "<keyframe>\n" + "\n".join(keys) + "\n</keyframe>\n"
    return xml.replace("</mujoco>", block + "</mujoco>")
