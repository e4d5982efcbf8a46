"""The answer rule (omnihang_jax.selection) and the views inside the Stages 1-3 pipeline
(``pipeline.make_hang_pipeline``): "value_clear" picks by the score and the observed-cloud inside
counts, per start and pooled; each view's candidates are a one-view pipeline's on that subsample
of the clouds; the fused pipeline gives the sequential one's candidates. The tiny networks and
clouds here are shared by tests.test_rank_values and tests.test_train_ranker."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from omnihang_jax import pipeline, selection, stage3
from omnihang_jax.stage1 import STAGE1_TINY, make_stage1
from omnihang_jax.stage2 import STAGE2_TINY, make_stage2
from omnihang_jax.stage3 import CEMConfig, PairClouds

CFG = stage3.VALUE_TINY  # 64 + 64 state points
PIPE = pipeline.PipelineConfig(
    num_proposals=2, cem=CEMConfig(population=8, iterations=2, elites=3),
    starts=("stage2", "stage1"),
)  # fmt: skip
CLEAR = selection.SelectConfig("value_clear", depth=0.001, radius=0.003, max_points=0)


@pytest.fixture(scope="module")
def params():
    return {
        "stage1": jax.jit(make_stage1(STAGE1_TINY).init)(jax.random.key(0)),
        "stage2": jax.jit(make_stage2(STAGE2_TINY).init)(jax.random.key(1)),
        "value": jax.jit(stage3.make_value(CFG).init)(jax.random.key(2)),
    }


def plane_pairs(batch=2, n=128, m=128):
    """A 2-cm sphere over a flat support patch z = 0 (outward normals +z), per pair."""
    rng = np.random.default_rng(0)
    obj = rng.normal(size=(batch, n, 3)).astype(np.float32)
    obj /= np.linalg.norm(obj, axis=-1, keepdims=True)
    sup = np.zeros((batch, m, 3), np.float32)
    sup[..., :2] = rng.uniform(-0.05, 0.05, (batch, m, 2))
    sup_n = np.broadcast_to(np.float32([0, 0, 1]), (batch, m, 3)).copy()
    return PairClouds(0.02 * obj, obj, sup, sup_n)


def _counts(clouds, poses, config):
    return np.stack([
        np.asarray(selection.inside_counts(
            clouds.object_points[i], clouds.support_points[i], clouds.support_normals[i],
            poses[i], config.depth, config.radius))
        for i in range(len(poses))
    ])  # fmt: skip


@pytest.mark.slow  # ~55 s on 2 cores (compiles the tiny Stages 1-3)
def test_pipeline_value_clear_per_start_and_pooled(params):
    """One compiled pipeline (CLEAR, pooled starts; the paper's rule is test_stage3's): each
    start's pick is the rule over its own refined candidates, the answer the rule over all, and
    the ranked pool is every candidate in the order of the rule's key."""
    clouds = plane_pairs()
    cfg = dataclasses.replace(PIPE, select=CLEAR, pool_starts=True)
    out = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, CFG, cfg))(
        params, jax.random.key(8), clouds
    )
    for name in cfg.starts:
        counts = _counts(clouds, np.asarray(out.refined[name]), CLEAR)
        want = np.asarray(selection.select(out.scores[name], counts, CLEAR))
        np.testing.assert_array_equal(np.asarray(out.best[name]), want)
    cands = np.concatenate([np.asarray(out.refined[n]) for n in cfg.starts], axis=1)
    scores = np.concatenate([np.asarray(out.scores[n]) for n in cfg.starts], axis=1)
    keys = np.asarray(selection.select_key(scores, _counts(clouds, cands, CLEAR), CLEAR))
    pick = keys.argmax(1)
    np.testing.assert_array_equal(np.asarray(out.pose), cands[np.arange(len(cands)), pick])
    np.testing.assert_allclose(np.asarray(out.ranked_keys), -np.sort(-keys, axis=1), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(out.ranked[:, 0]), np.asarray(out.pose))


