"""omnihang_jax.augment: the turned pair is the same physical pair; the train step uses it."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from omnihang_jax import augment, train
from omnihang_jax import poses as P
from omnihang_jax.data import HangSample


def _batch(b=3, n=16, m=20, d=4, seed=0):
    rng = np.random.default_rng(seed)
    quats = Rotation.random(b * d, random_state=seed).as_quat()  # xyzw
    poses = np.concatenate([rng.normal(0, 0.05, (b * d, 3)), np.roll(quats, 1, axis=1)], 1).reshape(
        b, d, 7
    )
    normals = rng.normal(size=(b, m, 3))
    return HangSample(
        object_points=rng.normal(0, 0.02, (b, n, 3)).astype(np.float32),
        object_normals=np.zeros((b, n, 3), np.float32),
        support_points=rng.normal(0, 0.05, (b, m, 3)).astype(np.float32),
        support_normals=(normals / np.linalg.norm(normals, axis=-1, keepdims=True)).astype(
            np.float32
        ),
        stable_poses=poses.astype(np.float32),
        pose_mask=np.ones((b, d), bool),
        object_contact_maps=np.zeros((b, d, n), np.float32),
        support_contact_maps=np.zeros((b, d, m), np.float32),
        contact_pairs=np.zeros((b, d, 2, 2), np.int32),
        contact_mask=np.zeros((b, d, 2), bool),
    )


def _posed(poses, points):
    """Object points placed by xyz + wxyz poses [B, D, 7] -> [B, D, N, 3]."""
    rot = Rotation.from_quat(np.roll(poses.reshape(-1, 7)[:, 3:], -1, axis=1)).as_matrix()
    rot = rot.reshape(poses.shape[:2] + (3, 3))
    return np.einsum("bdij,bnj->bdni", rot, points) + poses[:, :, None, :3]


def test_turn_is_a_rigid_motion_of_the_whole_pair():
    batch = _batch()
    out = augment.augment_pair(batch, jax.random.key(1), jitter=0.0, yaw=np.pi)
    np.testing.assert_array_equal(np.asarray(out.object_points), batch.object_points)
    # the support turned by some angle about z, the same for points and normals
    sup0, sup1 = batch.support_points, np.asarray(out.support_points)
    np.testing.assert_allclose(sup1[..., 2], sup0[..., 2], atol=1e-6)
    angle = np.arctan2(sup1[:, 0, 1], sup1[:, 0, 0]) - np.arctan2(sup0[:, 0, 1], sup0[:, 0, 0])
    rz = np.asarray(augment.yaw_matrix(jnp.asarray(angle, jnp.float32)))
    np.testing.assert_allclose(np.einsum("bij,bnj->bni", rz, sup0), sup1, atol=1e-5)
    np.testing.assert_allclose(
        np.einsum("bij,bnj->bni", rz, batch.support_normals), out.support_normals, atol=1e-5
    )
    # every stable pose turned with it: the posed object cloud is the turned posed cloud
    before = _posed(batch.stable_poses, batch.object_points)
    after = _posed(np.asarray(out.stable_poses), batch.object_points)
    np.testing.assert_allclose(np.einsum("bij,bdnj->bdni", rz, before), after, atol=1e-5)
    q = np.asarray(out.stable_poses)[..., 3:]
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-5)
    assert np.any(np.abs(angle) > 1e-3)


def test_jitter_and_off():
    batch = _batch()
    same = augment.augment_pair(batch, jax.random.key(0), 0.0, 0.0)
    assert same is batch
    out = augment.augment_pair(batch, jax.random.key(0), 0.002, 0.0)
    noise = np.asarray(out.object_points) - batch.object_points
    assert 0.001 < noise.std() < 0.003
    np.testing.assert_array_equal(np.asarray(out.stable_poses), batch.stable_poses)


@pytest.mark.slow  # augmentation options off by default; compiles a tiny step twice each
@pytest.mark.parametrize("stage, options", [
    ("1", dict(augment_jitter=0.003, augment_yaw=1.0)),
    ("2a", dict(augment_object_turn=32)),
])  # fmt: skip
def test_train_step_augments_when_asked(stage, options):
    config = train.WHERE_TINY
    batch = jax.tree.map(jnp.asarray, _batch(b=2, n=config.num_object_points, m=64, d=4))
    state = train.make_init_state(stage, config)(jax.random.key(0))
    key = jax.random.key(3)
    plain = jax.jit(train.make_train_step(stage, config))(state, batch, key)[1]["loss"]
    aug_cfg = dataclasses.replace(config, train=dataclasses.replace(config.train, **options))
    aug = jax.jit(train.make_train_step(stage, aug_cfg))(state, batch, key)[1]["loss"]
    assert np.isfinite(float(aug)) and float(aug) != float(plain)


def test_turn_passes_fields_a_stage1_pack_leaves_off():
    # data.PackedDataset(fields=...) gives the fields Stage 1 does not use as [B, 1] zeros
    batch = _batch()._replace(support_normals=np.zeros((3, 1), np.float32))
    out = augment.augment_pair(batch, jax.random.key(1), jitter=0.001, yaw=np.pi)
    np.testing.assert_array_equal(np.asarray(out.support_normals), batch.support_normals)
    assert not np.allclose(np.asarray(out.support_points)[..., :2], batch.support_points[..., :2])


@pytest.mark.parametrize("frames", [1, 32])
def test_object_turn_keeps_every_placement(frames):
    """``turn_object``: the object cloud (and normals) about its box centre in a turned frame,
    and each stable pose of the moved cloud places every object point where the original pose
    placed it; the support is untouched."""
    batch = _batch()
    normals = np.random.default_rng(2).normal(size=batch.object_points.shape)
    batch = batch._replace(object_normals=normals.astype(np.float32))
    out = augment.augment_pair(batch, jax.random.key(4), 0.0, 0.0, turn_object=frames)
    np.testing.assert_array_equal(np.asarray(out.support_points), batch.support_points)
    before = _posed(batch.stable_poses, batch.object_points)
    after = _posed(np.asarray(out.stable_poses), np.asarray(out.object_points))
    np.testing.assert_allclose(after, before, atol=1e-5)
    assert not np.allclose(np.asarray(out.object_points), batch.object_points, atol=1e-3)
    # the cloud is read about its box centre
    centres = np.asarray(jax.vmap(P.box_centre)(jnp.asarray(out.object_points)))
    np.testing.assert_allclose(centres, 0.0, atol=1e-5)
    # the points turned as the normals: the rotation that fits the normals fits the points
    n0, n1 = batch.object_normals[0], np.asarray(out.object_normals)[0]
    r, *_ = np.linalg.lstsq(n0, n1, rcond=None)
    p0, p1 = batch.object_points[0], np.asarray(out.object_points)[0]
    np.testing.assert_allclose((p0 - p0.mean(0)) @ r, p1 - p1.mean(0), atol=1e-4)
    q = np.asarray(out.stable_poses)[..., 3:]
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-5)


def test_residual_turns_stay_within_the_hypotheses_cover():
    """M = 32: what the nearest frame hypothesis leaves of a uniform frame is at most the
    cover's radius (about 73 degrees); M = 1: the uniform frame itself (angles up to 180)."""

    def angles(frames):
        r = np.asarray(augment.residual_turns(jax.random.key(0), 2000, frames))
        return np.degrees(np.arccos(np.clip((np.trace(r, axis1=1, axis2=2) - 1) / 2, -1, 1)))

    near, anywhere = angles(32), angles(1)
    assert near.max() < 75 and 30 < np.median(near) < 50
    assert anywhere.max() > 150 and np.median(anywhere) > 100
