"""The planner's own states as NCE training data (twenty-ninth session, issue 13):
``planner.RecordingChecker``, ``eval_paths.save_mined`` (``--split train --mine DIR``) and
``train_collision --mined DIR --mined-share S``."""

from __future__ import annotations

import dataclasses as dc

import numpy as np
import pytest

pytest.importorskip("ompl")

from omnihang_jax import collision, planner  # noqa: E402


def test_recording_checker_keeps_verdicts_and_a_bounded_reservoir():
    box = planner.AnalyticChecker([(np.array([-0.1, -0.1, -0.1]), np.array([0.1, 0.1, 0.1]))])
    rec = planner.RecordingChecker(box, cap=50, seed=3)
    rng = np.random.default_rng(0)
    poses = np.concatenate([rng.uniform(-0.3, 0.3, (40, 3)), np.tile([1.0, 0, 0, 0], (40, 1))], 1)

    out = rec(poses)

    assert np.array_equal(out, box(poses))
    assert np.array_equal(rec.called, out) and np.allclose(rec.poses, poses)
    # an edge through the box is blocked: not recorded (its per-state verdicts are unknown)
    through = planner.interpolate_segment(
        np.array([-0.5, 0, 0, 1, 0, 0, 0.0]), np.array([0.5, 0, 0, 1, 0, 0, 0.0]), 20
    )
    assert rec.any_colliding(through) and rec.seen == 40
    # a free edge is recorded with every state called free
    beside = through.copy()
    beside[:, 1] = 0.5
    assert not rec.any_colliding(beside)
    assert rec.seen == 40 + len(beside) and len(rec.poses) == 50  # the cap holds
    assert np.array_equal(rec.called, box(rec.poses))  # whatever the reservoir kept
    with pytest.raises(ValueError, match="cap"):
        planner.RecordingChecker(box, cap=0)


def _mug_case():
    """A real pair: the mug and the single-rod hook, their observed clouds, and as the goal a
    pose in front of the rod (save_mined needs no hanging goal)."""
    from experiments.eval_paths import PairCase
    from sim import camera
    from sim.assets import objects, supports  # noqa: F401  (registers the generators)
    from sim.assets.base import build_object, build_support
    from sim.scene import build_scene

    obj, sup = build_object("mug", 3), build_support("single_rod_hook", 0)
    scene = build_scene(obj, sup)
    rng = np.random.default_rng(0)
    cam = camera.CameraConfig(n_points=1024)
    oc = camera.partial_cloud(scene, "object", np.array([0.0, 0.6, 0.3]), rng, cam)
    sc = camera.partial_cloud(scene, "support", np.array([0.0, 0.6, 0.3]), rng, cam)
    peg = sup.features[0]
    through = 0.5 * (np.asarray(peg.base) + np.asarray(peg.tip))
    goal = planner.start_pose(scene, np.array([*through, 1, 0, 0, 0]))
    meta = dict(pair_index=7, object_name="mug_0003", support_name="single_rod_hook_0000",
                object_category="mug", support_family="single_rod_hook", split="train")  # fmt: skip
    case = PairCase("00007_mug_0003__single_rod_hook_0000", meta, scene, oc.points, oc.normals,
                    sc.points, sc.normals, goal)  # fmt: skip
    return case, through


