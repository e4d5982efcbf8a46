"""The object's frame from its cloud: a learned canonicaliser that makes where to hang
independent of the frame an object is handed over in.

Stages 1 and 2 read the object cloud in the object's own frame and were trained on the
library's frames (upright, handle along +x); Stage 3, the rankers, the answer rule and the check
read the object only as placed by a candidate pose, so they do not care which frame it came in.
:class:`FrameNet` maps an object cloud in any frame (any rotation, any shift) back into a frame
that looks like the library's: for the cloud ``p`` it predicts ``M`` hypotheses, each a rotation
``G`` and a point ``c_hat``, and the canonical cloud is

    q = G (p - mean(p)) + c_hat

with a score per hypothesis. The network sees the cloud minus its mean, so it is shift-invariant
by construction; rotation is learned from turned copies of the library's clouds.

Training (``experiments.train_frame``): every training object's partial clouds, each seen from a
camera anywhere on the sphere and turned by a uniform random rotation; the loss is a
Chamfer-style set loss between each hypothesis's canonical cloud and the cloud in the library
frame, winner takes all over the hypotheses (symmetric objects have several right answers; a set
loss accepts any of them), plus cross-entropy teaching the score which hypothesis won.

Use (``where.WhereConfig.frame``): the answer canonicalises the object cloud with the
best-scored hypothesis, runs Stages 1-3 on it, and maps every pose back with :func:`pose_back`.
"""

from __future__ import annotations

import dataclasses
import os
from typing import NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from omnihang_jax import pointnet2
from omnihang_jax.config import load_config, save_config
from omnihang_jax.pointnet2 import PointNet2Config, PointNet2Encoder, SharedMLP
from omnihang_jax.stage1 import rotation_from_6d
from omnihang_jax.stage3 import _subsample_index

__all__ = [
    "FrameConfig",
    "FrameNet",
    "Frame",
    "canonicalise",
    "chamfer",
    "frame_loss",
    "load_frame",
    "make_canonicaliser",
    "pose_back",
    "random_rotations",
    "save_frame",
    "subsample",
]


@dataclasses.dataclass(frozen=True)
class FrameConfig:
    """The canonicaliser's architecture."""

    encoder: PointNet2Config = pointnet2.SMALL
    num_points: int = 512  # evenly spaced subsample of the observed cloud
    hypotheses: int = 4  # M frames proposed per cloud
    head: tuple[int, ...] = (256, 128)
    offset_scale: float = 0.1  # m: c_hat = offset_scale * head output


FRAME_TINY = FrameConfig(encoder=pointnet2.TINY, num_points=64, hypotheses=2, head=(32,))


class Frame(NamedTuple):
    """M hypotheses of a batch: rotation [B, M, 3, 3] (G, given -> canonical), centre [B, M, 3]
    (c_hat, the cloud's mean in the canonical frame), logits [B, M] (higher: more likely)."""

    rotation: jax.Array
    centre: jax.Array
    logits: jax.Array


class FrameNet(nn.Module):
    config: FrameConfig

    @nn.compact
    def __call__(self, points: jax.Array, normals: jax.Array) -> Frame:
        """points, normals [B, N, 3] in any frame (N = config.num_points)."""
        cfg = self.config
        centred = points - jnp.mean(points, axis=1, keepdims=True)
        feature, _ = PointNet2Encoder(cfg.encoder, name="encoder")(centred, normals)
        h = SharedMLP(cfg.head, name="head")(feature)
        m = cfg.hypotheses
        out = nn.Dense(m * 10, name="out")(h).reshape(points.shape[0], m, 10)
        # start near the identity in every hypothesis, each a little apart
        eye6 = jnp.array([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])
        rotation = rotation_from_6d(out[..., :6] + eye6)
        centre = cfg.offset_scale * out[..., 6:9]
        return Frame(rotation, centre, out[..., 9])


def subsample(points: np.ndarray | jax.Array, n: int):
    """The evenly spaced subsample of [..., P, 3] (the pipeline's view (0, 1))."""
    return jnp.take(points, _subsample_index(points.shape[-2], n), axis=-2)


def canonicalise(points, normals, rotation, centre):
    """The cloud [N, 3] (+ normals) in the hypothesis' canonical frame: G (p - mean p) + c_hat."""
    mean = jnp.mean(points, axis=-2, keepdims=True)
    q = jnp.einsum("ij,nj->ni", rotation, points - mean) + centre
    return q, jnp.einsum("ij,nj->ni", rotation, normals), mean[0]


def pose_back(poses7, rotation, centre, mean):
    """Poses [..., 7] of the canonical cloud (q = G (p - m) + c_hat) as poses of the given cloud
    p: x = R_c q + t_c = (R_c G) p + t_c + R_c (c_hat - G m)."""
    from jaxlie import SO3

    r_c = SO3(poses7[..., 3:] / jnp.linalg.norm(poses7[..., 3:], axis=-1, keepdims=True))
    offset = centre - rotation @ mean
    t = poses7[..., :3] + r_c.apply(jnp.broadcast_to(offset, poses7[..., :3].shape))
    q = (r_c @ SO3.from_matrix(jnp.broadcast_to(rotation, (*poses7.shape[:-1], 3, 3)))).wxyz
    return jnp.concatenate([t, q], axis=-1)


