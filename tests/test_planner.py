"""The planner and its ground truth: RRT-Connect goes around an obstacle that an exact checker
describes, the mesh check rejects a path through the support and accepts one that threads a
ring onto a hook, and the batched estimator checker agrees with per-pose calls."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("ompl")

from omnihang_jax import planner, retreats  # noqa: E402
from sim import geometry, proposals  # noqa: E402
from sim.assets import objects, supports  # noqa: E402, F401  (registers the generators)
from sim.assets.base import Asset, HangLoop, build_object, build_support  # noqa: E402
from sim.scene import build_scene  # noqa: E402

FAST = planner.PlannerConfig(time_limit=10.0)
# An L-shaped tunnel around the origin: a corridor under a ceiling that opens 3 cm to +x into a
# shaft going up (the two-move retreat and route-table tests)
L_TUNNEL = [
    ([-0.2, -0.2, -0.2], [0.2, 0.2, -0.015]),  # floor
    ([-0.2, -0.2, 0.015], [0.015, 0.2, 0.2]),  # ceiling over the goal, up to x = 0.015
    ([0.05, -0.2, -0.2], [0.2, 0.2, 0.2]),  # the shaft's far wall
    ([-0.2, -0.2, -0.2], [-0.015, 0.2, 0.2]),  # behind the goal
    ([-0.2, 0.015, -0.2], [0.2, 0.2, 0.2]),  # the corridor's sides
    ([-0.2, -0.2, -0.2], [0.2, -0.015, 0.2]),
]


def test_planner_goes_around_an_obstacle_with_an_exact_checker():
    # a slab between start and goal (|x| < 5 cm, z < 30 cm); the sphere (r 2 cm) must pass over it
    slab = planner.AnalyticChecker([([-0.05, -1.0, -1.0], [0.05, 1.0, 0.3])], radius=0.02)
    start = np.array([-0.3, 0.0, 0.0, 1, 0, 0, 0])
    goal = np.array([0.3, 0.0, 0.0, 0, 0, 0, 1])  # half a turn too
    bounds = (np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.5, 0.6]))
    straight = planner.interpolate_path(np.stack([start, goal]), 0.002, 0.05)
    assert slab(straight).any(), "the straight path must be blocked, or the test proves nothing"

    res = planner.plan(slab, start, goal, bounds, 0.05, FAST)

    assert res.status == "Exact solution" and res.path is not None
    np.testing.assert_allclose(res.path[0], start, atol=1e-9)
    np.testing.assert_allclose(res.path[-1][:3], goal[:3], atol=1e-9)
    assert abs(abs(np.dot(res.path[-1][3:], goal[3:])) - 1) < 1e-9
    dense = planner.interpolate_path(res.path, 0.002, 0.05)
    assert not slab(dense).any()
    assert dense[:, 2].max() > 0.32  # it went over the slab
    assert res.checker_calls < res.states_checked  # motions were checked in batches


def test_interpolation_matches_omplish_slerp_and_keeps_unit_quaternions():
    a = np.array([0, 0, 0, 1, 0, 0, 0.0])
    b = np.array([1, 0, 0, 0, 0, 0, 1.0])  # half a turn about z
    seg = planner.interpolate_segment(a, b, 4)
    np.testing.assert_allclose(np.linalg.norm(seg[:, 3:], axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(seg[1, 3:], [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)], atol=1e-12)
    np.testing.assert_allclose(seg[-1], b, atol=1e-12)


def _mug_on_rod():
    return build_object("mug", 3), build_support("single_rod_hook", 0)


def test_straight_path_through_the_support_is_rejected_by_the_mesh_check():
    obj, sup = _mug_on_rod()
    scene = build_scene(obj, sup)
    mesh = planner.MeshChecker(scene)
    weight = planner.object_radius(scene)
    # the mug's centre moves along y straight through the middle of the hook's rod
    peg = sup.features[0]
    through = 0.5 * (np.asarray(peg.base) + np.asarray(peg.tip))
    front = planner.start_pose(scene, np.array([*through, 1, 0, 0, 0]))
    behind = front.copy()
    behind[1] = through[1] - (front[1] - through[1])
    path = np.stack([front, behind])

    free, deepest, n = planner.dense_check(mesh, path, 0.002, weight)

    assert not free and deepest > 1e-3 and n > 100
    # the same distance moved sideways in front of the support stays free
    aside = front.copy()
    aside[0] += front[1] - behind[1]
    assert planner.dense_check(mesh, np.stack([front, aside]), 0.002, weight)[0]


def ring_on_rod():
    """(scene, goal, peg): a 3-cm ring threaded exactly half way along a single-rod hook
    (also tests/test_approach.py)."""
    parts = geometry.ring([0, 0, 0], [0, 0, 1], 0.03, 0.004, 12)
    free_r = 0.03 * np.cos(np.pi / 12) - 0.004
    ring = Asset("ring", "object", "others", 0, parts, [HangLoop(np.zeros(3), np.array([0, 0, 1.0]), free_r)], {})  # fmt: skip
    hook = build_support("single_rod_hook", 0)
    loop, peg = ring.features[0], hook.features[0]
    exact = proposals.ProposalConfig(jitter_angle=0.0, jitter_position=0.0)
    lo, hi, _ = proposals._peg_range(ring, loop, peg, 1.0, exact)
    goal = proposals.thread_pose(ring, loop, peg, 0.5 * (lo + hi), 1.0, exact)
    return build_scene(ring, hook), goal, peg


def test_mesh_planner_threads_a_ring_onto_a_hook():
    scene, goal, _ = ring_on_rod()
    mesh = planner.MeshChecker(scene)
    assert not mesh(goal[None])[0], "the threaded pose is free of penetration"
    start = planner.start_pose(scene, goal)
    weight = planner.object_radius(scene)

    res = planner.plan(mesh, start, goal, planner.default_bounds(scene), weight, FAST)

    assert res.path is not None, res.status
    free, deepest, _ = planner.dense_check(mesh, res.path, 0.002, weight)
    assert free, f"the mesh planner's own path penetrates {deepest * 1e3:.2f} mm"


def test_estimator_checker_batches_agree_with_single_calls():
    import jax

    from omnihang_jax import collision

    cfg = collision.NCE_PRESETS["tiny"]
    params = collision.make_nce(cfg).init(jax.random.key(0))
    rng = np.random.default_rng(0)
    oc = rng.uniform(-0.03, 0.03, (cfg.object_points, 3))
    sc = rng.uniform(-0.05, 0.05, (cfg.support_points, 3))
    prob = jax.jit(collision.nce_probability(cfg))
    poses = np.concatenate([rng.uniform(-0.05, 0.05, (8, 3)), rng.normal(size=(8, 4))], 1)
    poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    p = np.asarray(prob(params, oc, sc, poses))
    thr = float(np.median(p))  # about half the poses collide
    checker = planner.EstimatorChecker(lambda *a: prob(*a) > thr, params, oc, sc)
    batched = checker(poses[:5])  # padded to 8; a single call is a batch of 1
    single = np.array([checker(x[None])[0] for x in poses[:5]])
    np.testing.assert_array_equal(batched, single)
    np.testing.assert_array_equal(batched, p[:5] > thr)
    eight = planner.EstimatorChecker(lambda *a: prob(*a) > thr, params, oc, sc, min_batch=8)
    np.testing.assert_array_equal(np.array([eight(x[None])[0] for x in poses[:5]]), single)
    assert checker(poses[:0]).shape == (0,)
    with pytest.raises(ValueError, match="power of two"):
        planner.EstimatorChecker(lambda *a: prob(*a) > thr, params, oc, sc, min_batch=3)
    sizes = [checker.padded_size(b) for b in (1, 2, 3, 5, 8, 9, 17, 36, 137)]
    assert sizes == [1, 2, 4, 8, 8, 16, 24, 40, 144]


def test_any_colliding_checks_coarse_states_first_with_the_same_answer():
    """An edge's states: 8 evenly spaced ones first (the far end among them), the rest only
    when those are free; the answer is always that of one call on all states."""
    batches = []

    def collides(params, object_cloud, support_cloud, poses):  # x inside the slab
        batches.append(len(poses))
        x = np.asarray(poses)[:, 0]
        return (x > params[0]) & (x < params[1])

    oc = sc = np.zeros((4, 3), np.float32)
    edge = np.tile(np.array([0, 0, 0, 1, 0, 0, 0], np.float32), (36, 1))
    edge[:, 0] = np.arange(1, 37) / 36  # x from 1/36 to 1
    cases = [((0.3, 0.5), True, [8]), ((2.0, 3.0), False, [8, 32]), ((0.05, 0.07), True, [8, 32])]
    for slab, want, calls in cases:  # a wide run (caught coarse), none, a narrow run (fine)
        checker = planner.EstimatorChecker(collides, np.array(slab), oc, sc)
        batches.clear()
        assert checker.any_colliding(edge) is want
        assert batches == calls
        assert bool(checker(edge).any()) is want
    checker = planner.EstimatorChecker(collides, np.array((0.3, 0.5)), oc, sc)
    batches.clear()
    assert checker.any_colliding(edge[:16]) and batches == [16]  # short edges: one call


class _Counting:
    """A checker that records the batches it was asked about."""

    def __init__(self, checker):
        self.checker, self.batches = checker, []

    def __call__(self, poses):
        self.batches.append(len(poses))
        return self.checker(poses)


def test_planner_goes_around_two_obstacles_with_a_cascade():
    """RRT-Connect with a CascadeChecker of two exact checkers avoids both obstacles."""
    slab = planner.AnalyticChecker([([-0.05, -1.0, -1.0], [0.05, 1.0, 0.3])], radius=0.02)
    roof = _Counting(planner.AnalyticChecker([([-0.05, -1.0, 0.45], [0.05, 1.0, 1.0])], 0.02))
    start = np.array([-0.3, 0.0, 0.0, 1, 0, 0, 0])
    goal = np.array([0.3, 0.0, 0.0, 1, 0, 0, 0])
    bounds = (np.array([-0.5, -0.5, -0.5]), np.array([0.5, 0.5, 0.6]))
    cascade = planner.CascadeChecker(slab, roof)
    res = planner.plan(cascade, start, goal, bounds, 0.05, FAST)
    assert res.status == "Exact solution"
    dense = planner.interpolate_path(res.path, 0.002, 0.05)
    assert not slab(dense).any() and not roof.checker(dense).any()
    assert 0.32 < dense[np.abs(dense[:, 0]) < 0.05, 2].min()  # through the gap between them
    assert sum(roof.batches) < cascade.states_first  # the second saw fewer states


def test_goal_distances_equal_pose_distance():
    rng = np.random.default_rng(2)
    poses = np.concatenate([rng.normal(0, 0.1, (20, 3)), rng.normal(size=(20, 4))], 1)
    goal = poses[3].copy()
    want = [planner.pose_distance(p, goal, 0.07) for p in poses]
    np.testing.assert_allclose(planner.goal_distances(poses, goal, 0.07), want, atol=1e-9)
    assert planner.goal_distances(poses, goal, 0.07)[3] < 1e-6


def _slot():
    """A goal at the bottom of a square vertical shaft 8 cm deep (walls 1.2 cm from the axis,
    a floor) for a sphere of radius 1 cm: it fits with 2 mm to spare, so the only retreat is
    straight up."""
    w = 0.012
    boxes = [
        ([-0.2, -0.2, -0.2], [-w, 0.2, 0.08]),
        ([w, -0.2, -0.2], [0.2, 0.2, 0.08]),
        ([-0.2, -0.2, -0.2], [0.2, -w, 0.08]),
        ([-0.2, w, -0.2], [0.2, 0.2, 0.08]),
        ([-0.2, -0.2, -0.2], [0.2, 0.2, -0.015]),  # floor
    ]
    checker = planner.AnalyticChecker(boxes, radius=0.01)
    goal = np.array([0.0, 0.0, 0.0, 1, 0, 0, 0])
    return checker, goal


def test_retreat_leaves_a_slot_along_its_open_direction_and_is_deterministic():
    checker, goal = _slot()
    # every direction but straight up is blocked within 2 cm
    found = retreats.find_retreat(checker, goal, (0.02, 0.06), 0.005)
    assert found is not None
    np.testing.assert_allclose(found.direction, [0, 0, 1])
    assert found.length == 0.02 and found.states_checked >= 4
    np.testing.assert_allclose(found.pregoal, [0, 0, 0.02, 1, 0, 0, 0])
    seg = planner.interpolate_segment(goal, found.pregoal, 20)
    assert not checker(seg).any()
    again = retreats.find_retreat(checker, goal, (0.02, 0.06), 0.005)
    np.testing.assert_array_equal(again.pregoal, found.pregoal)
    # a lid over the slot: no straight retreat of 2 cm is free, so none is returned
    lid = planner.AnalyticChecker([*checker.boxes, ([-0.2, -0.2, 0.025], [0.2, 0.2, 0.2])], 0.01)
    assert retreats.find_retreat(lid, goal, (0.02,), 0.005) is None


def test_plan_with_retreat_ends_straight_in_at_the_goal_or_falls_back():
    checker, goal = _slot()
    start = np.array([0.3, 0.0, 0.3, 1, 0, 0, 0])
    bounds = (np.array([-0.4, -0.4, -0.1]), np.array([0.4, 0.4, 0.5]))
    # 10 cm up clears the shaft; RRT-Connect alone would have to find its 4-mm-wide opening
    cfg = planner.PlannerConfig(time_limit=10.0, retreat_lengths=(0.1,))
    res, found = retreats.plan_with_retreat(checker, start, goal, bounds, 0.05, cfg)
    assert found is not None and res.path is not None
    np.testing.assert_allclose(res.path[-1], goal)
    np.testing.assert_allclose(res.path[-2], found.pregoal, atol=1e-9)
    dense = planner.interpolate_path(res.path, 0.002, 0.05)
    assert not checker(dense).any()
    assert res.states_checked > found.states_checked and res.planning_s >= found.seconds
    # retreat off: the plain plan, no retreat searched
    plain, none = retreats.plan_with_retreat(checker, start, goal, bounds, 0.05, FAST)
    assert none is None and plain.status in ("Exact solution", "Approximate solution", "Timeout")
    # no free retreat (a lid over the shaft): the plain plan
    lid = planner.AnalyticChecker([*checker.boxes, ([-0.2, -0.2, 0.03], [0.2, 0.2, 0.04])], 0.01)
    quick = planner.PlannerConfig(time_limit=0.5, retreat_lengths=(0.1,))
    _, blocked = retreats.plan_with_retreat(lid, start, goal, bounds, 0.05, quick)
    assert blocked is None


def test_posed_points_matches_the_jax_transform():
    """planner.posed_points (NumPy, host checkers) = collision.transform_points (JAX)."""
    from omnihang_jax import collision

    rng = np.random.default_rng(0)
    poses = np.concatenate([rng.normal(size=(5, 3)), rng.normal(size=(5, 4))], axis=1)
    points = rng.normal(size=(7, 3))
    want = np.asarray(
        collision.transform_points(poses.astype(np.float32), points.astype(np.float32))
    )
    np.testing.assert_allclose(planner.posed_points(poses, points), want, rtol=1e-4, atol=1e-5)


def test_goal_ball_nce_and_the_hang_hybrid_checker():
    """collision.goal_ball_collides: the NCE's own threshold within the ball of the goal,
    the far threshold beyond it; planner.hybrid_checker (the `hang` command's checker) calls
    exactly the observed-cloud test OR that NCE, with the settings of a selection file."""
    import dataclasses

    import jax

    from omnihang_jax import collision

    rng = np.random.default_rng(7)
    n = 4096  # a 6 x 6 cm flat support patch at z = 0, outward normals +z
    patch = np.concatenate([rng.uniform(-0.03, 0.03, (n, 2)), np.zeros((n, 1))], 1)
    patch, normals = patch.astype(np.float32), np.tile([0, 0, 1.0], (n, 1)).astype(np.float32)
    obj = rng.uniform(-0.01, 0.01, (4096, 3)).astype(np.float32)
    cfg = collision.NCE_PRESETS["tiny"]
    params = collision.make_nce(cfg).init(jax.random.key(1))
    goal = np.array([0, 0, 0.004, 1, 0, 0, 0], np.float32)
    poses = np.tile(goal, (40, 1))
    poses[:, :3] += rng.normal(0, 0.02, (40, 3)) * np.linspace(0.1, 2.0, 40)[:, None]
    q = rng.normal(size=(40, 4)) * 0.05 + [1, 0, 0, 0]
    poses[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
    poses[:, 2] = np.abs(poses[:, 2])  # most above the patch, a few close to it
    poses[:4, 2] = -0.006  # 6 mm into it: the test's
    oc, sc = (collision.subsample_cloud(obj, cfg.object_input, 0),
              collision.subsample_cloud(patch, cfg.support_input, 1))  # fmt: skip
    p = np.asarray(jax.jit(collision.nce_probability(cfg))(params, oc, sc, poses))
    near_t, far_t, ball, weight = float(np.quantile(p, 0.8)), float(np.quantile(p, 0.3)), 0.02, 0.05
    dist = np.array([planner.pose_distance(x, goal, weight) for x in poses])
    assert (dist <= ball).any() and (dist > ball).any()
    fn = collision.goal_ball_collides(dataclasses.replace(cfg, threshold=near_t), far_t, ball)
    got = np.asarray(jax.jit(fn)((params, goal, np.float32(weight)), oc, sc, poses))
    np.testing.assert_array_equal(got, p > np.where(dist <= ball, near_t, far_t))
    assert (got != (p > far_t)).any() and (got != (p > near_t)).any()  # both sides matter

    geo = collision.GeometricConfig(depth=0.002, radius=0.004, min_points=2)
    settings = planner.HybridSettings(geo, far_t, near_t, ball)
    checker = planner.hybrid_checker(cfg, params, obj, patch, normals, settings, goal, weight)
    grid = collision.support_grid(patch, normals, geo.voxel, geo.max_voxels, geo.margin)
    test = np.asarray(jax.jit(collision.geometric_collides(geo))(
        grid, collision.subsample_cloud(obj, geo.object_points, 0), grid.points, poses))  # fmt: skip
    assert test[:4].all() and not test.all()
    np.testing.assert_array_equal(checker(poses), test | got)


def _box_surface(lo, hi, n=30):
    """Points on the faces of an axis-aligned box (an observed support cloud)."""
    g = np.linspace(0, 1, n)
    u, v = np.meshgrid(g, g)
    u, v = u.ravel(), v.ravel()
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pts = []
    for axis in range(3):
        a, b = [i for i in range(3) if i != axis]
        for side in (lo[axis], hi[axis]):
            p = np.zeros((len(u), 3))
            p[:, axis] = side
            p[:, a] = lo[a] + u * (hi[a] - lo[a])
            p[:, b] = lo[b] + v * (hi[b] - lo[b])
            pts.append(p)
    return np.concatenate(pts)


def _clearance_along(path, support, weight=0.05):
    dense = planner.interpolate_path(path, 0.002, weight)
    from scipy.spatial import cKDTree

    return cKDTree(support).query(dense[:, :3])[0], dense


def test_clear_path_moves_a_grazing_path_away_and_keeps_it_free_and_its_ends():
    """A straight path 1 cm over a box (the support) is lifted towards the target clearance:
    the ends and the goal's neighbourhood stay, every state stays free for the checker, and
    the observed clearance along the path grows."""
    lo, hi = (-0.1, -0.1, -0.1), (0.1, 0.1, 0.1)
    checker = planner.AnalyticChecker([(lo, hi)], radius=0.005)
    support = _box_surface(lo, hi)
    q = [1.0, 0, 0, 0]
    start, goal = np.array([0, -0.3, 0.11, *q]), np.array([0, 0.3, 0.11, *q])
    path = np.stack([start, goal])
    bounds = (np.full(3, -0.5), np.full(3, 0.5))
    cfg = planner.ClearanceConfig(target=0.04, keep_ball=0.05)
    out = planner.clear_path(path, checker, np.zeros((1, 3)), support, goal, 0.05, bounds,
                             0.005, cfg)  # fmt: skip
    before, _ = _clearance_along(path, support)
    after, dense = _clearance_along(out.path, support)
    assert np.allclose(out.path[0], start) and np.allclose(out.path[-1], goal)
    assert not checker(dense).any()
    assert before.min() < 0.0125 and out.gap_before < 0.0125
    over_box = np.abs(dense[:, 1]) < 0.1  # the part above the box, far from both ends
    assert after[over_box].min() > 0.035 and out.gap_after > 0.035
    assert out.moves > 0 and out.removed > 0  # lifted, then the straight stretches merged
    near_goal = planner.goal_distances(out.path, goal, 0.05) <= 0.05
    assert np.all(out.path[near_goal, 2] == pytest.approx(0.11))  # the goal ball untouched


def test_clear_path_never_pushes_into_what_the_checker_blocks():
    """A ceiling 3 cm over the box: the path rises only as far as the checker allows."""
    lo, hi = (-0.1, -0.1, -0.1), (0.1, 0.1, 0.1)
    ceiling = ((-0.2, -0.2, 0.13), (0.2, 0.2, 0.2))
    checker = planner.AnalyticChecker([(lo, hi), ceiling], radius=0.005)
    support = _box_surface(lo, hi)  # the ceiling is not observed: only the checker knows it
    q = [1.0, 0, 0, 0]
    start, goal = np.array([0, -0.3, 0.11, *q]), np.array([0, 0.3, 0.11, *q])
    bounds = (np.full(3, -0.5), np.full(3, 0.5))
    out = planner.clear_path(np.stack([start, goal]), checker, np.zeros((1, 3)), support, goal,
                             0.05, bounds, 0.005, planner.ClearanceConfig(target=0.05))  # fmt: skip
    _, dense = _clearance_along(out.path, support)
    assert not checker(dense).any()
    assert out.moves > 0 and 0.012 < out.gap_after < 0.025


def test_the_retreat_can_be_chosen_by_another_checker():
    """``plan_with_retreat(retreat_checker=...)``: the retreat's
    direction comes from the second checker, the search still from the first. A checker that
    wrongly calls the shaft's walls free would leave sideways (its first direction in order
    after straight up is blocked by nothing it knows); the exact checker sends it up."""
    exact, goal = _slot()
    blind = planner.AnalyticChecker([([-0.2, -0.2, -0.2], [0.2, 0.2, -0.015])], radius=0.01)
    lid = planner.AnalyticChecker([([-0.2, -0.2, 0.02], [0.2, 0.2, 0.2])], radius=0.01)
    # the blind checker with a lid over the goal: up is blocked for it, sideways is not
    blind_lid = planner.AnalyticChecker([*blind.boxes, *lid.boxes], radius=0.01)
    assert retreats.find_retreat(blind_lid, goal, (0.03,), 0.005).direction[2] <= 0
    start = np.array([0.3, 0.0, 0.3, 1, 0, 0, 0])
    bounds = (np.array([-0.4, -0.4, -0.1]), np.array([0.4, 0.4, 0.5]))
    cfg = planner.PlannerConfig(time_limit=5.0, retreat_lengths=(0.1,))
    _, found = retreats.plan_with_retreat(
        exact, start, goal, bounds, 0.05, cfg, retreat_checker=exact
    )
    np.testing.assert_allclose(found.direction, [0, 0, 1])
    _, chosen = retreats.plan_with_retreat(
        blind_lid, start, goal, bounds, 0.05, dataclasses.replace(cfg, time_limit=0.2),
        retreat_checker=exact,
    )  # fmt: skip
    np.testing.assert_allclose(chosen.direction, [0, 0, 1])  # the exact checker's choice


def test_route_states_are_free_exactly_for_the_free_routes_of_the_table():
    """``retreats.route_states`` (what a planner's checker is asked before
    it takes a route network's choice) walks the route ``route_table`` checks: in the L-shaped
    tunnel the exact checker calls every state free for the table's routes, and some state
    colliding for every route it rejects; a two-move route's states pass its corner and end
    at its pre-goal."""
    exact = planner.AnalyticChecker(L_TUNNEL, radius=0.01)
    goal = np.array([0.0, 0.0, 0.0, 1, 0, 0, 0])
    routes = retreats.move_routes((0.015, 0.03))
    table = retreats.route_table(exact, goal, routes, 0.045, 0.002, None, lambda pose: True)
    for r in range(0, len(routes), 7):
        states = retreats.route_states(goal, routes[r], 0.045, 0.002)
        assert (not exact(states).any()) == table[r], routes[r]
    two = routes[table & (routes[:, 0] >= 0)][0]
    states = retreats.route_states(goal, two, 0.045, 0.005)
    retreat = retreats.route_retreat(goal, two, 0.045)
    np.testing.assert_allclose(states[-1], retreat.pregoal, atol=1e-9)
    assert np.isclose(np.linalg.norm(states - retreat.via[0], axis=1), 0, atol=1e-9).any()
    assert not np.isclose(np.linalg.norm(states - goal, axis=1), 0).any()  # the goal excluded
