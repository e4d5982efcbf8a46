"""The completion-aware NCE (twenty-eighth session): its input clouds are half observed, half
the shape-completion networks' carved prediction; training and the planner build the same
clouds, the batched prediction equals the per-pair one, the cache is reused, and a planner
that is not given the predicted points fails with a clear error."""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from omnihang_jax import collision, completion

from .test_completion import TINY_NET


def _nets():
    init, _ = completion.make_completion(TINY_NET)
    params = init(jax.random.key(3))
    return {
        "object": (TINY_NET, params),
        "support": (dataclasses.replace(TINY_NET, kind="support"), params),
    }


def _sphere_half(rng, n, centre, towards_y=-1.0):
    u = rng.normal(size=(4 * n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 1] * towards_y > 0][:n]
    return (0.04 * u + centre).astype(np.float32)


def test_completed_cloud_is_half_observed_half_predicted_and_fixed():
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(101, 3)).astype(np.float32)
    pred = rng.normal(size=(40, 3)).astype(np.float32) + 10.0
    c = completion.completed_cloud(obs, pred)
    assert c.shape == obs.shape
    n_obs = 101 - 101 // 2
    assert np.isin(c[:n_obs], obs).all(axis=1).all() and len(np.unique(c[:n_obs], axis=0)) == n_obs
    assert (c[n_obs:] > 5).all()  # the rest are predicted points (with replacement: 50 of 40)
    np.testing.assert_array_equal(c, completion.completed_cloud(obs, pred))  # fixed subsets
    # carving left nothing: observed points only, all distinct
    c0 = completion.completed_cloud(obs, np.zeros((0, 3)))
    assert c0.shape == obs.shape and len(np.unique(c0, axis=0)) == 101
    with pytest.raises(ValueError, match=r"\[N>1, 3\]"):
        completion.completed_cloud(obs[:1], pred)


def test_batched_prediction_equals_one_pair_at_a_time():
    nets = _nets()
    rng = np.random.default_rng(1)
    objects = np.stack([_sphere_half(rng, 300, [0, 0, 0]) for _ in range(5)])
    supports = np.stack([_sphere_half(rng, 300, [0, 0.1, 0.2]) for _ in range(5)])
    eyes = [(np.array([0, -0.5, 0.0]), np.array([0, -0.4, 0.2]))] * 5
    many = completion.predict_points_many(nets, objects, supports, eyes, chunk=2)
    plain = completion.predict_points_many(nets, objects, supports, None, chunk=2)
    for i in range(5):
        po, ps = completion.predict_points(nets, objects[i], supports[i], eyes[i])
        np.testing.assert_allclose(many[i][0], po, atol=1e-5)
        np.testing.assert_allclose(many[i][1], ps, atol=1e-5)
        assert plain[i][0].shape == (TINY_NET.n_output, 3)  # not carved: every point
    bad = objects.copy()
    bad[2, 5] = np.nan
    with pytest.raises(ValueError, match=r"pairs \[2\] hold NaN"):
        completion.predict_points_many(nets, bad, supports)


