"""The approach of a hang, learned from partial clouds.

A hang is an insertion: the last centimetres into the goal are the reverse of taking the object
off. Measured: half of the best planner's colliding paths collide only within the goal's last 4.5 cm, and that planning to
a pre-goal 4.5 cm back along a straight approach the *full meshes* call free lifts F1 by ~10.
The full meshes are not observed; this module learns the approach from what is.

The **approach network** sees the partial object cloud posed at the goal and the partial
support cloud, both centred on the goal's position (support frame, z up), and scores each of
the planner's 26 straight retreat directions (``retreats.RETREAT_DIRECTIONS``): the logit that
the orientation-keeping segment of ``length`` from the goal along it is free of the support and
the wall on the full meshes. Its two branches are the contact NCE's
(:mod:`omnihang_jax.collision`): a global PointNet++ on evenly strided subsets of both clouds
and a local one on the contact patch (millimetre offsets to the other cloud as features).

Labels are geometry, not physics: :func:`approach_labels` runs ``retreats.free_retreats`` with a
``collision.MeshChecker`` on every stable pose of a training pair (~10 ms a pose).
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Callable
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from omnihang_jax import collision, planner, retreats
from omnihang_jax.pointnet2 import PointNet2Encoder
from omnihang_jax.stage2 import combine_clouds

DIRECTIONS = retreats.RETREAT_DIRECTIONS  # [26, 3] unit, support frame, upward first


@dataclasses.dataclass(frozen=True)
class ApproachConfig:
    """Approach network.

    pointnet / local_pointnet: presets of the global and the contact-patch branch
      (``collision.POINTNETS``). object_points / support_points: the global branch's strided
      subsets; local_points: the patch's points per cloud; local_from: points of each partial
      cloud the network is given (a planner's fixed subset, ``collision.subsample_cloud`` seed 0).
    head: MLP widths between the two codes and the 26 logits.
    length / resolution: the approach the labels judge (m; states every ``resolution``).
    threshold: a planner uses the best direction only when its probability reaches this
      (below it, the plain plan to the goal).
    first_lengths: empty, the 26 straight approaches above; else a **route
      network**: one output per route of ``retreats.move_routes(first_lengths)`` (one or two
      straight moves, the last ``length`` long), labelled free *and* ending at least ``clear``
      (m) off the support and the wall on the full meshes (:func:`route_labels`).
    """

    pointnet: str = "fast"
    local_pointnet: str = "local"
    object_points: int = 256
    support_points: int = 256
    local_points: int = 256
    local_from: int = 2048
    head: tuple[int, ...] = (128, 64)
    length: float = 0.045
    resolution: float = 0.002
    threshold: float = 0.5
    first_lengths: tuple[float, ...] = ()
    clear: float = 0.01

    @property
    def routes(self) -> np.ndarray:
        """[R, 3] the outputs' routes (``retreats.move_routes``; the 26 straight moves when
        ``first_lengths`` is empty), computed once per tuple of lengths (read-only)."""
        return _routes(tuple(self.first_lengths))

    @property
    def outputs(self) -> int:
        return len(self.routes)


@functools.lru_cache(maxsize=16)
def _routes(first_lengths: tuple[float, ...]) -> np.ndarray:
    routes = retreats.move_routes(first_lengths)
    routes.setflags(write=False)
    return routes


PRESETS = {
    "tiny": ApproachConfig(
        pointnet="tiny",
        local_pointnet="tiny",
        object_points=64,
        support_points=64,
        local_points=32,
        local_from=128,
        head=(32,),
    ),  # fmt: skip
    "contact": ApproachConfig(),
}


class _ApproachNet(nn.Module):
    config: ApproachConfig

    @nn.compact
    def __call__(self, object_posed, support_points, patch):
        """object_posed [B, N, 3], support_points [B, M, 3] (goal-centred support frame), patch
        (points [B, 2L, 3], features [B, 2L, 5]) -> logits [B, 26]."""
        c = self.config
        points, flags = combine_clouds(object_posed, support_points)
        code, _ = PointNet2Encoder(collision.POINTNETS[c.pointnet], name="encoder")(points, flags)
        local, _ = PointNet2Encoder(collision.POINTNETS[c.local_pointnet], name="local")(*patch)
        x = jnp.concatenate([code, local], axis=-1)
        for width in c.head:
            x = nn.relu(nn.Dense(width)(x))
        return nn.Dense(c.outputs)(x)


@functools.cache
def _init(config: ApproachConfig) -> Callable:
    """The jitted initialiser, one per config (one compilation however many networks)."""
    net = _ApproachNet(config)
    obj = jnp.zeros((1, config.object_points, 3))
    sup = jnp.zeros((1, config.support_points, 3))
    patch = (jnp.zeros((1, 2 * config.local_points, 3)), jnp.zeros((1, 2 * config.local_points, 5)))  # fmt: skip
    return jax.jit(lambda k: net.init(k, obj, sup, patch)["params"])


def make_approach_net(config: ApproachConfig) -> collision.EstimatorNets:
    """init(key) -> params; apply(params, object_points [B, N, 3] object frame, support_points
    [B, M, 3] support frame, goals [B, 7]) -> logits [B, 26] (positive: the approach along
    that direction is free)."""
    net = _ApproachNet(config)

    def init(key):
        return _init(config)(key)

    def apply(params, object_points, support_points, goals):
        centre = goals[:, None, :3]
        posed = collision.transform_points(goals, object_points) - centre
        support = support_points - centre
        patch = collision.contact_patch(posed, support, config.local_points)
        posed = collision._strided(posed, config.object_points)
        support = collision._strided(support, config.support_points)
        return net.apply({"params": params}, posed, support, patch)

    return collision.EstimatorNets(init, apply)


def approach_probabilities(config: ApproachConfig) -> Callable:
    """``probabilities(params, object_cloud [N, 3], support_cloud [M, 3], goals [B, 7]) -> [B,
    26]``: one pair's clouds, every goal."""
    nets = make_approach_net(config)

    def probabilities(params, object_cloud, support_cloud, goals):
        b = goals.shape[0]
        obj = jnp.broadcast_to(object_cloud, (b, *object_cloud.shape))
        sup = jnp.broadcast_to(support_cloud, (b, *support_cloud.shape))
        return jax.nn.sigmoid(nets.apply(params, obj, sup, goals))

    return probabilities


