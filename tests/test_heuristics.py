"""The observed-cloud penetration heuristic: a ball sunk into a wall scores above one resting
on it, proposals are ranked least-penetrating first, and the evaluation's ranked predictor
puts the heuristic's pick in front."""

from __future__ import annotations

import numpy as np

from omnihang_jax import evaluate, heuristics
from omnihang_jax.data import HangSample


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


def test_ranked_predictor_puts_the_clear_proposal_first():
    ball, support, normals = _clouds(np.random.default_rng(2))
    sample = HangSample(
        object_points=ball,
        object_normals=ball,
        support_points=support,
        support_normals=normals,
        stable_poses=_pose(0.02)[None],
        pose_mask=np.ones(1, bool),
        object_contact_maps=np.zeros((1, 500), np.float32),
        support_contact_maps=np.zeros((1, 2000), np.float32),
        contact_pairs=np.zeros((1, 1, 2), np.int32),
        contact_mask=np.zeros((1, 1), bool),
    )
    sunk, clear = _pose(0.01), _pose(0.025)

    def predict(sample, meta):
        return evaluate.PairPrediction(np.stack([sunk, clear]), np.stack([clear, sunk]))

    out = evaluate.ranked_fn(predict, object_stride=1)(sample, {"pair_index": 0})
    np.testing.assert_array_equal(out.stage1_poses[0], clear)
    np.testing.assert_array_equal(out.stage2_poses[0], clear)


def test_pose_errors_default_beside_their_results():
    assert evaluate.default_errors_path("r/hanging_success.json").name == "pose_errors.json"
    assert (
        evaluate.default_errors_path("r/hanging_success_demo.json").name == "pose_errors_demo.json"
    )
    assert evaluate.default_errors_path("r/x.json").name == "x.pose_errors.json"


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


def test_spread_per_category_is_balanced_and_ordered():
    from pathlib import Path

    names = [f"{i:05d}_bag_{i % 3:04d}__hook_0000.npz" for i in range(10)]
    names += [f"{i:05d}_clothes_hanger_0001__hook_0000.npz" for i in range(10, 12)]
    got = [f.name for f in evaluate.spread_per_category([Path(n) for n in names], 3)]
    assert got == sorted(got) and len(got) == 5
    assert [n for n in got if "_bag_" in n] == [names[0], names[3], names[6]]
