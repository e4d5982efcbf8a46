"""Vector Neuron layers (Deng et al., "Vector Neurons: a general framework for SO(3)-equivariant
networks", ICCV 2021): features are lists of 3-vectors, ``[..., C, 3]``, and every layer commutes
with a rotation of its input, so a network built from them turns its output with its input by
construction instead of by training on turned copies.

- :class:`VNLinear`: ``W V`` over the channel axis (no bias: a bias would not turn).
- :class:`VNLeakyReLU`: a learned direction ``k = U V`` per channel; the part of ``q = W V``
  pointing against ``k`` is projected out (leaky by ``negative_slope``).
- :func:`edge_features`: the k nearest neighbours of each point as three vector channels
  ``(x_j - x_i, x_i, x_i x x_j)`` (VN-DGCNN's first layer), all of which turn with the cloud.
- :class:`VNInvariant`: rotation-invariant features ``V T^T`` against a learned equivariant frame
  ``T`` (3 channels), for the heads whose outputs must not turn (scores).
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

__all__ = ["VNInvariant", "VNLeakyReLU", "VNLinear", "VNLinearReLU", "edge_features"]

EPS = 1e-6


class VNLinear(nn.Module):
    """[..., C_in, 3] -> [..., features, 3]."""

    features: int

    @nn.compact
    def __call__(self, v: jax.Array) -> jax.Array:
        w = self.param(
            "kernel", nn.initializers.lecun_normal(), (v.shape[-2], self.features), jnp.float32
        )
        return jnp.einsum("...ci,co->...oi", v, w)


class VNLeakyReLU(nn.Module):
    """The vector ReLU: q where q . k >= 0, else q minus its component along k."""

    negative_slope: float = 0.2

    @nn.compact
    def __call__(self, q: jax.Array) -> jax.Array:
        k = VNLinear(q.shape[-2], name="direction")(q)
        dot = jnp.sum(q * k, axis=-1, keepdims=True)
        k_sq = jnp.sum(k * k, axis=-1, keepdims=True)
        projected = q - (dot / (k_sq + EPS)) * k
        relu = jnp.where(dot >= 0, q, projected)
        return self.negative_slope * q + (1 - self.negative_slope) * relu


class VNLinearReLU(nn.Module):
    features: int
    negative_slope: float = 0.2

    @nn.compact
    def __call__(self, v: jax.Array) -> jax.Array:
        return VNLeakyReLU(self.negative_slope)(VNLinear(self.features)(v))


class VNInvariant(nn.Module):
    """[..., C, 3] -> [..., C * 3] invariant: the features in a frame that turns with them."""

    @nn.compact
    def __call__(self, v: jax.Array) -> jax.Array:
        t = VNLinear(3, name="frame")(VNLinearReLU(max(v.shape[-2] // 2, 3))(v))  # [..., 3, 3]
        inv = jnp.einsum("...ci,...ti->...ct", v, t)
        return inv.reshape(*inv.shape[:-2], -1)


def edge_features(points: jax.Array, k: int) -> jax.Array:
    """points [B, N, 3] (centred) -> [B, N, k, 3, 3]: per point and neighbour (its own k nearest,
    itself included) the channels (x_j - x_i, x_i, x_i x x_j)."""
    d2 = jnp.sum((points[:, :, None] - points[:, None]) ** 2, axis=-1)
    _, idx = jax.lax.top_k(-jax.lax.stop_gradient(d2), k)  # [B, N, k]
    nb = jax.vmap(lambda p, i: p[i])(points, idx)  # [B, N, k, 3]
    xi = jnp.broadcast_to(points[:, :, None], nb.shape)
    return jnp.stack([nb - xi, xi, jnp.cross(xi, nb)], axis=-2)
