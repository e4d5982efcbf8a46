"""Training-time augmentation of (object, support) pairs that the camera and physics allow.

* ``jitter`` (m): Gaussian noise on every observed point (object and support clouds), a depth
  camera's noise; normals, contact maps and contact pairs index points and stay as they are.
* ``yaw`` (rad): the whole pair turned by one angle, uniform in [-yaw, yaw], about the
  vertical axis through the support frame's origin: support points and normals turn, and so
  does every stable pose (t -> R t, q -> q_z q). Gravity is along -z, so a turned stable pose
  is stable for the turned support (exact, not an approximation); the object cloud is in the
  object's own frame and does not change.

* ``turn_object`` (M, an int): the object read as ``where.FRAMES`` reads it: about its
  principal-box centre (``poses.box_centre``), in the frame that the nearest of M frame
  hypotheses (``poses.super_fibonacci(M)``) leaves of a uniform random frame (M = 1: the
  uniform random frame itself). Object points become R (p - c), normals R n, and every stable
  pose describes the same placement of the moved cloud (q -> q R^T, t -> t + R_q c). Exact:
  the support, gravity and the placements stay; only the frame the object cloud is written in
  changes. For networks that read objects in any frame (docs/where.md, "Objects in any frame").

Pure and jit-friendly: ``augment_pair(batch, key, jitter, yaw) -> batch`` on a batched
``data.HangSample`` (leading B axis; fields a packed Stage-1 set leaves off, e.g. support normals
as [B, 1] zeros, pass through); with ``jitter = yaw = 0`` the batch is returned as is.
Used by ``train.make_train_step`` for Stage 1 when ``TrainConfig.augment_jitter`` /
``augment_yaw`` are set (``train_where --augment-jitter M --augment-yaw RAD``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from omnihang_jax.poses import box_centre, quaternion_to_matrix, reframe, super_fibonacci

__all__ = [
    "yaw_matrix",
    "turn_poses",
    "random_rotations",
    "residual_turns",
    "turn_object_frame",
    "augment_pair",
]


def yaw_matrix(angle: jax.Array) -> jax.Array:
    """[...] angles (rad) -> [..., 3, 3] rotations about +z."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    zero, one = jnp.zeros_like(angle), jnp.ones_like(angle)
    rows = [jnp.stack([c, -s, zero], -1), jnp.stack([s, c, zero], -1),
            jnp.stack([zero, zero, one], -1)]  # fmt: skip
    return jnp.stack(rows, -2)


def turn_poses(poses: jax.Array, angle: jax.Array) -> jax.Array:
    """Poses [B, D, 7] (xyz + wxyz, object in support frame) seen from a support frame turned
    by ``angle`` [B] about z: translation R_z t, rotation q_z * q."""
    rot = yaw_matrix(angle)  # [B, 3, 3]
    t = jnp.einsum("bij,bdj->bdi", rot, poses[..., :3])
    half = 0.5 * angle[:, None]
    qw, qz = jnp.cos(half), jnp.sin(half)  # q_z = (cos a/2, 0, 0, sin a/2)
    w, x, y, z = (poses[..., i] for i in range(3, 7))
    q = jnp.stack([qw * w - qz * z, qw * x - qz * y, qw * y + qz * x, qw * z + qz * w], -1)
    return jnp.concatenate([t, q], -1)


def random_rotations(key: jax.Array, n: int) -> jax.Array:
    """[n, 3, 3] uniform random rotations (normalised Gaussian quaternions)."""
    return quaternion_to_matrix(jax.random.normal(key, (n, 4)))


def residual_turns(key: jax.Array, n: int, frames: int) -> jax.Array:
    """[n, 3, 3] the turn of an object handed over in a uniform random frame A as the nearest of
    ``frames`` hypotheses H_i (``super_fibonacci``) leaves it, H_i A with the largest trace:
    what Stage 1 sees in its best frame under ``where.FRAMES``. ``frames`` = 1: A itself."""
    a = random_rotations(key, n)
    if frames <= 1:
        return a
    h = quaternion_to_matrix(jnp.asarray(super_fibonacci(frames), a.dtype))  # [M, 3, 3]
    seen = jnp.einsum("mij,njk->nmik", h, a)  # [n, M, 3, 3]
    best = jnp.argmax(jnp.trace(seen, axis1=-2, axis2=-1), axis=1)  # the smallest angle
    return seen[jnp.arange(n), best]


def turn_object_frame(poses: jax.Array, rot: jax.Array) -> jax.Array:
    """Poses [B, D, 7] of the object -> the same placements of the object written in a frame
    turned by ``rot`` [B, 3, 3] (points R p): rotation Q R^T, translation unchanged."""
    return reframe(poses, jnp.swapaxes(rot, -1, -2)[:, None])


def augment_pair(batch, key: jax.Array, jitter: float, yaw: float, turn_object: int = 0):
    """A batched ``HangSample`` with jittered points, a random turn about z and the object read
    about its box centre in a turned frame (module docstring). ``jitter`` / ``yaw`` /
    ``turn_object`` are static."""
    if jitter <= 0 and yaw <= 0 and not turn_object:
        return batch
    if turn_object:
        key, k_turn = jax.random.split(key)
        pts = jnp.asarray(batch.object_points)
        rot = residual_turns(k_turn, pts.shape[0], int(turn_object)).astype(pts.dtype)
        centre = jax.vmap(box_centre)(pts.astype(jnp.float32)).astype(pts.dtype)  # [B, 3]
        normals = batch.object_normals
        if normals.shape == pts.shape:
            normals = jnp.einsum("bij,bnj->bni", rot, normals.astype(rot.dtype))
        poses = jnp.asarray(batch.stable_poses)
        q_rot = quaternion_to_matrix(poses[..., 3:])  # [B, D, 3, 3]
        moved = poses.at[..., :3].add(jnp.einsum("bdij,bj->bdi", q_rot, centre))
        batch = batch._replace(
            object_points=jnp.einsum("bij,bnj->bni", rot, pts - centre[:, None]),
            object_normals=normals.astype(batch.object_normals.dtype),
            stable_poses=turn_object_frame(moved, rot).astype(poses.dtype),
        )
    if jitter <= 0 and yaw <= 0:
        return batch
    k_obj, k_sup, k_yaw = jax.random.split(key, 3)
    obj, sup, sup_n = batch.object_points, batch.support_points, batch.support_normals
    poses = batch.stable_poses
    if jitter > 0:
        obj = obj + jitter * jax.random.normal(k_obj, obj.shape, obj.dtype)
        sup = sup + jitter * jax.random.normal(k_sup, sup.shape, sup.dtype)
    if yaw > 0:
        angle = jax.random.uniform(k_yaw, (obj.shape[0],), minval=-yaw, maxval=yaw)
        rot = yaw_matrix(angle).astype(sup.dtype)
        sup = jnp.einsum("bij,bnj->bni", rot, sup)
        if sup_n.shape == sup.shape:  # Stage-1 batches of a packed set carry [B, 1] zeros
            sup_n = jnp.einsum("bij,bnj->bni", rot, sup_n.astype(sup.dtype)).astype(sup_n.dtype)
        poses = turn_poses(poses, angle).astype(poses.dtype)
    return batch._replace(
        object_points=obj, support_points=sup, support_normals=sup_n, stable_poses=poses
    )
