"""scripts/probe_approach_rule.py (thirty-sixth session, issue 13): which rule picks the
approach direction from the network's probabilities."""

import importlib.util
from pathlib import Path

import numpy as np

from omnihang_jax import approach

SPEC = importlib.util.spec_from_file_location(
    "probe_approach_rule", Path(__file__).resolve().parents[1] / "scripts/probe_approach_rule.py"
)
probe = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(probe)


def test_argmax_order_threshold_and_open_side():
    prob = np.full((3, 26), 0.1)
    prob[0, [0, 10]] = [0.75, 0.9]  # up 0.75, towards the wall (-y) 0.9
    prob[1, [3, 5]] = [0.6, 0.65]  # nothing reaches 0.7
    prob[2, [2, 1]] = [0.8, 0.95]  # up-and-towards-the-wall 0.8, up-and-(-x) 0.95
    wall = np.array([True, True, False])
    assert approach.DIRECTIONS[10][1] < 0 and approach.DIRECTIONS[2][1] < 0
    assert probe.choose(prob, wall, "argmax", 0.7, False).tolist() == [10, -1, 1]
    assert probe.choose(prob, wall, "argmax", 0.7, True).tolist() == [0, -1, 1]
    assert probe.choose(prob, wall, "order", 0.7, False).tolist() == [0, -1, 1]  # first in order
    assert probe.choose(prob, wall, "argmax", 0.5, False).tolist() == [10, 5, 1]
    labels = np.zeros((3, 26), bool)
    labels[0, 0] = labels[1, 5] = True  # the wall direction of goal 0 is blocked
    rows = {(r["rule"], r["threshold"], r["open_side"]): r for r in probe.table(prob, labels, wall)}
    plain, open_side = rows[("argmax", 0.7, False)], rows[("argmax", 0.7, True)]
    assert (
        plain["used"] == round(2 / 3, 4)
        and plain["used_free"] == 0.0
        and plain["used_blocked"] == 2
    )
    assert open_side["used_free"] == 0.5 and open_side["used_blocked"] == 1
