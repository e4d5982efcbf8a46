"""The value state's near points (ValueConfig.support_near / object_near): the contact region
of the observed clouds at a higher density, for the answer's ranker (twenty-first session)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from omnihang_jax import refine, stage3

NEAR = dataclasses.replace(stage3.VALUE_TINY, support_near=16, object_near=8, near_pool=128)
IDENTITY = np.array([0, 0, 0, 1, 0, 0, 0], np.float32)


def _clouds(n=512, m=512, seed=0):
    rng = np.random.default_rng(seed)
    obj = rng.uniform(-0.02, 0.02, (n, 3)).astype(np.float32)  # a 4-cm cube at the origin
    sup = rng.uniform(-0.5, 0.5, (m, 3)).astype(np.float32)  # a 1-m cube around it
    normals = lambda k: np.tile(np.float32([0, 0, 1]), (k, 1))  # noqa: E731
    return stage3.PairClouds(obj, normals(n), sup, normals(m))


def test_subsample_index_adds_the_pool():
    assert len(stage3.subsample_index(4096, stage3.VALUE_TINY, "support")) == 64
    idx = stage3.subsample_index(4096, NEAR, "support")
    assert len(idx) == 64 - 16 + 128 and idx.max() < 4096
    assert len(stage3.subsample_index(4096, NEAR, "object")) == 64 - 8 + 128
    with pytest.raises(ValueError, match="support_near"):
        stage3.subsample_index(100, dataclasses.replace(NEAR, support_near=64), "support")


def test_near_points_are_the_nearest_of_the_pool():
    full = _clouds()
    small = stage3.subsample_clouds(jax.tree.map(jnp.asarray, full), NEAR)
    pose = IDENTITY.copy()
    pose[:3] = [0.1, 0.0, 0.0]  # the object moved 10 cm along x
    got = stage3.near_points(small, jnp.asarray(pose), NEAR)
    assert got.support_points.shape == (64, 3) and got.object_points.shape == (64, 3)
    # the 16 near support points: the pool points closest to the posed object
    pool = np.asarray(small.support_points[48:])
    anchors = (
        (np.arange(NEAR.near_anchors) * 56) // NEAR.near_anchors
        if NEAR.near_anchors < 56
        else np.arange(56)
    )
    obj_w = np.asarray(small.object_points[:56])[anchors] + pose[:3]
    d = np.min(np.linalg.norm(pool[:, None] - obj_w[None], axis=-1), axis=1)
    want = np.sort(d)[:16]
    got_near = np.asarray(got.support_points[48:])
    d_got = np.min(np.linalg.norm(got_near[:, None] - obj_w[None], axis=-1), axis=1)
    np.testing.assert_allclose(np.sort(d_got), want, atol=1e-6)
    # the evenly spaced part is unchanged; the object points stay in the object frame
    np.testing.assert_array_equal(got.support_points[:48], small.support_points[:48])
    assert np.abs(np.asarray(got.object_points)).max() <= 0.02 + 1e-6
    # without near points the clouds pass unchanged
    plain = stage3.subsample_clouds(jax.tree.map(jnp.asarray, full), stage3.VALUE_TINY)
    assert stage3.near_points(plain, jnp.asarray(pose), stage3.VALUE_TINY) is plain


@pytest.mark.slow  # ~22 s on 2 cores: compiles and trains a near-point ranker
def test_a_near_point_value_network_scores_and_trains_from_v(tmp_path):
    """The same encoder and head: V's weights load into the near-point network, which scores
    a pair's candidates (finite, and different from V's: it sees other points)."""
    value = stage3.make_value(stage3.VALUE_TINY)
    params = value.init(jax.random.key(0))
    refine.save_value(tmp_path / "v", NEAR, params)
    config, loaded = refine.load_value(tmp_path / "v")
    assert config == NEAR
    full = jax.tree.map(jnp.asarray, _clouds())
    poses = jnp.asarray(np.stack([IDENTITY] * 3) + np.float32([[0.03 * i, 0, 0, 0, 0, 0, 0]
                                                                for i in range(3)]))  # fmt: skip
    near = stage3.make_value(NEAR).score(loaded, stage3.subsample_clouds(full, NEAR), poses)
    plain = value.score(params, stage3.subsample_clouds(full, stage3.VALUE_TINY), poses)
    assert near.shape == (3,) and np.all(np.isfinite(near))
    assert not np.allclose(near, plain)


def test_old_value_configs_load_without_near_points():
    config, _ = refine.load_value("weights/rankers/listwise")
    assert config.support_near == 0 and config.object_near == 0
