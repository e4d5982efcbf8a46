"""The thirty-ninth session's issue-13 probes: a path refusal scored from the runs
(scripts/probe_path_gaps.py) and the approach rule broken down by support family
(scripts/probe_approach_rule.py)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / f"scripts/{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_refusing_paths_by_clearance_is_scored_as_pairs_without_a_path():
    gaps = _load("probe_path_gaps")
    paths = [
        dict(run="a", collision_free=True, min_gap_beyond={"0.045": 0.010}),
        dict(run="a", collision_free=False, min_gap_beyond={"0.045": 0.002}),
        dict(run="a", collision_free=True, min_gap_beyond={"0.045": 0.003}),
        dict(run="b", collision_free=False, min_gap_beyond={"0.045": None}),
    ]
    pairs = {"a": 4, "b": 2}
    base = gaps.score(paths, pairs, lambda p: False)
    # run a: 2 free of 3 returned, 4 pairs; run b: 0 of 1, 2 pairs; means over runs
    assert base["precision"] == pytest.approx(100 * (2 / 3 + 0) / 2, abs=0.1)
    assert base["recall"] == pytest.approx(100 * (2 / 4 + 0) / 2, abs=0.1)

    def refuse(p):
        v = p["min_gap_beyond"]["0.045"]
        return v is not None and v < 0.0025

    out = gaps.score(paths, pairs, refuse)
    assert out["refused_colliding"] == 1 and out["refused_free"] == 0
    assert out["precision"] == pytest.approx(100 * (1 + 0) / 2, abs=0.1)  # a: 2 of 2
    assert out["recall"] == base["recall"]  # a refused colliding path costs no recall


def test_the_approach_rule_by_family_counts_used_and_free_goals():
    rule = _load("probe_approach_rule")
    assert rule.family_of(Path("x/00676_bag_0009__pegboard_hook_0004.npz")) == "pegboard_hook"
    assert rule.family_of(Path("12_mug_0001__towel_bar_0010.npz")) == "towel_bar"
    from omnihang_jax import approach

    d = len(approach.DIRECTIONS)
    prob = np.zeros((3, d))
    labels = np.zeros((3, d), bool)
    prob[0, 0], labels[0, 0] = 0.9, True  # used, free
    prob[1, 0], labels[1, 1] = 0.9, True  # used, blocked (another direction is free)
    prob[2, 0] = 0.1  # not used
    out = rule.by_family(prob, labels, np.array([False] * 3), ["a", "a", "b"], 0.5)
    assert out["a"] == dict(goals=2, any_free=1.0, used=1.0, used_free=0.5)
    assert out["b"] == dict(goals=1, any_free=0.0, used=0.0, used_free=None)


def test_the_lattice_route_leaves_an_l_shaped_tunnel():
    """scripts/probe_route_bfs.py: the breadth-first lattice search finds the way out of the
    planner test's L-shaped tunnel (+x, then up) with an exact checker standing in for the
    meshes (its clearance: the distance to the boxes minus the sphere's radius)."""
    bfs = _load("probe_route_bfs")
    from omnihang_jax import planner

    boxes = [
        ([-0.2, -0.2, -0.2], [0.2, 0.2, -0.015]),
        ([-0.2, -0.2, 0.015], [0.015, 0.2, 0.2]),
        ([0.05, -0.2, -0.2], [0.2, 0.2, 0.06]),
        ([-0.2, -0.2, -0.2], [-0.015, 0.2, 0.2]),
        ([-0.2, 0.015, -0.2], [0.2, 0.2, 0.2]),
        ([-0.2, -0.2, -0.2], [0.2, -0.015, 0.2]),
    ]
    exact = planner.AnalyticChecker(boxes, radius=0.01)

    class Exact:
        def __call__(self, poses):
            return exact(poses)

        def clearance(self, pose):
            p = np.asarray(pose, float).reshape(-1, 7)[:, :3]
            d = min(np.linalg.norm(p - np.clip(p, lo, hi), axis=1).min() for lo, hi in exact.boxes)
            return np.array([d - exact.radius])

    goal = np.array([0.0, 0.0, 0.0, 1, 0, 0, 0])
    bounds = (np.array([-0.3, -0.3, -0.3]), np.array([0.3, 0.3, 0.3]))
    route, expanded = bfs.bfs_route(Exact(), goal, 0.015, 0.01, 500, bounds)
    assert route is not None and route[0] == [0, 0, 0] and expanded <= 500
    pts = 0.015 * np.asarray(route, float)
    assert pts[-1][2] > 0.06  # out over the far wall's top, 1 cm clear
    assert not exact(np.concatenate([pts, np.tile([1, 0, 0, 0], (len(pts), 1))], 1)).any()
    # a lid over the shaft: no way off
    lid = planner.AnalyticChecker([*boxes, ([-0.2, -0.2, 0.07], [0.2, 0.2, 0.2])], radius=0.01)
    exact.boxes = lid.boxes
    assert bfs.bfs_route(Exact(), goal, 0.015, 0.01, 500, bounds)[0] is None
