"""scripts/probe_oracle_approach.py (thirty-fourth session, issue 13): the upper bound of a
right approach over the goal's last centimetres."""

import importlib.util
from pathlib import Path

import numpy as np

SPEC = importlib.util.spec_from_file_location(
    "probe_oracle_approach",
    Path(__file__).resolve().parents[1] / "scripts/probe_oracle_approach.py",
)
probe = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(probe)


def test_a_path_is_free_near_only_or_far_by_where_it_penetrates():
    dist = np.array([0.20, 0.10, 0.04, 0.01, 0.0])
    tol = 1e-3
    assert probe.classify(np.zeros(5), dist, 0.045, tol) == "free"
    assert probe.classify(np.array([0, 0, 5e-4, 0, 0]), dist, 0.045, tol) == "free"  # tolerated
    assert probe.classify(np.array([0, 0, 3e-3, 2e-3, 0]), dist, 0.045, tol) == "near"
    assert probe.classify(np.array([0, 2e-3, 3e-3, 0, 0]), dist, 0.045, tol) == "far"
    assert probe.classify(np.array([0, 2e-3, 0, 0, 0]), dist, 0.2, tol) == "near"


def test_the_bound_frees_near_only_paths_of_pairs_with_an_approach():
    classes = ["free", "free", "near", "near", "far"]
    approach = [True, False, True, False, True]
    out = probe.bound(classes, approach, pairs=10)
    assert out["as_planned"] == dict(returned=5, collision_free=2, precision=40.0, recall=20.0,
                                     f1=26.7)  # fmt: skip
    # the near-only path with an approach counts free; the one without and the far one do not
    assert out["with_oracle_approach"]["collision_free"] == 3
    assert out["with_oracle_approach"]["precision"] == 60.0
    assert (out["near_only"], out["far"], out["near_only_with_approach"]) == (2, 1, 1)
    assert probe.prf(0, 0, 10)["f1"] == 0.0


def test_runs_are_compared_on_the_pairs_all_of_them_planned():
    spec = importlib.util.spec_from_file_location(
        "compare_path_runs", Path(__file__).resolve().parents[1] / "scripts/compare_path_runs.py"
    )
    cmp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cmp)
    a = {"p0": dict(returned=True, collision_free=True), "p1": dict(returned=True, collision_free=False),
         "p2": dict(returned=False, collision_free=False)}  # fmt: skip
    b = {
        "p0": dict(returned=True, collision_free=True),
        "p1": dict(returned=True, collision_free=True),
    }
    out = cmp.compare({"a": a, "b": b})
    assert out["common_pairs"] == 2 and out["pairs_differing"] == 1  # p2: only in a
    assert out["runs"]["a"] == dict(pairs=2, returned=2, collision_free=1, precision=50.0,
                                    recall=50.0, f1=50.0)  # fmt: skip
    assert out["runs"]["b"]["f1"] == 100.0
    # no approach anywhere: every common pair is a "same decision" pair
    assert out["approach_decision"]["same"]["a"]["pairs"] == 2
    assert out["approach_decision"]["differ"]["a"]["pairs"] == 0


def test_runs_are_split_by_their_approach_decision():
    spec = importlib.util.spec_from_file_location(
        "compare_path_runs", Path(__file__).resolve().parents[1] / "scripts/compare_path_runs.py"
    )
    cmp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cmp)
    up, front = {"first_tried": [0.0, 0.0, 1.0]}, {"first_tried": [0.0, 1.0, 0.0]}
    a = {"p0": dict(returned=True, collision_free=True, approach=up),
         "p1": dict(returned=True, collision_free=True, approach=front),
         "p2": dict(returned=False, collision_free=False, approach={"best_p": 0.3})}  # fmt: skip
    b = {"p0": dict(returned=True, collision_free=True, approach=up),
         "p1": dict(returned=True, collision_free=False, approach=up),
         "p2": dict(returned=True, collision_free=False, approach=None)}  # fmt: skip
    out = cmp.compare({"a": a, "b": b})["approach_decision"]
    assert out["same"]["a"]["pairs"] == 2 and out["differ"]["a"]["pairs"] == 1  # p1 differs
    assert out["differ"]["a"]["collision_free"] == 1 and out["differ"]["b"]["collision_free"] == 0
    assert out["same"]["b"]["returned"] == 2 and out["same"]["a"]["returned"] == 1


