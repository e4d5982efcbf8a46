"""The observed-cloud penetration heuristic: a ball sunk into a wall scores above one resting
on it, proposals are ranked least-penetrating first, and the evaluation's ranked predictor
puts the heuristic's pick in front."""

from __future__ import annotations

import numpy as np

from omnihang_jax import heuristics


def _clouds(rng):
    # the observed support: the face z = 0 of a slab, normals +z (towards the camera)
    xy = rng.uniform(-0.1, 0.1, size=(2000, 2))
    support = np.concatenate([xy, np.zeros((2000, 1))], axis=1).astype(np.float32)
    normals = np.tile(np.float32([0, 0, 1]), (2000, 1))
    d = rng.normal(size=(500, 3))
    ball = (0.02 * d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    return ball, support, normals


def _pose(z):
    return np.float32([0.0, 0.0, z, 1.0, 0.0, 0.0, 0.0])


def test_sunk_ball_scores_above_resting_ball_and_far_points_do_not_count():
    ball, support, normals = _clouds(np.random.default_rng(0))
    resting = heuristics.penetration_score(ball, support, normals, _pose(0.0205))
    sunk = heuristics.penetration_score(ball, support, normals, _pose(0.012))
    deep = heuristics.penetration_score(ball, support, normals, _pose(-0.05))
    assert float(resting) == 0.0
    assert 0.05 < float(sunk) < 0.5
    # wholly behind the visible face, farther than the window: not counted (partial view)
    assert float(deep) == 0.0


def test_rank_by_penetration_orders_least_first_and_is_stable():
    ball, support, normals = _clouds(np.random.default_rng(1))
    poses = np.stack([_pose(0.012), _pose(0.03), _pose(0.005), _pose(0.04)])
    order, scores = heuristics.rank_by_penetration(ball, support, normals, poses)
    assert scores[1] == scores[3] == 0.0 and scores[2] > scores[0] > 0
    assert np.asarray(order).tolist() == [1, 3, 0, 2]


def test_separate_backs_a_sunken_pose_out_and_leaves_a_free_one():
    """A flat support patch (normal +z) and an object patch: sunk 1 cm into it, separate
    moves it up until nothing is inside; a pose above the surface is left unchanged."""
    g = np.stack(np.meshgrid(np.linspace(-0.03, 0.03, 13), np.linspace(-0.03, 0.03, 13)), -1)
    g = g.reshape(-1, 2)
    sup = np.concatenate([g, np.zeros((len(g), 1))], 1).astype(np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (len(sup), 1))
    obj = np.concatenate([g * 0.5, np.zeros((len(g), 1))], 1).astype(np.float32)
    sunk = np.float32([0, 0, -0.01, 1, 0, 0, 0])
    assert float(heuristics.penetration_score(obj, sup, nrm, sunk)) > 0.9
    pose, shift, score = heuristics.separate(obj, sup, nrm, sunk)
    assert float(score) <= 0.01 and 0.008 <= float(shift) <= 0.014
    np.testing.assert_allclose(np.asarray(pose)[:2], 0.0, atol=1e-6)  # straight up
    np.testing.assert_array_equal(np.asarray(pose)[3:], sunk[3:])  # rotation kept
    free = np.float32([0, 0, 0.005, 1, 0, 0, 0])
    pose, shift, _ = heuristics.separate(obj, sup, nrm, free)
    assert float(shift) == 0.0
    np.testing.assert_array_equal(np.asarray(pose), free)
