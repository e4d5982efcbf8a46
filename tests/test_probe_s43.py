"""The forty-third session's issue-13 probe: a lattice route searched with the planner's own
checker (scripts/probe_checked_lattice.py), its truth on the meshes and its summary."""

import importlib.util
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))


def _load(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / f"scripts/{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


class Slab:
    """A stand-in for ``collision.MeshChecker``: 2 mm deep wherever x > 5 cm; the clearance is
    the height z."""

    def penetration(self, poses):
        return np.where(np.asarray(poses)[:, 0] > 0.05, 0.002, 0.0)

    def clearance(self, poses):
        return np.asarray(poses)[:, 2]


def test_route_truth_walks_the_whole_route_and_summary_counts_by_kind():
    from omnihang_jax import planner

    probe = _load("probe_checked_lattice")
    goal = np.array([0.0, 0, 0, 1, 0, 0, 0])

    def retreat(via_x, end):
        via = np.array([[via_x, 0, 0, 1, 0, 0, 0]])
        return planner.Retreat(np.array([*end, 1, 0, 0, 0]), np.array([0, 0, 1.0]), 0.02, 0, 0.0,
                               via=via)  # fmt: skip

    good = probe.route_truth(Slab(), goal, retreat(0.03, (0.03, 0, 0.02)))
    assert good["free"] and good["good"] and good["end_clear_m"] == 0.02
    low = probe.route_truth(Slab(), goal, retreat(0.03, (0.03, 0, 0.005)))
    assert low["free"] and not low["good"]  # free but not 1 cm off
    # the corner beyond the slab's edge: the segment into it collides though both ends of the
    # route are outside
    deep = probe.route_truth(Slab(), goal, retreat(0.06, (0.0, 0, 0.02)))
    assert not deep["free"] and not deep["good"] and deep["deepest_m"] == 0.002
    rows = [
        dict(kind="threaded", decision="none", lattice={"0.01": dict(found=True, truth=good)}),
        dict(kind="threaded", decision="none", lattice={"0.01": dict(found=True, truth=deep)}),
        dict(kind="off_straight", decision="route", lattice={"0.01": dict(found=False)}),
        dict(kind="off_straight", decision="route", lattice={}),  # not searched
    ]
    table = probe.summarise(rows, [0.01])["0.01"]
    assert table["all"] == dict(goals=3, found=2, good=1, free=1, good_of_found=0.5)
    assert table["kind:off_straight"]["found"] == 0
    assert table["kind:off_straight"]["good_of_found"] is None


def test_cem_iteration_summary_reads_the_histories():
    """``scripts/probe_cem_iterations.py`` (issue 12): from best-log-V histories, the share of
    candidates the later iterations improve, and whether the best candidate is already found."""
    probe = _load("probe_cem_iterations")
    log = np.log
    # one pair, two candidates, 4 iterations: the first improves at iteration 4 and overtakes
    h = np.array([[[log(0.5), log(0.6), log(0.6), log(0.9)],
                   [log(0.7), log(0.8), log(0.8), log(0.8)]]])  # fmt: skip
    out = probe.summarise(h, upto=(2, 3))
    assert out["3"]["candidates_improved_after"] == 0.5
    assert out["3"]["same_best_candidate"] == 0.0  # after 3 the second leads; at 4 the first
    assert np.isclose(out["3"]["mean_gain_in_v"], (0.3 + 0.0) / 2, atol=1e-5)
    assert np.isclose(out["3"]["best_candidate_gain_in_v"], 0.9 - 0.8, atol=1e-5)
