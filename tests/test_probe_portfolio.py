"""scripts/probe_portfolio.py (thirty-third session, issue 13): several runs' returned paths pooled
per pair, one kept by a rule the planner knows, against the oracle."""

import importlib.util
import json
from pathlib import Path

import pytest

SPEC = importlib.util.spec_from_file_location(
    "probe_portfolio", Path(__file__).resolve().parents[1] / "scripts/probe_portfolio.py"
)
probe_portfolio = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(probe_portfolio)


def _row(pair, returned, free=False, gap=0.01, waypoints=10, seconds=1.0):
    return {"pair_index": pair, "returned": returned, "collision_free": free,
            "clear_gap_after_m": gap, "clear_gap_before_m": gap, "waypoints": waypoints,
            "planning_s": seconds}  # fmt: skip


def _write(path, rows):
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return str(path)


def test_pooled_runs_keep_one_path_per_pair_by_each_rule(tmp_path):
    # pair 0: run a times out, run b returns a free path; pair 1: both return, a's collides
    # (larger clearance, more waypoints, faster), b's is free; pair 2: neither returns
    a = _write(tmp_path / "a.jsonl", [_row(0, False), _row(1, True, False, 0.03, 20, 0.5),
                                      _row(2, False)])  # fmt: skip
    b = _write(tmp_path / "b.jsonl", [_row(0, True, True), _row(1, True, True, 0.01, 5, 2.0),
                                      _row(2, False), _row(3, True, True)])  # fmt: skip
    res = probe_portfolio.main(["--runs", f"{a},{b}", "--out", str(tmp_path / "p.json")])
    assert res["pairs"] == 3  # pair 3 is in one run only
    assert [r["returned"] for r in res["each_run"]] == [1, 2]
    assert res["each_run"][0]["free"] == 0 and res["each_run"][1]["free"] == 2
    first = res["first_run_that_returned"]  # pair 0 from b, pair 1 from a (colliding)
    assert (first["returned"], first["free"]) == (2, 1)
    assert first["precision"] == pytest.approx(50.0) and first["recall"] == pytest.approx(100 / 3)
    assert res["largest_clearance_after"]["free"] == 1  # a's colliding path on pair 1
    assert res["fewest_waypoints"]["free"] == 2  # b's on pair 1
    assert res["first_in_time"]["free"] == 1  # a's (0.5 s)
    assert res["oracle"]["free"] == 2 and res["oracle"]["precision"] == pytest.approx(100.0)
    assert res["clearance_after_colliding_m"]["median"] == pytest.approx(0.03)
    assert json.loads((tmp_path / "p.json").read_text())["pairs"] == 3


def test_runs_without_a_shared_pair_are_refused(tmp_path):
    a = _write(tmp_path / "a.jsonl", [_row(0, True, True)])
    b = _write(tmp_path / "b.jsonl", [_row(1, True, True)])
    with pytest.raises(SystemExit):
        probe_portfolio.main(["--runs", f"{a},{b}", "--out", str(tmp_path / "p.json")])
    assert not (tmp_path / "p.json").exists()
