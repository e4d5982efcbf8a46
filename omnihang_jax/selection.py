"""Choosing the where-to-hang answer among Stage 3's refined candidates.

The paper evaluates "the candidate with the best final Stage-3 score": the highest V. V sees
512 + 512 subsampled points and cannot resolve millimetres, and most of its wrong picks start
inside the support. The observed clouds can: a candidate whose posed object cloud has points
more than ``depth`` behind the observed support surface (and within ``radius`` of it sideways)
is inside the support as far as the camera can tell (the test of
:class:`omnihang_jax.collision.GeometricConfig`, on the full 4,096-point clouds).

Rules (:class:`SelectConfig`):

* ``"value"``: the highest score (the paper's rule, ``SelectConfig()``).
* ``"value_clear"``: the highest score among candidates with at most ``max_points`` object
  points inside the observed support; when every candidate has more, the one with the fewest
  (ties by score). One key does both: ``score - 1e4 * max(count - max_points, 0)`` (log V lies
  in [-50, 0] in practice, so one extra inside point outweighs any score difference).

:data:`CHOSEN` is the default answer's rule (``pipeline.ANSWER_PIPELINE``), chosen on the
validation objects: ``value_clear`` at depth 0.5 mm, radius 5 mm, no point inside.

Both functions are pure: :func:`inside_counts` ([P] poses of one pair) and :func:`select_key`
broadcast over leading axes, so the jitted pipeline and host-side code (the rankers' pools,
``omnihang_jax.pools``) compute exactly the same numbers.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

__all__ = ["CHOSEN", "RULES", "SelectConfig", "inside_counts", "select", "select_key"]

RULES = ("value", "value_clear")
# weight of one inside point over log V in "value_clear" (lexicographic in practice)
_INSIDE_WEIGHT = 1e4


@dataclasses.dataclass(frozen=True)
class SelectConfig:
    """How the pipeline picks its answer among the refined candidates (module docstring).
    ``depth`` / ``radius`` (m): the observed-cloud test's; ``max_points``: inside points a
    candidate may have and still count as clear."""

    rule: str = "value"
    depth: float = 0.001
    radius: float = 0.003
    max_points: int = 0

    def __post_init__(self):
        if self.rule not in RULES:
            raise ValueError(f"SelectConfig.rule must be one of {RULES}, got {self.rule!r}")
        if self.depth < 0 or self.radius <= 0 or self.max_points < 0:
            raise ValueError(
                f"SelectConfig needs depth >= 0, radius > 0, max_points >= 0; got depth "
                f"{self.depth}, radius {self.radius}, max_points {self.max_points}"
            )


# the default answer's rule, chosen on the validation objects (docs/where.md)
CHOSEN = SelectConfig("value_clear", depth=0.0005, radius=0.005, max_points=0)


def inside_counts(
    object_points: jax.Array,
    support_points: jax.Array,
    support_normals: jax.Array,
    poses: jax.Array,
    depth: float,
    radius: float,
) -> jax.Array:
    """One pair: object_points [N, 3] (object frame), support_points / support_normals
    [M, 3] (support frame, unit outward normals), poses [P, 7] (xyz + wxyz) -> [P] int32:
    object points more than ``depth`` behind the nearest observed support point's surface
    and within ``radius`` of it sideways (``collision.inside_points``)."""
    from omnihang_jax import collision

    posed = collision.transform_points(poses, object_points)
    along, length = collision.nearest_support_offsets(posed, support_points, support_normals)
    return collision.inside_points(along, length, depth, radius)


def select_key(scores: jax.Array, counts: jax.Array, config: SelectConfig) -> jax.Array:
    """[..., P] final scores (log V) and inside counts -> [..., P] keys; the answer is the
    argmax over the last axis."""
    if config.rule == "value":
        return scores
    excess = jnp.maximum(counts - config.max_points, 0).astype(scores.dtype)
    return scores - _INSIDE_WEIGHT * excess


def select(scores: jax.Array, counts: jax.Array, config: SelectConfig) -> jax.Array:
    """[..., P] -> [...] int32 index of the answer."""
    return jnp.argmax(select_key(scores, counts, config), axis=-1)