def test_splice_takes_each_row_from_the_run_that_decided_alike(tmp_path):
    """scripts/approach_decisions.py splice (thirty-eighth session): a pair's row comes from the
    reference that covers it (decided alike, ``diff``'s decisions), else from the new run; a pair
    to plan without a new row stops the splice."""
    import json

    import pytest

    spec = importlib.util.spec_from_file_location(
        "approach_decisions", Path(__file__).resolve().parents[1] / "scripts/approach_decisions.py"
    )
    dec = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(dec)
    assert dec.decision({"first_tried": [0.7071, 0.0, 0.70711]}) == (0.707, 0.0, 0.707)
    assert dec.decision({"best_p": 0.3}) is None and dec.decision(None) is None
    # a route network's route (fortieth session) decides over the straight rule's record
    routed = {"first_tried": [0, 0, 1], "route": {"best": [3, 0.015, 0], "waypoints": 2}}
    assert dec.decision(routed) == ("route", 3, 0.015, 0)
    assert dec.decision({"route": {"best": [3, 0.015, 0], "best_p": 0.2}}) is None
    ref = [dict(pair=p, returned=True, collision_free=p != "p1") for p in ("p0", "p1", "p2")]
    ref2 = [dict(pair="p2", returned=False, collision_free=False)]
    new = [dict(pair="p1", returned=True, collision_free=True)]
    for name, rows in (("ref", ref), ("ref2", ref2), ("new", new)):
        (tmp_path / f"{name}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    r1, r2 = str(tmp_path / "ref.jsonl"), str(tmp_path / "ref2.jsonl")
    decisions = {
        "p0": dict(covered_by=r1),
        "p1": dict(covered_by=None, new=None),
        "p2": dict(covered_by=r2, new=None),
    }
    (tmp_path / "d.json").write_text(json.dumps(dict(decisions=decisions)))
    args = ["splice", "--decisions", str(tmp_path / "d.json"), "--new",
            str(tmp_path / "new.jsonl"), "--out", str(tmp_path / "out.jsonl")]  # fmt: skip
    assert dec.main(args) == 3
    rows = dec.read_rows(tmp_path / "out.jsonl")
    assert [rows[p]["returned"] for p in ("p0", "p1", "p2")] == [True, True, False]
    assert rows["p1"]["collision_free"] and rows["p1"]["spliced_from"].endswith("new.jsonl")
    assert rows["p0"]["spliced_from"] == r1 and rows["p2"]["spliced_from"] == r2
    decisions["p1"]["new"] = [0.0, 0.0, 1.0]  # diff's rule used an approach, the new row none
    (tmp_path / "d.json").write_text(json.dumps(dict(decisions=decisions)))
    with pytest.raises(SystemExit, match="decided otherwise"):
        dec.main(args)
    decisions["p1"]["new"] = None
    decisions["p2"]["covered_by"] = None
    (tmp_path / "d.json").write_text(json.dumps(dict(decisions=decisions)))
    with pytest.raises(SystemExit, match="p2"):
        dec.main(args)


def test_multistart_keeps_the_first_path_of_the_runs_that_returned_one():
    """scripts/probe_multistart.py (forty-sixth session): of k runs a pair keeps the path the rule
    picks among those returned (never by the mesh check), none when no run returned one."""
    spec = importlib.util.spec_from_file_location(
        "probe_multistart", Path(__file__).resolve().parents[1] / "scripts/probe_multistart.py"
    )
    ms = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ms)

    def row(returned, free, s, flags=0):
        return dict(returned=returned, collision_free=free, planning_s=s, clear_s=0.0,
                    estimator_dense_flags=flags, clear_gap_after_m=0.01 * s)  # fmt: skip

    a = {"p0": row(True, False, 9.0), "p1": row(False, False, 60.0), "p2": row(False, False, 60.0)}
    b = {
        "p0": row(True, True, 2.0, flags=3),
        "p1": row(True, True, 5.0),
        "p2": row(False, False, 60.0),
    }
    out = ms.multistart({"a": a, "b": b}, "first")["by_k"]
    assert out["k1"]["readings"]["a"]["collision_free"] == 0
    both = out["k2"]["readings"]["a + b"]
    assert both == dict(
        pairs=3, returned=2, collision_free=2, precision=100.0, recall=66.7, f1=80.0
    )
    # fewest flags on the dense path first: p0 keeps a's colliding path
    both = ms.multistart({"a": a, "b": b}, "fewest_flags")["by_k"]["k2"]["readings"]["a + b"]
    assert both["returned"] == 2 and both["collision_free"] == 1
