"""Collision estimators on partial point clouds: how the planner decides a pose is free.

The estimators share one signature, so that OMPL's planner (``omnihang_jax.planner``, host
side) sees them as interchangeable state-validity checkers::

    collides(params, object_cloud [N, 3], support_cloud [M, 3], poses [B, 7]) -> [B] bool

``object_cloud`` is in the OBJECT frame, ``support_cloud`` in the SUPPORT frame, ``poses`` are
object-in-support poses (xyz metres + quaternion wxyz, the dataset's convention). The functions
are pure and un-jitted; the caller wraps them in ``jax.jit`` once and then checks many states
(every interpolated state of an edge) per call.

- **NCE** (the paper's neural collision estimator): PointNet++ on ONE cloud, the object cloud
  moved by the pose plus the support cloud, with a flag feature (1 object, 0 support: the
  Stage 2a form, ``stage2.combine_clouds``), then an MLP to one logit; trained with cross
  entropy on the dataset's collision labels. ``params`` = its Flax parameters.
- **HCE** (the paper's heuristic baseline): a PointNet++ predicts outward normals of a partial
  cloud (trained with ``L = -sum(n_hat . n)``); the collision score of a pose is minus the
  mean, over object points, of the cosine between (object point - nearest support point) and
  that support point's normal (points inside the support lie behind the normal: cosine < 0).
  Colliding when the score is above a threshold chosen on training pairs. ``params`` = the
  normal net's parameters.
- **Observed-cloud penetration test** (:class:`GeometricConfig`, not in the paper): the pose
  collides when an object point lies more than ``depth`` behind its nearest observed support
  point's surface (along that point's ray-cast outward normal) and within ``radius`` of it
  sideways. The default planner ORs it with the NCE (``planner.hybrid_checker``): the NCE
  calls most poses a few mm inside a rod free; this catches them. ``params`` = a per-pair
  nearest-support lookup table (:func:`support_grid`).

Factories (:func:`make_nce`, :func:`make_normal_net`) hide the Flax modules and return plain
init / apply functions; :func:`nce_collides`, :func:`hce_collides`, :func:`geometric_collides`
and :func:`goal_ball_collides` return the ``collides`` functions. The full-mesh ground truth
and the planner's scene geometry live in :mod:`omnihang_jax.meshes` (re-exported here).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from collections.abc import Callable
from typing import NamedTuple

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from omnihang_jax.meshes import (  # noqa: F401  (re-exported)
    MeshChecker,
    cloud_gap,
    default_bounds,
    object_radius,
    posed_points,
    start_pose,
)
from omnihang_jax.pointnet2 import (
    PRESETS,
    PointNet2Config,
    PointNet2Encoder,
    PointNet2Segmentation,
    SALevel,
)
from omnihang_jax.stage2 import combine_clouds

__all__ = [
    "NCEConfig",
    "NormalNetConfig",
    "EstimatorNets",
    "NCE_PRESETS",
    "NORMAL_PRESETS",
    "quaternion_matrix",
    "transform_points",
    "inverse_transform_points",
    "make_nce",
    "crop_support",
    "contact_patch",
    "make_normal_net",
    "normal_loss",
    "heuristic_score",
    "nce_collides",
    "nce_probability",
    "hce_collides",
    "nearest_support_offsets",
    "GeometricConfig",
    "SupportGrid",
    "support_grid",
    "grid_offsets",
    "inside_points",
    "penetration_count",
    "geometric_collides",
    "subsample_cloud",
    "save_estimator",
    "load_estimator",
    "binary_metrics",
    "balanced_threshold",
    "MeshChecker",
    "object_radius",
    "default_bounds",
    "start_pose",
]


@dataclasses.dataclass(frozen=True)
class NCEConfig:
    """Neural collision estimator.

    pointnet: PointNet++ preset name (``pointnet2.PRESETS`` or ``"fast"``, below) of the
      combined-cloud encoder.
    object_points / support_points: points of each cloud the network sees (subsampled from
      the 4,096-point partial clouds: the paper used the full clouds; 512 + 512 keeps a
      planner's check at CPU speed and PointNet++'s first level still sees ~1 cm patches).
    head: widths of the MLP between the global feature and the collision logit.
    threshold: probability above which a pose counts as colliding.
    support_crop_from: 0 (the network sees the support cloud it is given), or N >
      support_points: it is given N support points and keeps the ``support_points`` of them
      nearest to the posed object (:func:`crop_support`): ~N / support_points times denser
      where contact happens, for the millimetre gaps of a hanging pose.
    local_points: 0 (one global branch), or L > 0: the **contact NCE**.
      The estimator is given ``local_from`` points of each cloud. The global branch sees an
      evenly strided ``object_points`` / ``support_points`` of them (or the support crop, when
      ``support_crop_from`` is set); a second, local branch (``local_pointnet``, millimetre-scale
      balls) sees the L support points nearest the posed object and the L object points nearest
      those (:func:`contact_patch`), centred on the patch, each point with its offset to the
      nearest point of the other cloud as a feature. Both codes go to the head.
    """

    pointnet: str = "small"
    object_points: int = 512
    support_points: int = 512
    head: tuple[int, ...] = (128, 64)
    threshold: float = 0.5
    support_crop_from: int = 0
    local_points: int = 0
    local_from: int = 2048
    local_pointnet: str = "local"

    @property
    def support_input(self) -> int:
        """Support points the estimator is given (the planner's fixed subset)."""
        if self.local_points:
            return self.local_from
        return self.support_crop_from or self.support_points

    @property
    def object_input(self) -> int:
        """Object points the estimator is given (the planner's fixed subset)."""
        return self.local_from if self.local_points else self.object_points


@dataclasses.dataclass(frozen=True)
class NormalNetConfig:
    """HCE normal network: PointNet++ segmentation net -> per-point unit normal.

    pointnet: preset name. points: points per cloud it sees. threshold: heuristic score
    above which a pose collides (chosen on training pairs by ``train_collision``).
    """

    pointnet: str = "small"
    points: int = 1024
    threshold: float = 0.0


# A PointNet++ for CPU-speed collision checks on 256 + 256 points (a planner makes thousands
# of checks per pair): 2.5 / 6 / 15 cm balls (a rod's cross-section, a hook, a handle), then a
# group-all level with absolute xyz (scale 0.3 m, a support's size) that keeps where things are.
FAST = PointNet2Config(
    sa_levels=(
        SALevel(64, 0.025, 16, (32, 32, 64)),
        SALevel(16, 0.06, 16, (64, 64, 128)),
        SALevel(4, 0.15, 8, (128, 128)),
        SALevel(1, 0.3, 0, (128, 256), group_all=True),
    ),
    fp_mlps=((128,), (128, 64), (64, 64), (64, 64)),
    num_points=512,
)
# The contact NCE's local branch (``NCEConfig.local_points``): the patch where object and support
# are closest, ~2-5 mm point spacing; 1 / 2.5 cm balls, then group-all on patch-centred xyz
# (scale 6 cm, the size of a patch).
LOCAL = PointNet2Config(
    sa_levels=(
        SALevel(64, 0.01, 16, (32, 32, 64)),
        SALevel(16, 0.025, 16, (64, 64, 128)),
        SALevel(1, 0.06, 0, (128, 256), group_all=True),
    ),
    fp_mlps=((128,), (128, 64), (64, 64)),
    num_points=512,
)
POINTNETS = {**PRESETS, "fast": FAST, "local": LOCAL}

NCE_PRESETS = {
    "tiny": NCEConfig(pointnet="tiny", object_points=64, support_points=64, head=(32,)),
    "fast": NCEConfig(pointnet="fast", object_points=256, support_points=256, head=(128, 64)),
    "small": NCEConfig(),
    "tiny_contact": NCEConfig(
        pointnet="tiny",
        object_points=64,
        support_points=64,
        head=(32,),
        local_points=32,
        local_from=128,
        local_pointnet="tiny",
    ),
    # fast's global branch on strided subsets + the local contact branch
    "contact": NCEConfig(
        pointnet="fast",
        object_points=256,
        support_points=256,
        head=(128, 64),
        local_points=256,
        local_from=2048,
    ),
}
NORMAL_PRESETS = {
    "tiny": NormalNetConfig(pointnet="tiny", points=128),
    "fast": NormalNetConfig(pointnet="fast", points=512),
    "small": NormalNetConfig(),
}
# train_collision --preset names the normal net too: the contact NCEs' HCE is their global
# branch's
NORMAL_PRESETS |= {"tiny_contact": NORMAL_PRESETS["tiny"], "contact": NORMAL_PRESETS["fast"]}


class EstimatorNets(NamedTuple):
    """Plain functions of a network: ``init(key) -> params``, ``apply(params, ...)``."""

    init: Callable
    apply: Callable


# ----------------------------------------------------------------------------------------------
# Poses


def quaternion_matrix(quaternion: jax.Array) -> jax.Array:
    """[..., 4] quaternion (w, x, y, z), normalised here -> [..., 3, 3] rotation matrix."""
    q = quaternion / jnp.linalg.norm(quaternion, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def transform_points(poses: jax.Array, points: jax.Array) -> jax.Array:
    """poses [B, 7], points [B, N, 3] or [N, 3] (object frame) -> [B, N, 3] support frame."""
    rot = quaternion_matrix(poses[:, 3:])
    if points.ndim == 2:
        return jnp.einsum("bij,nj->bni", rot, points) + poses[:, None, :3]
    return jnp.einsum("bij,bnj->bni", rot, points) + poses[:, None, :3]


def inverse_transform_points(poses: jax.Array, points: jax.Array) -> jax.Array:
    """The inverse of :func:`transform_points`: poses [B, 7] (object frame -> support frame),
    points [N, 3] or [B, N, 3] in the SUPPORT frame -> [B, N, 3] in the object frame."""
    rot = quaternion_matrix(poses[:, 3:])
    shifted = (points[None] if points.ndim == 2 else points) - poses[:, None, :3]
    return jnp.einsum("bji,bnj->bni", rot, shifted)


# ----------------------------------------------------------------------------------------------
# NCE


class _NCENet(nn.Module):
    config: NCEConfig

    @nn.compact
    def __call__(
        self,
        object_posed: jax.Array,
        support_points: jax.Array,
        patch: tuple[jax.Array, jax.Array] | None = None,
    ) -> jax.Array:
        """object_posed [B, N, 3] (support frame), support_points [B, M, 3] -> logits [B].
        patch: the local branch's (points [B, 2L, 3], features [B, 2L, 5]) when
        ``config.local_points`` (:func:`contact_patch`)."""
        points, flags = combine_clouds(object_posed, support_points)
        feature, _ = PointNet2Encoder(POINTNETS[self.config.pointnet], name="encoder")(
            points, flags
        )
        if self.config.local_points:
            local, _ = PointNet2Encoder(POINTNETS[self.config.local_pointnet], name="local")(*patch)
            feature = jnp.concatenate([feature, local], axis=-1)
        x = feature
        for width in self.config.head:
            x = nn.relu(nn.Dense(width)(x))
        return nn.Dense(1)(x)[:, 0]


def make_nce(config: NCEConfig) -> EstimatorNets:
    """NCE as plain functions.

    init(key) -> params. apply(params, object_points [B, N, 3] object frame, support_points
    [B, M, 3], poses [B, 7]) -> collision logits [B] (positive: colliding).
    """
    net = _NCENet(config)

    def init(key):
        return _nce_init(config)(key)

    def apply(params, object_points, support_points, poses):
        posed = transform_points(poses, object_points)
        patch = None
        if config.local_points:
            patch = contact_patch(posed, support_points, config.local_points)
            posed = _strided(posed, config.object_points)
        if support_points.shape[1] > config.support_points:
            if config.local_points and not config.support_crop_from:  # the contact NCE
                support_points = _strided(support_points, config.support_points)
            else:  # as before the contact NCE: given more support points, keep the nearest
                support_points = crop_support(posed, support_points, config.support_points)
        return net.apply({"params": params}, posed, support_points, patch)

    return EstimatorNets(init, apply)


def _strided(points: jax.Array, n: int) -> jax.Array:
    """[B, N, 3] -> [B, n, 3]: every (N // n)-th point (the fixed subsets are random already)."""
    if points.shape[1] <= n:
        return points
    return points[:, :: points.shape[1] // n][:, :n]


# Offsets to the other cloud are given in units of 1 cm, clipped at 3 cm: millimetres matter,
# a far point only needs to know it is far.
PATCH_SCALE = 0.01
PATCH_CLIP = 3.0


def contact_patch(object_posed: jax.Array, support_points: jax.Array, k: int, probes: int = 32):
    """The contact NCE's local input: where the posed object and the support are closest.

    object_posed [B, N, 3], support_points [B, M, 3] (support frame) -> (points [B, 2k, 3],
    features [B, 2k, 5]). The k support points nearest the posed object (:func:`crop_support`
    with ``probes`` object probes), then the k object points nearest those; xyz relative to the
    support patch's centroid; features = (flag 1 object / 0 support, offset to the nearest
    point of the other patch / 1 cm (3), its length / 1 cm), clipped at 3 cm."""
    sup = crop_support(object_posed, support_points, k, probes)
    obj = crop_support(sup, object_posed, k, probes)
    centre = jnp.mean(sup, axis=1, keepdims=True)
    obj, sup = obj - centre, sup - centre
    # squared distances [B, k_obj, k_sup] as |a|^2 + |b|^2 - 2 a.b at full f32 precision (no
    # TF32: millimetres on centred coordinates of a few cm), then gathers from the [B, k, 3]
    # clouds. (The first version gathered from a broadcast [B, k, k, 3] difference: XLA's GPU
    # compiler spent minutes on that fusion.)
    cross = jnp.einsum("bic,bjc->bij", obj, sup, precision=jax.lax.Precision.HIGHEST)
    d2 = jnp.sum(obj**2, -1)[:, :, None] + jnp.sum(sup**2, -1)[:, None, :] - 2.0 * cross
    to_sup = jnp.take_along_axis(sup, jnp.argmin(d2, axis=2)[..., None], axis=1) - obj
    to_obj = jnp.take_along_axis(obj, jnp.argmin(d2, axis=1)[..., None], axis=1) - sup
    offsets = jnp.concatenate([to_sup, to_obj], axis=1) / PATCH_SCALE
    length = jnp.sqrt(jnp.sum(offsets**2, axis=-1, keepdims=True) + 1e-12)
    offsets = offsets * jnp.minimum(1.0, PATCH_CLIP / length)
    points, flags = combine_clouds(obj, sup)
    features = jnp.concatenate([flags, offsets, jnp.minimum(length, PATCH_CLIP)], axis=-1)
    return points, features


def crop_support(object_posed: jax.Array, support_points: jax.Array, k: int, probes: int = 32):
    """[B, N, 3], [B, M, 3] -> [B, k, 3]: the k support points nearest to the posed object
    (distance to the nearest of ``probes`` evenly strided object points)."""
    stride = max(1, object_posed.shape[1] // probes)
    probe = object_posed[:, ::stride]
    d2 = jnp.sum((support_points[:, :, None, :] - probe[:, None, :, :]) ** 2, axis=-1).min(-1)
    _, idx = jax.lax.top_k(-d2, k)
    return jnp.take_along_axis(support_points, idx[..., None], axis=1)


def nce_probability(config: NCEConfig) -> Callable:
    """``probability(params, object_cloud [N, 3], support_cloud [M, 3], poses [B, 7]) -> [B]``:
    the NCE's collision probability of every pose (clouds shared by the batch)."""
    nets = make_nce(config)

    def probability(params, object_cloud, support_cloud, poses):
        b = poses.shape[0]
        obj = jnp.broadcast_to(object_cloud, (b, *object_cloud.shape))
        sup = jnp.broadcast_to(support_cloud, (b, *support_cloud.shape))
        return jax.nn.sigmoid(nets.apply(params, obj, sup, poses))

    return probability


def nce_collides(config: NCEConfig) -> Callable:
    """``collides(params, object_cloud, support_cloud, poses) -> [B] bool`` (NCE)."""
    probability = nce_probability(config)

    def collides(params, object_cloud, support_cloud, poses):
        return probability(params, object_cloud, support_cloud, poses) > config.threshold

    return collides


# ----------------------------------------------------------------------------------------------
# HCE


class _NormalNet(nn.Module):
    config: NormalNetConfig

    @nn.compact
    def __call__(self, points: jax.Array) -> jax.Array:
        """points [B, N, 3] -> unit normals [B, N, 3]. The cloud is centred first: normals do
        not depend on where the cloud sits."""
        centred = points - jnp.mean(points, axis=1, keepdims=True)
        features, _ = PointNet2Segmentation(POINTNETS[self.config.pointnet], name="pointnet")(
            centred
        )
        normals = nn.Dense(3)(features)
        return normals / (jnp.linalg.norm(normals, axis=-1, keepdims=True) + 1e-9)


@functools.cache
def _nce_init(config: NCEConfig) -> Callable:
    """The NCE's jitted initialiser, one per config (op-by-op PointNet++ initialisation takes
    ~10x longer; one compilation however many networks are made)."""
    net = _NCENet(config)
    obj = jnp.zeros((1, config.object_points, 3))
    sup = jnp.zeros((1, config.support_points, 3))
    patch = None
    if config.local_points:
        patch = (
            jnp.zeros((1, 2 * config.local_points, 3)),
            jnp.zeros((1, 2 * config.local_points, 5)),
        )
    return jax.jit(lambda k: net.init(k, obj, sup, patch)["params"])


@functools.cache
def _normal_init(config: NormalNetConfig) -> Callable:
    net = _NormalNet(config)
    return jax.jit(lambda k: net.init(k, jnp.zeros((1, config.points, 3)))["params"])


def make_normal_net(config: NormalNetConfig) -> EstimatorNets:
    """init(key) -> params; apply(params, points [B, N, 3]) -> unit normals [B, N, 3]."""
    net = _NormalNet(config)

    def init(key):
        return _normal_init(config)(key)

    def apply(params, points):
        return net.apply({"params": params}, points)

    return EstimatorNets(init, apply)


def normal_loss(predicted: jax.Array, true: jax.Array) -> jax.Array:
    """The paper's HCE normal loss -sum(n_hat . n), averaged over points: [..., 3] -> []."""
    return -jnp.mean(jnp.sum(predicted * true, axis=-1))


def nearest_support_offsets(
    posed: jax.Array, support_cloud: jax.Array, support_normals: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """For every posed point [B, N, 3] (support frame), its offset to the nearest support
    point s_k of ``support_cloud`` [M, 3]: (component along s_k's outward normal n_k [B, N]
    (negative: behind the observed surface), length of the offset [B, N]). Shared by the
    HCE score and, exactly, the observed-cloud penetration test (:func:`grid_offsets`)."""
    support_cloud, support_normals = jnp.asarray(support_cloud), jnp.asarray(support_normals)

    def one(points):
        d2 = (
            jnp.sum(points**2, -1)[:, None]
            - 2.0 * points @ support_cloud.T
            + jnp.sum(support_cloud**2, -1)[None, :]
        )
        k = jnp.argmin(d2, axis=1)
        offset = points - support_cloud[k]
        return jnp.sum(offset * support_normals[k], -1), jnp.linalg.norm(offset, axis=-1)

    # poses in chunks of at most 2**24 distances (64 MB): memory stays bounded for large B
    b, per_pose = posed.shape[0], posed.shape[1] * support_cloud.shape[0]
    if b * per_pose > 2**24:
        return jax.lax.map(one, posed, batch_size=max(1, min(b, 2**24 // per_pose)))
    return jax.vmap(one)(posed)


def heuristic_score(
    object_cloud: jax.Array, support_cloud: jax.Array, support_normals: jax.Array, poses
) -> jax.Array:
    """HCE score of every pose (paper, Sec. V-D): object_cloud [N, 3] object frame,
    support_cloud [M, 3], support_normals [M, 3] outward, poses [B, 7] -> [B].

    For each posed object point p_i, nearest support point s_k: cosine between (p_i - s_k)
    and n_k; the score is minus its mean over the object points (higher: deeper inside)."""
    support_cloud, support_normals = jnp.asarray(support_cloud), jnp.asarray(support_normals)
    posed = transform_points(jnp.asarray(poses), jnp.asarray(object_cloud))  # [B, N, 3]
    along, length = nearest_support_offsets(posed, support_cloud, support_normals)
    return -jnp.mean(along / (length + 1e-9), axis=-1)


def hce_collides(config: NormalNetConfig) -> Callable:
    """``collides(params, object_cloud, support_cloud, poses) -> [B] bool`` (HCE): the normal
    net predicts the support cloud's normals (once per call), then the heuristic score."""
    nets = make_normal_net(config)

    def collides(params, object_cloud, support_cloud, poses):
        normals = nets.apply(params, support_cloud[None])[0]
        return heuristic_score(object_cloud, support_cloud, normals, poses) > config.threshold

    return collides


# ----------------------------------------------------------------------------------------------
# Observed-cloud penetration test (the hybrid checker's first test, planner.hybrid_checker)


@dataclasses.dataclass(frozen=True)
class GeometricConfig:
    """Observed-cloud penetration test: an object point is *inside* when, relative to its
    nearest observed support point s (outward normal n), it lies more than ``depth`` behind
    the surface (offset . n < -depth) and within ``radius`` of s sideways (the offset minus
    its normal part): a point beside the observed surface, e.g. behind a rod whose nearest
    observed point is on the rod's silhouette, does not count. The pose collides when more
    than ``min_points`` object points are inside.

    object_points: size of the planner's fixed subset of the 4,096-point object cloud (seed
    0). The support side is the whole observed support cloud through a nearest-point lookup
    table (:func:`support_grid`: ``voxel`` m cells, at most ``max_voxels``, the cloud's box
    grown by ``margin``). ``omnihang_jax.paths.PlannerConfig`` sets depth, radius and min points
    (docs/how.md, "The default planner").
    """

    depth: float = 0.001
    radius: float = 0.003
    min_points: int = 0
    object_points: int = 4096
    voxel: float = 0.001
    max_voxels: int = 2_000_000
    margin: float = 0.01


class SupportGrid(NamedTuple):
    """Nearest observed support point of every cell of a voxel grid over the support cloud
    (host-built once per pair, :func:`support_grid`): the lookup replaces a search over all
    M support points per object point (~25 ms a pose on this CPU for 1,024 x 4,096)."""

    origin: jax.Array  # [3] corner of cell (0, 0, 0)
    voxel: jax.Array  # [] cell size, m
    dims: jax.Array  # [3] int32 cells per axis (X, Y, Z)
    # [max_voxels] int32: index of the support point nearest the centre of cell (i, j, k) at
    # (i * Y + j) * Z + k, -1 beyond ``reach`` and in the padding: one shape for every pair,
    # so the planner's jitted checker compiles once, not per pair
    nearest: jax.Array
    points: jax.Array  # [M, 3] support cloud (support frame)
    normals: jax.Array  # [M, 3] its outward normals


def support_grid(
    support_cloud: np.ndarray,
    support_normals: np.ndarray,
    voxel: float = 0.001,
    max_voxels: int = 2_000_000,
    margin: float = 0.01,
    reach: float = 0.015,
    keep: np.ndarray | None = None,
) -> SupportGrid:
    """Host: the :class:`SupportGrid` of a support cloud [M, 3] with outward normals; cells of
    ``voxel`` m (coarsened until the grid has at most ``max_voxels`` cells) over the cloud's
    box grown by ``margin``. A point's nearest support point is that of its cell's centre:
    within half a cell diagonal of the true nearest distance. ``keep`` [M] bool (optional):
    cells whose nearest point is not kept answer -1 (never inside), as beyond ``reach``."""
    from scipy.spatial import cKDTree

    points = np.asarray(support_cloud, np.float32)
    lo = points.min(0) - margin
    extent = points.max(0) + margin - lo
    while np.prod(np.ceil(extent / voxel)) > max_voxels:
        voxel *= 1.25
    shape = tuple(int(x) for x in np.ceil(extent / voxel))
    axes = [lo[i] + voxel * (np.arange(shape[i]) + 0.5) for i in range(3)]
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    # cells farther than ``reach`` from every support point: -1, never inside
    _, idx = cKDTree(points).query(centres, distance_upper_bound=reach)
    flat = np.full(max_voxels, -1, np.int32)
    valid = idx < len(points)
    if keep is not None:
        keep = np.asarray(keep, bool)
        valid &= keep[np.minimum(idx, len(points) - 1)]
    flat[: len(idx)] = np.where(valid, idx, -1)
    return SupportGrid(
        jnp.asarray(lo, jnp.float32),
        jnp.asarray(voxel, jnp.float32),
        jnp.asarray(shape, jnp.int32),
        jnp.asarray(flat),
        jnp.asarray(points),
        jnp.asarray(support_normals, jnp.float32),
    )


def grid_offsets(grid: SupportGrid, posed: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """:func:`nearest_support_offsets` through the lookup table: posed [B, N, 3] -> (along
    the normal [B, N], offset length [B, N], in the grid and within its reach [B, N] bool)."""
    cell = jnp.floor((posed - grid.origin) / grid.voxel).astype(jnp.int32)
    dims = grid.dims
    in_grid = jnp.all((cell >= 0) & (cell < dims), axis=-1)
    cell = jnp.clip(cell, 0, dims - 1)
    k = grid.nearest[(cell[..., 0] * dims[1] + cell[..., 1]) * dims[2] + cell[..., 2]]
    in_grid = in_grid & (k >= 0)
    k = jnp.maximum(k, 0)
    offset = posed - grid.points[k]
    return jnp.sum(offset * grid.normals[k], -1), jnp.linalg.norm(offset, axis=-1), in_grid


def inside_points(along: jax.Array, length: jax.Array, depth: float, radius: float):
    """[..., N] offsets to the nearest support points -> [...] int32 count of points more
    than ``depth`` behind the surface and within ``radius`` of the point sideways."""
    lateral2 = length**2 - along**2
    return jnp.sum((along < -depth) & (lateral2 < radius**2), axis=-1, dtype=jnp.int32)


def penetration_count(
    object_cloud: jax.Array, grid: SupportGrid, poses: jax.Array, depth: float, radius: float
) -> jax.Array:
    """Object points inside the observed support (:class:`GeometricConfig`) per pose:
    object_cloud [N, 3] (object frame), poses [B, 7] -> [B] int32."""
    posed = transform_points(jnp.asarray(poses), jnp.asarray(object_cloud))
    along, length, in_grid = grid_offsets(grid, posed)
    return inside_points(jnp.where(in_grid, along, 0.0), length, depth, radius)

    # table's points inside the object


def geometric_collides(config: GeometricConfig) -> Callable:
    """``collides(params, object_cloud, support_cloud, poses) -> [B] bool``: the
    observed-cloud penetration test. ``params``: the :class:`SupportGrid` of the support
    cloud; the support cloud is the table's, the argument is there for the common signature
    and not read."""

    def collides(params, object_cloud, support_cloud, poses):
        count = penetration_count(object_cloud, params, poses, config.depth, config.radius)
        return count > config.min_points

    return collides


def goal_ball_collides(config: NCEConfig, far_threshold: float, ball: float):
    """``collides((params, goal [7], weight), object_cloud, support_cloud, poses)``: the NCE
    with its own threshold (chosen so that stable goals pass) within ``ball`` (planner
    metric: translation + weight x angle, m) of the goal, and ``far_threshold`` (stricter)
    elsewhere: lenient only where the object must touch the support."""
    probability = nce_probability(config)

    def collides(params, object_cloud, support_cloud, poses):
        nce_params, goal, weight = params
        p = probability(nce_params, object_cloud, support_cloud, poses)
        dot = jnp.abs(poses[:, 3:] @ goal[3:]) / jnp.linalg.norm(poses[:, 3:], axis=1)
        angle = 2.0 * jnp.arccos(jnp.clip(dot, 0.0, 1.0))
        dist = jnp.linalg.norm(poses[:, :3] - goal[:3], axis=1) + weight * angle
        return p > jnp.where(dist <= ball, config.threshold, far_threshold)

    return collides


# ----------------------------------------------------------------------------------------------
# Host helpers: clouds, weights, metrics


def subsample_indices(size: int, n: int, seed: int = 0) -> np.ndarray:
    """The sorted row indices :func:`subsample_cloud` keeps of a ``size``-row cloud (so that
    per-point arrays, e.g. normals, can follow the same subset)."""
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(size, n, replace=size < n))


def subsample_cloud(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """A fixed random subset of ``n`` rows (with replacement only if there are fewer)."""
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[-1] != 3 or len(points) == 0:
        raise ValueError(f"a cloud must be [N>0, 3], got {points.shape}")
    return points[subsample_indices(len(points), n, seed)]


WEIGHTS_FILE = "params.msgpack"


def save_estimator(folder: str | os.PathLike, config, params, **extra) -> None:
    """``folder/{config.json, params.msgpack}``; ``extra`` (metrics, steps) goes into the JSON."""
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, WEIGHTS_FILE), "wb") as f:
        f.write(flax.serialization.to_bytes(jax.device_get(params)))
    meta = {"kind": type(config).__name__, "config": dataclasses.asdict(config), **extra}
    with open(os.path.join(folder, "config.json"), "w") as f:
        json.dump(meta, f, indent=2)


def load_estimator(folder: str | os.PathLike, kinds: dict | None = None,
                   trainer: str = "experiments.train_collision"):  # fmt: skip
    """(config, params, meta) of a folder written by :func:`save_estimator`. ``kinds``: config
    class name -> (config class, network factory), the collision estimators' by default;
    ``trainer``: the module named when the folder is missing."""
    path = os.path.join(folder, "config.json")
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path} not found: train it first (`python -m {trainer}`)")
    with open(path) as f:
        meta = json.load(f)
    if kinds is None:
        kinds = {
            "NCEConfig": (NCEConfig, make_nce),
            "NormalNetConfig": (NormalNetConfig, make_normal_net),
        }
    if meta.get("kind") not in kinds:
        raise ValueError(f"{path}: unknown estimator kind {meta.get('kind')!r}")
    cls, factory = kinds[meta["kind"]]
    raw = dict(meta["config"])
    for key in ("head", "first_lengths"):  # JSON lists back to the configs' tuples
        if key in raw:
            raw[key] = tuple(raw[key])
    config = cls(**raw)
    target = factory(config).init(jax.random.key(0))
    with open(os.path.join(folder, WEIGHTS_FILE), "rb") as f:
        params = flax.serialization.from_bytes(target, f.read())
    return config, params, meta


def binary_metrics(predicted: np.ndarray, label: np.ndarray) -> dict:
    """Accuracy, precision, recall, F1 of the positive class (colliding), balanced accuracy."""
    p, y = np.asarray(predicted, bool), np.asarray(label, bool)
    tp, fp = int(np.sum(p & y)), int(np.sum(p & ~y))
    fn, tn = int(np.sum(~p & y)), int(np.sum(~p & ~y))
    prec = tp / max(tp + fp, 1)
    rec = tp / max(tp + fn, 1)
    return dict(
        n=len(y),
        positive_fraction=float(y.mean()) if len(y) else 0.0,
        accuracy=(tp + tn) / max(len(y), 1),
        precision=prec,
        recall=rec,
        f1=2 * prec * rec / max(prec + rec, 1e-12),
        balanced_accuracy=0.5 * (rec + tn / max(tn + fp, 1)),
        free_precision=tn / max(tn + fn, 1),  # of the poses called free, how many are
        specificity=tn / max(tn + fp, 1),  # of the free poses, how many are called free
    )


def balanced_threshold(scores: np.ndarray, label: np.ndarray) -> float:
    """The score threshold (colliding above) with the best balanced accuracy. The labels are
    ~80 % colliding, so plain accuracy would favour calling everything colliding."""
    scores, label = np.asarray(scores, float), np.asarray(label, bool)
    if label.all() or (~label).all():
        raise ValueError("a threshold needs both colliding and free examples")
    cands = np.unique(np.quantile(scores, np.linspace(0.0, 1.0, 401)))
    tpr = (scores[None, label] > cands[:, None]).mean(1)
    tnr = (scores[None, ~label] <= cands[:, None]).mean(1)
    return float(cands[np.argmax(tpr + tnr)])
