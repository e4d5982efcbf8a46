"""Stage 2: closed-form translation, labels, selection, losses vs oracles, tests that learn."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from omnihang_jax import data, losses, poses, train, train_losses
from omnihang_jax.stage2 import (
    STAGE2_ORIGINAL,
    STAGE2_TINY,
    clearance_offset,
    combine_clouds,
    correspondence_labels,
    make_stage2,
    positive_scores,
    select_correspondences,
    solve_translation,
    training_selection_scores,
)


def test_solve_translation_recovers_known_translation():
    rng = np.random.default_rng(0)
    rotation = np.asarray(poses.rotation_matrix(rng.normal(size=(4, 3)).astype(np.float32)))
    t_true = rng.normal(0, 0.1, (4, 3)).astype(np.float32)
    o = rng.normal(0, 0.05, (4, 5, 3)).astype(np.float32)
    s = np.einsum("bij,bkj->bki", rotation, o) + t_true[:, None]
    # Two slots are garbage with weight 0: they must not matter.
    s[:, 3:] += 1.0
    weights = np.array([[1, 1, 1, 0, 0]] * 4, np.float32)
    t = solve_translation(rotation, o, s, weights)
    np.testing.assert_allclose(t, t_true, atol=1e-6)
    # Noisy pairs: the weighted least-squares optimum is the weighted mean residual.
    s_noisy = s + rng.normal(0, 0.01, s.shape).astype(np.float32)
    w = rng.uniform(0.1, 1, (4, 5)).astype(np.float32)
    t = np.asarray(solve_translation(rotation, o, s_noisy, w))
    residual = s_noisy - np.einsum("bij,bkj->bki", rotation, o)
    np.testing.assert_allclose(t, (w[..., None] * residual).sum(1) / w.sum(1)[:, None], atol=1e-6)

    def objective(tt):
        moved = jnp.einsum("bij,bkj->bki", rotation, o) + tt[:, None]
        return jnp.sum(w[..., None] * (moved - s_noisy) ** 2)

    grad = jax.grad(objective)(jnp.asarray(t))
    np.testing.assert_allclose(grad, 0.0, atol=1e-5)  # stationary point


def test_select_correspondences_threshold_and_fallback():
    probs = np.zeros((2, 3, 4), np.float32)
    probs[0, 1, 2], probs[0, 2, 3], probs[0, 0, 0], probs[0, 2, 0] = 0.9, 0.8, 0.6, 0.4
    probs[1, 2, 1], probs[1, 0, 3] = 0.3, 0.2  # nothing above 0.5 -> best pair only
    chosen = select_correspondences(probs, 3, 0.5)
    np.testing.assert_array_equal(chosen.object_slot[0], [1, 2, 0])
    np.testing.assert_array_equal(chosen.support_slot[0], [2, 3, 0])
    np.testing.assert_array_equal(chosen.weight[0], [1, 1, 1])
    np.testing.assert_array_equal(chosen.object_slot[1, 0], 2)
    np.testing.assert_array_equal(chosen.support_slot[1, 0], 1)
    np.testing.assert_array_equal(chosen.weight[1], [1, 0, 0])
    probs[0, 0, 0] = 0.45
    np.testing.assert_array_equal(select_correspondences(probs, 3, 0.5).weight[0], [1, 1, 0])


def test_correspondence_labels_match_brute_force():
    rng = np.random.default_rng(1)
    B, N, M, K1, K2, C, r = 2, 40, 30, 8, 6, 3, 0.04
    obj = rng.uniform(-0.05, 0.05, (B, N, 3)).astype(np.float32)
    sup = rng.uniform(-0.05, 0.05, (B, M, 3)).astype(np.float32)
    oi = np.stack([rng.choice(N, K1, replace=False) for _ in range(B)]).astype(np.int32)
    si = np.stack([rng.choice(M, K2, replace=False) for _ in range(B)]).astype(np.int32)
    pairs = np.stack([rng.integers(0, N, (B, C)), rng.integers(0, M, (B, C))], -1).astype(np.int32)
    mask = np.array([[True, True, False], [True, False, False]])
    got = np.asarray(correspondence_labels(obj, sup, oi, si, pairs, mask, r))
    want = np.zeros((B, K1, K2), bool)
    for b in range(B):
        for u in range(K1):
            for v in range(K2):
                for c in range(C):
                    if not mask[b, c]:
                        continue
                    near_o = np.sum((obj[b, oi[b, u]] - obj[b, pairs[b, c, 0]]) ** 2) < r**2
                    near_s = np.sum((sup[b, si[b, v]] - sup[b, pairs[b, c, 1]]) ** 2) < r**2
                    want[b, u, v] |= near_o and near_s
    np.testing.assert_array_equal(got, want)
    assert want.any() and not want.all()


def test_correspondence_losses_match_numpy():
    rng = np.random.default_rng(2)
    logits = rng.normal(size=(3, 4, 5, 2)).astype(np.float32)
    labels = rng.uniform(size=(3, 4, 5)) < 0.3
    labels[2] = False
    ce = np.asarray(losses.correspondence_cross_entropy(logits, labels))
    logp = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
    want_ce = -np.where(labels, logp[..., 1], logp[..., 0]).mean((1, 2))
    np.testing.assert_allclose(ce, want_ce, rtol=1e-5)
    score = np.asarray(positive_scores(logits))
    lr = np.asarray(losses.listnet_loss(score, labels))
    for b in range(3):
        y = labels[b].ravel().astype(np.float64)
        s = score[b].ravel().astype(np.float64)
        want = 0.0 if y.sum() == 0 else -np.sum(y / y.sum() * (s - np.log(np.exp(s).sum())))
        np.testing.assert_allclose(lr[b], want, rtol=1e-5, atol=1e-6)
    # sigmoid(log-odds) is the positive-class softmax probability.
    np.testing.assert_allclose(
        jax.nn.sigmoid(score), jax.nn.softmax(logits)[..., 1], rtol=1e-5, atol=1e-6
    )
    huber = losses.contact_score_loss(jnp.array([[0.0, 0.5]]), jnp.array([[2.0, 0.5]]), 1.0)
    np.testing.assert_allclose(huber, [(2.0 - 0.5) / 2], rtol=1e-6)  # linear branch: |e| - d/2


def test_original_config_matches_facts():
    cfg = STAGE2_ORIGINAL
    assert (cfg.k_object, cfg.k_support, cfg.k_pairs) == (128, 128, 3)
    assert cfg.feature_dim == 64 and cfg.correspondence_mlp == (128, 64)
    assert cfg.pointnet.num_points == 8192


def test_refine_shapes_and_combined_cloud():
    net = make_stage2(STAGE2_TINY)
    params = jax.jit(net.init)(jax.random.key(0))
    batch = data.synthetic_batch(jax.random.key(1), 2, 128)
    points, flags = combine_clouds(batch.object_points, batch.support_points)
    assert points.shape == (2, 256, 3) and flags.shape == (2, 256, 1)
    assert float(flags[:, :128].min()) == 1.0 and float(flags[:, 128:].max()) == 0.0
    pose6 = poses.pose7_to_pose6(batch.stable_poses[:, 0])
    out = jax.jit(net.refine)(params, batch.object_points, batch.support_points, pose6)
    K3 = STAGE2_TINY.k_pairs
    assert out.pose6.shape == (2, 6) and out.object_indices.shape == (2, K3)
    assert out.contact_scores.shape == (2, 256)
    assert bool(jnp.all((out.contact_scores >= 0) & (out.contact_scores <= 1)))
    np.testing.assert_array_equal(out.pose6[:, 3:], pose6[:, 3:])  # rotation kept from Stage 1
    assert bool(jnp.all(out.weight[:, 0] == 1))
    # The translation is exactly the closed form over the chosen indices.
    o = np.take_along_axis(batch.object_points, np.asarray(out.object_indices)[..., None], 1)
    s = np.take_along_axis(batch.support_points, np.asarray(out.support_indices)[..., None], 1)
    t = solve_translation(poses.rotation_matrix(pose6[:, 3:]), o, s, out.weight)
    np.testing.assert_allclose(out.pose6[:, :3], t, atol=1e-6)


def test_clearance_moves_along_support_normal_and_zero_is_identical():
    """Flat support patch (z = 0, normals +z), object points on it: a clearance c moves the
    Stage-2 translation by exactly c along +z; c = 0 leaves the result bit-identical."""
    rng = np.random.default_rng(0)
    m = n = 128
    support = np.zeros((2, m, 3), np.float32)
    support[..., :2] = rng.uniform(-0.05, 0.05, (2, m, 2))
    normals = np.broadcast_to(np.array([0, 0, 1], np.float32), (2, m, 3))
    obj = np.zeros((2, n, 3), np.float32)  # object hangs below its contact points
    obj[..., :2] = rng.uniform(-0.03, 0.03, (2, n, 2))
    obj[:, n // 2 :, 2] = -rng.uniform(0.01, 0.1, (2, n - n // 2))
    pose6 = np.concatenate([rng.normal(0, 0.01, (2, 3)), np.zeros((2, 3))], -1).astype(np.float32)
    params = jax.jit(make_stage2(STAGE2_TINY).init)(jax.random.key(0))

    def refine(clearance, with_normals=True):
        net = make_stage2(dataclasses.replace(STAGE2_TINY, clearance=clearance))
        return jax.jit(net.refine)(params, obj, support, pose6, normals if with_normals else None)

    base = jax.jit(make_stage2(STAGE2_TINY).refine)(params, obj, support, pose6)
    for out in (refine(0.0), refine(0.0, with_normals=False)):
        for a, b in zip(out, base, strict=True):
            np.testing.assert_array_equal(a, b)  # bit-identical
    c = 0.004
    for with_normals in (True, False):  # given normals, then the PCA fallback
        out = refine(c, with_normals)
        np.testing.assert_array_equal(out.support_indices, base.support_indices)
        np.testing.assert_array_equal(out.pose6[:, 3:], base.pose6[:, 3:])
        np.testing.assert_allclose(out.pose6[:, :3] - base.pose6[:, :3], [[0, 0, c]] * 2, atol=1e-7)
    np.testing.assert_allclose(
        clearance_offset(jnp.asarray(normals[:, :3]), jnp.asarray([[1, 1, 0], [0, 0, 0]]), c),
        [[0, 0, c], [0, 0, 0]],  # zero weights -> no offset
    )


def _memorise_config():
    """TINY, no pose noise: the tests below memorise a handful of fixed pairs."""
    cfg = train.WHERE_TINY
    return dataclasses.replace(
        cfg,
        stage2=dataclasses.replace(cfg.stage2, pose_noise_translation=0.0, pose_noise_rotation=0.0),
        train=dataclasses.replace(cfg.train, lr_stage2=2e-3),
    )


def _fit(stage, config, steps):
    batch = data.synthetic_batch(jax.random.key(0), 4, 128, max_poses=1)
    loss_fn = jax.jit(train_losses.make_loss_fn(stage, config))
    state = jax.jit(train.make_init_state(stage, config))(jax.random.key(1))
    step = jax.jit(train.make_train_step(stage, config))
    before = {k: float(v) for k, v in loss_fn(state.params, batch, jax.random.key(7))[1].items()}
    for i in range(steps):
        state, _ = step(state, batch, jax.random.key(i))
    after = {k: float(v) for k, v in loss_fn(state.params, batch, jax.random.key(7))[1].items()}
    return before, after


def test_stage2a_overfits_contact_maps():
    """Huber loss (TINY keeps the facts' loss) of the contact scores on 4 fixed pairs falls
    >= 5x."""
    before, after = _fit("2a", _memorise_config(), 300)
    print(f"stage2a loss {before['contact_loss']:.4f} -> {after['contact_loss']:.4f}")
    assert before["contact_loss"] / after["contact_loss"] >= 5.0
    assert after["top_k_map_value"] > before["top_k_map_value"]


def test_stage2b_overfits_correspondences():
    """On 4 fixed pairs: cross-entropy falls >= 3x, ListNet's excess over its floor >= 5x,
    and the best-ranked pair is a true correspondence for every pair."""
    config = _memorise_config()
    config = dataclasses.replace(
        config, stage2=dataclasses.replace(config.stage2, train_features_in_2b=True)
    )
    before, after = _fit("2b", config, 300)
    print(
        f"stage2b CE {before['cross_entropy']:.3f}->{after['cross_entropy']:.3f}, "
        f"ListNet excess {before['listnet_excess']:.3f}->{after['listnet_excess']:.3f}, "
        f"top1 {before['top1_precision']:.2f}->{after['top1_precision']:.2f}"
    )
    assert before["cross_entropy"] / after["cross_entropy"] >= 3.0
    assert before["listnet_excess"] / after["listnet_excess"] >= 5.0
    assert after["top1_precision"] == 1.0


@pytest.mark.slow  # ~15 s on 2 cores: the small preset's train step (tiny ones train above)
def test_small_preset_trains_a_step_with_pair_offsets():
    """SMALL (real-object radii, pair offsets in 2b) builds, takes a 2b step, gives finite
    losses, and its correspondence logits depend on the candidates' positions."""
    config = dataclasses.replace(
        train.WHERE_SMALL, train=dataclasses.replace(train.WHERE_SMALL.train, batch_size=2)
    )
    assert config.stage2.pair_offset_scale > 0
    batch = data.synthetic_batch(jax.random.key(0), 2, 256)
    init, step, _ = train._jitted("2b", config)
    state = init(jax.random.key(1))
    state, metrics = step(state, batch, jax.random.key(2))
    assert all(np.isfinite(float(v)) for v in metrics.values())
    net = make_stage2(config.stage2)
    f = jnp.ones((1, 4, config.stage2.feature_dim))
    xyz = jax.random.normal(jax.random.key(3), (1, 4, 3)) * 0.05
    a = net.correspond(state.params, f, f, xyz, xyz)
    b = net.correspond(state.params, f, f, xyz, xyz + 0.03)
    assert a.shape == (1, 4, 4, 2) and not np.allclose(a, b)


def test_contact_loss_options_match_numpy():
    """ListNet over points (object and support parts separately) and soft-target BCE."""
    rng = np.random.default_rng(0)
    logits = rng.normal(size=(2, 10)).astype(np.float32)
    target = rng.uniform(size=(2, 10)).astype(np.float32) * (rng.uniform(size=(2, 10)) > 0.5)
    target[1, 4:] = 0.0  # second pair: empty support map -> that part contributes 0
    scores = 1 / (1 + np.exp(-logits))
    got = losses.contact_score_loss(
        jnp.asarray(scores),
        jnp.asarray(target),
        kind="listnet",
        logits=jnp.asarray(logits),
        num_object=4,
    )
    want = np.zeros(2)
    for b in range(2):
        for sl in (slice(0, 4), slice(4, 10)):
            y, z = target[b, sl], logits[b, sl]
            if y.sum() > 0:
                want[b] -= np.sum(y / y.sum() * (z - np.log(np.sum(np.exp(z)))))
    np.testing.assert_allclose(got, want, rtol=1e-5)
    bce = losses.contact_score_loss(
        jnp.asarray(scores), jnp.asarray(target), kind="bce", logits=jnp.asarray(logits)
    )
    ref = -(target * np.log(scores) + (1 - target) * np.log(1 - scores)).mean(-1)
    np.testing.assert_allclose(bce, ref, rtol=1e-4)


@pytest.mark.slow  # ~49 s on 2 cores, training options off by default
def test_predicted_and_mixed_selection_train_without_recompiling():
    """2b with candidates chosen by the net's scores ("predicted") or per pair at random
    ("mixed"): one jit, finite metrics over steps; "mixed" rows are either the GT map or the
    scores."""
    batch = data.synthetic_batch(jax.random.key(0), 4, 128, max_poses=2)
    for mode in ("predicted", "mixed"):
        config = dataclasses.replace(
            train.WHERE_TINY,
            stage2=dataclasses.replace(
                train.WHERE_TINY.stage2, train_selection=mode, contact_loss="listnet"
            ),
        )
        state = jax.jit(train.make_init_state("2b", config))(jax.random.key(1))
        step = jax.jit(train.make_train_step("2b", config))
        for i in range(3):
            state, metrics = step(state, batch, jax.random.key(i))
            assert all(np.isfinite(float(v)) for v in metrics.values())
        assert step._cache_size() == 1
    target = jnp.zeros((64, 5))
    scores = jnp.ones((64, 5))
    mixed = training_selection_scores("mixed", target, scores, jax.random.key(0))
    rows = np.asarray(mixed[:, 0])
    assert set(np.unique(rows)) == {0.0, 1.0} and np.all(mixed == mixed[:, :1])