def make_canonicaliser(config: FrameConfig):
    """``to_frame(params, clouds) -> (clouds in the best hypothesis' frame, back)`` for one
    pair's ``stage3.PairClouds`` (no batch axis); ``back(poses [..., 7])`` maps poses of the
    canonical cloud to poses of the given one. Jit- and vmap-friendly."""
    net = FrameNet(config)

    def to_frame(params, clouds):
        pts = subsample(clouds.object_points, config.num_points)
        nrm = subsample(clouds.object_normals, config.num_points)
        out = net.apply(params, pts[None], nrm[None])
        best = jnp.argmax(out.logits[0])
        rotation, centre = out.rotation[0, best], out.centre[0, best]
        q, qn, mean = canonicalise(clouds.object_points, clouds.object_normals, rotation, centre)
        moved = clouds._replace(object_points=q, object_normals=qn)
        return moved, lambda poses: pose_back(poses, rotation, centre, mean)

    return to_frame


def chamfer(a: jax.Array, b: jax.Array) -> jax.Array:
    """Symmetric Chamfer distance of two clouds [N, 3], [M, 3]: the mean distance (m) from each
    point to the nearest of the other cloud, both ways, halved."""
    # the nearest neighbours are found without gradient; the distances to them carry it (the
    # same value and gradient as min over the matrix, without differentiating [N, M] entries)
    d = jax.lax.stop_gradient(pointnet2.squared_distance(a[:, None, :], b[None, :, :]))
    near_b, near_a = jnp.argmin(d, axis=1), jnp.argmin(d, axis=0)

    def dist(x, y):
        return jnp.sqrt(jnp.maximum(jnp.sum((x - y) ** 2, axis=-1), 1e-12))

    return 0.5 * (jnp.mean(dist(a, b[near_b])) + jnp.mean(dist(b, a[near_a])))


def random_rotations(key: jax.Array, n: int) -> jax.Array:
    """[n, 3, 3] rotations uniform on SO(3) (normalised Gaussian quaternions)."""
    from jaxlie import SO3

    q = jax.random.normal(key, (n, 4))
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jax.vmap(lambda w: SO3(w).as_matrix())(q)


def frame_loss(
    frame: Frame,
    turned: jax.Array,
    canonical: jax.Array,
    relax: float = 0.05,
    point_weight: float = 1.0,
):
    """Winner-takes-all loss over the hypotheses. turned [B, N, 3] (the network's input),
    canonical [B, N, 3] (the same points, in order, in the library frame). A hypothesis' error is
    its Chamfer distance to the canonical cloud (any symmetric answer is right) plus
    ``point_weight`` x the mean distance of each point to its own canonical position (a strong
    signal far from the answer). Returns (loss, metrics); the metrics are Chamfer's."""

    def per(rot, centre, p, target):
        mean = jnp.mean(p, axis=0)
        q = jnp.einsum("ij,nj->ni", rot, p - mean) + centre
        own = jnp.mean(jnp.sqrt(jnp.maximum(jnp.sum((q - target) ** 2, -1), 1e-12)))
        return chamfer(q, target), own

    cd, own = jax.vmap(lambda r, c, p, t: jax.vmap(per, (0, 0, None, None))(r, c, p, t))(
        frame.rotation, frame.centre, turned, canonical
    )  # [B, M] each
    err = cd + point_weight * own
    best = jnp.argmin(err, axis=1)
    wta = jnp.min(err, axis=1)
    ce = -jnp.take_along_axis(jax.nn.log_softmax(frame.logits), best[:, None], axis=1)[:, 0]
    chosen = jnp.take_along_axis(cd, jnp.argmax(frame.logits, axis=1)[:, None], axis=1)[:, 0]
    loss = jnp.mean((1 - relax) * wta + relax * jnp.mean(err, axis=1)) / 0.01 + 0.1 * jnp.mean(ce)
    return loss, {
        "chamfer_best_mm": 1e3 * jnp.mean(jnp.min(cd, axis=1)),
        "chamfer_chosen_mm": 1e3 * jnp.mean(chosen),
        "score_accuracy": jnp.mean(jnp.argmax(frame.logits, axis=1) == best),
    }


def save_frame(folder: str | os.PathLike, config: FrameConfig, params, meta: dict | None = None):
    """``config.json`` + ``params.msgpack`` (the weights-folder format)."""
    from flax import serialization

    os.makedirs(folder, exist_ok=True)
    save_config(config, os.path.join(folder, "config.json"), role="frame", **(meta or {}))
    with open(os.path.join(folder, "params.msgpack"), "wb") as f:
        f.write(serialization.to_bytes(params))


def load_frame(folder: str | os.PathLike) -> tuple[FrameConfig, dict]:
    """(config, params) of a weights folder written by :func:`save_frame`."""
    from flax import serialization

    path = os.path.join(folder, "config.json")
    if not os.path.exists(path):
        raise FileNotFoundError(f"{path} not found: not a frame-network weights folder")
    config, _ = load_config(FrameConfig, path)
    n = config.num_points
    template = jax.eval_shape(
        FrameNet(config).init, jax.random.key(0), jnp.zeros((1, n, 3)), jnp.zeros((1, n, 3))
    )
    with open(os.path.join(folder, "params.msgpack"), "rb") as f:
        return config, serialization.from_bytes(template, f.read())
