"""PointNet++ in pure JAX + Flax linen (no custom CUDA ops).

Building blocks follow Qi et al. 2017 and the original TF implementation used by OmniHang:

* ``farthest_point_sample``: iterative FPS starting from index 0 (``jax.lax.fori_loop``).
* ``ball_query``: the first ``nsample`` points (in index order) strictly within ``radius``,
  padded with the first index found; if no point is within the radius, the nearest point.
* ``group_points``: relative xyz (``p - centroid``) concatenated with point features.
* ``SetAbstraction``: FPS + ball query + shared MLP (``nn.Dense`` over the last axis) + max-pool,
  or "group all" (one global region, absolute xyz) when ``level.group_all``.
* ``FeaturePropagation``: 3-NN inverse-squared-distance interpolation (as in the original TF
  ``three_interpolate``) + skip concatenation + shared MLP.
* ``PointNet2Encoder`` (global feature + per-level outputs) and ``PointNet2Segmentation``
  (per-point features).

Differences from the original, on purpose: no batch norm in the shared MLPs (keeps ``apply`` a
pure function of ``params`` with no mutable ``batch_stats``). Batch norm is what let the original
take metre-scale offsets (~1e-2) as they are; instead we divide the grouped xyz by the level's
radius (as PointNeXt does), which puts the MLP inputs at O(1). All functions are batched over a leading ``B`` axis, jit- and vmap-friendly, and
take static sizes (``npoint``, ``nsample``) from the config.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp

__all__ = [
    "SALevel",
    "PointNet2Config",
    "ORIGINAL",
    "TINY",
    "SMALL",
    "PRESETS",
    "squared_distance",
    "gather_points",
    "farthest_point_sample",
    "ball_query",
    "group_points",
    "three_nn_interpolate",
    "SharedMLP",
    "SetAbstraction",
    "FeaturePropagation",
    "PointNet2Encoder",
    "PointNet2Segmentation",
]


@dataclasses.dataclass(frozen=True)
class SALevel:
    """One set-abstraction level.

    npoint: number of centroids chosen by FPS (ignored when ``group_all``).
    radius: ball-query radius in metres. Grouped xyz are also divided by it before the MLP
      (relative offsets in [-1, 1]; for group-all levels it is the scale of the absolute xyz).
    nsample: points gathered per centroid.
    mlp: widths of the shared MLP applied to every grouped point before max-pooling.
    group_all: one region containing every point, xyz kept absolute (PointNet++ "group all").
    """

    npoint: int
    radius: float
    nsample: int
    mlp: tuple[int, ...]
    group_all: bool = False


@dataclasses.dataclass(frozen=True)
class PointNet2Config:
    """PointNet++ architecture.

    sa_levels: set-abstraction levels, finest first.
    fp_mlps: feature-propagation MLPs, coarsest first, one per SA level; used only by the
      segmentation net. The last width is the per-point feature size (W in the paper).
    num_points: number of input points the preset was designed for (documentation and
      checks; the nets accept any N >= the first level's npoint).
    """

    sa_levels: tuple[SALevel, ...]
    fp_mlps: tuple[tuple[int, ...], ...]
    num_points: int

    @property
    def global_feature_dim(self) -> int:
        return self.sa_levels[-1].mlp[-1]

    @property
    def point_feature_dim(self) -> int:
        return self.fp_mlps[-1][-1]


# The original OmniHang encoder (facts file, "Networks"): 4096 points, five SA levels. Radii are
# in metres (objects are real-size). The fifth level is kept exactly as in the original
# (npoint=1, radius 0.2 m, nsample 16) rather than "group all": after level four only 16 points
# remain, so it pools all of them whenever they lie within 20 cm of the first one.
# The FP widths are our choice (the facts only fix W = 64 for Stage 2b's per-point features).
ORIGINAL = PointNet2Config(
    sa_levels=(
        SALevel(512, 0.01, 32, (32, 32, 64)),
        SALevel(128, 0.02, 32, (64, 64, 128)),
        SALevel(64, 0.04, 32, (128, 128, 256)),
        SALevel(16, 0.08, 32, (256, 256, 512)),
        SALevel(1, 0.20, 16, (512, 512, 1024)),
    ),
    fp_mlps=((512, 512), (256, 256), (256, 256), (128, 128), (128, 128, 64)),
    num_points=4096,
)

# Test preset: a few dozen points, small MLPs, exercises both ball-query and group-all levels.
# Radii suit the synthetic ring/peg scenes (objects of a few centimetres).
TINY = PointNet2Config(
    sa_levels=(
        SALevel(32, 0.02, 8, (16, 16, 32)),
        SALevel(8, 0.05, 8, (32, 32, 64)),
        SALevel(1, 0.1, 0, (64, 128), group_all=True),
    ),
    fp_mlps=((64,), (64, 32), (32, 32)),
    num_points=128,
)

# CPU preset for real objects (5-70 cm) on 2048-point clouds: radii 1.5 / 3 / 6 / 12 cm cover
# contact-sized patches up to handle-sized parts, then a group-all level with absolute xyz
# (scale 0.3 m, the size of a support) keeps where things are. Trains in minutes on 2 cores.
SMALL = PointNet2Config(
    sa_levels=(
        SALevel(128, 0.015, 16, (32, 32, 64)),
        SALevel(32, 0.03, 16, (64, 64, 128)),
        SALevel(16, 0.06, 16, (128, 128)),
        SALevel(4, 0.12, 8, (128, 256)),
        SALevel(1, 0.3, 0, (256, 256), group_all=True),
    ),
    fp_mlps=((256,), (128, 128), (128, 64), (64, 64), (64, 64)),
    num_points=2048,
)

PRESETS = {"original": ORIGINAL, "tiny": TINY, "small": SMALL}


# ----------------------------------------------------------------------------------------------
# Sampling and grouping (pure functions, integer outputs carry no gradient).


def squared_distance(a: jax.Array, b: jax.Array) -> jax.Array:
    """Squared Euclidean distance with broadcasting.

    a, b: [..., 3] float32 (broadcastable). Returns [...] float32. Written as an explicit sum of
    three squares so that the numpy oracle in the tests reproduces it bit for bit.
    """
    d = a - b
    return d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]


def _by_min_reductions() -> bool:
    """Whether :func:`first_argmin` / :func:`first_argmax` use two plain reductions (the CPU,
    where XLA runs the paired value-index reduction of argmin slowly: V 1.4x faster on 2 cores)
    or ``jnp.argmin`` / ``jnp.argmax`` (other backends). The indices are the same either way."""
    return jax.default_backend() == "cpu"


def _first_index(x: jax.Array, axis: int, extreme: Callable, arg: Callable) -> jax.Array:
    """The first index along ``axis`` where ``x`` takes its ``extreme`` (jnp.min / jnp.max), as
    int32: ``arg`` (jnp.argmin / jnp.argmax) off the CPU, two plain reductions on it."""
    if not _by_min_reductions():
        return arg(x, axis=axis).astype(jnp.int32)
    axis = axis % x.ndim
    hit = x == extreme(x, axis=axis, keepdims=True)
    iota = jax.lax.broadcasted_iota(jnp.int32, x.shape, axis)
    return jnp.min(jnp.where(hit, iota, x.shape[axis]), axis=axis)


def first_argmin(x: jax.Array, axis: int = -1) -> jax.Array:
    """``jnp.argmin(x, axis)``, the first index of the minimum, as int32 (read at trace time:
    :func:`_by_min_reductions`). For finite ``x``."""
    return _first_index(x, axis, jnp.min, jnp.argmin)


def first_argmax(x: jax.Array, axis: int = -1) -> jax.Array:
    """``jnp.argmax(x, axis)``, the first index of the maximum, as int32."""
    return _first_index(x, axis, jnp.max, jnp.argmax)


def gather_points(values: jax.Array, idx: jax.Array) -> jax.Array:
    """Batched gather along the point axis.

    values: [B, N, C]; idx: [B, ...] int32 indices into N. Returns [B, ..., C].
    """
    return jax.vmap(lambda v, i: v[i])(values, idx)


# FPS is S - 1 sequential steps: on a GPU at batch 1 a step costs about as much at 1,280 as at
# 1,920 states (the value network's first level, 127 steps: 1.60 / 1.75 ms on one H200), so a
# loop iteration's overhead, not its arithmetic, sets it. ``unroll`` steps per loop iteration
# (lax.fori_loop's unroll: the same operations, the same indices) cut that overhead on a GPU:
# the first level 1.80 -> 1.53 ms at 8, the three-view answer pipeline 104.4 -> 97.1 ms at
# batch 1 on one H200, side by side (97.5 at 4). It lengthens compilation (the answer pipeline on the CPU: 13.6 s at 1, 22.8 s at 8), so on a CPU,
# where the loop's overhead is small beside its arithmetic, it stays 1.
# FPS_UNROLL: None = FPS_UNROLL_GPU on a GPU backend, 1 elsewhere; an int forces it.
FPS_UNROLL: int | None = None
FPS_UNROLL_GPU = 8


def fps_unroll() -> int:
    """The FPS unroll used when none is given: FPS_UNROLL, else by the default backend."""
    if FPS_UNROLL is not None:
        return FPS_UNROLL
    return FPS_UNROLL_GPU if jax.default_backend() in ("gpu", "cuda", "rocm") else 1


def farthest_point_sample(
    points: jax.Array, num_samples: int, unroll: int | None = None
) -> jax.Array:
    """Farthest point sampling, deterministic start at index 0 (as the original CUDA kernel).

    points: [B, N, 3] float32, metres. num_samples: static S <= N. unroll: steps per loop
    iteration (None: ``fps_unroll()`` when traced; any value gives the same indices).
    Returns idx: [B, S] int32; idx[:, 0] == 0 and each next index maximises the distance to the
    already chosen set (ties broken by the lowest index).
    """
    batch, n, _ = points.shape
    if num_samples > n:
        raise ValueError(f"farthest_point_sample: num_samples={num_samples} > N={n}")

    def body(i, carry):
        idx, min_d2, last = carry
        last_point = jnp.take_along_axis(points, last[:, None, None], axis=1)  # [B, 1, 3]
        min_d2 = jnp.minimum(min_d2, squared_distance(points, last_point))
        nxt = first_argmax(min_d2, axis=-1)
        return idx.at[:, i].set(nxt), min_d2, nxt

    idx = jnp.zeros((batch, num_samples), jnp.int32)
    min_d2 = jnp.full((batch, n), 1e10, points.dtype)
    last = jnp.zeros((batch,), jnp.int32)
    unroll = fps_unroll() if unroll is None else unroll
    idx, _, _ = jax.lax.fori_loop(
        1, num_samples, body, (idx, min_d2, last), unroll=max(1, min(unroll, num_samples - 1))
    )
    return jax.lax.stop_gradient(idx)


BALL_QUERY_METHODS = ("cumsum", "count", "top_k")
# the method ``ball_query`` uses when none is given (read at trace time, like FPS_UNROLL; every
# method gives the same indices). "cumsum" is the fastest on the GPU: V's first level on the
# three-view CEM population 2.43 ms against 3.15 (count) and 10.04 (top_k) on one H200;
# the others give the same indices at other speeds.
BALL_QUERY_METHOD = "cumsum"


def ball_query(
    points: jax.Array,
    centroids: jax.Array,
    radius: float,
    nsample: int,
    method: str | None = None,
) -> jax.Array:
    """Ball query as in the original PointNet++ kernel.

    points: [B, N, 3] float32; centroids: [B, S, 3] float32; radius in metres; nsample static.
    Returns idx: [B, S, nsample] int32 -- the first ``nsample`` point indices (ascending index
    order) with squared distance strictly below ``radius**2``; empty slots repeat the first index
    found. If no point lies within the radius, every slot holds the nearest point.

    method: how the first ``nsample`` hits are found (same answer; None: ``BALL_QUERY_METHOD``
    when traced): "cumsum" = the running
    count of hits along N, then a binary search for counts 1..nsample (memory-bound, fast on
    a GPU), "count" = the same running count, the j-th hit's position read as the number of
    indices whose count is below j (a compare-and-sum instead of the binary search), or
    "top_k" = the ``nsample`` smallest hit indices (``jax.lax.top_k``); the three are compared
    by a benchmark.
    """
    method = BALL_QUERY_METHOD if method is None else method
    n = points.shape[1]
    d2 = squared_distance(centroids[:, :, None, :], points[:, None, :, :])  # [B, S, N]
    within = d2 < radius**2
    k = min(nsample, n)
    if method == "cumsum":
        count = jnp.cumsum(within, axis=-1, dtype=jnp.int32)  # nondecreasing along N
        targets = jnp.arange(1, k + 1, dtype=jnp.int32)
        # position of the j-th hit = first index whose running count reaches j (N if none)
        first = jax.vmap(jax.vmap(lambda c: jnp.searchsorted(c, targets, side="left")))(count)
        first = first.astype(jnp.int32)
    elif method == "count":
        count = jnp.cumsum(within, axis=-1, dtype=jnp.int32)
        targets = jnp.arange(1, k + 1, dtype=jnp.int32)
        first = jnp.sum(count[..., :, None] < targets, axis=-2, dtype=jnp.int32)
    elif method == "top_k":
        candidates = jnp.where(within, jnp.arange(n, dtype=jnp.int32), n)
        first = -jax.lax.top_k(-candidates, k)[0]  # k smallest candidates, ascending
    else:
        raise ValueError(f"unknown ball-query method {method!r}; expected {BALL_QUERY_METHODS}")
    if k < nsample:
        first = jnp.concatenate(
            [first, jnp.full(first.shape[:-1] + (nsample - k,), n, jnp.int32)], axis=-1
        )
    nearest = first_argmin(d2, axis=-1)[..., None]
    pad = jnp.where(first[..., :1] == n, nearest, first[..., :1])
    return jax.lax.stop_gradient(jnp.where(first == n, pad, first))


def group_points(
    points: jax.Array, features: jax.Array | None, centroids: jax.Array, idx: jax.Array
) -> jax.Array:
    """Gather each centroid's neighbourhood.

    points: [B, N, 3]; features: [B, N, C] or None; centroids: [B, S, 3]; idx: [B, S, K] int32.
    Returns [B, S, K, 3 + C]: xyz relative to the centroid, then the neighbours' features.
    """
    grouped = gather_points(points, idx) - centroids[:, :, None, :]
    if features is None:
        return grouped
    return jnp.concatenate([grouped, gather_points(features, idx)], axis=-1)


def three_nn_interpolate(
    dense_points: jax.Array, sparse_points: jax.Array, sparse_features: jax.Array
) -> jax.Array:
    """Interpolate features from a sparse to a dense point set (3 nearest neighbours).

    dense_points: [B, N, 3]; sparse_points: [B, S, 3]; sparse_features: [B, S, C].
    Weights are inverse squared distances, clipped at 1e-10 and normalised, as in the original TF
    ``three_interpolate``. With S < 3 the S available neighbours are used. Returns [B, N, C].
    """
    d2 = squared_distance(dense_points[:, :, None, :], sparse_points[:, None, :, :])  # [B, N, S]
    k = min(3, sparse_points.shape[1])
    neg_d2, idx = jax.lax.top_k(-d2, k)
    inv = 1.0 / jnp.maximum(-neg_d2, 1e-10)
    weights = inv / jnp.sum(inv, axis=-1, keepdims=True)  # [B, N, k]
    neighbours = gather_points(sparse_features, idx)  # [B, N, k, C]
    return jnp.sum(weights[..., None] * neighbours, axis=2)


# ----------------------------------------------------------------------------------------------
# Modules


class SharedMLP(nn.Module):
    """Dense layers over the last axis (= 1x1 convolutions), ReLU between layers.

    features: layer widths. activate_last: ReLU after the last layer too.
    """

    features: Sequence[int]
    activate_last: bool = True

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for i, width in enumerate(self.features):
            x = nn.Dense(width)(x)
            if self.activate_last or i < len(self.features) - 1:
                x = nn.relu(x)
        return x


class SetAbstraction(nn.Module):
    """One PointNet++ set-abstraction level."""

    level: SALevel

    @nn.compact
    def __call__(
        self, points: jax.Array, features: jax.Array | None
    ) -> tuple[jax.Array, jax.Array]:
        """points: [B, N, 3] float32 metres; features: [B, N, C] float32 or None.

        Returns (centroids [B, S, 3], centroid_features [B, S, mlp[-1]]), S = npoint (1 for
        group-all, whose centroid is the origin).
        """
        level = self.level
        if level.group_all:
            centroids = jnp.zeros((points.shape[0], 1, 3), points.dtype)
            grouped = points if features is None else jnp.concatenate([points, features], -1)
            grouped = grouped[:, None]  # [B, 1, N, 3 + C]
        else:
            centre_idx = farthest_point_sample(points, level.npoint)
            centroids = gather_points(points, centre_idx)
            idx = ball_query(points, centroids, level.radius, level.nsample)
            grouped = group_points(points, features, centroids, idx)
        # Offsets in units of the radius: O(1) inputs without batch norm (module docstring).
        # (a concatenate, not ``.at[..., :3].divide``: XLA constant-folded that scatter at
        # every compilation, seconds per compile)
        grouped = jnp.concatenate([grouped[..., :3] / level.radius, grouped[..., 3:]], axis=-1)
        pooled = jnp.max(SharedMLP(level.mlp)(grouped), axis=2)
        return centroids, pooled


class FeaturePropagation(nn.Module):
    """Upsample features from a coarse level to a finer one."""

    mlp: Sequence[int]

    @nn.compact
    def __call__(
        self,
        dense_points: jax.Array,
        sparse_points: jax.Array,
        dense_features: jax.Array | None,
        sparse_features: jax.Array,
    ) -> jax.Array:
        """dense_points [B, N, 3], sparse_points [B, S, 3], dense_features [B, N, C1] or None,
        sparse_features [B, S, C2]. Returns [B, N, mlp[-1]]."""
        x = three_nn_interpolate(dense_points, sparse_points, sparse_features)
        if dense_features is not None:
            x = jnp.concatenate([x, dense_features], axis=-1)
        return SharedMLP(self.mlp)(x)


class PointNet2Encoder(nn.Module):
    """PointNet++ encoder: a stack of set-abstraction levels."""

    config: PointNet2Config

    @nn.compact
    def __call__(
        self, points: jax.Array, features: jax.Array | None = None
    ) -> tuple[jax.Array, tuple[tuple[jax.Array, jax.Array | None], ...]]:
        """points: [B, N, 3] float32 metres; features: [B, N, C] float32 or None.

        Returns (global_feature [B, sa_levels[-1].mlp[-1]] -- 1024 in ORIGINAL --, levels), where
        levels[0] = (points, features) and levels[i] = (centroids [B, S_i, 3], features
        [B, S_i, C_i]) for SA level i.
        """
        levels = [(points, features)]
        for i, level in enumerate(self.config.sa_levels):
            levels.append(SetAbstraction(level, name=f"sa{i}")(*levels[-1]))
        global_feature = jnp.max(levels[-1][1], axis=1)
        return global_feature, tuple(levels)


class PointNet2Segmentation(nn.Module):
    """PointNet++ encoder + feature-propagation decoder: per-point features."""

    config: PointNet2Config

    @nn.compact
    def __call__(
        self, points: jax.Array, features: jax.Array | None = None
    ) -> tuple[jax.Array, jax.Array]:
        """points: [B, N, 3] float32 metres; features: [B, N, C] float32 or None.

        Returns (point_features [B, N, fp_mlps[-1][-1]] -- W = 64 in ORIGINAL --,
        global_feature [B, sa_levels[-1].mlp[-1]]).
        """
        if len(self.config.fp_mlps) != len(self.config.sa_levels):
            raise ValueError("PointNet2Config needs one fp_mlp per SA level")
        global_feature, levels = PointNet2Encoder(self.config, name="encoder")(points, features)
        upsampled = levels[-1][1]
        for i, mlp in enumerate(self.config.fp_mlps):
            dense_points, dense_features = levels[-2 - i]
            sparse_points = levels[-1 - i][0]
            upsampled = FeaturePropagation(mlp, name=f"fp{i}")(
                dense_points, sparse_points, dense_features, upsampled
            )
        return upsampled, global_feature