def test_save_mined_labels_what_the_checker_judged_with_the_meshes(tmp_path):
    """With the meshes as the recorded checker the labels equal its verdicts (no misses, no
    false alarms); the returned path's dense states are added; states far from the observed
    support are left out."""
    from experiments.eval_paths import MINE_GAP, save_mined

    case, through = _mug_case()
    mesh = planner.MeshChecker(case.scene)
    rec = planner.RecordingChecker(mesh, cap=10_000)
    front = case.goal
    behind = front.copy()
    behind[1] = through[1] - (front[1] - through[1])
    path = np.stack([front, behind])  # straight through the rod
    states = planner.interpolate_path(path, 0.004, planner.object_radius(case.scene))
    up = np.tile(case.goal, (60, 1))  # straight up from the rod: colliding, grazing, clear
    up[:, :3] = through + np.outer(np.linspace(0, 0.3, 60), [0, 0, 1.0])
    far = states.copy()
    far[:, 2] += 1.0  # a metre above everything
    rec(np.concatenate([states, up, far]))
    config = planner.PlannerConfig()

    counts = save_mined(case, rec, mesh, path, "mesh", config, (tmp_path, 10_000))

    with np.load(tmp_path / f"{case.name}.npz") as f:
        assert int(f["pair_index"]) == 7 and str(f["method"]) == "mesh"
        pen, called, gap, source = f["penetration"], f["called"], f["gap"], f["source"]
        assert np.all(gap < MINE_GAP) and np.all(f["poses"][:, 2] < 0.9)  # far ones left out
    colliding = pen > config.penetration_tolerance
    assert colliding.any() and (~colliding).any()
    assert np.array_equal(colliding, called)
    assert counts["missed"] == 0 and counts["false_alarms"] == 0
    assert counts["colliding"] == int(colliding.sum()) and (source == 1).sum() > 0
    assert counts["recorded"] == 2 * len(states) + len(up)


def _pair_file(path, index, rng):
    from omnihang_jax import dataset_bridge

    n = 64
    fields = {
        k: rng.normal(size=(n, 3)).astype(np.float32)
        for k in ("object_points", "object_normals", "support_points", "support_normals")
    }
    fields |= dict(
        collision_poses=np.tile(np.float32([0, 0, 0, 1, 0, 0, 0]), (10, 1)),
        collision_labels=np.zeros(10, bool),
        stable_poses=np.tile(np.float32([0, 0, 0, 1, 0, 0, 0]), (2, 1)),
    )
    meta = dict(pair_index=index, object_name="o", support_name="s", object_category="mug",
                support_family="rod", split="train")  # fmt: skip
    fields |= {k: np.array(meta[k]) for k in dataset_bridge.META_KEYS}
    np.savez(path, **fields)


def test_load_collision_data_adds_mined_rows_to_their_pairs(tmp_path):
    from experiments.train_collision import NEAR_TOLERANCE, load_collision_data

    rng = np.random.default_rng(1)
    files = [tmp_path / "00001_a.npz", tmp_path / "00002_b.npz"]
    for i, f in enumerate(files):
        _pair_file(f, i + 1, rng)
    mined = tmp_path / "mined"
    mined.mkdir()
    pen = np.array([0.0, 0.0005, 0.002, 0.01], np.float32)
    np.savez(mined / "00002_b.npz", poses=rng.normal(size=(4, 7)).astype(np.float32),
             penetration=pen, pair_index=np.array(2))  # fmt: skip

    data = load_collision_data(files, stable_free=True, mined_dir=mined)

    assert data.far_mined.sum() == 4 and len(data.far_mined) == len(data.far_poses) == 8
    rows = data.far_mined
    assert np.all(data.far_pair[rows] == 1)  # the second pair's rows
    assert np.array_equal(data.far_labels[rows], pen > NEAR_TOLERANCE)
    assert not data.far_near[rows].any() and not data.far_transit[rows].any()
    # without the folder nothing changes
    plain = load_collision_data(files, stable_free=True)
    assert not plain.far_mined.any() and len(plain.far_poses) == 4
    np.savez(mined / "00001_a.npz", poses=np.zeros((1, 7), np.float32),
             penetration=np.zeros(1, np.float32), pair_index=np.array(99))  # fmt: skip
    with pytest.raises(ValueError, match="pair 99"):
        load_collision_data(files, mined_dir=mined)
    with pytest.raises(FileNotFoundError, match="no such folder"):
        load_collision_data(files, mined_dir=tmp_path / "missing")


