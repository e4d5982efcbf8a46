"""Stage 3 (paper, "Local Refinement"): a value function V(s) searched by CEM.

State ``s`` = the object cloud moved by a candidate pose plus the support cloud, as one cloud
with an object/support flag (the Stage-2a input form). ``V(s)`` is a PointNet++ encoder and the
original head (encoder -> 1024 -> 512 -> 256 -> 2, facts file): the probability that the
pose hangs stably (reward 1 under ``omnihang_jax.evaluate.protocol_stability``).

Two additions of ours, both switchable in :class:`ValueConfig` (documented in
docs/stage3.md):

* **contact features**: every point carries, besides its flag, the signed and unsigned
  distance to the nearest point of the *other* cloud (signed along that point's outward
  normal, so a negative value means "behind the other surface"). A hang fails at 3 mm of
  penetration while the PointNet++ levels group at centimetres; these two numbers make
  millimetre penetration visible to the first layer (the same quantity the paper's heuristic
  collision estimator uses).
* **object-centred input**: both clouds are expressed relative to the candidate's position,
  so V sees the geometry of the contact, not where the support sits in its frame.

CEM (facts): a diagonal Gaussian over a 6-D local action ``a = (dt, w)`` around the initial
pose: the object turns by ``exp(w)`` about a pivot (the contact centre) and shifts by ``dt``;
population 32, 10 iterations, 10 elites, initial variance 1e-2 (translation) / 1e-1 (axis-angle),
actions clipped to +-2 cm / +-0.5 rad. :func:`make_cem` returns a pure ``optimise`` that the
caller ``jax.vmap``s over proposals and pairs and ``jax.jit``s once (house style).

Shapes: clouds ``[N, 3]`` float32 metres (object in its own frame, support in the support
frame), poses ``[7]`` = xyz + quaternion wxyz of the object frame in the support frame.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from omnihang_jax import pointnet2
from omnihang_jax.pointnet2 import PointNet2Config, PointNet2Encoder, first_argmin, squared_distance

__all__ = [
    "ValueConfig",
    "VALUE_SMALL",
    "VALUE_TINY",
    "VALUE_PRESETS",
    "PairClouds",
    "stack_clouds",
    "subsample_clouds",
    "subset_clouds",
    "subset_shift",
    "subsample_index",
    "near_points",
    "posed_state",
    "ValueNet",
    "ValueNetwork",
    "make_value",
    "value_loss",
    "CEMConfig",
    "CEMState",
    "CEMResult",
    "apply_action",
    "contact_pivot",
    "make_cem",
    "Refined",
    "make_refiner",
    "cem_keys",
]


# ----------------------------------------------------------------------------------------------
# Configuration


@dataclasses.dataclass(frozen=True)
class ValueConfig:
    """Value-network architecture and training settings."""

    pointnet: PointNet2Config = dataclasses.replace(pointnet2.SMALL, num_points=1024)
    # points in the state, subsampled from the 4096-point clouds: 512 + 512 keeps CEM's
    # population (B x K x 32 states per iteration) and its [512, 512] distance maps in memory
    num_object_points: int = 512
    num_support_points: int = 512
    head: tuple[int, ...] = (1024, 512, 256)  # facts: encoder -> 1024 -> 512 -> 256 -> 2
    contact_features: bool = True  # ours: signed/unsigned distance to the other cloud
    feature_scale: float = 0.01  # m: distances are divided by 1 cm (hangs fail at 3 mm)...
    feature_clip: float = 3.0  # ...and clipped to +-3 cm: beyond that only "far" matters
    centre_on_object: bool = True  # ours: clouds relative to the candidate's position
    # ours (the near-point ranker): of the num_*_points, this many are the
    # points nearest the other cloud at the candidate pose, taken from ``near_pool`` evenly
    # spaced points of the observed cloud (the rest stay evenly spaced over the whole cloud):
    # the contact region at up to 8x the density (0: the plain subsample; ``near_points``)
    support_near: int = 0
    object_near: int = 0
    near_pool: int = 2048
    near_anchors: int = 64  # "nearest": to this many evenly spaced points of the other cloud
    # training
    learning_rate: float = 3e-4  # peak of warm-up + cosine (the facts' stages use 1e-4-5e-4)
    warmup_steps: int = 500
    weight_decay: float = 1e-4
    grad_clip: float = 1.0  # global-norm clipping
    batch_size: int = 64
    # data augmentation of the state (the camera's noise): Gaussian jitter of every point
    point_jitter: float = 0.0005  # m


VALUE_SMALL = ValueConfig()
VALUE_TINY = ValueConfig(
    pointnet=dataclasses.replace(pointnet2.TINY, num_points=128),
    num_object_points=64,
    num_support_points=64,
    head=(64, 32),
    warmup_steps=10,
    batch_size=16,
)
VALUE_PRESETS = {"small": VALUE_SMALL, "tiny": VALUE_TINY}


# ----------------------------------------------------------------------------------------------
# State


class PairClouds(NamedTuple):
    """The observed clouds of one pair (or a batch, leading B axis).

    object_points [N, 3], object_normals [N, 3] (object frame); support_points [M, 3],
    support_normals [M, 3] (support frame). float32, metres, unit outward normals.
    """

    object_points: Any
    object_normals: Any
    support_points: Any
    support_normals: Any


def stack_clouds(samples) -> PairClouds:
    """The clouds of several pairs (anything with the PairClouds fields, e.g. ``HangSample``)
    as one batched PairClouds of float32 numpy arrays [B, ...]."""
    return PairClouds(*(np.stack([np.asarray(getattr(x, f), np.float32) for x in samples])
                        for f in PairClouds._fields))  # fmt: skip


def _subsample_index(n: int, k: int) -> jnp.ndarray:
    # evenly spaced indices: the derived clouds are area-weighted resamples in random order
    return (jnp.arange(k) * n) // k


def subsample_index(n: int, config: ValueConfig, which: str) -> np.ndarray:
    """Indices into an ``n``-point observed cloud (``which``: "object" or "support") that
    :func:`subsample_clouds` keeps: ``num_*_points - *_near`` evenly spaced points, then, with
    ``*_near`` > 0, the ``near_pool`` evenly spaced points :func:`posed_state` picks the near
    points from."""
    total = config.num_object_points if which == "object" else config.num_support_points
    near = config.object_near if which == "object" else config.support_near
    if not 0 <= near < total:
        raise ValueError(f"ValueConfig.{which}_near = {near}: must be in [0, {total})")
    index = (np.arange(total - near) * n) // (total - near)
    if near:
        index = np.concatenate([index, (np.arange(config.near_pool) * n) // config.near_pool])
    return index


def subsample_clouds(clouds: PairClouds, config: ValueConfig) -> PairClouds:
    """Take ``num_object_points`` / ``num_support_points`` evenly spaced points (any leading
    axes; a cloud smaller than that repeats points); with ``object_near`` / ``support_near``
    the pool of :func:`subsample_index` follows them (``posed_state`` picks from it)."""
    n, m = clouds.object_points.shape[-2], clouds.support_points.shape[-2]
    io = jnp.asarray(subsample_index(n, config, "object"))
    js = jnp.asarray(subsample_index(m, config, "support"))
    return PairClouds(
        clouds.object_points[..., io, :],
        clouds.object_normals[..., io, :],
        clouds.support_points[..., js, :],
        clouds.support_normals[..., js, :],
    )


def subset_shift(n: int, config: ValueConfig, which: str, index: int, subsets: int) -> int:
    """Points an ``n``-point cloud is rolled by for subset ``index`` of ``subsets``
    (:func:`subset_clouds`): ``index / subsets`` of the evenly spaced part's stride."""
    if not 0 <= index < subsets:
        raise ValueError(f"subset {index} of {subsets}: need 0 <= index < subsets")
    total = config.num_object_points if which == "object" else config.num_support_points
    near = config.object_near if which == "object" else config.support_near
    stride = max(n // (total - near), 1)
    return (index * stride) // subsets


def subset_clouds(clouds: PairClouds, config: ValueConfig, index: int = 0, subsets: int = 1):
    """Subset ``index`` of ``subsets`` evenly spaced subsets of the observed clouds: the clouds
    rolled by :func:`subset_shift` points, then :func:`subsample_clouds` (index 0: exactly
    ``subsample_clouds``). The pipeline's views (``PipelineConfig.views``) are such subsets."""
    n, m = clouds.object_points.shape[-2], clouds.support_points.shape[-2]
    so = subset_shift(n, config, "object", index, subsets)
    ss = subset_shift(m, config, "support", index, subsets)
    rolled = PairClouds(
        jnp.roll(clouds.object_points, -so, axis=-2),
        jnp.roll(clouds.object_normals, -so, axis=-2),
        jnp.roll(clouds.support_points, -ss, axis=-2),
        jnp.roll(clouds.support_normals, -ss, axis=-2),
    )
    return subsample_clouds(rolled, config)


def _so3(pose7: jax.Array) -> jaxlie.SO3:
    wxyz = pose7[..., 3:]
    return jaxlie.SO3(wxyz=wxyz / jnp.linalg.norm(wxyz, axis=-1, keepdims=True))


def near_points(clouds: PairClouds, pose7: jax.Array, config: ValueConfig) -> PairClouds:
    """One pair (unbatched, subsampled by :func:`subsample_clouds`) at one pose -> exactly
    ``num_object_points`` / ``num_support_points`` points: the evenly spaced ones, then the
    ``support_near`` pool points of the support nearest the (posed) object, and the
    ``object_near`` pool points of the object nearest the support ("nearest": to
    ``near_anchors`` evenly spaced points of the other cloud's evenly spaced part, which keeps
    the distance map small). Object points stay in the object frame. Without near points:
    ``clouds`` unchanged."""
    if not (config.object_near or config.support_near):
        return clouds
    go = config.num_object_points - config.object_near
    gs = config.num_support_points - config.support_near
    rot, t = _so3(pose7).as_matrix(), pose7[:3]
    op, on, sp, sn = clouds
    ao = _subsample_index(go, min(config.near_anchors, go))
    as_ = _subsample_index(gs, min(config.near_anchors, gs))
    if config.support_near:
        d2 = squared_distance(sp[gs:, None], (op[ao] @ rot.T + t)[None])  # [pool, anchors]
        _, j = jax.lax.top_k(-jnp.min(d2, axis=1), config.support_near)
        sp = jnp.concatenate([sp[:gs], sp[gs:][j]])
        sn = jnp.concatenate([sn[:gs], sn[gs:][j]])
    if config.object_near:
        d2 = squared_distance((op[go:] @ rot.T + t)[:, None], sp[as_][None])  # [pool, anchors]
        _, i = jax.lax.top_k(-jnp.min(d2, axis=1), config.object_near)
        op = jnp.concatenate([op[:go], op[go:][i]])
        on = jnp.concatenate([on[:go], on[go:][i]])
    return PairClouds(op, on, sp, sn)


def posed_state(
    clouds: PairClouds, pose7: jax.Array, config: ValueConfig
) -> tuple[jax.Array, jax.Array]:
    """One pair (unbatched, already subsampled) at one pose -> the state cloud.

    Returns (points [N+M, 3], features [N+M, C]): object points first (flag 1), then support
    points (flag 0); C = 3 with contact features (flag, signed, unsigned distance), else 1.
    With ``object_near`` / ``support_near`` the points are first picked by :func:`near_points`.
    """
    clouds = near_points(clouds, pose7, config)
    rot = _so3(pose7).as_matrix()
    t = pose7[:3]
    obj = clouds.object_points @ rot.T + t
    obj_n = clouds.object_normals @ rot.T
    sup, sup_n = clouds.support_points, clouds.support_normals
    n, m = obj.shape[0], sup.shape[0]
    flags = jnp.concatenate([jnp.ones((n, 1)), jnp.zeros((m, 1))]).astype(jnp.float32)
    feats = [flags]
    if config.contact_features:
        d2 = squared_distance(obj[:, None], sup[None])  # [N, M]
        i = first_argmin(d2, axis=1)  # nearest support point of each object point
        j = first_argmin(d2, axis=0)  # nearest object point of each support point
        off_o = obj - sup[i]
        off_s = sup - obj[j]
        signed = jnp.concatenate(
            [jnp.sum(off_o * sup_n[i], -1), jnp.sum(off_s * obj_n[j], -1)]
        )  # < 0: behind the other cloud's surface
        dist = jnp.sqrt(jnp.concatenate([jnp.min(d2, axis=1), jnp.min(d2, axis=0)]) + 1e-12)
        c = config.feature_clip
        feats += [
            jnp.clip(signed / config.feature_scale, -c, c)[:, None],
            jnp.clip(dist / config.feature_scale, 0.0, c)[:, None],
        ]
    points = jnp.concatenate([obj, sup])
    if config.centre_on_object:
        points = points - t
    return points.astype(jnp.float32), jnp.concatenate(feats, axis=-1).astype(jnp.float32)


# ----------------------------------------------------------------------------------------------
# Network


class ValueNet(nn.Module):
    """PointNet++ encoder on the state cloud + the original head -> 2 logits (fail, hang)."""

    config: ValueConfig

    @nn.compact
    def __call__(self, points: jax.Array, features: jax.Array) -> jax.Array:
        """points [B, P, 3], features [B, P, C] -> logits [B, 2]."""
        g, _ = PointNet2Encoder(self.config.pointnet, name="encoder")(points, features)
        h = g
        for i, width in enumerate(self.config.head):
            h = nn.relu(nn.Dense(width, name=f"head{i}")(h))
        return nn.Dense(2, name="logits")(h)


class ValueNetwork(NamedTuple):
    """Plain functions around :class:`ValueNet` (un-jitted; callers jit).

    init(key) -> params
    logits(params, clouds [B, ...] subsampled, poses [B, 7], key=None) -> [B, 2]
    value(params, clouds, poses) -> [B] P(hang) in [0, 1]
    score(params, clouds unbatched, poses [P, 7]) -> [P] log P(hang) (for CEM, one pair)
    """

    config: ValueConfig
    init: Callable
    logits: Callable
    value: Callable
    score: Callable


def make_value(config: ValueConfig) -> ValueNetwork:
    net = ValueNet(config)
    state_fn = jax.vmap(lambda c, p: posed_state(c, p, config))

    def logits(params, clouds: PairClouds, poses, key=None):
        points, feats = state_fn(clouds, poses)
        if key is not None and config.point_jitter > 0:  # training-time camera noise
            points = points + config.point_jitter * jax.random.normal(key, points.shape)
        return net.apply(params, points, feats)

    def init(key):
        n = config.num_object_points + config.num_support_points
        c = 3 if config.contact_features else 1
        return net.init(key, jnp.zeros((1, n, 3)), jnp.zeros((1, n, c)))

    def value(params, clouds, poses):
        return jax.nn.softmax(logits(params, clouds, poses), axis=-1)[..., 1]

    def score(params, clouds: PairClouds, poses):
        p = poses.shape[0]
        tiled = jax.tree.map(lambda x: jnp.broadcast_to(x, (p,) + x.shape), clouds)
        return jax.nn.log_softmax(logits(params, tiled, poses), axis=-1)[..., 1]

    return ValueNetwork(config, init, logits, value, score)


def value_loss(logits: jax.Array, rewards: jax.Array) -> tuple[jax.Array, dict]:
    """Cross-entropy of the 2-way success classifier (facts: "success classifier ... -> 2").

    logits [B, 2], rewards [B] in {0, 1}. Returns (loss, metrics with accuracy).
    """
    rewards = rewards.astype(jnp.int32)
    logp = jax.nn.log_softmax(logits, axis=-1)
    ce = -jnp.take_along_axis(logp, rewards[:, None], axis=-1)[:, 0]
    pred = jnp.argmax(logits, axis=-1)
    return ce.mean(), {"cross_entropy": ce.mean(), "accuracy": jnp.mean(pred == rewards)}


# ----------------------------------------------------------------------------------------------
# CEM over SE(3)


@dataclasses.dataclass(frozen=True)
class CEMConfig:
    """Cross-entropy method around an initial pose (facts file, "Stage 3")."""

    population: int = 32
    iterations: int = 10
    elites: int = 10
    init_var_translation: float = 1e-2  # m^2 (facts)
    init_var_rotation: float = 1e-1  # rad^2 (facts)
    clip_translation: float = 0.02  # m: actions within +-2 cm (facts)
    clip_rotation: float = 0.5  # rad: axis-angle components within +-0.5 (facts)
    min_std_translation: float = 5e-4  # m: keep exploring at the millimetre scale
    min_std_rotation: float = 5e-3  # rad
    rounds: int = 1  # ours: > 1 restarts CEM from the best pose found (widens the box)


@flax.struct.dataclass
class CEMState:
    """Search state carried through ``lax.scan`` (one pose)."""

    mean: jax.Array  # [6] action mean (dt xyz, axis-angle)
    std: jax.Array  # [6]
    best_action: jax.Array  # [6]
    best_score: jax.Array  # []


class CEMResult(NamedTuple):
    """pose [7] refined; action [6]; score [] its score; initial_score [] the initial pose's;
    history [iterations] best score after each iteration; top_poses [M, 7] / top_scores [M]:
    the M best-scored members of the final iteration's population (``keep_top`` of
    :func:`make_cem`; M = 0 by default), best first: the poses the score likes most, which
    the RL loop labels as hard cases (V's false positives are among them)."""

    pose: jax.Array
    action: jax.Array
    score: jax.Array
    initial_score: jax.Array
    history: jax.Array
    top_poses: Any = None
    top_scores: Any = None


def apply_action(pose7: jax.Array, pivot: jax.Array, action: jax.Array) -> jax.Array:
    """Turn the object by ``exp(action[3:])`` about ``pivot`` [3] (support frame), then shift
    it by ``action[:3]``. pose7 [7], action [..., 6] -> [..., 7]."""
    turn = jaxlie.SO3.exp(action[..., 3:])
    base = _so3(pose7)
    rot = turn @ base
    t = pivot + turn.apply(pose7[:3] - pivot) + action[..., :3]
    wxyz = rot.wxyz
    wxyz = jnp.where(wxyz[..., :1] < 0, -wxyz, wxyz)
    return jnp.concatenate([t, wxyz], axis=-1)


def contact_pivot(
    clouds: PairClouds, pose7: jax.Array, sigma: float = 0.01, min_weight: float = 1.0
) -> jax.Array:
    """The contact centre of a candidate: the posed object points weighted by
    exp(-d^2 / 2 sigma^2), d = distance to the nearest support point. Falls back to the
    object's origin (the candidate's position) when fewer than ``min_weight`` points are near.
    Returns [3] (support frame)."""
    obj = clouds.object_points @ _so3(pose7).as_matrix().T + pose7[:3]
    d2 = jnp.min(squared_distance(obj[:, None], clouds.support_points[None]), axis=1)
    w = jnp.exp(-d2 / (2 * sigma**2))
    total = jnp.sum(w)
    centre = jnp.sum(w[:, None] * obj, axis=0) / jnp.maximum(total, 1e-9)
    return jnp.where(total >= min_weight, centre, pose7[:3])


def make_cem(score_fn: Callable, config: CEMConfig = CEMConfig(), keep_top: int = 0) -> Callable:
    """``optimise(key, init_pose [7], pivot [3], *score_args) -> CEMResult``.

    ``score_fn(poses [P, 7], *score_args) -> [P]`` is maximised. Pure and un-jitted; vmap it
    over proposals and pairs and jit once. The initial pose (action 0) is scored first, so the
    result is never worse than the start under ``score_fn``. ``keep_top`` M > 0 also returns
    the M best members of the last iteration's population (``CEMResult.top_poses``; with
    ``rounds`` > 1, of the last round).
    """
    if not 0 <= keep_top <= config.population:
        raise ValueError(f"keep_top must be in [0, population={config.population}], got {keep_top}")
    lo = jnp.array([-config.clip_translation] * 3 + [-config.clip_rotation] * 3)
    hi = -lo
    std0 = jnp.sqrt(jnp.array([config.init_var_translation] * 3 + [config.init_var_rotation] * 3))
    min_std = jnp.array([config.min_std_translation] * 3 + [config.min_std_rotation] * 3)
    n_elite = min(config.elites, config.population)
    n_top = max(n_elite, keep_top)

    def one_round(key, init_pose, pivot, score_args, best_action, best_score):
        def step(state: CEMState, key):
            eps = jax.random.normal(key, (config.population, 6))
            actions = jnp.clip(state.mean + state.std * eps, lo, hi)
            poses = jax.vmap(lambda a: apply_action(init_pose, pivot, a))(actions)
            scores = score_fn(poses, *score_args)
            scores = jnp.where(jnp.isfinite(scores), scores, -jnp.inf)
            top, idx = jax.lax.top_k(scores, n_top)
            elite = actions[idx[:n_elite]]
            i_best = idx[0]
            better = top[0] > state.best_score
            new = CEMState(
                mean=jnp.mean(elite, axis=0),
                std=jnp.maximum(jnp.std(elite, axis=0), min_std),
                best_action=jnp.where(better, actions[i_best], state.best_action),
                best_score=jnp.where(better, top[0], state.best_score),
            )
            return new, (new.best_score, poses[idx[:keep_top]], top[:keep_top])

        state = CEMState(jnp.zeros(6), std0, best_action, best_score)
        state, (history, top_p, top_s) = jax.lax.scan(
            step, state, jax.random.split(key, config.iterations)
        )
        return state, history, top_p[-1], top_s[-1]

    def optimise(key, init_pose, pivot, *score_args) -> CEMResult:
        init_pose = jnp.asarray(init_pose, jnp.float32)
        s0 = score_fn(init_pose[None], *score_args)[0]
        s0 = jnp.where(jnp.isfinite(s0), s0, -jnp.inf)
        pose, action, best = init_pose, jnp.zeros(6), s0
        histories = []
        for r in range(config.rounds):
            state, history, top_poses, top_scores = one_round(
                jax.random.fold_in(key, r), pose, pivot, score_args, jnp.zeros(6), best
            )
            new_pose = apply_action(pose, pivot, state.best_action)
            # a round that found nothing better leaves pose (action 0 = unchanged)
            pivot = pivot + state.best_action[:3]
            pose, best = new_pose, state.best_score
            action = state.best_action if r == 0 else action  # first-round action (clipped box)
            histories.append(history)
        return CEMResult(pose, action, best, s0, jnp.concatenate(histories), top_poses, top_scores)

    return optimise


class Refined(NamedTuple):
    """CEM from K starts per pair: poses [B, K, 7], scores [B, K] (final log V),
    initial_scores [B, K], best [B] (index of the best final score); top_poses [B, K, M, 7],
    top_scores [B, K, M]: the M best members of each final population (``keep_top``)."""

    poses: Any
    scores: Any
    initial_scores: Any
    best: Any
    top_poses: Any = None
    top_scores: Any = None


def cem_keys(key, b: int, k: int):
    """[B, K] the CEM key of each of K starts of B pairs that ``make_refiner``'s ``refine``
    draws from ``key`` (the fused pipeline gives every start the key of its own CEM)."""
    return jax.random.split(key, b * k).reshape(b, k)


def make_refiner(
    value_config: ValueConfig, cem_config: CEMConfig = CEMConfig(), keep_top: int = 0
) -> Callable:
    """``refine(value_params, key, clouds [B, ...] subsampled, starts [B, K, 7], keys=None) ->
    Refined``: CEM on V from every start, vmapped over starts and pairs (``keys`` [B, K]: each
    start's own CEM key instead of ``key``'s split). Pure, un-jitted. ``keep_top``
    M > 0 also returns each final population's M best members (the RL loop's hard cases)."""
    value = make_value(value_config)
    cem = make_cem(lambda poses, p, c: value.score(p, c, poses), cem_config, keep_top)

    def refine_one(key, pose, clouds, value_params):
        return cem(key, pose, contact_pivot(clouds, pose), value_params, clouds)

    per_pair = jax.vmap(refine_one, in_axes=(0, 0, None, None))
    batched = jax.vmap(per_pair, in_axes=(0, 0, 0, None))

    def refine(value_params, key, clouds: PairClouds, starts, keys=None) -> Refined:
        b, k = starts.shape[:2]
        if keys is None:  # else: [B, K] the CEM's keys, one per start (key unused)
            keys = cem_keys(key, b, k)
        res = batched(keys, starts, clouds, value_params)
        return Refined(
            res.pose, res.score, res.initial_score, jnp.argmax(res.score, axis=1),
            res.top_poses, res.top_scores,
        )  # fmt: skip

    return refine
