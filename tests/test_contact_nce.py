"""The contact NCE (``NCEConfig.local_points``): its local patch is where the clouds are closest,
its offsets read millimetres, batched and unbatched calls agree, weights round-trip (it learns
the rod task in ``test_collision.test_nce_learns_collisions_on_a_tiny_set``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from omnihang_jax import collision


def _brute_nearest(a, b):
    """For every row of a: the offset to its nearest row of b."""
    d = np.linalg.norm(a[:, None] - b[None], axis=-1)
    return b[np.argmin(d, axis=1)] - a


def test_contact_patch_is_the_closest_region_with_offsets_to_the_other_cloud():
    rng = np.random.default_rng(0)
    # support: a 40 cm bar of points; object: a 1-cm blob 4 mm above its x = +0.1 end
    support = np.stack(
        [rng.uniform(-0.2, 0.2, 512), rng.uniform(-0.005, 0.005, 512), np.zeros(512)], 1
    ).astype(np.float32)
    blob = (rng.normal(0, 0.003, (256, 3)) + [0.1, 0, 0.004 + 0.01]).astype(np.float32)
    far = (rng.normal(0, 0.003, (256, 3)) + [0.1, 0, 0.5]).astype(np.float32)
    obj = np.concatenate([blob, far])
    k = 32
    points, features = collision.contact_patch(
        jnp.asarray(obj[None]), jnp.asarray(support[None]), k
    )
    points, features = np.asarray(points)[0], np.asarray(features)[0]
    assert points.shape == (2 * k, 3) and features.shape == (2 * k, 5)
    np.testing.assert_array_equal(features[:k, 0], 1.0)  # flags: object first, then support
    np.testing.assert_array_equal(features[k:, 0], 0.0)
    # the patch is centred on its support points, which lie under the blob, not along the bar
    sup = np.asarray(collision.crop_support(jnp.asarray(obj[None]), support[None], k))[0]
    assert np.all(np.abs(sup[:, 0] - 0.1) < 0.03)
    centre = sup.mean(0)
    np.testing.assert_allclose(points[k:] + centre, sup, atol=1e-6)
    obj_rel, sup_rel = points[:k], points[k:]
    assert np.all(obj_rel[:, 2] + centre[2] < 0.1)  # blob points only, none of the far blob
    # offsets (units of 1 cm, clipped at 3) are the brute-force nearest offsets between the patches
    want_obj = _brute_nearest(obj_rel, sup_rel) / collision.PATCH_SCALE
    want_sup = _brute_nearest(sup_rel, obj_rel) / collision.PATCH_SCALE
    want = np.concatenate([want_obj, want_sup])
    length = np.linalg.norm(want, axis=1, keepdims=True)
    want = want * np.minimum(1.0, collision.PATCH_CLIP / length)
    np.testing.assert_allclose(features[:, 1:4], want, atol=1e-4)
    np.testing.assert_allclose(features[:, 4], np.minimum(length[:, 0], 3.0), atol=1e-4)
    assert np.all(features[:, 4] <= collision.PATCH_CLIP + 1e-6)


def test_contact_nce_batched_agrees_with_one_pose_and_round_trips(tmp_path):
    rng = np.random.default_rng(1)
    cfg = collision.NCE_PRESETS["tiny_contact"]
    assert cfg.object_input == cfg.local_from == cfg.support_input == 128
    params = collision.make_nce(cfg).init(jax.random.key(0))
    assert "local" in params and "encoder" in params
    oc = rng.normal(0, 0.02, (cfg.object_input, 3)).astype(np.float32)
    sc = rng.normal(0, 0.1, (cfg.support_input, 3)).astype(np.float32)
    poses = np.tile(np.array([0, 0, 0, 1, 0, 0, 0], np.float32), (5, 1))
    poses[:, :3] = rng.normal(0, 0.05, (5, 3))
    prob = jax.jit(collision.nce_probability(cfg))
    batched = np.asarray(prob(params, oc, sc, poses))
    single = np.array([np.asarray(prob(params, oc, sc, p[None]))[0] for p in poses])
    np.testing.assert_allclose(batched, single, rtol=1e-4, atol=1e-5)
    collision.save_estimator(tmp_path / "nce", cfg, params)
    cfg2, params2, _ = collision.load_estimator(tmp_path / "nce")
    assert cfg2 == cfg
    np.testing.assert_allclose(np.asarray(prob(params2, oc, sc, poses)), batched, rtol=1e-6)


def test_hang_plans_with_the_best_committed_nce():
    """The hang command's "how" uses the contact NCE when its weights are in the tree (they are
    committed), not the alphabetically first folder (the sixth session's CPU NCE)."""
    from pathlib import Path

    from omnihang_jax import hang

    found = hang.find_collision_weights()
    assert found == Path("weights/collision_s18_contact/nce")
    cfg, _, _ = collision.load_estimator(found)
    assert cfg.local_points > 0 and cfg.threshold > 0.5


def test_joint_selection_of_the_nce_threshold_and_the_observed_cloud_test():
    """``eval_paths --select-geometric --select-nce-thresholds``: the NCE's threshold is
    searched with the test's settings on training validation pairs; a higher threshold never
    lowers the goal pass at the same test setting, and the chosen row keeps the target."""
    from experiments.eval_paths import select_geometric

    sel = select_geometric(
        "datasets/paper", "weights/collision_s18_contact", val_pairs=2, goal_pass=0.8,
        depths=(0.001, 0.003), radii=(0.003,), min_points=(0, 5), nce_thresholds=(0.3, 0.9),
    )  # fmt: skip
    assert sel["validation_pairs"] == 2 and len(sel["table"]) == 2 * 2 * 1 * 2
    rows = {(r["nce_threshold"], r["depth"], r["min_points"]): r for r in sel["table"]}
    for (t, d, m), row in rows.items():
        if t == 0.3:
            assert rows[(0.9, d, m)]["goal_pass"] >= row["goal_pass"]
            assert rows[(0.9, d, m)]["near_recall"] <= row["near_recall"]
    chosen = sel["chosen"]
    qualifying = [r for r in sel["table"] if r["goal_pass"] >= 0.8]
    assert (chosen is None) == (not qualifying)
    if qualifying:
        assert chosen["goal_pass"] >= 0.8 and chosen["nce_threshold"] in (0.3, 0.9)
        assert chosen["free_precision"] == max(r["free_precision"] for r in qualifying)
    assert sel["nce"]["threshold"] == 0.56  # the NCE's own row at its own threshold


def test_hce_thresholds_chosen_by_the_nces_goal_pass_rule():
    """``eval_paths --hce-goal-pass``: both HCE thresholds are the lowest scores that keep the
    target share of the validation pairs' stable poses free; the balanced-accuracy threshold
    saved with the weights is reported beside it, and a laxer threshold never detects more."""
    from experiments.eval_paths import hce_goal_pass_thresholds

    with pytest.raises(ValueError, match="goal_pass"):
        hce_goal_pass_thresholds("datasets/paper", "weights/collision_s18_contact", 2, 0.0)
    sel = hce_goal_pass_thresholds("datasets/paper", "weights/collision_s18_contact", 2, 0.9)
    assert sel["validation_pairs"] == 2 and sel["stable_poses"] > 0
    for name in ("hce", "hce_true_normals"):
        chosen, balanced = sel[name]["chosen"], sel[name]["balanced"]
        assert chosen["goal_pass"] >= 0.9
        if balanced["goal_pass"] < 0.9:  # the balanced threshold blocks goals: chosen is laxer
            assert chosen["threshold"] > balanced["threshold"]
            assert chosen["near_recall"] <= balanced["near_recall"]
