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

__all__ = ["penetration_score", "rank_by_penetration", "separate"]

TOL = 0.002  # m behind the support surface before a point counts as inside
WINDOW = 0.015  # m: farther from every observed support point, a point is not counted


def _inside(object_points, support_points, support_normals, pose, tol, window):
    """(inside [N] bool, outward normal [N, 3] of each object point's nearest support point)
    for the object cloud moved to ``pose`` (module docstring)."""
    q = pose[3:7] / jnp.maximum(jnp.linalg.norm(pose[3:7]), 1e-12)
    rot = jaxlie.SO3(wxyz=q).as_matrix()
    p = object_points @ rot.T + pose[:3]
    d2 = jnp.sum((p[:, None, :] - support_points[None, :, :]) ** 2, axis=-1)  # [N, M]
    j = jnp.argmin(d2, axis=1)
    s, n = support_points[j], support_normals[j]
    n = n / jnp.maximum(jnp.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    signed = jnp.sum((p - s) * n, axis=-1)
    dist = jnp.sqrt(jnp.take_along_axis(d2, j[:, None], axis=1)[:, 0])
    return (signed < -tol) & (dist < window), n


def penetration_score(
    object_points: jax.Array,
    support_points: jax.Array,
    support_normals: jax.Array,
    pose: jax.Array,
    tol: float = TOL,
    window: float = WINDOW,
) -> jax.Array:
    """Fraction [] of object points inside the observed support at ``pose`` (see module)."""
    inside, _ = _inside(object_points, support_points, support_normals, pose, tol, window)
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


@jax.jit
def separate(
    object_points: jax.Array,
    support_points: jax.Array,
    support_normals: jax.Array,
    pose: jax.Array,
    max_shift: float = 0.03,
    accept: float = 0.01,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Back a penetrating pose out of the observed support: (pose [7], shift [] m, score []).

    The direction is the mean outward normal of the support points nearest to the object
    points that are inside (module docstring); the shift is the smallest of 0, 2, ..., 30 mm
    (``max_shift``) whose :func:`penetration_score` is at most ``accept``, else the shift of
    least penetration. Rotation unchanged. A pose with nothing inside is returned as is.
    """
    inside, n = _inside(object_points, support_points, support_normals, pose, TOL, WINDOW)
    direction = jnp.sum(jnp.where(inside[:, None], n, 0.0), axis=0)
    direction = direction / jnp.maximum(jnp.linalg.norm(direction), 1e-12)
    offsets = jnp.linspace(0.0, max_shift, 16)
    moved = pose[None, :].repeat(16, 0).at[:, :3].add(offsets[:, None] * direction[None, :])
    scores = jax.vmap(penetration_score, in_axes=(None, None, None, 0))(
        object_points, support_points, support_normals, moved
    )
    ok = scores <= accept
    k = jnp.where(jnp.any(ok), jnp.argmax(ok), jnp.argmin(scores))
    return moved[k], offsets[k], scores[k]
