"""Stage Two: contact point matching (paper, "Stage Two: Contact Point Matching").

2a. The object cloud, moved by the Stage-1 pose, and the support cloud are combined into one
    cloud with a 4th channel flag (1 object, 0 support). A PointNet++ segmentation net gives
    per-point features F^OS (W = 64) and a contact score s_hat in [0, 1] (sigmoid), fitted to the
    soft contact maps with a Huber loss (``losses.contact_score_loss``).
2b. The top-K1 object and top-K2 support points by score are paired; the pairwise feature map
    [K1, K2, 2W] goes through 1x1 convolutions (Dense over the last axis) 128-64-2, giving
    correspondence logits. Loss: two-class cross-entropy L_c + ListNet ranking loss L_r (Eq. 2).
    The top-K3 pairs with probability above ``threshold`` (delta) are kept -- the single best pair
    if none passes -- and the translation is solved in closed form with the Stage-1 rotation R:
    t = sum_i w_i (s_i - R o_i) / sum_i w_i (least squares for R o_i + t = s_i).

Ground-truth correspondence labels (our definition; the paper stores "contact point
correspondences" without fixing the matching rule): a candidate pair (u, v) is positive when the
object point u lies within ``correspondence_radius`` of the object point of some ground-truth
contact pair (object frame) AND the support point v lies within the same radius of that pair's
support point (support frame). See ``correspondence_labels``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from omnihang_jax import pointnet2
from omnihang_jax.pointnet2 import (
    PointNet2Config,
    PointNet2Segmentation,
    SharedMLP,
    gather_points,
    squared_distance,
)
from omnihang_jax.poses import rotation_matrix, transform_points

__all__ = [
    "Stage2Config",
    "STAGE2_ORIGINAL",
    "STAGE2_TINY",
    "STAGE2_SMALL",
    "Stage2Net",
    "Stage2Network",
    "Stage2Output",
    "Correspondences",
    "make_stage2",
    "combine_clouds",
    "top_contact_points",
    "correspondence_labels",
    "TRAIN_SELECTIONS",
    "training_selection_scores",
    "positive_scores",
    "select_correspondences",
    "solve_translation",
    "estimate_support_normals",
    "clearance_offset",
    "ANSWER_LIFT",
]


@dataclasses.dataclass(frozen=True)
class Stage2Config:
    """Stage-2 architecture, selection and training settings."""

    # Segmentation net on the combined (object + support) cloud: 2 x 4096 = 8192 points.
    pointnet: PointNet2Config = dataclasses.replace(pointnet2.ORIGINAL, num_points=8192)
    k_object: int = 128  # K1: object points kept by contact score (facts)
    k_support: int = 128  # K2: support points kept by contact score (facts)
    k_pairs: int = 3  # K3: correspondences used to solve the translation (facts)
    threshold: float = 0.5  # delta: minimum pair probability (paper; value ours)
    correspondence_mlp: tuple[int, ...] = (128, 64)  # hidden 1x1 convs before the 2 logits
    huber_delta: float = 1.0  # Huber transition; 1 = TF default, i.e. plain 0.5 L2 on [0, 1] maps
    contact_positive_weight: float = 0.0  # 2a point weights 1 + w * map (ours; 0 = facts)
    # 2a loss (``losses.contact_score_loss``): "huber" (facts) | "bce" | "focal" | "listnet".
    contact_loss: str = "huber"
    correspondence_radius: float = 0.01  # 1 cm: GT label radius, ~ the contact-map spread
    # Training inputs: the GT stable pose perturbed to mimic Stage-1 errors (ours).
    pose_noise_translation: float = 0.01  # metres, std per axis
    pose_noise_rotation: float = 0.05  # radians, std per axis-angle component
    # Which scores pick the K1/K2 candidates while training 2b: "ground_truth" soft maps
    # (guarantees positives, decouples 2b from 2a's quality), "predicted" (the net's scores, as
    # at inference) or "mixed" (per pair, either one with probability 1/2).
    train_selection: str = "ground_truth"
    # 2b also fine-tunes the segmentation features; its loss then keeps the 2a Huber term so the
    # contact scores stay calibrated. False freezes the features (stop_gradient).
    train_features_in_2b: bool = True
    # Pair geometry in 2b (ours, off = paper): > 0 adds the offset s_v - o_u between the posed
    # candidates (support frame, divided by this scale in metres) and its length to the first
    # 1x1 conv of every pair. Our PointNet++ features are built from radius-normalised local
    # offsets, so without this 2b cannot tell which object point sits next to which support
    # point; with it the near pairs of the (roughly posed) clouds are the natural candidates.
    pair_offset_scale: float = 0.0
    # Clearance (ours; 0 = paper, bit-identical): after the translation is solved,
    # the object moves this far (metres) along the mean outward normal of the observed support
    # cloud at the chosen (weighted) support correspondence points: contact points solved ON
    # each other leave no gap, and a posed object then often starts > 3 mm inside the support.
    # Normals: the cloud's own (``refine(..., support_normals=...)``) or, without them, a PCA
    # estimate over ``clearance_neighbours`` support points (``estimate_support_normals``).
    clearance: float = 0.0
    clearance_neighbours: int = 16

    @property
    def feature_dim(self) -> int:
        return self.pointnet.point_feature_dim


STAGE2_ORIGINAL = Stage2Config()
STAGE2_TINY = Stage2Config(
    pointnet=dataclasses.replace(pointnet2.TINY, num_points=256),
    k_object=16,
    k_support=16,
    k_pairs=3,
    correspondence_mlp=(32, 16),
)
STAGE2_SMALL = Stage2Config(
    pointnet=dataclasses.replace(pointnet2.SMALL, num_points=4096),
    k_object=32,
    k_support=32,
    k_pairs=3,
    correspondence_mlp=(64, 32),
    pose_noise_translation=0.02,
    pair_offset_scale=0.05,
    contact_positive_weight=20.0,
    contact_loss="listnet",  # measured best on the demo (docs/networks.md, "2a loss options")
)


class Stage2Net(nn.Module):
    """Stage-2 network as a linen module (use ``make_stage2`` for plain functions)."""

    config: Stage2Config

    def setup(self):
        cfg = self.config
        self.segmentation = PointNet2Segmentation(cfg.pointnet)
        self.score_head = nn.Dense(1)
        # First 1x1 conv on [f_o, f_s] written as Wo f_o + Ws f_s + b: the same layer, without
        # materialising the [K1, K2, 2W] map.
        self.pair_object = nn.Dense(cfg.correspondence_mlp[0])
        self.pair_support = nn.Dense(cfg.correspondence_mlp[0], use_bias=False)
        self.pair_mlp = SharedMLP(tuple(cfg.correspondence_mlp[1:]) + (2,), activate_last=False)
        if cfg.pair_offset_scale > 0:
            self.pair_offset = nn.Dense(cfg.correspondence_mlp[0], use_bias=False)

    def contact_logits(self, points: jax.Array, flags: jax.Array) -> tuple[jax.Array, jax.Array]:
        """points [B, P, 3] metres, flags [B, P, 1] (1 object, 0 support).

        Returns (point_features F^OS [B, P, W], contact logits [B, P]; scores = sigmoid).
        """
        features, _ = self.segmentation(points, flags)
        return features, self.score_head(features)[..., 0]

    def contact(self, points: jax.Array, flags: jax.Array) -> tuple[jax.Array, jax.Array]:
        """points [B, P, 3] metres, flags [B, P, 1] (1 object, 0 support).

        Returns (point_features F^OS [B, P, W], contact_scores [B, P] in [0, 1]).
        """
        features, logits = self.contact_logits(points, flags)
        return features, jax.nn.sigmoid(logits)

    def correspond(
        self,
        object_features: jax.Array,
        support_features: jax.Array,
        object_xyz: jax.Array | None = None,
        support_xyz: jax.Array | None = None,
    ) -> jax.Array:
        """object_features [B, K1, W], support_features [B, K2, W] -> logits [B, K1, K2, 2].

        object_xyz [B, K1, 3] (posed, support frame), support_xyz [B, K2, 3]: the candidates'
        positions, used only when ``config.pair_offset_scale > 0``.
        """
        h = (
            self.pair_object(object_features)[:, :, None]
            + self.pair_support(support_features)[:, None]
        )
        if self.config.pair_offset_scale > 0:
            h = h + self.pair_offset(
                pair_offset_features(object_xyz, support_xyz, self.config.pair_offset_scale)
            )
        return self.pair_mlp(nn.relu(h))

    def __call__(self, points, flags, num_object: int):
        """Full forward pass (used for init): contact scores, top-K selection, logits."""
        features, scores = self.contact(points, flags)
        object_idx, support_idx = top_contact_points(
            scores, num_object, self.config.k_object, self.config.k_support
        )
        object_features = gather_points(features[:, :num_object], object_idx)
        support_features = gather_points(features[:, num_object:], support_idx)
        object_xyz = gather_points(points[:, :num_object], object_idx)
        support_xyz = gather_points(points[:, num_object:], support_idx)
        return scores, self.correspond(object_features, support_features, object_xyz, support_xyz)


# ----------------------------------------------------------------------------------------------
# Pure helpers


def combine_clouds(
    object_points_posed: jax.Array, support_points: jax.Array
) -> tuple[jax.Array, jax.Array]:
    """object_points_posed [B, N, 3] (support frame), support_points [B, M, 3].

    Returns (points [B, N+M, 3], flags [B, N+M, 1] float32: 1 object, 0 support).
    """
    batch, n, _ = object_points_posed.shape
    m = support_points.shape[1]
    points = jnp.concatenate([object_points_posed, support_points], axis=1)
    flags = jnp.concatenate(
        [jnp.ones((batch, n, 1), jnp.float32), jnp.zeros((batch, m, 1), jnp.float32)], axis=1
    )
    return points, flags


def pair_offset_features(object_xyz: jax.Array, support_xyz: jax.Array, scale: float) -> jax.Array:
    """object_xyz [B, K1, 3] (posed), support_xyz [B, K2, 3] -> [B, K1, K2, 4]: the offset
    (s_v - o_u) / scale and its length (see ``Stage2Config.pair_offset_scale``)."""
    offset = (support_xyz[:, None] - object_xyz[:, :, None]) / scale
    length = jnp.sqrt(jnp.sum(offset * offset, axis=-1, keepdims=True) + 1e-12)
    return jnp.concatenate([offset, length], axis=-1)


def top_contact_points(
    scores: jax.Array, num_object: int, k_object: int, k_support: int
) -> tuple[jax.Array, jax.Array]:
    """Top-K1 object and top-K2 support points by contact score.

    scores: [B, N+M] (first ``num_object`` = object points). Returns (object_idx [B, K1] into the
    object cloud, support_idx [B, K2] into the support cloud), int32, best first.
    """
    scores = jax.lax.stop_gradient(scores)
    _, object_idx = jax.lax.top_k(scores[:, :num_object], k_object)
    _, support_idx = jax.lax.top_k(scores[:, num_object:], k_support)
    return object_idx.astype(jnp.int32), support_idx.astype(jnp.int32)


TRAIN_SELECTIONS = ("ground_truth", "predicted", "mixed")


def training_selection_scores(
    mode: str, target: jax.Array, scores: jax.Array, key: jax.Array
) -> jax.Array:
    """Scores that pick the K1/K2 candidates while training 2b (``Stage2Config.train_selection``).

    target [B, P] ground-truth soft maps, scores [B, P] predicted. "ground_truth" -> target,
    "predicted" -> scores (as at inference), "mixed" -> per pair one of the two, each with
    probability 1/2 (``key``). Gradient-free (the top-K indices are constants).
    """
    if mode == "ground_truth":
        return target
    if mode == "predicted":
        return jax.lax.stop_gradient(scores)
    if mode == "mixed":
        use_gt = jax.random.bernoulli(key, 0.5, (target.shape[0], 1))
        return jnp.where(use_gt, target, jax.lax.stop_gradient(scores))
    raise ValueError(f"unknown train_selection {mode!r}; expected one of {TRAIN_SELECTIONS}")


def correspondence_labels(
    object_points: jax.Array,
    support_points: jax.Array,
    object_idx: jax.Array,
    support_idx: jax.Array,
    contact_pairs: jax.Array,
    contact_mask: jax.Array,
    radius: float,
) -> jax.Array:
    """Ground-truth labels of the K1 x K2 candidate pairs.

    object_points [B, N, 3] (object frame), support_points [B, M, 3] (support frame),
    object_idx [B, K1], support_idx [B, K2] int32 candidates; contact_pairs [B, C, 2] int32
    (object index, support index) of the ground-truth contacts at one stable pose, contact_mask
    [B, C] bool. Pair (u, v) is positive iff for some valid contact c both
    ||o_u - o_c|| < radius and ||s_v - s_c|| < radius. Returns [B, K1, K2] bool.
    """
    r2 = radius**2
    contact_mask = contact_mask.astype(bool)
    o_contact = gather_points(object_points, contact_pairs[..., 0])  # [B, C, 3]
    s_contact = gather_points(support_points, contact_pairs[..., 1])
    o_cand = gather_points(object_points, object_idx)  # [B, K1, 3]
    s_cand = gather_points(support_points, support_idx)
    near_o = (squared_distance(o_cand[:, :, None], o_contact[:, None]) < r2) & contact_mask[:, None]
    near_s = (squared_distance(s_cand[:, :, None], s_contact[:, None]) < r2) & contact_mask[:, None]
    both = jnp.einsum("bkc,blc->bkl", near_o.astype(jnp.float32), near_s.astype(jnp.float32))
    return both > 0


def positive_scores(logits: jax.Array) -> jax.Array:
    """Log-odds of the positive class, logit_1 - logit_0: [..., 2] -> [...].

    sigmoid(positive_scores) == softmax(logits)[..., 1], the pair probability y_hat.
    """
    return logits[..., 1] - logits[..., 0]


class Correspondences(NamedTuple):
    """Chosen contact pairs, K3 slots, best first.

    object_slot, support_slot: [B, K3] int32 indices into the K1 / K2 candidates.
    probability: [B, K3] float32 pair probabilities.
    weight: [B, K3] float32, 1 for pairs used to solve the translation, else 0.
    """

    object_slot: jax.Array
    support_slot: jax.Array
    probability: jax.Array
    weight: jax.Array


def select_correspondences(
    probabilities: jax.Array, k_pairs: int, threshold: float
) -> Correspondences:
    """Top-K3 pairs with probability > threshold (delta); the best pair if none passes.

    probabilities: [B, K1, K2] float32.
    """
    batch, _, k_support = probabilities.shape
    top_p, flat = jax.lax.top_k(probabilities.reshape(batch, -1), k_pairs)
    keep = (top_p > threshold).at[:, 0].set(True)  # sorted, so slot 0 is the fallback
    return Correspondences(
        object_slot=(flat // k_support).astype(jnp.int32),
        support_slot=(flat % k_support).astype(jnp.int32),
        probability=top_p,
        weight=keep.astype(jnp.float32),
    )


def solve_translation(
    rotation: jax.Array, object_points: jax.Array, support_points: jax.Array, weights: jax.Array
) -> jax.Array:
    """Closed-form translation aligning paired contact points under a fixed rotation.

    Minimises sum_i w_i ||R o_i + t - s_i||^2, solved by t = sum_i w_i (s_i - R o_i) / sum_i w_i.
    rotation [B, 3, 3]; object_points [B, K, 3] (object frame); support_points [B, K, 3]
    (support frame); weights [B, K] >= 0 with a positive sum. Returns t [B, 3] metres.
    """
    residual = support_points - jnp.einsum("bij,bkj->bki", rotation, object_points)
    w = weights[..., None]
    return jnp.sum(w * residual, axis=1) / jnp.maximum(jnp.sum(w, axis=1), 1e-12)


def estimate_support_normals(
    support_points: jax.Array, query_indices: jax.Array, away_from: jax.Array, neighbours: int
) -> jax.Array:
    """PCA normals of the support cloud at some of its points (fallback without normals).

    support_points [B, M, 3], query_indices [B, K] int32, away_from [B, 3]: the posed object's
    centroid (a hanging object's centroid lies below / beyond its contacts, so the support's
    outward normal there points away from it), neighbours: points per neighbourhood. The
    normal at a query point is the least-variance axis of its ``neighbours`` nearest support
    points, signed so that it points away from ``away_from``. Returns unit normals [B, K, 3].
    """
    query = gather_points(support_points, query_indices)  # [B, K, 3]
    d2 = squared_distance(query[:, :, None], support_points[:, None])  # [B, K, M]
    _, near = jax.lax.top_k(-d2, neighbours)  # [B, K, nb]
    batch, k, _ = near.shape
    local = gather_points(support_points, near.reshape(batch, k * neighbours)).reshape(
        batch, k, neighbours, 3
    )
    centred = local - jnp.mean(local, axis=2, keepdims=True)
    cov = jnp.einsum("bkni,bknj->bkij", centred, centred)
    _, vectors = jnp.linalg.eigh(cov)  # ascending eigenvalues
    normal = vectors[..., :, 0]
    side = jnp.sum(normal * (query - away_from[:, None]), axis=-1, keepdims=True)
    return jnp.where(side < 0, -normal, normal)


# The Stages 1+2 answer (omnihang_jax.where.stage1_2_answer) is the least penetrating Stage-2
# pose released this far (m) above (+z of the support frame). Chosen on the validation objects:
# 34.5 / 37.7 / 39.0 / 38.0 / 37.7 / 37.2 % at 0 / 2.5 / 5 / 7.5 / 10 / 15 mm.
ANSWER_LIFT = 0.005


def clearance_offset(support_normals: jax.Array, weights: jax.Array, clearance: float) -> jax.Array:
    """Translation offset [B, 3] = clearance * unit(sum_i w_i n_i).

    support_normals [B, K, 3] outward normals at the chosen support points, weights [B, K]
    (``Correspondences.weight``). A zero mean normal gives a zero offset.
    """
    mean = jnp.sum(weights[..., None] * support_normals, axis=1)
    norm = jnp.sqrt(jnp.sum(mean * mean, axis=-1, keepdims=True))
    unit = jnp.where(norm > 1e-9, mean / jnp.maximum(norm, 1e-9), 0.0)
    return clearance * unit


class Stage2Output(NamedTuple):
    """Result of ``Stage2Network.refine`` for B poses.

    pose6: [B, 6] Stage-2 pose (Stage-1 axis-angle, solved translation).
    object_indices, support_indices: [B, K3] int32 indices into the object / support clouds.
    probability, weight: [B, K3] as in ``Correspondences``.
    contact_scores: [B, N+M] per-point scores (object first).
    """

    pose6: jax.Array
    object_indices: jax.Array
    support_indices: jax.Array
    probability: jax.Array
    weight: jax.Array
    contact_scores: jax.Array


class Stage2Network(NamedTuple):
    """Plain functions around ``Stage2Net`` (un-jitted; callers jit).

    init(key) -> params.
    contact(params, points [B,P,3], flags [B,P,1]) -> (features [B,P,W], scores [B,P]).
    contact_logits(params, points, flags) -> (features [B,P,W], logits [B,P]).
    correspond(params, object_features [B,K1,W], support_features [B,K2,W], object_xyz=None,
      support_xyz=None) -> logits [B,K1,K2,2] (xyz: posed candidate positions, needed when
      ``pair_offset_scale > 0``).
    refine(params, object_points [B,N,3], support_points [B,M,3], pose6 [B,6],
      support_normals=None [B,M,3]) -> Stage2Output (normals: only for ``config.clearance``;
      without them a PCA estimate is used).
    """

    config: Stage2Config
    init: Callable
    contact: Callable
    correspond: Callable
    refine: Callable
    contact_logits: Callable


def make_stage2(config: Stage2Config) -> Stage2Network:
    """Build the Stage-2 network's pure functions for ``config``."""
    module = Stage2Net(config)

    def init(key: jax.Array):
        n = max(config.pointnet.num_points // 2, config.pointnet.sa_levels[0].npoint)
        n = max(n, config.k_object, config.k_support)
        pts = jnp.zeros((1, 2 * n, 3), jnp.float32) + jnp.linspace(0.0, 0.1, 2 * n)[None, :, None]
        points, flags = combine_clouds(pts[:, :n], pts[:, n:])
        return module.init(key, points, flags, n)["params"]

    def contact(params, points, flags):
        return module.apply({"params": params}, points, flags, method=Stage2Net.contact)

    def contact_logits(params, points, flags):
        return module.apply({"params": params}, points, flags, method=Stage2Net.contact_logits)

    def correspond(params, object_features, support_features, object_xyz=None, support_xyz=None):
        return module.apply(
            {"params": params},
            object_features,
            support_features,
            object_xyz,
            support_xyz,
            method=Stage2Net.correspond,
        )

    def refine(params, object_points, support_points, pose6, support_normals=None):
        n = object_points.shape[1]
        points, flags = combine_clouds(transform_points(pose6, object_points), support_points)
        features, scores = contact(params, points, flags)
        object_idx, support_idx = top_contact_points(scores, n, config.k_object, config.k_support)
        logits = correspond(
            params,
            gather_points(features[:, :n], object_idx),
            gather_points(features[:, n:], support_idx),
            gather_points(points[:, :n], object_idx),
            gather_points(support_points, support_idx),
        )
        chosen = select_correspondences(
            jax.nn.sigmoid(positive_scores(logits)), config.k_pairs, config.threshold
        )
        object_indices = jnp.take_along_axis(object_idx, chosen.object_slot, axis=1)
        support_indices = jnp.take_along_axis(support_idx, chosen.support_slot, axis=1)
        translation = solve_translation(
            rotation_matrix(pose6[:, 3:]),
            gather_points(object_points, object_indices),
            gather_points(support_points, support_indices),
            chosen.weight,
        )
        if config.clearance != 0.0:  # static: clearance 0 traces today's function exactly
            if support_normals is None:
                # PCA normals, signed away from the posed object's centroid.
                posed = jnp.concatenate([translation, pose6[:, 3:]], axis=-1)
                centroid = jnp.mean(transform_points(posed, object_points), axis=1)
                normals = estimate_support_normals(
                    support_points, support_indices, centroid, config.clearance_neighbours
                )
            else:
                normals = gather_points(support_normals.astype(jnp.float32), support_indices)
            translation = translation + clearance_offset(normals, chosen.weight, config.clearance)
        return Stage2Output(
            pose6=jnp.concatenate([translation, pose6[:, 3:]], axis=-1),
            object_indices=object_indices,
            support_indices=support_indices,
            probability=chosen.probability,
            weight=chosen.weight,
            contact_scores=scores,
        )

    return Stage2Network(
        config=config,
        init=jax.jit(init),  # one compilation, not op-by-op dispatch (the same parameters)
        contact=contact,
        correspond=correspond,
        refine=refine,
        contact_logits=contact_logits,
    )
