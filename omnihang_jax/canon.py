"""The object's frame, learned: a network that reads an object cloud in any frame and returns
H hypotheses of the transform that writes it in the library's frame.

The rest of "where to hang" was learned on objects written in the procedural library's frame
(a mug's handle along +x, its opening up). An object handed over in another frame (a robot's
grasp, a user's mesh) is first read about its principal-box centre c (``poses.box_centre``,
which turns and moves with the cloud), and the network gives H transforms (R_h, t_h): the
cloud ``R_h (p - c) + t_h`` is the object as the library would have written it. Stages 1-2 read
the object in each hypothesis (``pipeline.PipelineConfig.canon``), every proposal is turned
back, and V, which reads the object posed in the support frame, picks among them; nothing
after that depends on the object's frame.

Training (``train_where --stage canon``) is self-supervised from the library's own clouds:
every object cloud X is turned by a uniform random rotation A and read about its box centre,
and each hypothesis is scored by the Chamfer distance between ``R_h (A X - c) + t_h`` and X.
The Chamfer distance does not care which of an object's symmetries the network picks (a
glass turned about its axis is the same glass), and the loss is winner-takes-all over the H
hypotheses (with a small pull towards the true turn, ``CanonConfig.rotation_weight``, that
takes a hypothesis out of a wrong basin such as a flipped handle) (``CanonConfig.mean_weight`` of the mean keeps every head learning), so the heads
can cover an object that looks alike in a few frames (a bag front or back). A score head
learns which hypothesis wins. Depth noise of up to ``CanonConfig.jitter`` is added to the
turned clouds.

Usage::

    net = make_canon(CANON_SMALL)
    params = net.init(key)
    rot, shift, score = net.frames(params, centred_points)   # [B, H, 3, 3], [B, H, 3], [B, H]
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from omnihang_jax import pointnet2
from omnihang_jax.pointnet2 import PointNet2Config, PointNet2Encoder, SharedMLP
from omnihang_jax.poses import box_centre, principal_frame, quaternion_to_matrix
from omnihang_jax.stage1 import rotation_from_6d

__all__ = [
    "CanonConfig",
    "CANON_SMALL",
    "CANON_TINY",
    "CanonNetwork",
    "make_canon",
    "make_canon_loss",
    "chamfer",
    "rotation_angle",
]


@dataclasses.dataclass(frozen=True)
class CanonConfig:
    """The frame network's architecture and loss."""

    encoder: PointNet2Config = pointnet2.SMALL
    trunk: tuple[int, ...] = (512, 256)
    hypotheses: int = 4  # H transforms per cloud
    mean_weight: float = 0.05  # weight of the mean over hypotheses beside their minimum
    score_weight: float = 0.1  # weight of the score head's cross-entropy (which one wins)
    chamfer_points: int = 256  # points of each cloud in the Chamfer distance
    # weight (per m of Chamfer distance) of the squared Frobenius distance between each
    # hypothesis and the true turn: a pull out of a wrong basin of the Chamfer distance (a
    # flipped handle); 180 degrees off costs 8 x this, 10 degrees 0.06 x
    rotation_weight: float = 0.005
    jitter: float = 0.003  # the largest Gaussian depth noise (m) of a training cloud


CANON_SMALL = CanonConfig()
CANON_TINY = CanonConfig(encoder=pointnet2.TINY, trunk=(64,), hypotheses=2, chamfer_points=64)


class CanonNet(nn.Module):
    config: CanonConfig

    @nn.compact
    def __call__(self, points: jax.Array):
        """points [B, N, 3], the cloud about its box centre -> (rot [B, H, 3, 3], shift
        [B, H, 3] m, score [B, H] logits). The encoder reads the cloud in its principal frame
        P (``poses.principal_frame``), which turns with the cloud, and each hypothesis is a
        correction C_h of that frame: rot = C_h P^T."""
        cfg = self.config
        axes = jax.vmap(principal_frame)(points.astype(jnp.float32)).astype(points.dtype)
        points = jnp.einsum("bji,bnj->bni", axes, points)  # P^T p
        feature, _ = PointNet2Encoder(cfg.encoder, name="encoder")(points)
        x = SharedMLP(cfg.trunk, name="trunk")(feature)
        h = cfg.hypotheses
        out = nn.Dense(h * 10, name="head")(x).reshape(*x.shape[:-1], h, 10)
        # a head that starts near the identity turn and no shift
        six = out[..., :6] + jnp.array([1.0, 0.0, 0.0, 0.0, 1.0, 0.0], out.dtype)
        rot = rotation_from_6d(six) @ jnp.swapaxes(axes, -1, -2)[:, None]
        return rot, 0.1 * out[..., 6:9], out[..., 9]