@pytest.mark.slow  # the mined NCE, not adopted (twenty-ninth session); the default suite stays under 20 min
def test_nce_mined_share_draws_the_mined_rows_and_learns_them():
    """--mined-share: that fraction of every batch comes from the mined rows alone; a tiny
    NCE trained on the rod task's rows as mined rows gets them right above chance."""
    from experiments.train_collision import train_nce
    from omnihang_jax import collision
    from tests.test_collision import _rod_task

    rng = np.random.default_rng(6)
    train, mined = _rod_task(rng, 64), _rod_task(rng, 400)
    train = dc.replace(
        train, far_pair=mined.pair, far_poses=mined.poses, far_labels=mined.labels,
        far_near=np.zeros(400, bool), far_transit=np.zeros(400, bool), far_mined=np.ones(400, bool),
    )  # fmt: skip
    cfg = collision.NCE_PRESETS["tiny"]
    params, log = train_nce(
        train, cfg, steps=150, time_budget=120, batch=32, progress=False, mined_share=0.75
    )
    assert log["mined_share"] == 0.75 and log["mined_rows"] == 400
    nets = collision.make_nce(cfg)
    logits = nets.apply(params, mined.object_points[[0] * 400], mined.support_points[[0] * 400],
                        mined.poses)  # fmt: skip
    accuracy = float(np.mean((np.asarray(logits) > 0) == mined.labels))
    assert accuracy > 0.6, accuracy
    with pytest.raises(ValueError, match="shares"):
        train_nce(train, cfg, steps=1, time_budget=10, batch=32, progress=False, mined_share=1.25)


def test_wall_checker_flags_observed_points_behind_the_wall_plane():
    """planner.WallChecker: the mug pushed into the wall behind the hook collides with the wall
    in MuJoCo and is flagged; the same pose a few centimetres in front is neither; a margin
    flags what comes closer than it; eval_paths reads a free-standing support's NaN as no wall."""
    from experiments.eval_paths import _wall_of
    from sim.assets.base import build_support

    case, _ = _mug_case()
    wall_y = build_support("single_rod_hook", 0).wall_y
    assert wall_y is not None, "the single-rod hook is wall-mounted"
    mesh = planner.MeshChecker(case.scene)
    wall = planner.WallChecker(case.object_points, wall_y)
    back = float(case.object_points[:, 1].min())  # object frame: the cloud's side toward the wall
    # the observed back 1 cm into the wall, 40 cm up (clear of the hook, in front of the wall)
    into = np.array([0.0, wall_y - back - 0.01, 0.4, 1, 0, 0, 0])
    front = into.copy()
    front[1] += 0.05
    assert mesh(into[None])[0] and not mesh(front[None])[0]
    assert wall(np.stack([into, front])).tolist() == [True, False]
    assert planner.WallChecker(case.object_points, wall_y, margin=0.06)(front[None])[0]
    with pytest.raises(ValueError, match="finite"):
        planner.WallChecker(case.object_points, float("nan"))

    class F(dict):
        files = property(lambda self: list(self))

    assert _wall_of(F(wall_y=np.float32(np.nan))) is None and _wall_of(F()) is None
    assert _wall_of(F(wall_y=np.float32(0.25))) == 0.25


def test_fallback_plans_again_with_the_lax_checker_after_a_time_out(monkeypatch):
    """Thirtieth session: ``eval_paths --fallback-far-threshold``. The first plan (a checker
    that blocks everything but the start) times out; the second, with the fallback's checker
    (everything free), returns a path; the row says so and the summary's ``fallback.without``
    is the run with the first plans alone."""
    from experiments import eval_paths

    case, through = _mug_case()
    case = case._replace(goal=np.array([*through, 1.0, 0, 0, 0]))  # on the rod (goal exempt)
    start = planner.start_pose(case.scene, case.goal)
    assert np.linalg.norm(start[:3] - case.goal[:3]) > 0.05

    def blocked(poses):
        p = np.asarray(poses, float).reshape(-1, 7)
        return np.linalg.norm(p[:, :3] - start[:3], axis=1) > 0.01

    def free(poses):
        return np.zeros(len(np.asarray(poses).reshape(-1, 7)), bool)

    def fake_checkers(case, est, tolerance, methods):  # the lax estimators' NCE: "lax"
        return {"nce_geometric": free if est.nce == "lax" else blocked}

    monkeypatch.setattr(eval_paths, "checkers_for", fake_checkers)
    est = eval_paths.Estimators(*[None] * 8)._replace(
        nce_fallback="lax", fallback_far_threshold=0.9, fallback_time=2.0
    )
    config = planner.PlannerConfig(time_limit=0.3)
    rows, paths = eval_paths.evaluate_pair(case, est, config, ("nce_geometric",))
    (row,) = rows
    assert row["fallback"]["returned"] and row["fallback"]["far_threshold"] == 0.9
    assert row["returned"] and row["status"] == "Exact solution"
    assert row["planning_s"] >= 0.3 and "nce_geometric" in paths
    assert row["start_called_colliding"] is False  # judged by the first plan's checker
    summary = eval_paths.summarise([row], ("nce_geometric",))["nce_geometric"]
    assert summary["fallback"]["tried"] == 1 and summary["fallback"]["returned"] == 1
    assert summary["fallback"]["without"]["returned"] == 0 and summary["returned"] == 1
    # without a fallback the same pair is a time-out
    rows, _ = eval_paths.evaluate_pair(case, est._replace(nce_fallback=None), config,
                                       ("nce_geometric",))  # fmt: skip
    assert not rows[0]["returned"] and "fallback" not in rows[0]
    with pytest.raises(ValueError, match="evaluation"):  # mining records the first plan only
        eval_paths.evaluate_pair(case, est, config, ("nce_geometric",), mine=("unused", 10))