@functools.lru_cache(maxsize=8)
def jitted_probabilities(config: ApproachConfig) -> Callable:
    """:func:`approach_probabilities`, jitted once per config (the config is hashable)."""
    return jax.jit(approach_probabilities(config))


class ApproachPredictor:
    """A planner's view of a trained network: ``order(object_cloud, support_cloud, goal)`` ->
    (directions [K, 3] best first, their probabilities [K]); the clouds are the partial clouds
    as observed (any size: the fixed ``local_from`` subset is taken here). NaN clouds or goal:
    a clear ``ValueError``.

    ``params`` may be a list of networks' parameters (``configs`` their
    configs, the first's threshold counts) and ``views`` > 1 averages the probabilities over
    that many cloud subsets (seeds 0..views-1; seed 0 alone is the planner's default)."""

    def __init__(self, config: ApproachConfig, params, views: int = 1, configs=None):
        if views < 1:
            raise ValueError(f"views must be >= 1, got {views}")
        members = list(params) if isinstance(params, (list, tuple)) else [params]
        configs = list(configs) if configs is not None else [config] * len(members)
        if len(configs) != len(members):
            raise ValueError(f"{len(members)} networks but {len(configs)} configs")
        self.config, self.params, self.views = config, params, views
        self._members = [(c, p, jitted_probabilities(c)) for c, p in zip(configs, members)]

    def probabilities(self, object_cloud, support_cloud, goal) -> np.ndarray:
        obj = np.asarray(object_cloud, np.float32)
        sup = np.asarray(support_cloud, np.float32)
        goal = np.asarray(goal, np.float32).reshape(7)
        for name, x in (("object cloud", obj), ("support cloud", sup), ("goal", goal)):
            if not np.isfinite(x).all():
                raise ValueError(f"approach network: the {name} has NaN or inf values")
        total = np.zeros(self.config.outputs, np.float64)
        for config, params, probabilities in self._members:
            for seed in range(self.views):
                o = collision.subsample_cloud(obj, config.local_from, seed)
                s = collision.subsample_cloud(sup, config.local_from, seed)
                total += np.asarray(probabilities(params, o, s, goal[None]))[0]
        return (total / (len(self._members) * self.views)).astype(np.float32)

    def warm_up(self) -> None:
        """Compile outside a planner's clock (the fixed subset makes every call one shape)."""
        self.probabilities(np.zeros((8, 3)), np.ones((8, 3)), np.r_[0, 0, 0, 1, 0, 0, 0.0])

    def order(self, object_cloud, support_cloud, goal) -> tuple[np.ndarray, np.ndarray]:
        if self.config.first_lengths:
            raise ValueError("a route network ranks routes: use best_routes")
        p = self.probabilities(object_cloud, support_cloud, goal)
        idx = np.argsort(-p, kind="stable")
        return DIRECTIONS[idx], p[idx]

    def best_routes(self, object_cloud, support_cloud, goal) -> tuple[np.ndarray, np.ndarray]:
        """A route network's (routes [R, 3] best first, their probabilities [R])."""
        p = self.probabilities(object_cloud, support_cloud, goal)
        idx = np.argsort(-p, kind="stable")
        return self.config.routes[idx], p[idx]


