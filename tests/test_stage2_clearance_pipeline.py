"""The Stage-2 clearance through the Stages 1-3 code: ``pipeline.make_hang_pipeline`` takes the
support normals from its clouds."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from omnihang_jax import pipeline, stage3
from omnihang_jax.pipeline import HangOutput
from omnihang_jax.predict import Predictor, make_predict
from omnihang_jax.stage1 import STAGE1_TINY, make_stage1
from omnihang_jax.stage2 import STAGE2_TINY, clearance_offset, make_stage2
from omnihang_jax.stage3 import CEMConfig, PairClouds

C = 0.006  # m
PIPE = pipeline.PipelineConfig(
    num_proposals=2, cem=CEMConfig(population=8, iterations=2, elites=3),
    starts=("stage2", "stage1"),
)  # fmt: skip


def _tiny2(clearance: float):
    return dataclasses.replace(STAGE2_TINY, clearance=clearance)


@pytest.fixture(scope="module")
def params():
    return {
        "stage1": make_stage1(STAGE1_TINY).init(jax.random.key(0)),
        "stage2": make_stage2(STAGE2_TINY).init(jax.random.key(1)),
        "value": stage3.make_value(stage3.VALUE_TINY).init(jax.random.key(2)),
    }


def _plane_pairs(batch=2, n=128, m=128):
    """A 2-cm sphere over a flat support patch z = 0 (outward normals +z), per pair."""
    rng = np.random.default_rng(0)
    obj = rng.normal(size=(batch, n, 3)).astype(np.float32)
    obj /= np.linalg.norm(obj, axis=-1, keepdims=True)
    sup = np.zeros((batch, m, 3), np.float32)
    sup[..., :2] = rng.uniform(-0.05, 0.05, (batch, m, 2))
    sup_n = np.broadcast_to(np.float32([0, 0, 1]), (batch, m, 3)).copy()
    return PairClouds(0.02 * obj, obj, sup, sup_n)


def _old_pipeline(stage1_config, stage2_config, value_config, config):
    """make_hang_pipeline as it was before the support normals reached Stage 2."""
    pred_fn = make_predict(stage1_config, stage2_config)
    refine_fn = stage3.make_refiner(value_config, config.cem)

    def hang(params, key, clouds):
        k1, k3 = jax.random.split(key)
        pred = pred_fn(params["stage1"], params["stage2"], clouds.object_points,
                       clouds.support_points, k1, config.num_proposals)  # fmt: skip
        small = stage3.subsample_clouds(clouds, value_config)
        starts = {"stage1": pred.stage1_poses, "stage2": pred.stage2_poses}
        refined, scores, initial, best = {}, {}, {}, {}
        for i, name in enumerate(config.starts):
            res = refine_fn(params["value"], jax.random.fold_in(k3, i), small, starts[name])
            refined[name], scores[name] = res.poses, res.scores
            initial[name], best[name] = res.initial_scores, res.best
        first = config.starts[0]
        pose = jnp.take_along_axis(refined[first], best[first][:, None, None], axis=1)[:, 0]
        return HangOutput(pred.stage1_poses, pred.stage2_poses, refined, scores, initial, best,
                          pose)  # fmt: skip

    return hang


def _expected_offset(params, clouds, key, clearance):
    """The predictor's own clearance offset [B, K, 3] for the pipeline's Stage-1 key."""
    k1, _ = jax.random.split(key)
    pred = jax.jit(make_predict(STAGE1_TINY, _tiny2(clearance)), static_argnames="num_proposals")(
        params["stage1"], params["stage2"], clouds.object_points, clouds.support_points, k1,
        num_proposals=PIPE.num_proposals, support_normals=clouds.support_normals,
    )  # fmt: skip
    idx = np.asarray(pred.support_indices)  # [B, K, K3]
    normals = np.take_along_axis(
        np.asarray(clouds.support_normals)[:, None], idx[..., None], axis=2
    )  # [B, K, K3, 3]
    b, k, k3 = idx.shape
    off = clearance_offset(
        jnp.asarray(normals.reshape(b * k, k3, 3)),
        jnp.asarray(pred.weight).reshape(b * k, k3),
        clearance,
    )
    return np.asarray(off).reshape(b, k, 3), pred


@pytest.mark.slow  # three more pipeline compilations (~40 s on 2 cores); a refactor guard
def test_pipeline_clearance_zero_is_the_output_before_the_normals(params):
    clouds = _plane_pairs()
    key = jax.random.key(5)
    old = jax.jit(_old_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, PIPE))
    new = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, PIPE))
    a, b = old(params, key, clouds), new(params, key, clouds)
    # the fields the old pipeline had (the new one also returns the ranked pool)
    for x, y in zip(jax.tree.leaves(a[:7]), jax.tree.leaves(b[:7]), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))  # bit-identical


@pytest.mark.slow  # a second pipeline compile (~25 s on 2 cores)
def test_pipeline_clearance_c_moves_stage2_exactly(params):
    clouds = _plane_pairs()
    key = jax.random.key(5)
    new = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, PIPE))
    b = new(params, key, clouds)
    moved = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, _tiny2(C), stage3.VALUE_TINY, PIPE))
    m = moved(params, key, clouds)
    np.testing.assert_array_equal(np.asarray(m.stage1_poses), np.asarray(b.stage1_poses))
    np.testing.assert_array_equal(  # Stage 2 keeps the Stage-1 rotation
        np.asarray(m.stage2_poses)[..., 3:], np.asarray(b.stage2_poses)[..., 3:]
    )
    shift = np.asarray(m.stage2_poses)[..., :3] - np.asarray(b.stage2_poses)[..., :3]
    off, pred = _expected_offset(params, clouds, key, C)
    np.testing.assert_allclose(shift, off, atol=1e-7)  # exactly the predictor's offset
    np.testing.assert_allclose(shift, np.broadcast_to([0, 0, C], shift.shape), atol=1e-7)
    np.testing.assert_allclose(np.asarray(m.stage2_poses), pred.stage2_poses, atol=1e-7)
    assert np.isfinite(np.asarray(m.pose)).all()


def _fake_load_predictor(calls):
    def load(folder, seed=0, stage2_overrides=None):
        calls.append(stage2_overrides)
        p1 = make_stage1(STAGE1_TINY).init(jax.random.key(0))
        p2 = make_stage2(STAGE2_TINY).init(jax.random.key(1))
        config2 = dataclasses.replace(STAGE2_TINY, **(stage2_overrides or {}))
        return Predictor(STAGE1_TINY, p1, config2, p2, seed=seed)

    return load


def _fake_load_value(folder):
    return stage3.VALUE_TINY, stage3.make_value(stage3.VALUE_TINY).init(jax.random.key(2))
