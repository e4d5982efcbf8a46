"""The contact NCE (``NCEConfig.local_points``): its local patch is where the clouds are closest,
its offsets read millimetres, batched and unbatched calls agree, weights round-trip (it learns
the rod task in ``test_collision.test_nce_learns_collisions_on_a_tiny_set``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

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
    # every row is its own pose's score (one compilation: the same batch shape): rows keep
    # their scores when the batch is reordered, and when the other rows change
    order = np.roll(np.arange(5), 1)
    np.testing.assert_allclose(prob(params, oc, sc, poses[order]), batched[order], rtol=1e-4, atol=1e-5)  # fmt: skip
    other = poses.copy()
    other[1:, :3] = rng.normal(0, 0.05, (4, 3))
    changed = np.asarray(prob(params, oc, sc, other))
    np.testing.assert_allclose(changed[0], batched[0], rtol=1e-4, atol=1e-5)
    assert not np.allclose(changed[1:], batched[1:])
    collision.save_estimator(tmp_path / "nce", cfg, params)
    cfg2, params2, _ = collision.load_estimator(tmp_path / "nce")
    assert cfg2 == cfg
    np.testing.assert_allclose(np.asarray(prob(params2, oc, sc, poses)), batched, rtol=1e-6)