def usable(directions: np.ndarray, probs: np.ndarray, threshold: float, wall_mounted: bool,
           open_side: bool) -> np.ndarray:  # fmt: skip
    """[K] bool: the ranked directions a planner may use: probability >= ``threshold`` and,
    with ``open_side`` on a wall-mounted support, none towards the wall (-y: a pre-goal
    between the object and the wall is a narrow place to plan to)."""
    keep = np.asarray(probs) >= threshold
    if open_side and wall_mounted:
        keep &= np.asarray(directions)[:, 1] >= -1e-9
    return keep


class RouteChoice(NamedTuple):
    """A route network's choice for one goal (:func:`checked_route`)."""

    route: np.ndarray | None  # [3] the chosen route of ``config.routes`` (None: none)
    best: np.ndarray  # [3] the network's best route
    probability: float  # the chosen route's (or, with none, the best route's)
    rank: int | None  # its place among the routes, best first (None: none chosen)
    tried: int  # confident routes asked of the checker


def checked_route(predictor: ApproachPredictor, object_cloud, support_cloud, goal,
                  check: Callable | None = None, end_gap: float = 0.0, tries: int = 10,
                  resolution: float = 0.005) -> RouteChoice:  # fmt: skip
    """A route network's route for ``goal``. Without ``check``: its best route when that
    reaches the network's threshold (the route taken as free). With ``check`` (a planner's own collision checker on the observed
    clouds, poses [B, 7] -> [B] bool): the first route, best first and at most ``tries`` of
    them, at or above the threshold whose states (``retreats.route_states`` at ``resolution``)
    ``check`` calls free and whose end is at least ``end_gap`` (m) clear between the observed
    clouds (``collision.cloud_gap``; observed points lie on the true surfaces, so a route whose
    observed end gap is smaller cannot truly end that far off). On the validation objects'
    goals this makes 87 % of the routes truly good (free and >= 1 cm off) at threshold 0.3
    against 71 % unchecked."""
    routes, probs = predictor.best_routes(object_cloud, support_cloud, goal)
    config = predictor.config
    if probs[0] < config.threshold:
        return RouteChoice(None, routes[0], float(probs[0]), None, 0)
    if check is None:
        return RouteChoice(routes[0], routes[0], float(probs[0]), 0, 0)
    goal = np.asarray(goal, float).reshape(7)
    tried, support = 0, None
    for k in range(min(int(tries), len(routes))):
        if probs[k] < config.threshold:
            break
        tried += 1
        states = retreats.route_states(goal, routes[k], config.length, resolution)
        if planner.any_colliding(check, states):
            continue
        if end_gap > 0:
            if support is None:  # the support cloud's tree, built once for every route asked
                from scipy.spatial import cKDTree

                support = cKDTree(np.asarray(support_cloud, float))
            gap = collision.cloud_gap(object_cloud, support, states[-1:], upper=end_gap)
            if gap[0] < end_gap:
                continue
        return RouteChoice(routes[k], routes[0], float(probs[k]), k, tried)
    return RouteChoice(None, routes[0], float(probs[0]), None, tried)


