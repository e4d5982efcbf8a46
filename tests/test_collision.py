"""Collision estimators: poses move clouds as MuJoCo does, the heuristic reads inside from
outside, batched and unbatched calls agree, and the NCE learns collisions from labels."""

from __future__ import annotations

import jax
import mujoco
import numpy as np
import pytest

from omnihang_jax import collision


def _random_poses(rng, n, spread=0.05):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([rng.uniform(-spread, spread, (n, 3)), q], 1).astype(np.float32)


def test_quaternion_matrix_matches_mujoco():
    rng = np.random.default_rng(0)
    poses = _random_poses(rng, 20)
    ours = np.asarray(collision.quaternion_matrix(poses[:, 3:]))
    for q, rot in zip(poses[:, 3:], ours):
        want = np.zeros(9)
        mujoco.mju_quat2Mat(want, q.astype(float))
        np.testing.assert_allclose(rot, want.reshape(3, 3), atol=1e-6)


def _plate(rng, n=400):
    """A 20 x 20 cm plate's top face at z = 0 with outward normals +z."""
    pts = np.concatenate([rng.uniform(-0.1, 0.1, (n, 2)), np.zeros((n, 1))], 1)
    return pts.astype(np.float32), np.tile([0, 0, 1.0], (n, 1)).astype(np.float32)


def test_heuristic_score_is_low_above_the_plate_and_high_below():
    rng = np.random.default_rng(1)
    plate, normals = _plate(rng)
    blob = rng.normal(scale=0.005, size=(64, 3)).astype(np.float32)
    above = np.array([[0, 0, 0.03, 1, 0, 0, 0]], np.float32)
    below = np.array([[0, 0, -0.03, 1, 0, 0, 0]], np.float32)
    score = collision.heuristic_score(blob, plate, normals, np.concatenate([above, below]))
    assert score[0] < -0.9 and score[1] > 0.9  # paper: cosine <= 0 inside the support
    # with the normals flipped (a wrong normal net) the heuristic is fooled: it uses them
    flipped = collision.heuristic_score(blob, plate, -normals, above)
    assert flipped[0] > 0.9


