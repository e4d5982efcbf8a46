"""Stage 3: CEM over SE(3), the value network's state and loss, the pipeline in one jit."""

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np
import pytest

from omnihang_jax import pipeline, stage3
from omnihang_jax.stage3 import CEMConfig, PairClouds


def _bowl(target):
    """Score = -(|t - t*|^2 / 1 cm^2 + geodesic angle^2 / 0.1 rad^2): maximum at target."""
    target_rot = jaxlie.SO3(wxyz=target[3:])

    def score(poses):
        dt = jnp.sum((poses[:, :3] - target[:3]) ** 2, -1) / 1e-4
        rel = jaxlie.SO3(wxyz=poses[:, 3:]).inverse() @ target_rot
        ang = jnp.linalg.norm(rel.log(), axis=-1)
        return -(dt + ang**2 / 1e-2)

    return score


def test_cem_finds_quadratic_bowl_maximum():
    start = jnp.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    # the optimum lies inside the +-2 cm / +-0.5 rad box
    turn = jaxlie.SO3.exp(jnp.array([0.2, -0.1, 0.15]))
    target = jnp.concatenate([jnp.array([0.012, -0.008, 0.005]), turn.wxyz])
    optimise = jax.jit(stage3.make_cem(_bowl(target), CEMConfig(iterations=15)))
    res = optimise(jax.random.key(0), start, start[:3])
    assert float(res.score) > float(res.initial_score)
    assert np.linalg.norm(np.asarray(res.pose[:3] - target[:3])) < 2e-3  # within 2 mm
    rel = jaxlie.SO3(wxyz=res.pose[3:]).inverse() @ jaxlie.SO3(wxyz=target[3:])
    assert float(jnp.linalg.norm(rel.log())) < 0.05  # within 3 degrees
    # best-so-far is monotone
    assert np.all(np.diff(np.asarray(res.history)) >= 0)


def test_cem_clipping_holds_and_same_key_same_answer():
    start = jnp.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    far = jnp.array([0.5, 0.5, 0.5, 0.0, 1.0, 0.0, 0.0])  # far outside the box
    cfg = CEMConfig()
    optimise = jax.jit(stage3.make_cem(_bowl(far), cfg))
    res = optimise(jax.random.key(3), start, start[:3])
    a = np.asarray(res.action)
    assert np.all(np.abs(a[:3]) <= cfg.clip_translation + 1e-7)
    assert np.all(np.abs(a[3:]) <= cfg.clip_rotation + 1e-7)
    # pivot = start position: the displacement is the clipped translation
    assert np.all(np.abs(np.asarray(res.pose[:3])) <= cfg.clip_translation + 1e-6)
    # it pushes against the box towards the target
    assert np.all(a[:3] > 0.015)
    again = optimise(jax.random.key(3), start, start[:3])
    np.testing.assert_array_equal(np.asarray(res.pose), np.asarray(again.pose))
    other = optimise(jax.random.key(4), start, start[:3])
    assert not np.array_equal(np.asarray(res.action), np.asarray(other.action))


def test_cem_vmapped_over_pairs_and_proposals():
    targets = jnp.array([[0.01, 0.0, 0.0], [-0.01, 0.005, 0.0]])
    starts = jnp.tile(jnp.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]), (2, 3, 1))

    def score(poses, target):
        return -jnp.sum((poses[:, :3] - target) ** 2, -1)

    optimise = stage3.make_cem(score, CEMConfig())
    run = jax.jit(jax.vmap(jax.vmap(optimise, in_axes=(0, 0, 0, None)), in_axes=(0, 0, 0, 0)))
    keys = jax.random.split(jax.random.key(1), 6).reshape(2, 3)
    res = run(keys, starts, starts[..., :3], targets)
    assert res.pose.shape == (2, 3, 7)
    err = np.linalg.norm(np.asarray(res.pose[..., :3]) - np.asarray(targets)[:, None], axis=-1)
    assert np.median(err) < 2e-3 and err.max() < 1e-2  # 10 iterations of 32: not exact


