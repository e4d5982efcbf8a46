"""How to hang as one factory: the named planner configs, a planner built by make_planner, and
the evaluation's arithmetic."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from omnihang_jax import paths, paths_eval


def _differences(a: paths.PlannerConfig, b: paths.PlannerConfig) -> set[str]:
    return {f.name for f in dataclasses.fields(a) if getattr(a, f.name) != getattr(b, f.name)}


def test_named_configs_differ_only_where_intended():
    bare = {"checker", "approach", "routes", "clear_target", "replan", "mesh_fallback"}
    assert _differences(paths.DEFAULT, paths.PAPER_NCE) == bare
    assert _differences(paths.DEFAULT, paths.PAPER_HCE) == bare
    assert _differences(paths.DEFAULT, paths.MESH) == bare
    assert _differences(paths.PAPER_NCE, paths.PAPER_HCE) == {"checker"}
    assert paths.CONFIGS["default"] is paths.DEFAULT
    # the hybrid's numbers, once read from its selection file
    d = paths.DEFAULT
    assert (d.test_depth, d.test_radius, d.test_min_points) == (0.0005, 0.002, 0)
    assert (d.far_threshold, d.near_threshold, d.goal_ball) == (0.56, 0.99, 0.02)
    assert d.geometric.depth == 0.0005 and d.geometric.object_points == 4096
    with pytest.raises(ValueError, match="checker"):
        paths.PlannerConfig(checker="oracle")
    with pytest.raises(ValueError, match="mesh checker plans plainly"):
        dataclasses.replace(paths.MESH, clear_target=0.03)
    with pytest.raises(ValueError, match="routes need the approach"):
        dataclasses.replace(paths.DEFAULT, approach=None)


def test_the_hang_commands_checkers_name_configs():
    assert paths.for_hang("nce", 5.0).checker == "nce"
    assert paths.for_hang("mesh", 5.0, 0.0) == dataclasses.replace(
        paths.MESH, plan_time=5.0, replan_time=0.0
    )
    auto = paths.for_hang("auto", 7.0)
    assert auto in (dataclasses.replace(paths.DEFAULT, plan_time=7.0),
                    dataclasses.replace(paths.MESH, plan_time=7.0))  # fmt: skip
    with pytest.raises(ValueError, match="checker"):
        paths.for_hang("hybrid")
    missing = dataclasses.replace(paths.PAPER_NCE, weights="weights/no_such_folder")
    assert "missing" in paths.missing(missing)
    with pytest.raises(FileNotFoundError):
        paths.make_planner(missing)
    assert "full-mesh" in paths.describe(paths.MESH)
    assert "OR the NCE" in paths.describe(paths.DEFAULT)


def test_mesh_planner_from_the_factory_threads_a_ring_onto_a_hook():
    pytest.importorskip("ompl")
    from omnihang_jax import planner
    from tests.test_planner import ring_on_rod

    scene, goal, _ = ring_on_rod()
    plan = paths.make_planner(dataclasses.replace(paths.MESH, plan_time=10.0))
    clouds = paths.Clouds(np.zeros((8, 3)), np.zeros((8, 3)))
    assert plan(None, clouds, clouds, goal) is None  # the meshes' checker needs the scene
    out = plan(scene, clouds, clouds, goal)
    assert len(out.poses) > 1, out.info["status"]
    assert out.info["dense_check_collision_free"], out.info["deepest_penetration_m"]
    np.testing.assert_allclose(out.poses[-1], goal, atol=1e-9)
    # judged again on the meshes, the resampled path is free too
    weight = planner.object_radius(scene)
    free, _, _ = planner.dense_check(planner.MeshChecker(scene), out.poses, 0.002, weight)
    assert free


def _row(pair, seed, category, returned, free, status="Exact solution", t=1.0):
    return dict(pair=pair, seed=seed, category=category, returned=returned,
                collision_free=free, status=status, planning_s=t)  # fmt: skip


def test_precision_recall_f1_of_synthetic_records(tmp_path):
    rows = [
        _row("a", 1, "mug", True, True),
        _row("b", 1, "mug", True, False),
        _row("c", 1, "cap", False, False, "Timeout", 20.0),
        _row("d", 1, "cap", True, True),
        _row("a", 2, "mug", True, True),
        _row("b", 2, "mug", False, False, "Approximate solution", 20.0),
        _row("c", 2, "cap", True, True),
        _row("d", 2, "cap", True, True),
    ]
    s = paths_eval.summarise(rows)
    # 5 free of 6 returned, of 8 records
    assert (s["returned"], s["collision_free"], s["records"]) == (6, 5, 8)
    assert s["precision"] == round(100 * 5 / 6, 1) and s["recall"] == 62.5
    assert s["f1"] == round(100 * 2 * (5 / 6) * (5 / 8) / (5 / 6 + 5 / 8), 1)
    assert s["pairs"] == 4 and s["seeds"] == [1, 2] and s["timeouts"] == 2
    assert s["per_seed"]["1"] == dict(precision=66.7, recall=50.0, f1=57.1)
    assert s["per_category"]["cap"]["recall"] == 75.0
    assert s["mean_over_categories"]["recall"] == 62.5
    assert "f1_sd_over_seeds" in s
    assert paths_eval.prf([])["f1"] == 0.0
    # records: the last of a (pair, seed) counts; a damaged last line is left out
    path = tmp_path / "pairs.jsonl"
    path.write_text("\n".join(json.dumps(r) for r in rows[:2]) + "\n"
                    + json.dumps(dict(rows[1], returned=False)) + '\n{"pair": "tr')  # fmt: skip
    kept = paths_eval.read_records(path)
    assert len(kept) == 2 and not [r for r in kept if r["pair"] == "b"][0]["returned"]


def test_records_keep_one_config(tmp_path):
    path = tmp_path / "config.json"
    paths_eval._check_config(path, paths.PAPER_NCE)
    paths_eval._check_config(path, paths.PAPER_NCE)  # the same config resumes
    with pytest.raises(ValueError, match="checker"):
        paths_eval._check_config(path, paths.PAPER_HCE)
    with pytest.raises(ValueError, match="one of"):
        paths_eval.evaluate_paths(paths.MESH, tmp_path, records_path=tmp_path / "r.jsonl")


@pytest.mark.slow
def test_evaluate_two_held_out_pairs_with_the_meshes(tmp_path):
    """The evaluation end to end on two held-out pairs of the committed dataset: the mesh
    planner's paths are free on the meshes; a second run plans nothing new."""
    pytest.importorskip("ompl")
    config = dataclasses.replace(paths.MESH, plan_time=10.0)
    s = paths_eval.evaluate_paths(config, tmp_path, pairs=2, progress=False)
    assert s["pairs"] == 2 and s["seeds"] == [1] and s["precision"] == 100.0
    lines = (tmp_path / "pairs.jsonl").read_text().splitlines()
    again = paths_eval.evaluate_paths(config, tmp_path, pairs=2, progress=False)
    assert again["f1"] == s["f1"]
    assert (tmp_path / "pairs.jsonl").read_text().splitlines() == lines


