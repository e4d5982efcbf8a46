"""Pose conventions shared by every stage.

A hanging pose is the pose of the OBJECT frame expressed in the SUPPORT frame:
``p_support = R @ p_object + t``.

* ``pose7``: [..., 7] float32 = translation xyz (metres) + unit quaternion **wxyz** (the dataset
  format, ``HangSample.stable_poses``).
* ``pose6``: [..., 6] float32 = translation xyz (metres) + axis-angle / rotation vector (radians,
  angle in [0, pi]) -- what Stage 1 regresses (paper, "Stage One").

Conversions go through ``jaxlie.SO3``; all functions broadcast over leading axes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

__all__ = [
    "pose7_to_pose6",
    "pose6_to_pose7",
    "rotation_matrix",
    "transform_points",
    "quaternion_to_matrix",
    "quaternion_from_matrix",
    "reframe",
    "move_origin",
    "super_fibonacci",
    "box_centre",
]


def pose7_to_pose6(pose7: jax.Array) -> jax.Array:
    """[..., 7] (xyz + quaternion wxyz) -> [..., 6] (xyz + axis-angle, angle <= pi)."""
    pose7 = jnp.asarray(pose7, jnp.float32)
    wxyz = pose7[..., 3:]
    wxyz = wxyz / jnp.linalg.norm(wxyz, axis=-1, keepdims=True)
    return jnp.concatenate([pose7[..., :3], jaxlie.SO3(wxyz=wxyz).log()], axis=-1)


def pose6_to_pose7(pose6: jax.Array) -> jax.Array:
    """[..., 6] (xyz + axis-angle) -> [..., 7] (xyz + quaternion wxyz, w >= 0)."""
    pose6 = jnp.asarray(pose6, jnp.float32)
    wxyz = jaxlie.SO3.exp(pose6[..., 3:]).wxyz
    wxyz = jnp.where(wxyz[..., :1] < 0, -wxyz, wxyz)
    return jnp.concatenate([pose6[..., :3], wxyz], axis=-1)


def rotation_matrix(axis_angle: jax.Array) -> jax.Array:
    """[..., 3] rotation vector -> [..., 3, 3] rotation matrix."""
    return jaxlie.SO3.exp(jnp.asarray(axis_angle, jnp.float32)).as_matrix()


def transform_points(pose6: jax.Array, points: jax.Array) -> jax.Array:
    """Move object-frame points into the support frame.

    pose6: [..., 6]; points: [..., N, 3] (same leading axes). Returns [..., N, 3] = R p + t.
    """
    rot = rotation_matrix(pose6[..., 3:])
    return jnp.einsum("...ij,...nj->...ni", rot, points) + pose6[..., None, :3]


def quaternion_to_matrix(wxyz: jax.Array) -> jax.Array:
    """[..., 4] quaternions wxyz (normalised here) -> [..., 3, 3] rotation matrices."""
    wxyz = wxyz / jnp.linalg.norm(wxyz, axis=-1, keepdims=True)
    return jaxlie.SO3(wxyz=wxyz).as_matrix()


def quaternion_from_matrix(m: jax.Array) -> jax.Array:
    """[..., 3, 3] rotation matrices -> [..., 4] unit quaternions wxyz."""
    flat = jax.vmap(lambda r: jaxlie.SO3.from_matrix(r).wxyz)(m.reshape(-1, 3, 3))
    return flat.reshape(m.shape[:-2] + (4,))


def reframe(pose7: jax.Array, frames: jax.Array) -> jax.Array:
    """Poses [..., 7] of an object whose cloud was read in ``frames`` [..., 3, 3] (points
    ``H p``; leading axes broadcast) -> the same placements of the object as written before:
    rotation R H, translation unchanged."""
    rot = quaternion_to_matrix(pose7[..., 3:]) @ frames
    return jnp.concatenate([pose7[..., :3], quaternion_from_matrix(rot)], axis=-1)


def move_origin(pose7: jax.Array, offset: jax.Array) -> jax.Array:
    """Poses [..., 7] -> the same placements of the frame whose origin sits at ``offset`` [3]
    (or [..., 3], one per pose) in the object frame (points ``p - offset``): t + R offset, q
    unchanged (``omnihang_jax.paths.move_origin`` on the host)."""
    rot = quaternion_to_matrix(pose7[..., 3:])
    moved = pose7[..., :3] + jnp.einsum("...ij,...j->...i", rot, offset)
    return jnp.concatenate([moved, pose7[..., 3:]], axis=-1)


def super_fibonacci(n: int) -> np.ndarray:
    """[n, 4] unit quaternions (wxyz) spread evenly over SO(3) (Alexa, "Super-Fibonacci
    Spirals", CVPR 2022)."""
    phi, psi = np.sqrt(2.0), 1.533751168755204288118041
    s = np.arange(n) + 0.5
    r, big = np.sqrt(s / n), np.sqrt(1.0 - s / n)
    a, b = 2 * np.pi * s / phi, 2 * np.pi * s / psi
    xyzw = np.stack([r * np.sin(a), r * np.cos(a), big * np.sin(b), big * np.cos(b)], axis=1)
    return xyzw[:, [3, 0, 1, 2]]


def principal_frame(points: jax.Array) -> jax.Array:
    """[N, 3] -> [3, 3] the cloud's principal axes as columns, largest spread first, each of
    the first two pointing where the cloud's third moment along it is positive, the third
    their cross product: a frame that turns with the cloud (``P -> A P``) wherever the
    spreads and the moments are distinct."""
    centred = points - points.mean(0)
    _, axes = jnp.linalg.eigh(centred.T @ centred)  # ascending
    axes = axes[:, ::-1]
    skew = jnp.sum((centred @ axes) ** 3, axis=0)
    axes = axes * jnp.where(skew < 0, -1.0, 1.0).astype(axes.dtype)
    return axes.at[:, 2].set(jnp.cross(axes[:, 0], axes[:, 1]))


def box_centre(points: jax.Array) -> jax.Array:
    """[N, 3] -> [3] the centre of the cloud's box along its principal axes: it turns and moves
    with the cloud (``omnihang_jax.paths.principal_box`` on the host)."""
    mean = points.mean(0)
    centred = points - mean
    # the principal axes from the 3 x 3 scatter (eigh): batched SVDs of [N, 3] clouds are slow
    # on a GPU and the box's centre does not depend on the axes' order or signs
    _, axes = jnp.linalg.eigh(centred.T @ centred)  # columns
    proj = centred @ axes
    return mean + 0.5 * (proj.min(0) + proj.max(0)) @ axes.T
