"""Training-time augmentation of (object, support) pairs that the camera and physics allow.

* ``jitter`` (m): Gaussian noise on every observed point (object and support clouds), a depth
  camera's noise; normals, contact maps and contact pairs index points and stay as they are.
* ``yaw`` (rad): the whole pair turned by one angle, uniform in [-yaw, yaw], about the
  vertical axis through the support frame's origin: support points and normals turn, and so
  does every stable pose (t -> R t, q -> q_z q). Gravity is along -z, so a turned stable pose
  is stable for the turned support (exact, not an approximation); the object cloud is in the
  object's own frame and does not change.

Pure and jit-friendly: ``augment_pair(batch, key, jitter, yaw) -> batch`` on a batched
``data.HangSample`` (leading B axis; fields a packed Stage-1 set leaves off, e.g. support normals
as [B, 1] zeros, pass through); with ``jitter = yaw = 0`` the batch is returned as is.
Used by ``train.make_train_step`` for Stage 1 when ``TrainConfig.augment_jitter`` /
``augment_yaw`` are set (``train_where --augment-jitter M --augment-yaw RAD``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["yaw_matrix", "turn_poses", "augment_pair"]


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


def augment_pair(batch, key: jax.Array, jitter: float, yaw: float):
    """A batched ``HangSample`` with jittered points and a random turn about z (module
    docstring). ``jitter`` / ``yaw`` are static (Python floats)."""
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