def test_evaluate_paths_command_writes_the_config_entry(tmp_path, monkeypatch):
    """``experiments.evaluate paths`` passes the named config and the flags to
    ``paths_eval.evaluate_paths`` and merges its summary under the config's name, other keys
    kept; an unknown config is a one-line error before any planning."""
    from experiments import evaluate

    seen = {}

    def fake(config, **kw):
        seen.update(config=config, **kw)
        return dict(precision=90.0, recall=60.0, f1=72.0, pairs=kw["pairs"], seeds=kw["seeds"])

    monkeypatch.setattr(paths_eval, "evaluate_paths", fake)
    results = tmp_path / "paths.json"
    results.write_text(json.dumps({"published_paper": {"paper_nce": [65.8, 43.2, 52.1]}}))
    entry = evaluate.main(["paths", "--config", "mesh", "--pairs", "3", "--seed", "2", "--workers",
                           "1", "--records", str(tmp_path / "r.jsonl"), "--results", str(results),
                           "--no-progress"])  # fmt: skip
    assert seen["config"] == paths.MESH and seen["pairs"] == 3 and seen["seeds"] == [2]
    saved = json.loads(results.read_text())
    assert saved["mesh"]["f1"] == 72.0 == entry["f1"] and saved["mesh"]["config"] == "mesh"
    assert saved["published_paper"] == {"paper_nce": [65.8, 43.2, 52.1]}
    with pytest.raises(ValueError, match="--config"):
        evaluate.main(["paths", "--config", "octree"])
    entry = evaluate.main(["paths", "--config", "mesh", "--frame", "any", "--pairs", "3",
                           "--records", str(tmp_path / "any.jsonl"), "--results", str(results),
                           "--no-progress"])  # fmt: skip
    assert seen["frame"] == "any" and entry["frame"] == "any"
    assert json.loads(results.read_text())["mesh_any_frame"]["f1"] == 72.0


