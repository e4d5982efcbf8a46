"""Choosing the pipeline's answer among Stage 3's refined candidates.

The paper (facts file) evaluates "the candidate with the best final Stage-3 score": the
highest V. On the held-out pairs V's pick hangs in 55-57 % of pairs while *some* refined
candidate hangs in 75-82 %, and most of V's wrong picks start inside the support (690 of
842 failures of the eighth session's run are ``penetrating``, median 8 mm): V, which sees
512 + 512 subsampled points, cannot resolve millimetres. The observed clouds can: a
candidate whose posed object cloud has points more than ``depth`` behind the observed
support surface (and within ``radius`` of it sideways) is inside the support as far as the
camera can tell (the test of :class:`omnihang_jax.collision.GeometricConfig`, on the full
4,096-point clouds).

Rules (:class:`SelectConfig`):

* ``"value"``: the highest V (the paper's rule, ``SelectConfig()``).
* ``"value_clear"``: the highest V among candidates with at most ``max_points`` object points
  inside the observed support; when every candidate has more, the one with the fewest (ties
  by V). One key does both: ``score - 1e4 * max(count - max_points, 0)`` (log V lies in
  [-50, 0] in practice, so one extra inside point outweighs any V difference).

:data:`CHOSEN` is the rule chosen on validation objects (``experiments.rerank_stage3``, ninth
session): ``value_clear`` at depth 0.5 mm, radius 5 mm, no point inside, pooled over the
candidates refined from Stages 1 and 2 (``stage3.ANSWER_PIPELINE``); the pipeline's default
answer since the tenth session (held-out: results/hanging_success.json, docs/evaluation.md).

Both are pure: :func:`inside_counts` ([P] poses of one pair) and :func:`select_key`
broadcast over leading axes, so the jitted pipeline and the after-the-run study
(``experiments.rerank_stage3``) compute exactly the same numbers.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

__all__ = [
    "SelectConfig",
    "CHOSEN",
    "RULES",
    "INSIDE_GRID",
    "grid_key",
    "inside_counts",
    "inside_counts_grid",
    "support_inside_counts_grid",
    "select_key",
    "select",
]

RULES = ("value", "value_clear")
# the (depth, radius) settings (m) an evaluation records for every candidate
# (eval_pipeline's ``inside_counts``), so that rules can be chosen after the run
INSIDE_GRID = tuple((d, r) for d in (0.0005, 0.001, 0.002, 0.003) for r in (0.002, 0.003, 0.005))
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


# chosen on 345 validation-object pairs (results/rerank_stage3_val.json): 58.5 -> 68.9 %
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
    grid = ((depth, radius),)
    return inside_counts_grid(object_points, support_points, support_normals, poses, grid)[0]


def inside_counts_grid(
    object_points: jax.Array,
    support_points: jax.Array,
    support_normals: jax.Array,
    poses: jax.Array,
    grid=INSIDE_GRID,
) -> jax.Array:
    """:func:`inside_counts` for every (depth, radius) of ``grid`` (static) -> [G, P] int32;
    the nearest support points are found once."""
    from omnihang_jax import collision

    posed = collision.transform_points(poses, object_points)
    along, length = collision.nearest_support_offsets(posed, support_points, support_normals)
    return jnp.stack([collision.inside_points(along, length, d, r) for d, r in grid])


def support_inside_counts_grid(
    object_points: jax.Array,
    object_normals: jax.Array,
    support_points: jax.Array,
    poses: jax.Array,
    grid=INSIDE_GRID,
) -> jax.Array:
    """The symmetric test: observed SUPPORT points more than ``depth`` behind the posed
    observed OBJECT surface (its nearest point's outward normal) and within ``radius`` of it
    sideways, for every (depth, radius) of ``grid`` -> [G, P] int32. One pair: object
    points / normals [N, 3] (object frame), support points [M, 3], poses [P, 7]. Catches a
    thin support (a rod, a hook's tip) passing through the object where the object's points
    straddle it and none lies behind the observed support surface."""
    from omnihang_jax import collision

    rot = collision.quaternion_matrix(poses[:, 3:])  # [P, 3, 3] object -> support
    local = jnp.einsum("pji,pmj->pmi", rot, support_points[None] - poses[:, None, :3])
    along, length = collision.nearest_support_offsets(local, object_points, object_normals)
    return jnp.stack([collision.inside_points(along, length, d, r) for d, r in grid])


def grid_key(depth: float, radius: float) -> str:
    """Key of a (depth, radius) setting in recorded ``inside_counts``: "0.001_0.003"."""
    return f"{depth:g}_{radius:g}"


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