def test_apply_action_turns_about_pivot():
    pose = jnp.array([0.1, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    pivot = jnp.array([0.0, 0.0, 0.0])
    action = jnp.array([0.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2])
    out = stage3.apply_action(pose, pivot, action)
    np.testing.assert_allclose(np.asarray(out[:3]), [0.0, 0.1, 0.0], atol=1e-6)


def _clouds(n=64, m=64, seed=0):
    rng = np.random.default_rng(seed)
    obj = rng.normal(size=(n, 3)).astype(np.float32)
    obj /= np.linalg.norm(obj, axis=1, keepdims=True)
    sup = rng.uniform(-1, 1, size=(m, 3)).astype(np.float32)
    sup[:, 2] = 0.0  # a plane z = 0 with normals +z
    sup_n = np.tile(np.float32([0, 0, 1]), (m, 1))
    return PairClouds(obj * 0.02, obj, sup * 0.05, sup_n)


def test_state_contact_features_see_penetration():
    cfg = stage3.VALUE_TINY
    clouds = _clouds()
    above = jnp.array([0.0, 0.0, 0.03, 1.0, 0.0, 0.0, 0.0])  # sphere r=2 cm, 1 cm above plane
    inside = jnp.array([0.0, 0.0, 0.01, 1.0, 0.0, 0.0, 0.0])  # 1 cm into the plane
    pts, f_above = stage3.posed_state(clouds, above, cfg)
    _, f_inside = stage3.posed_state(clouds, inside, cfg)
    assert pts.shape == (128, 3) and f_above.shape == (128, 3)
    n = 64
    assert float(f_above[:n, 1].min()) > 0  # every object point above the plane
    assert float(f_inside[:n, 1].min()) < -0.5  # some > 5 mm behind it
    # centred on the candidate: the object cloud is the same in both states
    np.testing.assert_allclose(np.asarray(pts[:n]), np.asarray(clouds.object_points), atol=1e-6)


@pytest.mark.slow  # a tiny Stages 1-3 compile; test_where runs the pipeline through where
def test_value_pipeline_runs_in_one_jit():
    from omnihang_jax.stage1 import STAGE1_TINY, make_stage1
    from omnihang_jax.stage2 import STAGE2_TINY, make_stage2

    s1, s2 = make_stage1(STAGE1_TINY), make_stage2(STAGE2_TINY)
    v = stage3.make_value(stage3.VALUE_TINY)
    params = {
        "stage1": s1.init(jax.random.key(0)),
        "stage2": s2.init(jax.random.key(1)),
        "value": v.init(jax.random.key(2)),
    }
    cfg = pipeline.PipelineConfig(
        num_proposals=2, cem=CEMConfig(population=8, iterations=2, elites=3),
        starts=("stage2", "stage1"),
    )  # fmt: skip
    hang = jax.jit(pipeline.make_hang_pipeline(STAGE1_TINY, STAGE2_TINY, stage3.VALUE_TINY, cfg))
    c = _clouds(128, 128)
    batch = PairClouds(*(jnp.stack([x, x]) for x in c))
    out = hang(params, jax.random.key(5), batch)
    assert out.pose.shape == (2, 7)
    assert out.refined["stage1"].shape == (2, 2, 7)
    assert np.all(np.asarray(out.scores["stage2"]) >= np.asarray(out.initial_scores["stage2"]))
    assert np.isfinite(np.asarray(out.pose)).all()


@pytest.mark.parametrize("reward", [0, 1])
def test_value_loss_prefers_the_label(reward):
    logits = jnp.array([[2.0, -2.0], [-2.0, 2.0]])
    rewards = jnp.array([reward, reward])
    loss, m = stage3.value_loss(logits, rewards)
    assert float(m["accuracy"]) == 0.5
    assert np.isfinite(float(loss))


def test_cem_keeps_the_top_of_its_final_population():
    """keep_top M: the M best members of the last iteration's population, best first, scored
    as score_fn scores them, inside the box; M = 0 (default) keeps none; M > population fails."""
    start = jnp.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    target = jnp.array([0.01, -0.005, 0.0, 1.0, 0.0, 0.0, 0.0])
    score = _bowl(target)
    cfg = CEMConfig()
    res = jax.jit(stage3.make_cem(score, cfg, keep_top=8))(jax.random.key(0), start, start[:3])
    assert res.top_poses.shape == (8, 7) and res.top_scores.shape == (8,)
    s = np.asarray(res.top_scores)
    assert np.all(np.diff(s) <= 0)  # best first
    np.testing.assert_allclose(np.asarray(score(res.top_poses)), s, rtol=1e-4, atol=1e-3)
    assert s[0] <= float(res.score) + 1e-4  # the answer is the best-so-far
    assert np.all(np.abs(np.asarray(res.top_poses[:, :3])) <= cfg.clip_translation + 1e-6)
    # the final population has converged near the optimum: its top members are close to it
    assert np.median(np.linalg.norm(np.asarray(res.top_poses[:, :3] - target[:3]), axis=1)) < 5e-3
    none = jax.jit(stage3.make_cem(score, cfg))(jax.random.key(0), start, start[:3])
    assert none.top_poses.shape == (0, 7)
    np.testing.assert_array_equal(np.asarray(none.pose), np.asarray(res.pose))  # same search
    with pytest.raises(ValueError, match="keep_top"):
        stage3.make_cem(score, cfg, keep_top=cfg.population + 1)