def test_subset_zero_is_the_subsample_and_the_others_are_other_points():
    rng = np.random.default_rng(0)
    obj = rng.normal(scale=0.01, size=(2, 256, 3)).astype(np.float32)
    sup = rng.normal(scale=0.03, size=(2, 256, 3)).astype(np.float32)
    clouds = PairClouds(obj, obj / np.linalg.norm(obj, axis=-1, keepdims=True), sup, sup)
    base = stage3.subsample_clouds(clouds, CFG)
    for a, b in zip(base, stage3.subset_clouds(clouds, CFG, 0, 4), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    seen = []
    for j in range(4):
        sub = stage3.subset_clouds(clouds, CFG, j, 4)
        assert sub.object_points.shape == base.object_points.shape
        rows = {tuple(p) for p in np.asarray(sub.object_points[0])}
        assert rows <= {tuple(p) for p in clouds.object_points[0]}  # points of the cloud
        # each point keeps its own normal through the roll
        idx = [int(np.flatnonzero((clouds.object_points[0] == p).all(1))[0])
               for p in np.asarray(sub.object_points[0])]  # fmt: skip
        np.testing.assert_array_equal(
            np.asarray(sub.object_normals[0]), clouds.object_normals[0][idx]
        )
        seen.append(rows)
    assert all(not (seen[i] & seen[j]) for i in range(4) for j in range(i))  # disjoint subsets
    with pytest.raises(ValueError, match="subset 4 of 4"):
        stage3.subset_clouds(clouds, CFG, 4, 4)


@pytest.mark.slow  # 25-45 s on 2 cores
def test_two_view_pipeline_picks_among_both_views_candidates(params):
    """PipelineConfig.views = ((0, 1), (1, 2)): CEM and the ranking run on each subsample with
    the same keys; each view's candidates equal a one-view pipeline's on that subsample, and the
    answer is the best of all of them by the rule's key."""
    clouds = plane_pairs(n=256, m=256)
    v2 = jax.jit(stage3.make_value(CFG).init)(jax.random.key(7))
    base = dataclasses.replace(PIPE, select=selection.CHOSEN, pool_starts=True, rank_values=1,
                               rank_with_value=False, fuse=False)  # fmt: skip
    prm = {**params, "rank_values": [v2]}
    key = jax.random.key(3)
    outs = {}
    for views in (((0, 1),), ((1, 2),), ((0, 1), (1, 2))):
        cfg = dataclasses.replace(base, views=views)
        outs[views] = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, CFG, cfg))(
            prm, key, clouds
        )
    one, other, both = outs[((0, 1),)], outs[((1, 2),)], outs[((0, 1), (1, 2))]
    k = base.num_proposals
    for name in base.starts:
        np.testing.assert_allclose(
            np.asarray(both.refined[name][:, :k]), np.asarray(one.refined[name]), atol=1e-6
        )
        np.testing.assert_allclose(
            np.asarray(both.refined[name][:, k:]), np.asarray(other.refined[name]), atol=1e-6
        )
        np.testing.assert_allclose(
            np.asarray(both.scores[name][:, k:]), np.asarray(other.scores[name]), atol=1e-5
        )
    assert not np.allclose(np.asarray(one.scores["stage2"]), np.asarray(other.scores["stage2"]))
    full = jax.tree.map(np.asarray, clouds)
    cands = np.concatenate([np.asarray(both.refined[n]) for n in base.starts], axis=1)
    scores = np.concatenate([np.asarray(both.scores[n]) for n in base.starts], axis=1)
    pick = np.asarray(selection.select(scores, _counts(full, cands, selection.CHOSEN),
                                       selection.CHOSEN))  # fmt: skip
    np.testing.assert_allclose(np.asarray(both.pose), cands[np.arange(len(cands)), pick], atol=1e-6)


@pytest.mark.slow  # 75-90 s on 2 cores
def test_fused_pipeline_gives_the_sequential_pipelines_candidates(params):
    """PipelineConfig.fuse: one CEM over every view and start and one ranking pass (two rankers,
    one with near points) give the candidates, scores and answer of one CEM per view and start
    (two views, two starts: the stacking on both axes)."""
    views = ((0, 1), (1, 2))
    clouds = plane_pairs(n=256, m=256)
    near = dataclasses.replace(CFG, support_near=16, object_near=16)
    rankers = [jax.jit(stage3.make_value(CFG).init)(jax.random.key(7)),
               jax.jit(stage3.make_value(near).init)(jax.random.key(8))]  # fmt: skip
    base = dataclasses.replace(PIPE, select=selection.CHOSEN, pool_starts=True, rank_values=2,
                               rank_with_value=False, views=views)  # fmt: skip
    prm = {**params, "rank_values": rankers}
    key = jax.random.key(5)
    outs = {
        fuse: jax.jit(pipeline.make_hang_pipeline(
            STAGE1_TINY, STAGE2_TINY, CFG, dataclasses.replace(base, fuse=fuse), [CFG, near]
        ))(prm, key, clouds)
        for fuse in (False, True)
    }  # fmt: skip
    seq, fused = outs[False], outs[True]
    for name in base.starts:
        assert fused.refined[name].shape == (2, len(views) * base.num_proposals, 7)
        np.testing.assert_allclose(np.asarray(fused.refined[name]),
                                   np.asarray(seq.refined[name]), atol=1e-5)  # fmt: skip
        np.testing.assert_allclose(np.asarray(fused.scores[name]),
                                   np.asarray(seq.scores[name]), atol=1e-4)  # fmt: skip
        np.testing.assert_allclose(np.asarray(fused.initial_scores[name]),
                                   np.asarray(seq.initial_scores[name]), atol=1e-4)  # fmt: skip
    np.testing.assert_allclose(np.asarray(fused.pose), np.asarray(seq.pose), atol=1e-5)