def test_batched_and_unbatched_estimators_agree():
    rng = np.random.default_rng(2)
    nce_cfg = collision.NCE_PRESETS["tiny"]
    normal_cfg = collision.NORMAL_PRESETS["tiny"]
    nce_params = collision.make_nce(nce_cfg).init(jax.random.key(0))
    normal_params = collision.make_normal_net(normal_cfg).init(jax.random.key(1))
    oc = rng.uniform(-0.03, 0.03, (nce_cfg.object_points, 3)).astype(np.float32)
    sc, true_normals = _plate(rng, normal_cfg.points)
    poses = _random_poses(rng, 4)
    nce = jax.jit(collision.nce_probability(nce_cfg))
    score = jax.jit(collision.heuristic_score)
    normals = jax.jit(collision.make_normal_net(normal_cfg).apply)(normal_params, sc[None])[0]
    batched = {
        "nce": np.asarray(nce(nce_params, oc, sc[: nce_cfg.support_points], poses)),
        "hce": np.asarray(score(oc, sc, normals, poses)),
        "true": np.asarray(score(oc, sc, true_normals, poses)),
    }
    # every row is its own pose's score (one compilation: the same batch shape): rows keep
    # their scores when the batch is reordered, and when the other rows change
    order = np.roll(np.arange(len(poses)), 1)
    other = np.concatenate([poses[:1], _random_poses(rng, len(poses) - 1)])
    for name, fn in (
        ("nce", lambda x: nce(nce_params, oc, sc[: nce_cfg.support_points], x)),
        ("hce", lambda x: score(oc, sc, normals, x)),
        ("true", lambda x: score(oc, sc, true_normals, x)),
    ):
        np.testing.assert_allclose(fn(poses[order]), batched[name][order], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(fn(other)[0], batched[name][0], rtol=1e-5, atol=1e-6)
        assert not np.allclose(fn(other)[1:], batched[name][1:])  # the other rows did change
    # the collides functions are these scores against their thresholds
    thr = float(np.median(batched["hce"]))
    hce = jax.jit(collision.hce_collides(collision.NormalNetConfig("tiny", normal_cfg.points, thr)))
    np.testing.assert_array_equal(
        np.asarray(hce(normal_params, oc, sc, poses)), batched["hce"] > thr
    )


def _rod_task(rng, n_labels):
    """A 1 cm rod along x (support cloud on its surface) and a 2 cm ball (object cloud);
    a pose collides when the full shapes overlap: ball centre within 3 cm of the rod's axis.
    Half the poses collide (chance = 50 %)."""
    from omnihang_jax.collision_data import CollisionData

    t = rng.uniform(-0.1, 0.1, 400)
    a = rng.uniform(0, 2 * np.pi, 400)
    rod = np.stack([t, 0.01 * np.cos(a), 0.01 * np.sin(a)], 1)
    d = rng.normal(size=(400, 3))
    ball = 0.02 * d / np.linalg.norm(d, axis=1, keepdims=True)
    colliding = np.arange(n_labels) % 2 == 0
    radius = np.where(colliding, rng.uniform(0.0, 0.025, n_labels), rng.uniform(0.035, 0.06, n_labels))  # fmt: skip
    angle = rng.uniform(0, 2 * np.pi, n_labels)
    pos = np.stack(
        [rng.uniform(-0.08, 0.08, n_labels), radius * np.cos(angle), radius * np.sin(angle)], 1
    )
    poses = np.concatenate([pos, np.tile([1.0, 0, 0, 0], (n_labels, 1))], 1)
    return CollisionData(
        ball[None].astype(np.float32),
        ball[None].astype(np.float32),
        rod[None].astype(np.float32),
        rod[None].astype(np.float32),
        pair=np.zeros(n_labels, np.int32),
        poses=poses.astype(np.float32),
        labels=colliding,
        meta=[{}],
    )


@pytest.mark.parametrize(
    "preset", ["tiny", pytest.param("tiny_contact", marks=pytest.mark.slow)]
)  # tiny_contact: the contact NCE (its forward pass: test_contact_nce)
def test_nce_learns_collisions_on_a_tiny_set(preset):
    """train_nce learns the rod task; with a near-contact share of the batches and a
    validation curve (pairs never trained on) whose loss falls."""
    import dataclasses as dc

    from experiments.train_collision import train_nce

    rng = np.random.default_rng(3)
    train, held_out = _rod_task(rng, 2000), _rod_task(rng, 256)
    near = _rod_task(rng, 200)  # stand-ins for the near-contact rows
    train = dc.replace(
        train, far_pair=near.pair, far_poses=near.poses, far_labels=near.labels,
        far_near=np.ones(200, bool),
    )  # fmt: skip
    val = dc.replace(
        held_out, near_pair=near.pair[:100], near_poses=near.poses[:100],
        near_kind=np.ones(100, np.int8), near_labels=near.labels[:100],
    )  # fmt: skip
    cfg = collision.NCE_PRESETS[preset]
    prob = jax.jit(collision.nce_probability(cfg))
    oc = held_out.object_points[0, : cfg.object_input]
    sc = held_out.support_points[0, : cfg.support_input]

    def accuracy(params):
        return float(
            np.mean((np.asarray(prob(params, oc, sc, held_out.poses)) > 0.5) == held_out.labels)
        )

    before = accuracy(collision.make_nce(cfg).init(jax.random.key(0)))
    params, log = train_nce(
        train, cfg, steps=100, time_budget=120, batch=32, progress=False, near_share=0.25,
        val=val, val_every=50, val_labels=256,
    )  # fmt: skip
    after = accuracy(params)

    assert after >= 0.75, f"held-out accuracy {after:.2f} after {log['steps']} steps (chance 0.5)"
    assert after > before + 0.15
    assert log["near_share"] == 0.25 and log["schedule"] == "constant"
    curve = log["val_history"]
    assert [r["step"] for r in curve] == [1, 50, 100]
    assert curve[-1]["val_loss"] < curve[0]["val_loss"]
    assert 0.0 <= curve[-1]["val_near_accuracy"] <= 1.0


def test_the_cosine_schedule_sets_the_optimiser_rate_over_the_time_budget():
    """warmup_cosine's shape, and _loop setting it into the optimiser as the budget passes."""
    import time

    import optax

    from experiments.train_collision import _loop, warmup_cosine

    assert warmup_cosine(0.0, 1e-3) == pytest.approx(1e-4)
    assert warmup_cosine(0.03, 1e-3) == pytest.approx(1e-3)
    assert warmup_cosine(1.0, 1e-3) == pytest.approx(5e-5)
    assert warmup_cosine(0.5, 1e-3) < warmup_cosine(0.3, 1e-3) < 1e-3
    params = {"w": np.zeros(2, np.float32)}
    opt_state = optax.inject_hyperparams(optax.sgd)(learning_rate=1.0).init(params)
    rates = []

    def step(params, opt_state, key):
        rates.append(float(opt_state.hyperparams["learning_rate"]))
        time.sleep(0.01)
        return params, opt_state, np.float32(0), np.float32(0)

    peak = 1e-3
    _, log = _loop(
        step, params, opt_state, jax.random.key(0), 10**6, 0.6, 1, "test", False,
        lr_at=lambda frac: warmup_cosine(frac, peak),
    )  # fmt: skip
    assert rates[0] == pytest.approx(0.1 * peak)  # warm-up from 10 %
    assert max(rates) > 0.9 * peak and rates[-1] < 0.2 * peak  # the peak, then the decay
    assert log["steps"] == len(rates) and 20 < len(rates) < 80


def test_far_free_poses_never_touch_the_support_or_its_wall():
    from omnihang_jax import planner
    from omnihang_jax.collision_data import far_free_poses, pair_geometry
    from sim.assets import objects, supports  # noqa: F401  (registers the generators)
    from sim.assets.base import build_object, build_support
    from sim.scene import build_scene

    rng = np.random.default_rng(4)
    for category, family in (("mug", "pegboard_hook"), ("racquet", "mug_tree")):
        obj, sup = build_object(category, 1), build_support(family, 1)
        g = pair_geometry(obj, sup)
        poses = far_free_poses(
            rng, float(g["object_half_diagonal"]), g["support_bounds"], float(g["wall_y"]), 200
        )
        pen = planner.MeshChecker(build_scene(obj, sup), tolerance=0.0).penetration(poses)
        assert (pen == 0).all()
        # and they fill the planner's bounds, not just a far shell
        lo, hi = planner.default_bounds(build_scene(obj, sup))
        inside = np.all((poses[:, :3] >= lo) & (poses[:, :3] <= hi), axis=1)
        assert inside.mean() > 0.2


def _mug_on_pegboard():
    """A library mug and pegboard hook in one MuJoCo scene (the near-pose tests' pair)."""
    from sim.assets import objects, supports  # noqa: F401  (registers the generators)
    from sim.assets.base import build_object, build_support
    from sim.scene import build_scene

    return build_scene(build_object("mug", 1), build_support("pegboard_hook", 1))


def test_near_contact_poses_and_their_mesh_labels():
    from omnihang_jax import planner
    from omnihang_jax.collision_data import (
        NEAR_APPROACH,
        NEAR_COUNTS,
        NEAR_JITTER,
        NEAR_LIFT,
        NEAR_STABLE,
        near_contact_labels,
        near_contact_poses,
    )

    scene = _mug_on_pegboard()
    lo, hi = np.asarray(scene.support_bounds, float)
    centre = 0.5 * (lo + hi)
    stable = np.array([[*centre, 1, 0, 0, 0], [centre[0], hi[1], hi[2], 0, 1, 0, 0]], float)
    poses, kind = near_contact_poses(scene, stable, np.random.default_rng(0))
    assert (kind == NEAR_STABLE).sum() == 2 and np.allclose(poses[:2], stable)
    for k, n in NEAR_COUNTS.items():
        assert (kind == k).sum() == n
    np.testing.assert_allclose(np.linalg.norm(poses[:, 3:], axis=1), 1.0, atol=1e-5)
    # jitter: 0.5-30 mm from one of the stable poses
    shift = np.min(
        [np.linalg.norm(poses[kind == NEAR_JITTER, :3] - s[:3], axis=1) for s in stable], axis=0
    )
    assert shift.min() >= 4.9e-4 and shift.max() <= 0.0301
    # lift: straight up by 0.5-20 mm, same orientation
    lifted = poses[kind == NEAR_LIFT]
    up = np.min([np.abs(lifted[:, 2] - s[2]) for s in stable], axis=0)
    assert up.min() >= 4.9e-4 and up.max() <= 0.0201
    # approach: between a stable pose and the planner's start pose (same x, z and rotation)
    approach = poses[kind == NEAR_APPROACH]
    assert np.all(np.isin(approach[:, 0].round(5), stable[:, 0].round(5)))
    starts = [planner.start_pose(scene, s)[1] for s in stable]
    assert approach[:, 1].min() >= min(stable[:, 1]) - 1e-6
    assert approach[:, 1].max() <= max(starts) + 1e-6
    # labels: the planner's ground truth, pose by pose
    fields = near_contact_labels(scene, stable, stable, seed=0)
    mesh = planner.MeshChecker(scene)
    np.testing.assert_allclose(fields["near_penetration"], mesh.penetration(fields["near_poses"]))
    np.testing.assert_allclose(fields["collision_penetration"], mesh.penetration(stable))
    assert 0 < (fields["near_penetration"] > 1e-3).mean() < 1  # both kinds among them
    # the deepest contact's point: where there is one, inside the support's box (support
    # frame), none where nothing touches
    depth, point = mesh.deepest_contacts(fields["near_poses"])
    np.testing.assert_array_equal(depth, mesh.penetration(fields["near_poses"]))
    touching = depth > 0
    assert touching.any() and (~touching).any()
    assert np.isnan(point[~touching]).all() and np.isfinite(point[touching]).all()
    lo, hi = np.asarray(scene.support_bounds, float)
    assert np.all((point[touching] >= lo - 0.01) & (point[touching] <= hi + 0.01))


def test_transit_poses_are_near_the_support_at_the_boundary_and_leave_the_rest_unchanged():
    from omnihang_jax import planner
    from omnihang_jax.collision_data import (
        NEAR_TRANSIT,
        TRANSIT_DEEP,
        TRANSIT_GAP,
        near_contact_labels,
        near_contact_poses,
        observed_gap,
    )
    from sim import camera

    scene = _mug_on_pegboard()
    rng = np.random.default_rng(0)
    cfg = camera.CameraConfig(width=160, height=120, n_points=512)
    obj_eye, sup_eye = camera.default_eyes(scene, rng, cfg)
    clouds = dict(
        object_points=camera.partial_cloud(scene, "object", obj_eye, rng, cfg).points,
        support_points=camera.partial_cloud(scene, "support", sup_eye, rng, cfg).points,
    )
    lo, hi = np.asarray(scene.support_bounds, float)
    stable = np.array([[*(0.5 * (lo + hi)), 1, 0, 0, 0]], float)
    plain, plain_kind = near_contact_poses(scene, stable, np.random.default_rng(3))
    poses, kind = near_contact_poses(scene, stable, np.random.default_rng(3), clouds)
    # the earlier kinds are drawn as before; the transit poses come after them
    np.testing.assert_array_equal(poses[: len(plain)], plain)
    np.testing.assert_array_equal(kind[: len(plain)], plain_kind)
    transit = poses[kind == NEAR_TRANSIT]
    assert 10 <= len(transit) and np.all(kind[len(plain) :] == NEAR_TRANSIT)
    np.testing.assert_allclose(np.linalg.norm(transit[:, 3:], axis=1), 1.0, atol=1e-5)
    b_lo, b_hi = planner.default_bounds(scene)
    assert np.all((transit[:, :3] >= b_lo - 1e-6) & (transit[:, :3] <= b_hi + 1e-6))
    # near the support as the clouds see it, and at the boundary on the full meshes: free, or
    # colliding by at most TRANSIT_DEEP (the deep ones, easy for the NCE, are dropped)
    oc, sc = clouds["object_points"], clouds["support_points"]
    assert np.all(observed_gap(oc, sc, transit) < TRANSIT_GAP)
    pen = planner.MeshChecker(scene).penetration(transit)
    assert pen.max() <= TRANSIT_DEEP + 1e-9
    assert 0.2 < (pen > 1e-3).mean() < 0.8  # both sides of the boundary
    # the gap test against brute force
    strided = oc[np.linspace(0, len(oc) - 1, 256).astype(int)]
    moved = planner.posed_points(transit[:5].astype(float), strided)
    brute = np.linalg.norm(moved[:, :, None] - sc[None, None], axis=-1).min(axis=(1, 2))
    np.testing.assert_allclose(observed_gap(oc, sc, transit[:5]), brute, rtol=1e-5, atol=1e-7)
    # the upper bound: gaps at or beyond it come back as inf, the others unchanged
    bounded = observed_gap(oc, sc, transit[:5], upper=float(np.median(brute)))
    assert np.isinf(bounded).any() and np.isfinite(bounded).any()
    np.testing.assert_allclose(
        bounded[np.isfinite(bounded)], brute[np.isfinite(bounded)], rtol=1e-5
    )
    fields = near_contact_labels(scene, stable, stable, seed=0, clouds=clouds)
    assert np.isfinite(fields["near_gap"]).all() and fields["near_version"] == 2
    assert np.isnan(near_contact_labels(scene, stable, stable, seed=0)["near_gap"]).all()


def test_goal_pass_threshold_and_near_metrics():
    from experiments.train_collision import goal_pass_threshold, near_metrics
    from omnihang_jax.collision_data import NEAR_JITTER, NEAR_STABLE, CollisionData

    kind = np.array([NEAR_STABLE] * 10 + [NEAR_JITTER] * 4, np.int8)
    labels = np.array([False] * 10 + [True, True, False, False])
    data = CollisionData(
        *(np.zeros((1, 4, 3)) for _ in range(4)),
        pair=np.zeros(0, np.int32), poses=np.zeros((0, 7)), labels=np.zeros(0, bool), meta=[],
        near_pair=np.zeros(14, np.int32), near_poses=np.zeros((14, 7)), near_kind=kind,
        near_labels=labels,
    )  # fmt: skip
    stable_scores = np.linspace(0.1, 0.82, 10)  # 0.1, 0.18, ..., 0.82
    scores = np.concatenate([stable_scores, [0.9, 0.6, 0.3, 0.95]])
    # 90 % of the stable poses at or below 0.74: the lowest grid threshold reaching it
    assert goal_pass_threshold(scores, data, 0.9) == 0.74
    assert goal_pass_threshold(scores, data, 0.5) == 0.5  # never below 0.5
    assert goal_pass_threshold(scores, data, 1.0) == 0.82
    m = near_metrics(scores, data, 0.74)
    assert m["goal_pass"] == 0.9 and m["stable_poses"] == 10
    assert m["near"]["n"] == 4 and m["near"]["recall"] == 0.5 and m["near"]["precision"] == 0.5
    assert m["jitter"]["specificity"] == 0.5


def test_crop_support_keeps_the_points_nearest_to_the_object():
    rng = np.random.default_rng(0)
    support = rng.uniform(-0.2, 0.2, (1, 300, 3)).astype(np.float32)
    obj = rng.uniform(-0.01, 0.01, (1, 40, 3)).astype(np.float32)
    near = np.asarray(collision.crop_support(jax.numpy.asarray(obj), support, 20))[0]
    d = np.linalg.norm(support[0][:, None] - obj[0][::1][None], axis=-1).min(1)
    dn = np.linalg.norm(near[:, None] - obj[0][None], axis=-1).min(1)
    assert dn.max() <= np.sort(d)[19] + 1e-6  # the 20 nearest (probes = all 40 points)
    cfg = collision.NCEConfig(
        pointnet="tiny", object_points=32, support_points=32, head=(16,), support_crop_from=96
    )
    assert cfg.support_input == 96  # an NCE with a crop is given the points it crops from


def _patch(rng, n=3000, half=0.03):
    """A 6 x 6 cm flat support patch at z = 0 (~1 mm apart), outward normals +z."""
    pts = np.concatenate([rng.uniform(-half, half, (n, 2)), np.zeros((n, 1))], 1)
    return pts.astype(np.float32), np.tile([0, 0, 1.0], (n, 1)).astype(np.float32)


def test_penetration_test_calls_5mm_inside_colliding_and_5mm_above_free():
    rng = np.random.default_rng(3)
    patch, normals = _patch(rng)
    grid = collision.support_grid(patch, normals, max_voxels=200_000)
    # the lookup table finds the nearest support point (up to half a cell) like the search
    pts = rng.uniform([-0.025, -0.025, -0.008], [0.025, 0.025, 0.008], (1, 200, 3))
    along, length, ok = collision.grid_offsets(grid, jax.numpy.asarray(pts, jax.numpy.float32))
    exact_along, exact_length = collision.nearest_support_offsets(pts, patch, normals)
    assert np.all(np.asarray(ok))
    np.testing.assert_allclose(np.asarray(along), np.asarray(exact_along), atol=1e-6)
    np.testing.assert_allclose(np.asarray(length), np.asarray(exact_length), atol=1.5e-3)
    # a 2 x 2 cm flat object cloud 5 mm inside (below) the patch, and 5 mm above it
    obj = np.concatenate([rng.uniform(-0.01, 0.01, (64, 2)), np.zeros((64, 1))], 1)
    poses = np.array([[0, 0, -0.005, 1, 0, 0, 0], [0, 0, 0.005, 1, 0, 0, 0]], np.float32)
    geo = collision.GeometricConfig(depth=0.002, radius=0.004, min_points=2, object_points=64)
    test = jax.jit(collision.geometric_collides(geo))
    np.testing.assert_array_equal(np.asarray(test(grid, obj, None, poses)), [True, False])
    # beside the patch (5 cm off its edge, 5 mm lower): nothing observed there, free
    beside = np.array([[0.08, 0, -0.005, 1, 0, 0, 0]], np.float32)
    assert not bool(test(grid, obj, None, beside)[0])


def test_planner_labels_allow_the_evaluations_millimetre(tmp_path):
    """Planner labels: a dataset pose touching the support 0.4 mm deep is colliding for the
    dataset but free for the planner (1 mm tolerance); 5 mm deep stays colliding. Training
    rows: the stable poses (free), then the moved near-contact poses (flagged for the near
    share), never the stable or transit near-contact poses."""
    from omnihang_jax.collision_data import load_collision_data
    from omnihang_jax.dataset_bridge import META_KEYS

    rng = np.random.default_rng(0)
    meta = dict(zip(META_KEYS, (7, "mug_0", "hook_0", "mug", "hook", "train"), strict=False))
    poses = np.tile(np.array([0, 0, 0, 1, 0, 0, 0], np.float32), (3, 1))
    np.savez(
        tmp_path / "00007_pair.npz",
        object_points=rng.normal(size=(16, 3)).astype(np.float32),
        object_normals=rng.normal(size=(16, 3)).astype(np.float32),
        support_points=rng.normal(size=(16, 3)).astype(np.float32),
        support_normals=rng.normal(size=(16, 3)).astype(np.float32),
        collision_poses=poses,
        collision_labels=np.array([True, True, False]),
        collision_penetration=np.array([4e-4, 5e-3, 0.0], np.float32),
        stable_poses=poses[:2],
        near_poses=np.tile(poses[:1], (5, 1)),
        near_kind=np.array([0, 1, 1, 3, 4], np.int8),
        near_penetration=np.array([0.0, 2e-3, 1e-4, 0.0, 2e-3], np.float32),
        **{k: np.asarray(v) for k, v in meta.items()},
    )
    files = [tmp_path / "00007_pair.npz"]
    dataset = load_collision_data(files)
    planner = load_collision_data(files, training=True, planner_labels=True)
    np.testing.assert_array_equal(dataset.labels, [True, True, False])
    assert dataset.far_poses is None and len(dataset.near_kind) == 5  # metrics only
    np.testing.assert_array_equal(planner.labels, [False, True, False])
    np.testing.assert_array_equal(planner.far_labels, [False, False, True, False, False])
    np.testing.assert_array_equal(planner.far_near, [False, False, True, True, True])


def test_mesh_clearance_grows_as_the_object_moves_away_and_is_negative_inside():
    """``MeshChecker.clearance``: the smallest part-to-part distance, capped; it grows with a straight move away from the support, is
    negative where the meshes overlap (the penetration test agrees) and reads the cap far off."""
    from omnihang_jax import planner

    scene = _mug_on_pegboard()
    mesh = planner.MeshChecker(scene)
    lo, hi = np.asarray(scene.support_bounds, float)
    centre = 0.5 * (lo + hi)
    gaps = np.array([0.002, 0.01, 0.02, 1.0])
    inside = np.array([*centre, 1, 0, 0, 0], float)
    out = np.stack([inside.copy() for _ in range(4)])
    out[:, 1] = hi[1] - float(np.asarray(scene.obj.bounds())[0][1]) + gaps  # wholly in front
    c_in = mesh.clearance(inside)
    assert c_in[0] < 0 and mesh(inside[None])[0]
    c = mesh.clearance(out, cap=0.05)
    assert np.all(np.diff(c) >= -1e-9) and c[-1] == pytest.approx(0.05)
    # at least the gap to the support's front plane; an 8-mm step adds at most 8 mm
    assert np.all(c[:3] >= gaps[:3] - 1e-4) and 0.002 < c[1] - c[0] <= 0.008 + 1e-6
