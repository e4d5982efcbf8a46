"""How to hang: OMPL's RRT-Connect in SE(3) around a batched collision checker (host side).

This module is the host/device boundary of path planning. OMPL (C++, through its 2.x Python
bindings: ``ompl.base`` / ``ompl.geometric``) runs on the host; every collision question goes
to one ``checker(poses [B, 7]) -> colliding [B] bool``:

- :class:`EstimatorChecker` wraps a jitted ``collides(params, object_cloud, support_cloud,
  poses)`` from :mod:`omnihang_jax.collision` (NCE, HCE, HCE with true normals), padding each
  batch to a power of two so that only a handful of shapes is ever compiled;
- :class:`CascadeChecker` ORs a cheap checker and a costly one, asking the costly one only
  where the cheap one says free, and not at all for an edge the cheap one already blocks
  (the hybrid of ``omnihang_jax.paths``: the observed-cloud test, then the NCE);
- :class:`MeshChecker` asks MuJoCo (C) for contacts between the full object and support
  meshes (``mj_kinematics`` + ``mj_collision``, as ``sim.kernels.contact_query`` does): the
  paper's "ground truth" planner and the dense check of every returned path.

State validity is the checker on one state; motion validation (:class:`BatchedMotionValidator`)
interpolates the edge at the planner's resolution and checks all its states in batched calls
(an :class:`EstimatorChecker`: 8 evenly spaced states first, the others only if those are
free; same answer). Settings (:class:`PlannerConfig`, the original code was never released, facts file):

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
  called free. ``goal_radius`` > 0 exempts a ball around it (it lets estimator paths dive into the
  support). The dense check of
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

from omnihang_jax.meshes import (  # re-exported: the planner's ground truth and geometry
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
    "HybridSettings",
    "hybrid_checker",
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
    # lengths (m) of a straight retreat from the goal tried before planning
    # (retreats.plan_with_retreat); () = off, the plain plan
    retreat_lengths: tuple[float, ...] = ()


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
        """``pow2``: every batch padded to a power of two (fewer sizes to compile: one plan's
        checker, ``omnihang_jax.paths``)."""
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
    (``collision.geometric_collides``); :meth:`any_colliding` (an edge of the planner)
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


class HybridSettings(NamedTuple):
    """The default planner's checker (docs/how.md): the observed-cloud
    penetration test (``geometric``) first, the NCE only where it says free; the NCE's
    threshold is ``near_threshold`` within ``goal_ball`` (planner metric, m) of the goal and
    ``far_threshold`` beyond it (``goal_ball`` 0: ``far_threshold`` everywhere)."""

    geometric: Any  # collision.GeometricConfig
    far_threshold: float
    near_threshold: float
    goal_ball: float


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
    """:class:`HybridSettings`' checker for one pair: ``CascadeChecker(test, nce)`` (the NCE's
    fixed cloud subsets, seeds 0 / 1; the support's lookup table built here, once). Clouds: the observed ones, object frame
    / support frame, with the support's outward normals."""
    from omnihang_jax import collision

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


# ----------------------------------------------------------------------------------------------
# A returned path moved away from the observed support


@dataclasses.dataclass(frozen=True)
class ClearanceConfig:
    """Settings of :func:`clear_path`. Why: the
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
