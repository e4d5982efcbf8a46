"""Shape completion (omnihang_jax.completion, sim.camera.surface_cloud): the whole-surface target
covers what one camera misses, the Chamfer loss and coverage metrics are right on known sets,
a tiny network learns to fill the hidden half of a sphere, training resumes, bad clouds fail."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from omnihang_jax import completion
from sim import camera
from sim.assets.base import Asset
from sim.scene import build_scene

from .test_kernels import make_ring, support_of

TINY_NET = completion.CompletionConfig(
    kind="object", n_input=128, scale=0.05, encoder=(16, 32), encoder2=(32, 64), decoder=(64,),
    n_coarse=32, fold=(2, 2), fine=(32,),
)  # fmt: skip


def test_sphere_directions_are_unit_and_spread():
    d = camera.sphere_directions(42)
    assert d.shape == (42, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert np.linalg.norm(d.mean(axis=0)) < 0.05
    with pytest.raises(ValueError):
        camera.sphere_directions(0)


def test_surface_cloud_covers_what_one_camera_misses():
    ring: Asset = make_ring()
    scene = build_scene(ring, support_of("single_rod_hook"))
    cfg = camera.CameraConfig(width=160, height=120, n_points=512)
    rng = np.random.default_rng(0)
    whole = camera.surface_cloud(scene, "object", rng, cfg, n_dirs=26, n_points=1024)
    assert whole.shape == (1024, 3) and np.isfinite(whole).all()
    eye, _ = camera.default_eyes(scene, rng, cfg)
    part = camera.partial_cloud(scene, "object", eye, rng, cfg).points
    # every observed point lies on the whole surface; much of the whole surface is unobserved
    assert np.percentile(cKDTree(whole).query(part)[0], 95) < 0.004
    unseen = cKDTree(part).query(whole)[0] > 0.003
    assert 0.2 < unseen.mean() < 0.8
    # the whole surface reaches round the back: both sides of the ring's plane, all around
    assert whole[:, 2].min() < -0.002 and whole[:, 2].max() > 0.002


def test_chamfer_and_coverage_on_known_sets():
    a = jnp.asarray([[[0.0, 0, 0], [1.0, 0, 0]]])
    assert float(completion.chamfer(a, a)[0]) == pytest.approx(0.0, abs=1e-5)
    b = jnp.asarray([[[0.0, 0, 0]]])
    # a -> b: (0 + 1) / 2; b -> a: 0
    assert float(completion.chamfer(a, b)[0]) == pytest.approx(0.5, abs=1e-5)
    assert float(completion.chamfer(b, a)[0]) == pytest.approx(0.5, abs=1e-5)
    target = jnp.asarray([[[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]]])
    observed = jnp.asarray([[[0.0, 0, 0], [1.0, 0, 0]]])
    pred = jnp.asarray([[[2.0, 0, 0], [9.0, 0, 0]]])
    m = completion.coverage(pred, target, observed, tol=0.1)
    assert float(m["observed_coverage"][0]) == pytest.approx(0.5)
    assert float(m["coverage"][0]) == pytest.approx(0.75)
    assert float(m["accuracy"][0]) == pytest.approx(0.5)


def _sphere_views(n_bodies: int, n_views: int, seed: int) -> completion.CompletionData:
    """Spheres of random radius and centre; each view is the half facing a random camera."""
    rng = np.random.default_rng(seed)
    inputs, targets = [], []
    for _ in range(n_bodies):
        r, c = rng.uniform(0.02, 0.05), rng.normal(scale=0.02, size=3)
        u = rng.normal(size=(4000, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        targets.append(c + r * u[:256])
        views = []
        for _ in range(n_views):
            eye = rng.normal(size=3)
            eye /= np.linalg.norm(eye)
            half = u[u @ eye > 0.1]
            views.append(c + r * half[rng.choice(len(half), 256)])
        inputs.append(np.stack(views))
    return completion.CompletionData(
        np.asarray(inputs, np.float32), np.asarray(targets, np.float32), np.arange(n_bodies)
    )


def test_a_tiny_network_learns_the_hidden_half(tmp_path):
    train, val = _sphere_views(24, 4, 0), _sphere_views(6, 4, 1)
    _, apply = completion.make_completion(TINY_NET)
    tc = completion.CompletionTrainConfig(steps=300, batch=16, lr=3e-3, warmup=20, eval_every=100)
    summary = completion.train_completion(TINY_NET, train, val, tmp_path, tc, progress=False)
    rows = [json.loads(x) for x in (tmp_path / "history.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [100, 200, 300]
    config, params, meta = completion.load_completion(tmp_path)
    assert config == TINY_NET and meta["step"] == summary["best_step"]
    m = completion.evaluate(apply, params, val, config, tol=0.005)
    # untrained: the same network at its initial weights
    init, _ = completion.make_completion(TINY_NET)
    m0 = completion.evaluate(apply, init(jax.random.key(0)), val, config, tol=0.005)
    assert m["chamfer_mm"] < 0.5 * m0["chamfer_mm"]
    # observed + predicted covers more of the sphere than the observed half alone
    assert m["coverage_10mm"] > m["observed_coverage_10mm"] + 0.15
    assert (tmp_path / "curves.png").exists()


def test_training_resumes_and_refuses_another_network(tmp_path):
    train, val = _sphere_views(8, 2, 0), _sphere_views(2, 2, 1)
    tc = completion.CompletionTrainConfig(steps=20, batch=8, warmup=5, eval_every=10)
    completion.train_completion(TINY_NET, train, val, tmp_path, tc, progress=False)
    longer = dataclasses.replace(tc, steps=30)
    completion.train_completion(TINY_NET, train, val, tmp_path, longer, progress=False)
    steps = [json.loads(x)["step"] for x in (tmp_path / "history.jsonl").read_text().splitlines()]
    assert steps == [10, 20, 30]  # resumed at 20, not retrained from 0
    other = dataclasses.replace(TINY_NET, n_coarse=16)
    with pytest.raises(ValueError, match="another network"):
        completion.train_completion(other, train, val, tmp_path, longer, progress=False)


def test_predict_points_shapes_and_bad_clouds(tmp_path):
    init, _ = completion.make_completion(TINY_NET)
    params = init(jax.random.key(1))
    sup_cfg = dataclasses.replace(TINY_NET, kind="support")
    nets = {"object": (TINY_NET, params), "support": (sup_cfg, params)}
    rng = np.random.default_rng(0)
    obj, sup = rng.normal(size=(300, 3)) * 0.03, rng.normal(size=(50, 3)) * 0.05
    po, ps = completion.predict_points(nets, obj, sup)
    assert po.shape == ps.shape == (TINY_NET.n_output, 3) and np.isfinite(po).all()
    # in the cloud's frame: moving the cloud moves the prediction with it
    po2, _ = completion.predict_points(nets, obj + [1.0, 0, 0], sup)
    np.testing.assert_allclose(po2, po + [1.0, 0, 0], atol=1e-4)
    o, s = completion.clearance_clouds(obj, sup, po, ps, n_object=64)
    assert o.shape == (64 + 64, 3) and s.shape == (50 + TINY_NET.n_output, 3)
    # every observed support point is kept; the object's are a subset of observed + predicted
    np.testing.assert_array_equal(s[:50], sup)
    assert np.isin(o[:64], obj).all(axis=1).all() and np.isin(o[64:], po).all(axis=1).all()
    # carving that leaves no predicted points: the observed subset alone
    o2, _ = completion.clearance_clouds(obj, sup, np.zeros((0, 3)), np.zeros((0, 3)), n_object=64)
    assert o2.shape == (64, 3)
    # with cameras, fewer points: those the cameras would have seen are carved away
    pc, sc = completion.predict_points(nets, obj, sup, eyes=([0, -1.0, 0], [0, -1.0, 0]))
    assert len(pc) <= len(po) and len(sc) <= len(ps)
    bad = obj.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        completion.predict_points(nets, bad, sup)
    with pytest.raises(ValueError, match=r"\[N>0, 3\]"):
        completion.predict_points(nets, np.zeros((0, 3)), sup)
    # saved and loaded: the same predictions
    completion.save_completion(tmp_path / "object", TINY_NET, params)
    completion.save_completion(tmp_path / "support", sup_cfg, params)
    po3, _ = completion.predict_points(str(tmp_path), obj, sup)
    np.testing.assert_allclose(po3, po, atol=1e-6)
    with pytest.raises(FileNotFoundError, match="train_completion"):
        completion.load_completion(tmp_path / "missing")


def test_carving_keeps_the_hidden_back_and_drops_what_the_camera_saw_empty():
    rng = np.random.default_rng(0)
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    eye = np.array([0.0, -0.5, 0.0])
    r = 0.05
    seen = r * u[u[:, 1] < -0.05]  # the half of the sphere facing the camera (y < 0)
    back = r * u[u[:, 1] > 0.05][:300]  # the hidden half
    beside = back + [0.2, 0.0, 0.0]  # a phantom beside the body: the camera saw empty space there
    front = r * u[u[:, 1] < -0.3][:300] * 0.5 + [0, -0.1, 0]  # floating between camera and body
    pred = np.concatenate([back, beside, front])
    kept, mask = completion.carve(pred, seen, eye)
    assert mask[:300].mean() > 0.9  # the hidden back stays
    assert mask[300:600].mean() < 0.05  # beside the silhouette: gone
    assert mask[600:].mean() < 0.05  # in front of the observed surface: gone
    assert len(kept) == mask.sum()


def test_depth_map_measures_how_far_behind_the_seen_surface_along_the_ray():
    """The sphere's camera-facing half seen from y = -0.5: its centre lies one radius behind
    the surface along the ray, the hidden back point a diameter, a point in front negative,
    and a direction the camera saw empty is -inf (scripts/probe_shadow.py's slab test)."""
    rng = np.random.default_rng(0)
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = 0.05
    seen = r * u[u[:, 1] < -0.05]
    behind = completion.depth_map(seen, [0.0, -0.5, 0.0])
    got = behind(np.array([[0, 0, 0], [0, r, 0], [0, -r - 0.01, 0], [0.2, 0, 0]], float))
    np.testing.assert_allclose(got[:3], [r, 2 * r, -0.01], atol=0.003)
    assert got[3] == -np.inf


def test_the_hang_commands_far_test_on_completed_clouds(tmp_path):
    from omnihang_jax import hang

    init, _ = completion.make_completion(TINY_NET)
    params = init(jax.random.key(2))
    completion.save_completion(tmp_path / "object", TINY_NET, params)
    completion.save_completion(
        tmp_path / "support", dataclasses.replace(TINY_NET, kind="support"), params
    )
    rng = np.random.default_rng(0)
    u = rng.normal(size=(600, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    ball = 0.03 * u[u[:, 1] < 0]  # the half of a 3 cm ball its camera sees
    eye = np.array([0.0, -0.4, 0.0])

    def body(kind, points, eye):
        return hang.Body(kind, kind, "builtin", None, points, points, None, eye, {})

    obj, sup = body("object", ball, eye), body("support", ball + [0.0, 0.0, -0.1], eye)
    goal = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    test, info = hang.completed_far_test(obj, sup, goal, 0.05, folder=tmp_path)
    assert test is not None and info["used"] and info["support_points_added"] >= 0
    # far from the goal: the object pressed onto the support collides, lifted clear it does not
    far_down = np.array([0.0, 0.0, -0.1, 1.0, 0.0, 0.0, 0.0])  # inside the support ball
    far_up = np.array([0.3, 0.0, 0.3, 1.0, 0.0, 0.0, 0.0])
    assert test(np.stack([far_down, far_up])).tolist() == [True, False]
    # the goal's neighbourhood is left to the hybrid
    assert test(goal[None]).tolist() == [False]
    # a body given as a cloud has no camera: no carving, no test
    none, why = hang.completed_far_test(
        obj, body("support", sup.points, None), goal, 0.05, tmp_path
    )
    assert none is None and "camera" in why["why"]
    assert hang.completed_far_test(obj, sup, goal, 0.05, folder=tmp_path / "nothing")[0] is None


def test_carving_a_cloud_with_repeated_points_matches_its_distinct_points():
    # a partial cloud drawn with replacement repeats points; its carving must not collapse
    rng = np.random.default_rng(1)
    u = rng.normal(size=(6000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    eye = np.array([0.0, -0.5, 0.0])
    seen = 0.05 * u[u[:, 1] < -0.05][:1500]
    repeated = np.concatenate([seen, seen[: len(seen) * 3 // 4]])  # most points twice
    pred = np.concatenate(
        [0.05 * u[u[:, 1] > 0.05][:300], 0.05 * u[u[:, 1] > 0.05][:300] + [0.2, 0, 0]]
    )
    with np.errstate(all="raise"):  # no division by a zero cell
        _, mask = completion.carve(pred, repeated, eye)
    _, mask_distinct = completion.carve(pred, seen[::-1], eye)  # (order does not matter)
    np.testing.assert_array_equal(mask, mask_distinct)
    assert mask[:300].mean() > 0.9 and mask[300:].mean() < 0.05
    with pytest.raises(ValueError, match="two distinct points"):
        completion.carve(pred, np.repeat(seen[:1], 10, axis=0), eye)