def _cloud(rng, n=600):
    """An elongated, lopsided cloud (distinct principal axes), off its own origin."""
    return rng.normal(size=(n, 3)) * [0.06, 0.03, 0.012] + [0.02, -0.01, 0.03]


def test_the_planner_sees_the_same_pair_in_any_object_frame():
    """From clouds alone the planner's start, bounds and metric come from the object's
    principal box (``paths.cloud_frame``): the object handed over turned and shifted gives the
    same start placement, bounds and rotation weight, and the goal of the turned frame is the
    same placement as the library goal."""
    from omnihang_jax import planner, where_eval

    rng = np.random.default_rng(3)
    pts = _cloud(rng)
    obj = paths.Clouds(pts.astype(np.float32), np.tile([0.0, 0.0, 1.0], (len(pts), 1)))
    sup = paths.Clouds(rng.uniform([-0.1, -0.05, 0.8], [0.1, 0.05, 1.2], (500, 3)), None)
    goal = np.array([0.01, 0.12, 1.02, 0.9, 0.1, -0.3, 0.2])
    goal[3:] /= np.linalg.norm(goal[3:])
    views = []
    for pair in range(3):
        if pair == 0:
            turn = dict(object_rotation=np.eye(3), object_shift=np.zeros(3), support_yaw=0.0)
        else:
            turn = dict(where_eval.any_frame(1, pair, False), support_yaw=0.0)
        cloud, g = paths_eval.turned_object(obj, goal, turn)
        np.testing.assert_allclose(where_eval.poses_to_library(g, turn), goal, atol=1e-9)
        centred, gc, centre, geometry = paths.cloud_frame(cloud, sup, g)
        start = planner.start_pose(geometry, gc)
        # the start as a placement of the library-frame object
        start_lib = where_eval.poses_to_library(paths.move_origin(start, -centre), turn)
        views.append((start_lib, planner.default_bounds(geometry),
                      planner.object_radius(geometry), centred.points))  # fmt: skip
    for start, bounds, radius, _ in views[1:]:
        np.testing.assert_allclose(start[:3], views[0][0][:3], atol=1e-6)
        assert abs(abs(start[3:] @ views[0][0][3:]) - 1) < 1e-9
        np.testing.assert_allclose(bounds, views[0][1], atol=1e-6)
        assert radius == pytest.approx(views[0][2], abs=1e-6)
    # the centred clouds differ by the turn alone
    r = where_eval.any_frame(1, 1, False)["object_rotation"]
    np.testing.assert_allclose(views[1][3], views[0][3] @ r.T, atol=1e-5)


def test_the_any_frame_paths_protocol_refuses_what_it_cannot_judge(tmp_path):
    """The mesh checker reads the meshes in the library's frame: no any-frame run; records of
    one frame are not resumed in the other."""
    with pytest.raises(ValueError, match="mesh checker"):
        paths_eval.evaluate_paths(paths.MESH, tmp_path, frame="any")
    (tmp_path / "pairs.jsonl").write_text(json.dumps(
        {"pair": "a", "seed": 1, "frame": "any", "returned": False}) + "\n")  # fmt: skip
    with pytest.raises(ValueError, match="frame"):
        paths_eval.evaluate_paths(paths.MESH, tmp_path, frame="library")