class CanonNetwork(NamedTuple):
    """init(key) -> params; frames(params, points [B, N, 3] about the box centre) -> (rot
    [B, H, 3, 3], shift [B, H, 3], score [B, H]): hypothesis h writes the object as the
    library does, ``rot[h] p + shift[h]``; a higher score is a likelier winner."""

    init: Callable
    frames: Callable
    config: CanonConfig


def make_canon(config: CanonConfig) -> CanonNetwork:
    module = CanonNet(config)

    def init(key):
        points = jnp.zeros((1, config.encoder.num_points, 3), jnp.float32)
        return module.init(key, points)

    def frames(params, points):
        return module.apply(params, points)

    return CanonNetwork(init, frames, config)


def chamfer(a: jax.Array, b: jax.Array) -> jax.Array:
    """[..., P, 3], [..., Q, 3] -> [...] the symmetric Chamfer distance: the mean distance (m,
    not squared) from each point to the other cloud, averaged over both directions."""
    d2 = jnp.sum((a[..., :, None, :] - b[..., None, :, :]) ** 2, -1)
    d = jnp.sqrt(jnp.maximum(d2, 1e-12))
    return 0.5 * (d.min(-1).mean(-1) + d.min(-2).mean(-1))


def rotation_angle(a: jax.Array, b: jax.Array) -> jax.Array:
    """[..., 3, 3] x2 -> [...] the angle (rad) of the turn between two rotations."""
    cos = 0.5 * (jnp.trace(jnp.swapaxes(a, -1, -2) @ b, axis1=-2, axis2=-1) - 1.0)
    return jnp.arccos(jnp.clip(cos, -1.0, 1.0))


def make_canon_loss(config: CanonConfig) -> Callable:
    """``loss(params, object_points [B, N, 3] in the library's frame, key) -> (loss, metrics)``
    (module docstring). Metrics: ``chamfer_mm`` of the best hypothesis, ``chamfer_top_mm`` of
    the best-scored one, ``angle_deg`` the turn between the best hypothesis and the true one
    (large where an object's symmetry makes another turn as good)."""
    net = make_canon(config)
    p = config.chamfer_points

    def loss_fn(params, object_points, key):
        b, n, _ = object_points.shape
        k_rot, k_sigma, k_noise, k_a, k_b = jax.random.split(key, 5)
        turn = quaternion_to_matrix(jax.random.normal(k_rot, (b, 4)))  # A, uniform
        sigma = config.jitter * jax.random.uniform(k_sigma, (b, 1, 1))
        seen = jnp.einsum("bij,bnj->bni", turn, object_points)
        seen = seen + sigma * jax.random.normal(k_noise, seen.shape)
        seen = seen - jax.vmap(box_centre)(seen)[:, None]
        rot, shift, score = net.frames(params, seen)
        # the Chamfer distance on two different subsets of the points
        ia = jax.random.choice(k_a, n, (p,), replace=n < p)
        ib = jax.random.choice(k_b, n, (p,), replace=n < p)
        written = jnp.einsum("bhij,bnj->bhni", rot, seen[:, ia]) + shift[:, :, None]
        dist = chamfer(written, object_points[:, None, ib])  # [B, H]
        truth = jnp.swapaxes(turn, -1, -2)[:, None]  # A^T
        frob = jnp.sum((rot - truth) ** 2, axis=(-1, -2))  # [B, H]
        cost = dist + config.rotation_weight * frob
        best = jnp.argmin(cost, axis=1)
        ce = -jnp.take_along_axis(jax.nn.log_softmax(score, -1), best[:, None], 1)[:, 0]
        per_pair = cost.min(1) + config.mean_weight * cost.mean(1) + config.score_weight * ce
        best_rot = jnp.take_along_axis(rot, best[:, None, None, None], 1)[:, 0]
        top = jnp.argmax(score, axis=1)
        angle = rotation_angle(best_rot, truth[:, 0])
        metrics = {
            "loss": per_pair.mean(),
            "chamfer_mm": 1000 * dist.min(1).mean(),
            "chamfer_top_mm": 1000 * jnp.take_along_axis(dist, top[:, None], 1).mean(),
            "angle_deg": jnp.degrees(angle).mean(),
            "angle_within_15deg": (angle < jnp.radians(15.0)).mean(),
            "score_ce": ce.mean(),
        }
        return metrics["loss"], metrics

    return loss_fn