def test_with_fallback_refuses_a_stricter_threshold():
    from experiments import eval_paths

    est = eval_paths.Estimators(*[None] * 8)._replace(nce_far_threshold=0.56, nce_goal_ball=0.02)
    with pytest.raises(ValueError, match="laxer"):
        eval_paths.with_fallback(est, 0.5, 10.0)
    with pytest.raises(ValueError, match="goal-ball"):
        eval_paths.with_fallback(est._replace(nce_far_threshold=None), 0.9, 10.0)
    # the same threshold is a replan with the same checker (thirty-third session)
    same = eval_paths.with_fallback(est._replace(nce_config=collision.NCEConfig()), 0.56, 10.0)
    assert same.fallback_far_threshold == 0.56 and same.fallback_time == 10.0


@pytest.mark.parametrize("replan", ["same", "plain"])
def test_the_replan_after_a_time_out_keeps_or_drops_the_learned_approach(monkeypatch, replan):
    """Thirty-sixth session: ``eval_paths --approach-replan``. The first plan, to the learned
    approach's pre-goal, times out; the replan (everything free) either plans to the same
    pre-goal and ends straight in ('same') or plans plainly to the goal ('plain')."""
    from types import SimpleNamespace

    from experiments import eval_paths
    from omnihang_jax import approach

    case, through = _mug_case()
    case = case._replace(goal=np.array([*through, 1.0, 0, 0, 0]))
    start = planner.start_pose(case.scene, case.goal)
    up = approach.DIRECTIONS[0]

    def blocked(poses):
        p = np.asarray(poses, float).reshape(-1, 7)
        return np.linalg.norm(p[:, :3] - start[:3], axis=1) > 0.01

    def free(poses):
        return np.zeros(len(np.asarray(poses).reshape(-1, 7)), bool)

    class Up:  # the approach network: straight up, sure of it
        config = SimpleNamespace(threshold=0.5)

        def order(self, obj, sup, goal):
            return approach.DIRECTIONS, np.linspace(0.9, 0.0, len(approach.DIRECTIONS))

    monkeypatch.setattr(eval_paths, "checkers_for", lambda case, est, tol, methods: {
        "nce_geometric": free if est.nce == "lax" else blocked})  # fmt: skip
    est = eval_paths.Estimators(*[None] * 8)._replace(
        nce_fallback="lax", fallback_far_threshold=0.9, fallback_time=2.0, approach=Up(),
        approach_check="none", approach_replan=replan,
    )  # fmt: skip
    config = planner.PlannerConfig(time_limit=0.3, retreat_lengths=(0.045,))
    (row,), paths = eval_paths.evaluate_pair(case, est, config, ("nce_geometric",))
    assert row["returned"] and row["fallback"]["approach"] == replan
    assert row["approach"]["first_tried"] == [0.0, 0.0, 1.0]
    path = paths["nce_geometric"]
    np.testing.assert_allclose(path[-1][:3], case.goal[:3], atol=1e-9)
    if replan == "same":  # the path ends pre-goal (4.5 cm above) -> goal
        assert row["retreat"]["direction"] == up.round(3).tolist()
        np.testing.assert_allclose(path[-2][:3], case.goal[:3] + 0.045 * up, atol=1e-6)
    else:
        assert row["retreat"] is None
