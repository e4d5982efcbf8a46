"""Per-stage training losses of the goal-pose networks (``make_loss_fn``): Stage 1's set loss,
Stage 2a's contact scores, Stage 2b's correspondences; the pure losses are in
:mod:`omnihang_jax.losses`, the host loop in :mod:`omnihang_jax.train`."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import jaxlie

from omnihang_jax import losses
from omnihang_jax.data import HangSample
from omnihang_jax.pointnet2 import gather_points
from omnihang_jax.poses import pose7_to_pose6, rotation_matrix, transform_points
from omnihang_jax.stage1 import make_stage1, rotation_from_6d
from omnihang_jax.stage2 import (
    Stage2Config,
    combine_clouds,
    correspondence_labels,
    make_stage2,
    positive_scores,
    select_correspondences,
    solve_translation,
    top_contact_points,
    training_selection_scores,
)

if TYPE_CHECKING:
    from omnihang_jax.train import NetworksConfig

STAGES = ("1", "2a", "2b")
# every trainable network: the three goal-pose stages and the object-frame network
# (``omnihang_jax.canon``), which ``--stage all`` leaves out (``train_where --stage canon``)
ALL_STAGES = (*STAGES, "canon")


def _take_pose(x: jax.Array, d: jax.Array) -> jax.Array:
    """x: [B, D, ...], d: [B] -> x[b, d[b]]: [B, ...]."""
    return jax.vmap(lambda xb, db: xb[db])(x, d)


def _stage2_inputs(config: Stage2Config, batch: HangSample, key: jax.Array):
    """Pick one valid stable pose per pair, perturb it, build the combined cloud and targets."""
    k_pose, k_t, k_r = jax.random.split(key, 3)
    d = jax.random.categorical(k_pose, jnp.where(batch.pose_mask, 0.0, -jnp.inf), axis=-1)
    gt_pose6 = pose7_to_pose6(_take_pose(batch.stable_poses, d))  # [B, 6]
    noise = jnp.concatenate(
        [
            config.pose_noise_translation * jax.random.normal(k_t, gt_pose6[:, :3].shape),
            config.pose_noise_rotation * jax.random.normal(k_r, gt_pose6[:, 3:].shape),
        ],
        axis=-1,
    )
    input_pose6 = gt_pose6 + noise
    points, flags = combine_clouds(
        transform_points(input_pose6, batch.object_points), batch.support_points
    )
    target = jnp.concatenate(
        [
            _take_pose(batch.object_contact_maps, d),
            _take_pose(batch.support_contact_maps, d),
        ],
        axis=-1,
    )
    pairs = _take_pose(batch.contact_pairs, d)
    pair_mask = _take_pose(batch.contact_mask, d)
    return gt_pose6, points, flags, target, pairs, pair_mask


def _contact_loss(cfg2: Stage2Config, scores, logits, target, num_object: int) -> jax.Array:
    """Per-pair 2a loss ([B]) of ``cfg2.contact_loss`` (see ``losses.contact_score_loss``)."""
    return losses.contact_score_loss(
        scores,
        target,
        cfg2.huber_delta,
        cfg2.contact_positive_weight,
        kind=cfg2.contact_loss,
        logits=logits,
        num_object=num_object,
    )


def make_loss_fn(stage: str, config: NetworksConfig) -> Callable:
    """Loss of one stage: ``loss_fn(params, batch: HangSample, key) -> (loss, metrics)``.

    "1": set loss L_M (Eq. 1) between ``num_train_samples`` proposals and the stable poses.
    "2a": Huber loss of contact scores vs the soft contact maps of one random stable pose.
    "2b": L_c + L_r (Eq. 2) of the correspondence logits (+ the 2a Huber term when the
      segmentation features are fine-tuned, ``Stage2Config.train_features_in_2b``).
    Metrics are scalars (means over the batch).
    """
    if stage == "canon":
        from omnihang_jax.canon import make_canon_loss

        canon_loss = make_canon_loss(config.canon)
        return lambda params, batch, key: canon_loss(params, batch.object_points, key)
    if stage == "1":
        cfg1 = config.stage1
        net1 = make_stage1(cfg1)

        def stage1_loss(params, batch: HangSample, key):
            t, raw = net1.propose_raw(
                params, batch.object_points, batch.support_points, key, cfg1.num_train_samples
            )
            gt = pose7_to_pose6(batch.stable_poses)
            if cfg1.rotation == "6d":
                r_pred = rotation_from_6d(raw)
                r_gt = rotation_matrix(gt[..., 3:])
                dist = losses.pairwise_matrix_pose_distance(
                    t, r_pred, gt[..., :3], r_gt, cfg1.translation_weight
                )
                rot6 = jaxlie.SO3.from_matrix(jax.lax.stop_gradient(r_pred)).log()
                pred = jnp.concatenate([t, rot6], axis=-1)  # metrics only
            else:
                pred, dist = jnp.concatenate([t, raw], axis=-1), None
            loss = jnp.mean(
                losses.pose_set_loss(
                    pred, gt, batch.pose_mask, cfg1.translation_weight, dist, cfg1.set_loss_mean
                )
            )
            # Coverage of the ground truth: nearest proposal per stable pose.
            dt = jnp.linalg.norm(pred[:, :, None, :3] - gt[:, None, :, :3], axis=-1)
            dr = jnp.linalg.norm(pred[:, :, None, 3:] - gt[:, None, :, 3:], axis=-1)
            mask = batch.pose_mask.astype(jnp.float32)

            def mean_valid(x):
                return jnp.sum(jnp.min(x, 1) * mask) / jnp.sum(mask)

            return loss, {
                "loss": loss,
                "translation_error_m": mean_valid(dt),
                "rotation_error_rad": mean_valid(dr),
            }

        return stage1_loss

    if stage not in ("2a", "2b"):
        raise ValueError(f"unknown stage {stage!r}; expected one of {ALL_STAGES}")
    cfg2 = config.stage2
    net2 = make_stage2(cfg2)

    if stage == "2a":

        def stage2a_loss(params, batch: HangSample, key):
            _, points, flags, target, _, _ = _stage2_inputs(cfg2, batch, key)
            n = batch.object_points.shape[1]
            _, logits = net2.contact_logits(params, points, flags)
            scores = jax.nn.sigmoid(logits)
            loss = jnp.mean(_contact_loss(cfg2, scores, logits, target, n))
            object_idx, support_idx = top_contact_points(scores, n, cfg2.k_object, cfg2.k_support)
            # Mean ground-truth map value at the predicted top-K points (1 = perfect choice).
            hit = jnp.mean(jnp.take_along_axis(target[:, :n], object_idx, 1)) + jnp.mean(
                jnp.take_along_axis(target[:, n:], support_idx, 1)
            )
            return loss, {"loss": loss, "contact_loss": loss, "top_k_map_value": hit / 2}

        return stage2a_loss

    def stage2b_loss(params, batch: HangSample, key):
        gt_pose6, points, flags, target, pairs, pair_mask = _stage2_inputs(cfg2, batch, key)
        n = batch.object_points.shape[1]
        features, contact_logits = net2.contact_logits(params, points, flags)
        scores = jax.nn.sigmoid(contact_logits)
        huber = jnp.mean(_contact_loss(cfg2, scores, contact_logits, target, n))
        if not cfg2.train_features_in_2b:
            features = jax.lax.stop_gradient(features)
        selection = training_selection_scores(
            cfg2.train_selection, target, scores, jax.random.fold_in(key, 7)
        )
        object_idx, support_idx = top_contact_points(selection, n, cfg2.k_object, cfg2.k_support)
        logits = net2.correspond(
            params,
            gather_points(features[:, :n], object_idx),
            gather_points(features[:, n:], support_idx),
            gather_points(points[:, :n], object_idx),
            gather_points(points[:, n:], support_idx),
        )
        labels = correspondence_labels(
            batch.object_points,
            batch.support_points,
            object_idx,
            support_idx,
            pairs,
            pair_mask,
            cfg2.correspondence_radius,
        )
        ce = jnp.mean(losses.correspondence_cross_entropy(logits, labels))
        ranking_per_pair = losses.listnet_loss(positive_scores(logits), labels)
        ranking = jnp.mean(ranking_per_pair)
        # L_r minus its floor, the entropy log(#positives) of the normalised targets (= KL >= 0).
        num_pos = jnp.sum(labels, axis=(1, 2))
        excess = jnp.where(num_pos > 0, ranking_per_pair - jnp.log(jnp.maximum(num_pos, 1)), 0.0)
        loss = ce + ranking + (huber if cfg2.train_features_in_2b else 0.0)
        pred_o, pred_s = top_contact_points(scores, n, cfg2.k_object, cfg2.k_support)
        hit = jnp.mean(jnp.take_along_axis(target[:, :n], pred_o, 1)) + jnp.mean(
            jnp.take_along_axis(target[:, n:], pred_s, 1)
        )
        # Quality of the chosen pairs: label of the best pair, and the translation solved with
        # the ground-truth rotation (error in metres).
        probs = jax.nn.sigmoid(positive_scores(logits))
        chosen = select_correspondences(probs, cfg2.k_pairs, cfg2.threshold)
        best_label = jax.vmap(lambda lab, u, v: lab[u, v])(
            labels, chosen.object_slot[:, 0], chosen.support_slot[:, 0]
        )
        o = gather_points(
            batch.object_points, jnp.take_along_axis(object_idx, chosen.object_slot, 1)
        )
        s = gather_points(
            batch.support_points, jnp.take_along_axis(support_idx, chosen.support_slot, 1)
        )
        t = solve_translation(rotation_matrix(gt_pose6[:, 3:]), o, s, chosen.weight)
        return loss, {
            "loss": loss,
            "cross_entropy": ce,
            "listnet": ranking,
            "listnet_excess": jnp.mean(excess),
            "contact_loss": huber,
            "top_k_map_value": hit / 2,
            "positive_fraction": jnp.mean(labels),
            "top1_precision": jnp.mean(best_label),
            "translation_error_m": jnp.mean(jnp.linalg.norm(t - gt_pose6[:, :3], axis=-1)),
        }

    return stage2b_loss