def never_colliding(poses: np.ndarray) -> np.ndarray:
    """The approach segment's checker when the network's choice is taken as free."""
    return np.zeros(len(np.asarray(poses).reshape(-1, 7)), bool)


def save(folder: str | os.PathLike, config: ApproachConfig, params, **extra) -> None:
    """``folder/{config.json, params.msgpack}`` (``collision.save_estimator``'s format)."""
    collision.save_estimator(folder, config, params, **extra)


def load(folder: str | os.PathLike) -> tuple[ApproachConfig, object, dict]:
    """(config, params, meta) of a folder written by :func:`save`."""
    kinds = {"ApproachConfig": (ApproachConfig, make_approach_net)}
    return collision.load_estimator(folder, kinds, trainer="experiments.train_approach")


def load_predictor(folders, threshold: float | None = None, views: int = 1) -> ApproachPredictor:
    """The predictor of one folder (a str) or several (their mean), at
    ``threshold`` (default: the first network's), averaged over ``views`` cloud subsets."""
    folders = [folders] if isinstance(folders, (str, os.PathLike)) else list(folders)
    if not folders:
        raise ValueError("no approach network given")
    loaded = [load(f) for f in folders]
    config = loaded[0][0]
    if threshold is not None:
        config = dataclasses.replace(config, threshold=threshold)
    if len(loaded) == 1 and views == 1:
        return ApproachPredictor(config, loaded[0][1])
    return ApproachPredictor(config, [p for _, p, _ in loaded], views=views,
                             configs=[c for c, _, _ in loaded])  # fmt: skip


def approach_labels(scene, goals: np.ndarray, length: float = 0.045,
                    resolution: float = 0.002, tolerance: float = 1e-3) -> np.ndarray:  # fmt: skip
    """[G, 7] goals -> [G, 26] bool: is the straight approach along each direction free on
    the full meshes (``collision.MeshChecker``, penetration > ``tolerance`` collides) and
    inside the planner's bounds (``planner.default_bounds``)?"""
    mesh = collision.MeshChecker(scene, tolerance)
    bounds = planner.default_bounds(scene)
    goals = np.asarray(goals, float).reshape(-1, 7)
    return np.stack([retreats.free_retreats(mesh, g, length, resolution, bounds) for g in goals])


def route_labels(scene, goals: np.ndarray, config: ApproachConfig,
                 tolerance: float = 1e-3) -> np.ndarray:  # fmt: skip
    """[G, 7] goals -> [G, R] bool: is each route of ``config.routes`` free on the full meshes
    (penetration > ``tolerance`` collides, inside ``planner.default_bounds``) and does it end at
    least ``config.clear`` off the support and the wall (``MeshChecker.clearance``)?
    ``retreats.route_table``; ~30 ms a goal for the 1,038 routes of two first lengths (VM)."""
    mesh = collision.MeshChecker(scene, tolerance)
    bounds = planner.default_bounds(scene)
    routes = config.routes
    off = lambda pose: float(mesh.clearance(pose)[0]) >= config.clear  # noqa: E731
    goals = np.asarray(goals, float).reshape(-1, 7)
    return np.stack([
        retreats.route_table(mesh, g, routes, config.length, config.resolution, bounds, off)
        for g in goals
    ]).reshape(len(goals), len(routes))  # fmt: skip
