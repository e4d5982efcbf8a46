"""Objects in any frame (``pipeline.PipelineConfig.frames``): the frame hypotheses cover SO(3),
proposals made in a hypothesis frame turn back to the same placements of the cloud as given,
the box centre moves with the cloud, and V picks CEM's starts among every frame's proposals."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from omnihang_jax import paths, pipeline, stage3
from omnihang_jax import poses as P
from omnihang_jax.stage1 import STAGE1_TINY, make_stage1
from omnihang_jax.stage2 import STAGE2_TINY, make_stage2


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[A, B] rotation angles (rad) between the wxyz quaternions of a [A, 4] and b [B, 4]."""
    return 2 * np.arccos(np.clip(np.abs(a @ b.T), 0, 1))


def test_the_frame_hypotheses_cover_so3():
    """32 super-Fibonacci rotations: unit quaternions, no two within 40 degrees, and every
    rotation within 75 degrees of one of them (a random set of 32 leaves gaps over 90)."""
    q = P.super_fibonacci(32)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    pair = _angles(q, q) + np.eye(32) * 10
    assert pair.min() > np.radians(40)
    probes = Rotation.random(2000, random_state=0).as_quat()[:, [3, 0, 1, 2]]
    assert _angles(probes, q).min(1).max() < np.radians(75)
    rand = Rotation.random(32, random_state=1).as_quat()[:, [3, 0, 1, 2]]
    assert _angles(probes, rand).min(1).max() > np.radians(90)
    frames = np.asarray(pipeline.frame_hypotheses(jax.random.key(0), 32))
    np.testing.assert_allclose(frames @ frames.transpose(0, 2, 1), np.broadcast_to(np.eye(3),
                               (32, 3, 3)), atol=1e-5)  # fmt: skip
    np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-5)
    other = np.asarray(pipeline.frame_hypotheses(jax.random.key(1), 32))
    assert not np.allclose(frames, other, atol=1e-3)  # each pair its own turn of the set


def test_a_pose_found_in_a_hypothesis_frame_turns_back_to_the_same_placement():
    """A pose of the cloud read in frame H (points H p) and its turned-back pose place every
    point in the same spot (``poses.reframe``); ``poses.move_origin`` (JAX) agrees with the
    planner's host version."""
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3)) * 0.03
    frames = jnp.asarray(Rotation.random(3, random_state=2).as_matrix(), jnp.float32)
    q = Rotation.random(6, random_state=3).as_quat()[:, [3, 0, 1, 2]]
    poses = np.concatenate([rng.normal(size=(6, 3)) * 0.1, q], 1).reshape(3, 1, 2, 7)
    back = np.asarray(P.reframe(jnp.asarray(poses, jnp.float32), frames[:, None, None]))
    for m in range(3):
        for j in range(2):
            p, b = poses[m, 0, j], back[m, 0, j]
            seen = pts @ np.asarray(frames[m]).T  # the cloud read in frame m
            world = Rotation.from_quat(p[[4, 5, 6, 3]]).apply(seen) + p[:3]
            again = Rotation.from_quat(b[[4, 5, 6, 3]]).apply(pts) + b[:3]
            np.testing.assert_allclose(again, world, atol=1e-5)
    offset = np.array([0.01, -0.02, 0.03])
    host = paths.move_origin(poses.reshape(-1, 7), offset)
    dev = np.asarray(P.move_origin(jnp.asarray(poses.reshape(-1, 7)), jnp.asarray(offset)))
    np.testing.assert_allclose(dev, host, atol=1e-6)


def test_the_box_centre_moves_with_the_cloud():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(400, 3)) * [0.05, 0.02, 0.01] + [0.03, 0.0, -0.02]
    r = Rotation.random(random_state=4).as_matrix()
    c = np.asarray(P.box_centre(jnp.asarray(pts)))
    turned = np.asarray(P.box_centre(jnp.asarray(pts @ r.T + [0.1, 0.2, -0.05])))
    np.testing.assert_allclose(turned, r @ c + [0.1, 0.2, -0.05], atol=1e-6)
    np.testing.assert_allclose(c, paths.principal_box(pts)[0], atol=1e-6)


@pytest.mark.slow  # compiles tiny Stages 1-2 on 4 frames and V (~30 s on 2 cores)
def test_v_picks_the_starts_among_every_frames_proposals():
    """The Stage-1 starts are the K proposals of the pool (every frame's, turned back) that V
    scores highest on the first view; Stage 2 refines each of them (unit quaternions)."""
    cfg = dataclasses.replace(pipeline.PipelineConfig(num_proposals=2), frames=4)
    vcfg = stage3.VALUE_TINY
    params = {"stage1": make_stage1(STAGE1_TINY).init(jax.random.key(0)),
              "stage2": make_stage2(STAGE2_TINY).init(jax.random.key(1)),
              "value": stage3.make_value(vcfg).init(jax.random.key(2))}  # fmt: skip
    rng = np.random.default_rng(0)
    obj = (0.02 * rng.normal(size=(2, 128, 3))).astype(np.float32)
    sup = rng.uniform(-0.05, 0.05, (2, 128, 3)).astype(np.float32)
    normals = np.broadcast_to(np.float32([0, 0, 1]), (2, 128, 3))
    clouds = stage3.PairClouds(obj, normals, sup, normals)
    value = stage3.make_value(vcfg)
    fn = pipeline.make_frame_starts(STAGE1_TINY, STAGE2_TINY, value, cfg, vcfg)
    first, second, pool = jax.jit(fn)(params, jax.random.key(5), clouds)
    assert pool.shape == (2, 8, 7) and first.shape == second.shape == (2, 2, 7)
    small = stage3.subset_clouds(clouds, vcfg, 0, 1)
    score = np.asarray(jax.vmap(value.score, in_axes=(None, 0, 0))(params["value"], small, pool))
    for b in range(2):
        want = np.asarray(pool)[b][np.argsort(-score[b])[:2]]
        np.testing.assert_allclose(np.asarray(first)[b], want, atol=1e-6)
    for poses in (pool, second):
        np.testing.assert_allclose(np.linalg.norm(np.asarray(poses)[..., 3:], axis=-1), 1.0,
                                   atol=1e-5)  # fmt: skip