def test_training_data_become_completed_clouds_and_the_cache_is_reused(tmp_path):
    from experiments.train_collision import CollisionData, complete_collision_data

    rng = np.random.default_rng(2)
    p, n = 3, 64
    obj = np.stack([_sphere_half(rng, n, [0, 0, 0]) for _ in range(p)])
    sup = np.stack([_sphere_half(rng, n, [0, 0.1, 0]) for _ in range(p)])
    normals = np.ones_like(obj)
    data = CollisionData(
        obj, normals, sup, normals.copy(), pair=np.zeros(2, np.int32),
        poses=np.zeros((2, 7), np.float32), labels=np.zeros(2, bool),
        meta=[{"pair_index": 10 + i} for i in range(p)],
    )  # fmt: skip
    eyes = {10 + i: (np.array([0, -0.5, 0.0]), np.array([0, -0.4, 0.0])) for i in range(p)}
    nets = _nets()
    out = complete_collision_data(data, nets, eyes, tmp_path)
    for i in range(p):
        po, ps = completion.predict_points(nets, obj[i], sup[i], eyes[10 + i])
        np.testing.assert_allclose(
            out.object_points[i], completion.completed_cloud(obj[i], po), atol=1e-5
        )
        np.testing.assert_allclose(
            out.support_points[i], completion.completed_cloud(sup[i], ps), atol=1e-5
        )
    assert (out.object_normals[:, : n - n // 2] == 1).all() and (
        out.object_normals[:, n - n // 2 :] == 0
    ).all()
    np.testing.assert_array_equal(data.object_points, obj)  # the input is not changed
    assert sorted(f.name for f in tmp_path.iterdir()) == ["00010.npz", "00011.npz", "00012.npz"]
    # a second call reads the cache (no networks, no cameras needed)
    again = complete_collision_data(data, "no/such/folder", None, tmp_path)
    np.testing.assert_array_equal(again.object_points, out.object_points)
    with pytest.raises(ValueError, match="no camera"):
        complete_collision_data(data, nets, {10: eyes[10]}, tmp_path / "fresh")


def test_the_planner_gives_a_completion_nce_completed_clouds_or_a_clear_error():
    from experiments.eval_paths import PairCase, nce_clouds

    rng = np.random.default_rng(4)
    obj, sup = rng.normal(size=(64, 3)), rng.normal(size=(64, 3))
    case = PairCase(name="p", meta={}, scene=None, object_points=obj, object_normals=obj,
                    support_points=sup, support_normals=sup, goal=np.zeros(7))  # fmt: skip
    observed = collision.NCEConfig()
    assert nce_clouds(case, observed)[0] is obj
    completed = dataclasses.replace(observed, input_clouds="completed")
    with pytest.raises(ValueError, match="--completion"):
        nce_clouds(case, completed)
    pred = rng.normal(size=(30, 3)) + 5
    o, s = nce_clouds(case._replace(predicted_object=pred, predicted_support=pred), completed)
    np.testing.assert_array_equal(o, completion.completed_cloud(obj, pred))
    assert o.shape == obj.shape and s.shape == sup.shape
    with pytest.raises(ValueError, match="input_clouds"):
        collision.NCEConfig(input_clouds="both")


def test_rerank_nce_auc_and_rules_on_a_made_up_pool():
    from experiments.rerank_nce import auc, score_rules

    rng = np.random.default_rng(5)
    pos, neg = rng.normal(1.0, 1.0, 60), rng.normal(0.0, 1.0, 80)
    brute = np.mean([(p > q) + 0.5 * (p == q) for p in pos for q in neg])
    assert abs(auc(pos, neg) - brute) < 1e-12
    assert auc(np.array([1.0, 1.0]), np.array([1.0])) == 0.5  # ties count half
    # two pairs of one category, three candidates each: the rankers prefer candidate 0, which
    # penetrates; the NCE calls it colliding, so every NCE rule strict enough picks candidate 1
    rows = [{"category": "mug"}, {"category": "mug"}]
    key = np.array([[-1.0, -2.0, -3.0], [-1.0, -2.0, -3.0]])
    stable = np.array([[False, True, False], [False, True, True]])
    prob = np.array([[0.95, 0.1, 0.2], [0.95, 0.1, 0.2]])
    table = {t["rule"]: t["mean"] for t in score_rules(rows, key, stable, prob, 0.56)}
    assert table["committed"] == 0.0
    assert table["lex 0.56"] == table["lex 0.9"] == 100.0 and table["lex 0.99"] == 0.0
    assert table["soft 1"] == 100.0  # log(0.05) = -3.0 puts candidate 0 below candidate 1


def test_the_hang_commands_checkers_refuse_an_nce_on_completed_clouds():
    # the hang command and planner.hybrid_checker give observed clouds: a completion-aware NCE
    # there would be fed the wrong input silently
    from omnihang_jax import hang, planner

    with pytest.raises(ValueError, match="completed clouds"):
        hang._nce("weights/collision_s28_completed/nce")
    cfg = collision.NCEConfig(input_clouds="completed")
    with pytest.raises(ValueError, match="observed clouds"):
        planner.hybrid_checker(cfg, None, np.zeros((8, 3)), np.zeros((8, 3)), np.zeros((8, 3)),
                               None, np.zeros(7), 0.1)  # fmt: skip
    assert hang._nce("weights/collision_s18_contact/nce")[0].input_clouds == "observed"
