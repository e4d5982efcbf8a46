"""Training losses of the goal-pose networks (paper, "Goal Pose Prediction").

All losses return per-pair values [B]; callers average over the batch.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

__all__ = [
    "TRANSLATION_WEIGHT",
    "pairwise_pose_distance",
    "pose_set_loss",
    "pairwise_matrix_pose_distance",
    "CONTACT_LOSSES",
    "contact_score_loss",
    "correspondence_cross_entropy",
    "listnet_loss",
]

# Weight of the translation term in L (facts: "1000 x MSE(translation) + MSE(axis-angle)").
# Translations are metres (hanging offsets ~1e-1 m, errors ~1e-2 m, squared ~1e-4) while
# axis-angle components are radians ~1; 1000 puts both terms on a comparable scale.
TRANSLATION_WEIGHT = 1000.0

# Stand-in for +inf in masked minima (finite so that 0 * BIG stays finite under autodiff).
_BIG = 1e12


def pairwise_pose_distance(
    pred: jax.Array, gt: jax.Array, translation_weight: float = TRANSLATION_WEIGHT
) -> jax.Array:
    """L of Eq. 1 for every (predicted, ground-truth) pair.

    pred: [B, Z, 6], gt: [B, D, 6] (translation metres + axis-angle radians).
    Returns [B, Z, D] = w_t * ||t - t'||^2 + ||r - r'||^2 (squared norms; the facts' per-component
    MSE is the same up to a factor 3, which Adam ignores).
    """
    diff = pred[:, :, None, :] - gt[:, None, :, :]
    sq = jnp.square(diff)
    return translation_weight * jnp.sum(sq[..., :3], -1) + jnp.sum(sq[..., 3:], -1)


def pose_set_loss(
    pred: jax.Array,
    gt: jax.Array,
    gt_mask: jax.Array,
    translation_weight: float = TRANSLATION_WEIGHT,
    dist: jax.Array | None = None,
    mean: bool = False,
) -> jax.Array:
    """Set-matching loss L_M of Eq. 1 (Chamfer-style, both directions).

    L_M = sum_l min_k L(pred_l, gt_k) + sum_k min_l L(pred_l, gt_k), over valid k only.

    pred: [B, Z, 6] Stage-1 samples; gt: [B, D, 6] padded ground-truth stable poses;
    gt_mask: [B, D] bool (True = real pose, D_valid in [1, 50]). A pair without any valid pose
    contributes 0. Returns [B] float32.

    dist: a precomputed [B, Z, D] distance (e.g. ``pairwise_matrix_pose_distance``) instead of
    Eq. 1's on pose6; mean: average each direction over its terms (Z and the valid D) instead
    of summing (ours; the paper sums).
    """
    gt_mask = gt_mask.astype(bool)
    if dist is None:
        dist = pairwise_pose_distance(pred, gt, translation_weight)  # [B, Z, D]
    masked = jnp.where(gt_mask[:, None, :], dist, _BIG)
    pred_to_gt = jnp.min(masked, axis=2)  # [B, Z]
    has_gt = jnp.any(gt_mask, axis=1)
    pred_term = jnp.where(has_gt, jnp.sum(pred_to_gt, axis=1), 0.0)
    gt_to_pred = jnp.min(dist, axis=1)  # [B, D]
    gt_term = jnp.sum(jnp.where(gt_mask, gt_to_pred, 0.0), axis=1)
    if mean:
        pred_term = pred_term / dist.shape[1]
        gt_term = gt_term / jnp.maximum(jnp.sum(gt_mask, axis=1), 1)
    return pred_term + gt_term


def pairwise_matrix_pose_distance(
    t_pred: jax.Array,
    r_pred: jax.Array,
    t_gt: jax.Array,
    r_gt: jax.Array,
    translation_weight: float = TRANSLATION_WEIGHT,
) -> jax.Array:
    """Eq. 1's L with rotations compared as matrices: w_t ||t - t'||^2 + ||R - R'||_F^2.

    t_pred [B, Z, 3], r_pred [B, Z, 3, 3], t_gt [B, D, 3], r_gt [B, D, 3, 3] -> [B, Z, D].
    (||R - R'||_F^2 = 4 (1 - cos angle): continuous everywhere, unlike axis-angle at pi.)"""
    dt = jnp.sum(jnp.square(t_pred[:, :, None] - t_gt[:, None]), -1)
    dr = jnp.sum(jnp.square(r_pred[:, :, None] - r_gt[:, None]), (-1, -2))
    return translation_weight * dt + dr


CONTACT_LOSSES = ("huber", "bce", "focal", "listnet")


def contact_score_loss(
    scores: jax.Array,
    target: jax.Array,
    delta: float = 1.0,
    positive_weight: float = 0.0,
    kind: str = "huber",
    logits: jax.Array | None = None,
    num_object: int | None = None,
    focal_gamma: float = 2.0,
) -> jax.Array:
    """Stage-2a per-point fit of the soft contact maps.

    scores: [B, P] predicted contact scores in [0, 1] (= sigmoid(logits)); target: [B, P] soft
    maps in [0, 1]. ``kind``:

    * "huber" (facts): Huber(scores, target), delta 1 = 0.5 L2 on [0, 1] maps. Its gradient
      wrt the logit is (s - y) s (1 - s): it vanishes as the scores saturate near 0, which is
      how 2a "collapses" on the mostly-zero real maps.
    * "bce" (ours): soft-target binary cross-entropy on the logits, gradient (s - y).
    * "focal" (ours): BCE x |y - s|^focal_gamma (the soft-target "quality focal" form):
      down-weights the many easy zeros.
    * "listnet" (ours): top-one ranking over points, -sum y_n log softmax(logits), separately
      for the object (first ``num_object`` points) and the support part; the targets y are
      the maps normalised to sum 1. Top-K selection only needs the ranking.

    ``logits`` [B, P] are needed for every kind but "huber". positive_weight (ours, 0 = facts):
    point weights 1 + positive_weight * target, normalised to mean 1, so the few contact points
    are not drowned by the many zeros (not used by "listnet"). Returns [B].
    """
    if kind == "huber":
        loss = optax.losses.huber_loss(scores, target, delta=delta)
    elif kind in ("bce", "focal"):
        loss = optax.losses.sigmoid_binary_cross_entropy(logits, target)
        if kind == "focal":
            loss = loss * jnp.abs(target - scores) ** focal_gamma
    elif kind == "listnet":
        n = num_object if num_object is not None else target.shape[-1]
        parts = [(logits[:, :n], target[:, :n]), (logits[:, n:], target[:, n:])]
        total = 0.0
        for z, y in parts:
            if z.shape[-1] == 0:
                continue
            y_sum = jnp.sum(y, axis=-1, keepdims=True)
            y_n = y / jnp.maximum(y_sum, 1e-12)
            per = -jnp.sum(y_n * jax.nn.log_softmax(z, axis=-1), axis=-1)
            total = total + jnp.where(y_sum[:, 0] > 0, per, 0.0)
        return total
    else:
        raise ValueError(f"unknown contact loss {kind!r}; expected one of {CONTACT_LOSSES}")
    if positive_weight <= 0:
        return jnp.mean(loss, axis=-1)
    w = 1.0 + positive_weight * target
    return jnp.sum(w * loss, axis=-1) / jnp.sum(w, axis=-1)


def correspondence_cross_entropy(logits: jax.Array, labels: jax.Array) -> jax.Array:
    """L_c: two-class cross-entropy of every candidate pair.

    logits: [B, K1, K2, 2] (class 1 = valid contact pair); labels: [B, K1, K2] bool.
    Returns [B], mean over the K1*K2 pairs.
    """
    ce = optax.softmax_cross_entropy_with_integer_labels(logits, labels.astype(jnp.int32))
    return jnp.mean(ce, axis=(1, 2))


def listnet_loss(scores: jax.Array, labels: jax.Array) -> jax.Array:
    """L_r of Eq. 2 (ListNet top-one ranking loss over all K1*K2 pairs).

    L_r = -sum_(u,v) y_(u,v) log softmax(y_hat)_(u,v), targets y normalised to sum to 1.

    scores: [B, K1, K2] positive-class scores y_hat (we pass the log-odds logit_1 - logit_0:
    a softmax over probabilities in [0, 1] would be nearly flat); labels: [B, K1, K2] bool.
    A pair without any positive contributes 0. Returns [B].
    """
    batch = scores.shape[0]
    flat_scores = scores.reshape(batch, -1)
    y = labels.reshape(batch, -1).astype(jnp.float32)
    num_pos = jnp.sum(y, axis=-1, keepdims=True)
    y = y / jnp.maximum(num_pos, 1.0)
    return -jnp.sum(y * jax.nn.log_softmax(flat_scores, axis=-1), axis=-1)
