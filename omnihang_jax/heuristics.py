"""Heuristic scores of a pose from the observed partial clouds alone (no learning, no
simulator): how far the object, placed at the pose, sinks into the observed support.

The paper compares its neural collision estimator with a heuristic one for the "how"
part; the same idea ranks the "where" proposals here: among the K Stage-1 (or Stage-2)
proposals, prefer the one whose object cloud least enters the support cloud. A point
``p`` of the object cloud (moved to the pose) is *inside* when its nearest support point
``s`` is within ``window`` and ``p`` lies more than ``tol`` behind ``s``'s outward normal
``n``: ``(p - s) . n < -tol``. Partial clouds see one side of the support, so points far
behind the visible surface (beyond ``window``) are not counted: they are as likely past a
thin rod as inside it.

All functions are pure JAX (jit / vmap friendly). Shapes: clouds ``[N, 3]`` / ``[M, 3]``,
poses ``[7]`` = xyz (m) + quaternion wxyz, object frame in the support frame.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie

__all__ = ["penetration_score", "rank_by_penetration"]


def penetration_score(
    object_points: jax.Array,
    support_points: jax.Array,
    support_normals: jax.Array,
    pose: jax.Array,
    tol: float = 0.002,
    window: float = 0.015,
) -> jax.Array:
    """Fraction [] of object points inside the observed support at ``pose`` (see module)."""
    q = pose[3:7] / jnp.maximum(jnp.linalg.norm(pose[3:7]), 1e-12)
    rot = jaxlie.SO3(wxyz=q).as_matrix()
    p = object_points @ rot.T + pose[:3]
    d2 = jnp.sum((p[:, None, :] - support_points[None, :, :]) ** 2, axis=-1)  # [N, M]
    j = jnp.argmin(d2, axis=1)
    s, n = support_points[j], support_normals[j]
    n = n / jnp.maximum(jnp.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    signed = jnp.sum((p - s) * n, axis=-1)
    dist = jnp.sqrt(jnp.take_along_axis(d2, j[:, None], axis=1)[:, 0])
    inside = (signed < -tol) & (dist < window)
    return jnp.mean(inside.astype(jnp.float32))


@jax.jit
def rank_by_penetration(
    object_points: jax.Array,
    support_points: jax.Array,
    support_normals: jax.Array,
    poses: jax.Array,
) -> tuple[jax.Array, jax.Array]:
    """(order [K] int32, scores [K]) of ``poses`` [K, 7], least penetrating first (stable:
    ties keep the proposals' order)."""
    scores = jax.vmap(penetration_score, in_axes=(None, None, None, 0))(
        object_points, support_points, support_normals, poses
    )
    return jnp.argsort(scores, stable=True).astype(jnp.int32), scores
